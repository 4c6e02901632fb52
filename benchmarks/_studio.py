"""Studio preset names shared by the benchmarks: ``indoor``, ``outdoor``, the harder indoor rooms
(``large``, ``high_ceiling``, ``low_texture``, ``repetitive``), each optionally with ``+light`` (the
sequence filmed under other light than the scene scan), e.g. ``large+light``."""

from __future__ import annotations

from pathlib import Path

ROOMS = ("large", "high_ceiling", "low_texture", "repetitive")


def synth_config(seed: int, preset: str, seconds: float, scene_seconds: float):
    """The :class:`SynthConfig` of a benchmark preset name."""
    from embodmocap.synth.config import SynthConfig

    name, _, extra = preset.partition("+")
    if extra not in ("", "light"):
        raise ValueError(f"unknown preset modifier {extra!r} in {preset!r} (only '+light')")
    room = name if name in ROOMS else "standard"
    kind = "indoor" if name in ROOMS else name
    return SynthConfig(seed=seed, preset=kind, room=room, lighting_change=extra == "light",
                       seconds=seconds, scene_seconds=scene_seconds)


def ensure_session(path: Path, seed: int, preset: str, seconds: float, scene_seconds: float) -> Path:
    """Synthesise the session at ``path`` unless it is already there (sessions are reused)."""
    from embodmocap.synth.studio import synthesize

    if not (path / "ground_truth" / "ground_truth.json").is_file():
        synthesize(synth_config(seed, preset, seconds, scene_seconds), path)
    return path
