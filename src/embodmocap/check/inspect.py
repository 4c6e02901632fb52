"""``embodmocap inspect PATH``: what a capture or a session holds, and every problem found.

Nothing stops at the first problem: each capture, every perception file, the body model, the
manifest and the session folder's write access are checked and all problems are listed, so a user
fixes a session in one pass (session checks in ``inspect_session``).
"""

from __future__ import annotations

from pathlib import Path

from embodmocap.errors import EmbodMocapError
from embodmocap.io.captures import closest_layout, detect_format
from embodmocap.io.inspect_capture import check_capture, format_report
from embodmocap.io.layout import SessionLayout


def inspect_path(path: str | Path) -> tuple[str, list[str]]:
    """Return ``(printable text, problems)`` for a capture folder or a session folder."""
    path = Path(path)
    if not path.exists():
        return f"{path}: does not exist", [f"{path}: does not exist"]
    if (path / "session.toml").is_file():
        return _inspect_session(path)
    if detect_format(path) is None:
        msg = (f"{path}: neither a session (no session.toml) nor a capture folder of a known format "
               f"(Stray Scanner, Spectacular AI, Record3D): {closest_layout(path)}")
        return msg, [msg]
    report = check_capture(path)
    return format_report(report), list(report.problems)


def _inspect_session(root: Path) -> tuple[str, list[str]]:
    from embodmocap.check import inspect_session as chk
    from embodmocap.io.manifest import read_manifest

    lay = SessionLayout(root)
    lines = [f"session {root}"]
    try:
        manifest, found = read_manifest(lay.manifest)
    except EmbodMocapError as err:
        return "\n".join(lines + [f"  manifest: {err}"]), [str(err)]
    problems = [f"{lay.manifest}: {p}" for p in found]
    body = manifest.body_model or "(generated test model)"
    lines.append(f"  body model: {body}")
    problems += chk.body_model_problems(manifest.body_model)
    problems += chk.writable_problems(root)
    for name, scene in manifest.scenes.items():
        lines.append(f"  scene {name} ({'indoor' if scene.indoor else 'outdoor'}):")
        problems += _add_capture(lines, scene.capture, "    ")
    for name, seq in manifest.sequences.items():
        phones = "; one phone: no sync needed, no triangulation (less accurate)" if seq.one_view else ""
        lines.append(f"  sequence {name} (scene {seq.scene}, {len(seq.contacts)} contact markers{phones})")
        for vname, view in seq.views.items():
            sync = f", sync frame {view.sync_frame}" if view.sync_frame is not None else ""
            lines.append(f"    view {vname}{sync}:")
            problems += _add_capture(lines, view.capture, "      ")
            for label, folder, pattern in (("keypoints", view.keypoints, "*.json"), ("masks", view.masks, "*.png")):
                if folder is not None and Path(folder).is_dir():
                    lines.append(f"      {label}: {sum(1 for _ in Path(folder).glob(pattern))} files in {folder}")
            if view.body_prior is not None:
                ok = Path(view.body_prior).is_file()
                lines.append(f"      body prior: {view.body_prior}{'' if ok else ' (missing)'}")
            problems += chk.view_perception_problems(view)
    if lay.ground_truth.info.is_file():
        lines.append(f"  ground truth: {lay.ground_truth.root}")
    lines.append("")
    lines.append("problems:" if problems else "no problems found")
    lines += [f"  - {p}" for p in problems]
    return "\n".join(lines), problems


def _add_capture(lines: list[str], capture: Path, indent: str) -> list[str]:
    capture = Path(capture)
    if not capture.exists():
        lines.append(f"{indent}{capture}: missing")
        return []  # the manifest check already reported it
    report = check_capture(capture)
    lines += [indent + line for line in format_report(report).splitlines()]
    return list(report.problems)
