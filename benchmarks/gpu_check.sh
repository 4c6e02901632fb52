#!/usr/bin/env bash
# Stage IV's fit on cpu vs cuda in one run (issue 30): times, agreement, a small table in $OUT.
#
#   OUT=/tmp/out bash benchmarks/gpu_check.sh [SECONDS] [SESSION]
#
# Run from the repository root on a Linux x86-64 machine with an NVIDIA GPU and python3 with a CUDA
# build of torch. Needs only numpy, scipy and torch (no `pip install`: this repo's src/ goes on
# PYTHONPATH). SECONDS: length of the synthetic motion (default 60 = 1800 frames, 7 windows).
# SESSION (optional): a session whose Stages I-III are done; then `embodmocap motion --device
# cpu|cuda` is timed on copies of it as well (that needs every dependency of the package).
# Writes $OUT/gpu_check.json, $OUT/gpu_check.md and $OUT/gpu_check.log. Budget: under 6 minutes.
set -u
OUT="${OUT:-/tmp/out}"
mkdir -p "$OUT"
SECONDS_ARG="${1:-60}"
SESSION_ARG="${2:-}"
PY="${PYTHON:-python3}"
command -v "$PY" >/dev/null || PY=python
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
# numpy or scipy missing and wheels carried (WHEELS, default ./wheels: e.g. `pip download numpy scipy
# --only-binary=:all: --python-version 3.12 --platform manylinux2014_x86_64 -d wheels`): install them
# offline into /tmp/gpu_check_site (not under $OUT; nothing else on the machine is touched).
WHEELS="${WHEELS:-$PWD/wheels}"
if ! "$PY" -c "import numpy, scipy" 2>/dev/null && [ -d "$WHEELS" ]; then
  echo "numpy/scipy missing: installing from $WHEELS into /tmp/gpu_check_site"
  "$PY" -m pip install --no-index --find-links "$WHEELS" --target "/tmp/gpu_check_site" numpy scipy 2>&1 | tail -2
  export PYTHONPATH="$PYTHONPATH:/tmp/gpu_check_site"
fi
{
  echo "== $(date -u) on $(hostname); $($PY --version 2>&1)"
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || echo "nvidia-smi: not found"
  # What imports and what does not (only numpy, scipy and torch are needed for the fit check).
  for m in numpy scipy torch cv2 open3d pycolmap av tyro trimesh; do
    $PY -c "import $m; print('import $m: ok', getattr($m, '__version__', ''))" 2>/dev/null || echo "import $m: MISSING"
  done
  $PY -c "import torch; print('torch cuda build', torch.version.cuda, 'available', torch.cuda.is_available())" || true
  if err=$($PY -c "import embodmocap.motion.smplify, embodmocap.synth.motion" 2>&1); then echo "import embodmocap (fit + studio motion): ok"
  else echo "import embodmocap (fit + studio motion): FAILED: $(echo "$err" | tail -1)"; fi
} 2>&1 | tee "$OUT/gpu_check.log"
ARGS=(--seconds "$SECONDS_ARG")
[ -n "$SESSION_ARG" ] && ARGS+=(--session "$SESSION_ARG")
# 330 s cap: the script must end inside its 6-minute budget even on a slow CPU.
OUT="$OUT" timeout 330 "$PY" benchmarks/gpu_check.py "${ARGS[@]}" 2>&1 | tee -a "$OUT/gpu_check.log"
rc=${PIPESTATUS[0]}
[ "$rc" = 124 ] && echo "gpu_check.py ran past 330 s (rerun with a smaller SECONDS, e.g. 30)" | tee -a "$OUT/gpu_check.log"
exit "$rc"
