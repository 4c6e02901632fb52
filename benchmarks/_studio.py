"""Studio preset names shared by the benchmarks: ``indoor``, ``outdoor``, the harder indoor rooms
(``large``, ``high_ceiling``, ``low_texture``, ``repetitive``), each optionally with ``+light`` (the
sequence filmed under other light than the scene scan), e.g. ``large+light``, and ``+outward`` (the
scene scan before session 6, looking only outwards: ``SynthConfig.scan_turns_per_lap=0``) and
``+vio`` (Stage III's hard camera preset: ``SynthConfig.cameras="hard"``, the views' VIO with a
scale error and drift that grow with the path), e.g. ``outdoor+vio``."""

from __future__ import annotations

from pathlib import Path

ROOMS = ("large", "high_ceiling", "low_texture", "repetitive")


def synth_config(seed: int, preset: str, seconds: float, scene_seconds: float):
    """The :class:`SynthConfig` of a benchmark preset name."""
    from embodmocap.synth.config import SynthConfig

    name, *extra = preset.split("+")
    if set(extra) - {"light", "outward", "vio"}:
        raise ValueError(f"unknown preset modifier in {preset!r} (only '+light', '+outward', '+vio')")
    room = name if name in ROOMS else "standard"
    kind = "indoor" if name in ROOMS else name
    # "+outward": the scene scan of before session 6, which only looks outwards at the walls.
    return SynthConfig(seed=seed, preset=kind, room=room, lighting_change="light" in extra,
                       seconds=seconds, scene_seconds=scene_seconds, scan_turns_per_lap=0.0 if "outward" in extra else 1.0,
                       cameras="hard" if "vio" in extra else "standard")


def ensure_session(path: Path, seed: int, preset: str, seconds: float, scene_seconds: float) -> Path:
    """Synthesise the session at ``path`` unless it is already there (sessions are reused)."""
    from embodmocap.synth.studio import synthesize

    if not (path / "ground_truth" / "ground_truth.json").is_file():
        synthesize(synth_config(seed, preset, seconds, scene_seconds), path)
    return path
