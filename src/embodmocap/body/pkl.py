"""Read SMPL model files (.pkl as distributed, or .npz) into plain numpy arrays, without chumpy.

The official SMPL pickles were written by Python 2 and hold ``chumpy`` objects (``shapedirs``,
sometimes ``v_template``, ``J``) and a ``scipy.sparse`` ``J_regressor``. chumpy does not import on
current Python / numpy, so the pickle is read with an unpickler that:

- maps every ``chumpy.*`` class to :class:`_ChumpyStandIn`, which keeps the pickled state; the
  array is the state's ``x`` entry (what a plain ``chumpy.Ch`` holds);
- decodes Python-2 byte strings as latin-1 (numpy's pickled buffers need that);
- allows only the globals a model file needs (numpy arrays and dtypes, scipy sparse matrices,
  chumpy stand-ins, ``copyreg._reconstructor``, ``_codecs.encode``); anything else is refused,
  so loading a model file cannot run arbitrary code.

Sparse matrices become dense arrays. :func:`load_model_arrays` then checks the keys and shapes
every consumer relies on (see ``docs/formats.md``).
"""

from __future__ import annotations

import io
import logging
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from embodmocap.body.joints import SMPL_PARENTS
from embodmocap.errors import InputError

log = logging.getLogger(__name__)

#: Keys every body model file must have.
REQUIRED_KEYS: tuple[str, ...] = (
    "v_template", "f", "J_regressor", "weights", "kintree_table", "shapedirs", "posedirs",
)
#: Optional keys kept when present (metadata of the generated test model, or a user's own ids).
OPTIONAL_KEYS: tuple[str, ...] = (
    "vertex_ids", "vertex_id_names", "joint_names", "part_ids", "part_names", "gender",
    "generator", "version", "seed",
)

_FIX = "use an SMPL model file (.pkl or .npz, 24 joints) or write one with `embodmocap body make-test-model`"

_NUMPY_MODULES = {
    "numpy", "numpy.core.multiarray", "numpy._core.multiarray", "numpy.core.numeric",
    "numpy._core.numeric",
}
_NUMPY_NAMES = {"_reconstruct", "scalar", "ndarray", "dtype", "_frombuffer"}
_SPARSE_NAMES = {
    "csc_matrix", "csr_matrix", "coo_matrix", "lil_matrix", "csc_array", "csr_array", "coo_array",
}
_BUILTIN_NAMES = {"object", "set", "frozenset", "slice", "complex"}


class _ChumpyStandIn:
    """Takes the place of any chumpy class while unpickling; keeps the pickled state."""

    def __new__(cls, *args: Any, **kwargs: Any) -> "_ChumpyStandIn":
        obj = super().__new__(cls)
        obj.state = None
        return obj

    def __setstate__(self, state: Any) -> None:
        # A (dict, slots) pair is what pickle hands over for classes with __slots__.
        self.state = state[0] if isinstance(state, tuple) and len(state) == 2 else state

    def array(self) -> np.ndarray | None:
        """The array a plain ``chumpy.Ch`` holds, or None for a chumpy expression."""
        x = self.state.get("x") if isinstance(self.state, dict) else None
        if isinstance(x, _ChumpyStandIn):
            return x.array()
        return None if x is None else np.asarray(x)


class _ModelUnpickler(pickle.Unpickler):
    """Unpickler for SMPL model files: chumpy stand-ins and an allow-list of globals."""

    def find_class(self, module: str, name: str) -> Any:
        module = {"__builtin__": "builtins", "copy_reg": "copyreg"}.get(module, module)
        if module == "chumpy" or module.startswith("chumpy."):
            return _ChumpyStandIn
        if module in _NUMPY_MODULES and name in _NUMPY_NAMES:
            # numpy 2 moved numpy.core to numpy._core; pickles from numpy 1 name the old path.
            return super().find_class(module.replace("numpy.core", "numpy._core"), name)
        if module.startswith("scipy.sparse") and name in _SPARSE_NAMES:
            import scipy.sparse

            return getattr(scipy.sparse, name)
        # _codecs.encode rebuilds byte strings in protocol 0-2 pickles written by Python 3.
        safe = {("copyreg", "_reconstructor"), ("_codecs", "encode")}
        if (module, name) in safe or (module == "builtins" and name in _BUILTIN_NAMES):
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} from a body model file")


def _to_array(value: Any) -> Any:
    """Chumpy stand-ins and sparse matrices to dense numpy arrays; other values unchanged."""
    if isinstance(value, _ChumpyStandIn):
        return value.array()
    if hasattr(value, "toarray") and hasattr(value, "nnz"):  # any scipy.sparse matrix or array
        return np.asarray(value.toarray())
    return value


def read_smpl_pickle(path: str | Path) -> dict[str, Any]:
    """Read an SMPL ``.pkl`` (Python 2 or 3, with or without chumpy) into a dict.

    Chumpy arrays and sparse matrices become dense numpy arrays; a chumpy *expression* (not a
    plain array) becomes None. Other values (strings, dicts) are returned as they are.
    """
    path = Path(path)
    try:
        data = _ModelUnpickler(io.BytesIO(path.read_bytes()), encoding="latin1").load()
    except FileNotFoundError:
        raise InputError(path, "body model file not found", _FIX) from None
    except Exception as err:  # any unpickling failure means the file is not a model pickle
        raise InputError(path, f"cannot read as an SMPL pickle: {err}", _FIX) from err
    if not isinstance(data, dict):
        raise InputError(path, f"the pickle holds a {type(data).__name__}, not a dict of model arrays", _FIX)
    return {str(k): _to_array(v) for k, v in data.items()}


def _read_npz(path: Path) -> dict[str, Any]:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise InputError(path, "body model file not found", _FIX) from None
    except ValueError as err:  # object arrays (pickled inside the npz) or a corrupt archive
        raise InputError(path, f"cannot read the .npz: {err}", "re-save it with plain numeric/string arrays") from err
    except Exception as err:
        raise InputError(path, f"not a readable .npz archive: {err}", _FIX) from err


def load_model_arrays(path: str | Path) -> dict[str, np.ndarray]:
    """Read and check a body model file (.pkl or .npz) -> dict of numpy arrays.

    Returned keys: :data:`REQUIRED_KEYS` (float64 arrays; ``f`` and ``kintree_table`` int64) and
    those of :data:`OPTIONAL_KEYS` the file has. Raises :class:`InputError` naming the file and
    the missing keys or wrong shapes.
    """
    path = Path(path)
    if path.suffix.lower() == ".npz":
        raw = _read_npz(path)
    elif path.suffix.lower() in (".pkl", ".pickle"):
        raw = read_smpl_pickle(path)
    else:
        raise InputError(path, f"unknown body model file type '{path.suffix}'", "give a .pkl or .npz file")
    return check_model_arrays(raw, path)


def check_model_arrays(raw: dict[str, Any], path: str | Path | None = None) -> dict[str, np.ndarray]:
    """Check keys, shapes and values of model arrays; return them with canonical dtypes."""
    missing = [k for k in REQUIRED_KEYS if k not in raw]
    if missing:
        raise InputError(path, f"body model lacks required keys {missing}", _FIX)
    unusable = [k for k in REQUIRED_KEYS if raw[k] is None]
    if unusable:
        raise InputError(path, f"keys {unusable} are chumpy expressions, not arrays", "export the model's arrays with numpy first")
    style = raw.get("bs_style")
    if style is not None and str(np.asarray(style)) != "lbs":
        raise InputError(path, f"blend skinning style '{style}' is not supported", "use an LBS SMPL model")

    out: dict[str, np.ndarray] = {}
    try:
        for k in REQUIRED_KEYS:
            integral = k in ("f", "kintree_table")
            out[k] = np.asarray(raw[k], dtype=np.int64 if integral else np.float64)
    except (TypeError, ValueError) as err:
        raise InputError(path, f"body model arrays are not numeric: {err}", _FIX) from err

    V = out["v_template"].shape[0] if out["v_template"].ndim == 2 else -1
    nb = out["shapedirs"].shape[-1] if out["shapedirs"].ndim == 3 else 0
    expected = {
        "v_template": (V, 3), "f": (out["f"].shape[0], 3), "J_regressor": (24, V),
        "weights": (V, 24), "kintree_table": (2, 24), "shapedirs": (V, 3, nb), "posedirs": (V, 3, 207),
    }
    wrong = [f"{k} {out[k].shape} (expected {expected[k]})" for k in REQUIRED_KEYS if out[k].shape != expected[k]]
    if V < 1 or nb < 1 or wrong:
        raise InputError(path, f"body model arrays have wrong shapes: {', '.join(wrong) or 'empty mesh or shape space'}", _FIX)
    bad = [k for k in REQUIRED_KEYS if not np.all(np.isfinite(out[k]))]
    if bad:
        raise InputError(path, f"body model arrays {bad} contain NaN or inf", _FIX)
    if out["f"].min() < 0 or out["f"].max() >= V:
        raise InputError(path, f"faces index vertices outside 0..{V - 1}", _FIX)
    parents = out["kintree_table"][0].copy()
    parents[0] = -1  # official files store the root's parent as 2**32 - 1
    if tuple(parents.tolist()) != SMPL_PARENTS:
        raise InputError(path, "kintree_table is not SMPL's 24-joint tree", _FIX)
    out["kintree_table"][0] = parents

    for k in OPTIONAL_KEYS:
        if k in raw and raw[k] is not None:
            out[k] = np.asarray(raw[k])
    if "vertex_ids" in out:
        ids = out["vertex_ids"]
        names = out.get("vertex_id_names")
        if names is None or ids.shape != names.shape or ids.ndim != 1 or ids.min() < 0 or ids.max() >= V:
            raise InputError(path, "vertex_ids must be (K,) ids in range with matching vertex_id_names (K,)", _FIX)
    log.debug("body model %s: %d vertices, %d faces, %d betas", path, V, len(out["f"]), nb)
    return out
