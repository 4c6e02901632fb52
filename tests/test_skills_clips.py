"""`embodmocap skills`: the clip finder recovers the studio's scripted interactions (label, frames,
object box, target) from the true motion and the studio's scene mesh (an oracle Stage IV), finds
nothing but follow in a walk-only session, and writes skills.json resumably through the CLI."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from embodmocap.body.model import load_body_model
from embodmocap.skills.config import SkillsConfig
from embodmocap.io.stage_files import SKILLS_FORMAT as FORMAT, read_skills
from embodmocap.skills.stage import clips_of_motion
from skills_truth import FPS, bed_seeds, corner_error, match, scripted, surface_corners

CFG = SkillsConfig()
FOLLOW_MIN = int(round(CFG.follow_min_s * FPS))


@pytest.fixture(scope="module")
def body():
    return load_body_model(None)


@pytest.fixture(scope="module")
def six(body):
    """80 s in a room with a bed: all six interactions scripted (75 s just fit them), and the clips found."""
    built, script = scripted(body, bed_seeds(1)[0], seconds=80.0)
    clips, surfaces = clips_of_motion(script.params, body, built.vertices, built.faces, CFG)
    return built, script, clips, surfaces


def test_every_scripted_interaction_is_found_with_its_label_and_frames(six):
    built, script, clips, _ = six
    assert {c.skill for c in script.clips} == {"follow", "sit", "climb", "lie", "prone", "support"}
    pairs, missed, extra = match(script.clips, clips, tol=10, follow_min_frames=FOLLOW_MIN + int(FPS))
    assert not missed, [(m.skill, m.start, m.end) for m in missed]
    # Nothing but walking is found besides the scripted interactions.
    assert not [f for f in extra if f.skill != "follow"], [(f.skill, f.start, f.end) for f in extra]
    for t, f in pairs:
        assert abs(f.start - t.start) <= 10 and abs(f.end - t.end) <= 10, (t, f.start, f.end)
        if t.skill != "follow":  # the hold lies inside the clip and overlaps the scripted one
            assert f.start <= f.contact_start < f.contact_end <= f.end
            assert min(f.contact_end, t.contact_end) - max(f.contact_start, t.contact_start) > 0


def test_object_box_is_the_scripted_furniture_surface(six):
    built, script, clips, _ = six
    pairs, _, _ = match(script.clips, clips, tol=10, follow_min_frames=FOLLOW_MIN)
    checked = 0
    for t, f in pairs:
        if t.skill == "follow":
            assert f.object is None and f.contact_start is None
            continue
        furn = built.spec.furniture[t.furniture]
        err = corner_error(np.asarray(f.object.corners), surface_corners(furn))
        assert err < 0.05, (t.skill, t.furniture, err)
        assert abs(f.object.top_z - furn.top_z) < 0.02
        checked += 1
    assert checked == 5


def test_targets_follow_the_supplement(six, body):
    built, script, clips, _ = six
    pairs, _, _ = match(script.clips, clips, tol=10, follow_min_frames=FOLLOW_MIN)
    above = {"sit": 0.10, "climb": 0.94, "lie": 0.10, "prone": 0.10, "support": 0.0}
    for t, f in pairs:
        if t.skill == "follow":
            path = np.asarray(f.target.path)
            # Waypoints every 0.1 s along the walked path: as many as the clip's tenths of a second.
            assert len(path) == int(np.ceil((f.end - f.start) / (0.1 * FPS)))
            steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
            assert steps.max() < 0.2  # at most 2 m/s between waypoints 0.1 s apart
            continue
        corners = surface_corners(built.spec.furniture[t.furniture])
        top_centre = np.array([*corners[:, :2].mean(axis=0), corners[:, 2].max()])
        want = top_centre + [0.0, 0.0, above[t.skill]]
        if t.skill == "support":
            # The hand joints' centre over the hold, resting on the top (the part the hands bear on).
            p = script.params
            sl = slice(f.contact_start, f.contact_end)
            with torch.no_grad():
                j = body.forward(p.betas, p.global_orient[sl], p.body_pose[sl], p.transl[sl]).joints.cpu().numpy()
            want = j[:, [22, 23]].mean(axis=(0, 1))
            assert 0.0 < want[2] - corners[:, 2].max() < 0.12  # on the top, not above or inside it
        assert np.linalg.norm(np.asarray(f.target.position) - want) < 0.03, (t.skill, f.target.position, want)
        assert abs(np.linalg.norm(f.target.facing) - 1.0) < 1e-6


def test_parts_in_contact_name_the_interaction(six):
    _, script, clips, _ = six
    parts = {c.skill: set(c.parts) for c in clips if c.skill != "follow"}
    assert "pelvis" in parts["sit"]
    assert "back" in parts["lie"] and "front" in parts["prone"]
    assert {"left_hand", "right_hand"} <= parts["support"]
    assert {"left_foot", "right_foot"} <= parts["climb"]


def test_walk_only_session_has_only_follow_clips(body):
    built, script = scripted(body, 0, interactions=(), seconds=30.0)
    assert {c.skill for c in script.clips} == {"follow"}
    clips, _ = clips_of_motion(script.params, body, built.vertices, built.faces, CFG)
    assert clips and {c.skill for c in clips} == {"follow"}
    pairs, missed, _ = match(script.clips, clips, tol=10, follow_min_frames=FOLLOW_MIN + int(FPS))
    assert not missed


def test_default_script_is_unchanged_and_labels_its_clips(body):
    """The default interactions (chair, box, table, sofa) script what they always did; their
    clips are labelled sit / climb / support."""
    built, script = scripted(body, 0, interactions=("chair", "box", "table", "sofa"), seconds=20.0)
    names = [n for n, _, _ in script.segments]
    assert "lie" not in names and "prone" not in names and "follow" not in names
    skills = {c.skill for c in script.clips}
    assert skills <= {"follow", "sit", "climb", "support"} and skills - {"follow"}


# --------------------------------------------------------------------------------------------
# the command on a session


@pytest.fixture(scope="module")
def session(tmp_path_factory, body):
    """A session folder with the studio scene mesh, the test body model and a scripted sit + climb
    motion written as Stage IV's smpl_world.npz (the truth as the fit)."""
    from embodmocap.body.testmodel import write_test_model
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.smpl_file import write_smpl_npz
    from embodmocap.synth.scene import write_scene_ply

    root = tmp_path_factory.mktemp("skills") / "sess"
    (root / "captures" / "scene").mkdir(parents=True)
    (root / "captures" / "seq" / "v1").mkdir(parents=True)
    (root / "captures" / "seq" / "v2").mkdir(parents=True)
    (root / "session.toml").write_text(
        'version = 1\nbody_model = "body_model.npz"\n[scenes.room]\ncapture = "captures/scene"\n'
        '[sequences.seq]\nscene = "room"\n[sequences.seq.views.v1]\ncapture = "captures/seq/v1"\n'
        '[sequences.seq.views.v2]\ncapture = "captures/seq/v2"\n')
    write_test_model(root / "body_model.npz")
    built, script = scripted(body, 0, interactions=("sit", "climb"), seconds=25.0)
    lay = SessionLayout(root)
    write_scene_ply(built, lay.scene("room").mesh_raw)
    write_smpl_npz(lay.sequence("seq").smpl_world, script.params)
    return root, script


def test_cli_writes_skills_json_and_resumes(session):
    from embodmocap.cli import main

    root, script = session
    path = root / "sequences" / "seq" / "skills" / "skills.json"
    assert main(["skills", str(root)]) == 0
    raw = json.loads(path.read_text())
    assert raw["format"] == FORMAT and raw["sequence"] == "seq" and raw["n_frames"] == len(script.params)
    assert raw["fps"] == FPS and raw["config"]["follow_min_s"] == CFG.follow_min_s
    sf = read_skills(path)
    pairs, missed, extra = match([c for c in script.clips if c.skill != "follow"],
                                 [c for c in sf.clips if c.skill != "follow"], 10, FOLLOW_MIN)
    assert not missed and not extra
    for c in raw["clips"]:
        assert set(c) == {"id", "skill", "start", "end", "contact_start", "contact_end", "object", "target", "parts", "score"}
        assert 0.0 <= c["score"] <= 1.0
        if c["object"] is not None:
            o = c["object"]
            assert np.asarray(o["corners"]).shape == (8, 3) and np.asarray(o["R_world_box"]).shape == (3, 3)
    # A second run finds it up to date and leaves the file alone; --force redoes it, same bytes.
    before = path.read_bytes()
    mtime = path.stat().st_mtime_ns
    assert main(["skills", str(root), "--seq", "seq"]) == 0
    assert path.stat().st_mtime_ns == mtime
    assert main(["skills", str(root), "--force"]) == 0
    assert path.read_bytes() == before


def test_cli_names_a_missing_motion(session, tmp_path, capsys):
    from embodmocap.cli import main

    root, _ = session
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    (copy / "sequences" / "seq" / "smpl_world.npz").unlink()
    assert main(["skills", str(copy)]) == 2
    err = capsys.readouterr().err
    assert "smpl_world.npz" in err and "embodmocap motion" in err


def test_reader_rejects_a_broken_file(tmp_path, session):
    from embodmocap.errors import InputError

    root, _ = session
    src = root / "sequences" / "seq" / "skills" / "skills.json"
    if not src.is_file():
        from embodmocap.cli import main

        assert main(["skills", str(root)]) == 0
    d = json.loads(src.read_text())
    bad = tmp_path / "skills.json"
    d["clips"][0]["skill"] = "dance"
    bad.write_text(json.dumps(d))
    with pytest.raises(InputError, match="unknown skill"):
        read_skills(bad)
    d["format"] = "other/9"
    bad.write_text(json.dumps(d))
    with pytest.raises(InputError, match="format"):
        read_skills(bad)


# --------------------------------------------------------------------------------------------
# report and viewer


def test_report_section_lists_the_clips(session, tmp_path):
    from embodmocap.cli import main
    from embodmocap.evaluate.report import _Page, _skills_section

    root, _ = session
    path = root / "sequences" / "seq" / "skills" / "skills.json"
    if not path.is_file():
        assert main(["skills", str(root)]) == 0
    sf = read_skills(path)
    page = _Page(tmp_path, [], [])
    _skills_section(page, path, "seq")
    html = "".join(page.html_parts)
    assert "Skill clips" in html and html.count("data:image/png;base64,") == 1
    for c in sf.clips:
        assert f">{c.id}<" in html
    assert (tmp_path / "seq_skills.png").is_file()


def test_viewer_draws_the_clip_boxes_and_lists_the_clips(tmp_path_factory, body):
    """The viewer on the tiny Stage IV session with a skills.json found on its own scene mesh: one
    box per clip object (12 edges in the skill's colour), the targets, a clip list that moves the
    timeline to the chosen clip."""
    pytest.importorskip("viser")
    import socket

    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.mesh_file import read_mesh_ply
    from embodmocap.skills.contact import find_surfaces
    from embodmocap.io.stage_files import SkillClip, SkillObject, SkillsFile, SkillTarget, write_skills
    from embodmocap.viz.skills_layer import SKILL_RGB
    from embodmocap.viz.viewer import ViewerConfig, serve
    from stage4_session import SYNTH, make_stage4_session

    root = tmp_path_factory.mktemp("skills_viewer") / "session"
    make_stage4_session(root)
    lay = SessionLayout(root)
    v, f, _ = read_mesh_ply(lay.scene(SYNTH.scene_name).mesh_raw)
    boxes = find_surfaces(v, f, 0.0).boxes[:2]
    clips = [SkillClip(f"sit_{i:02d}", "sit", 2 * i, 2 * i + 4, 2 * i + 1, 2 * i + 3, SkillObject.of_box(b, None),
                       SkillTarget([float(b.center[0]), float(b.center[1]), b.top_z + 0.1], None, [1.0, 0.0]), ["pelvis"])
             for i, b in enumerate(boxes)]
    write_skills(lay.sequence(SYNTH.sequence_name).root / "skills" / "skills.json",
                 SkillsFile(root.name, SYNTH.sequence_name, SYNTH.fps, 10, clips))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    handle = serve(root, SYNTH.sequence_name, ViewerConfig(port=port, max_image_side=0))
    try:
        lines = handle.nodes["skills"]["/skills/boxes"]
        assert lines.points.shape == (12 * len(clips), 2, 3)
        np.testing.assert_allclose(lines.points[:12].reshape(-1, 3).min(0), np.min(clips[0].object.corners, 0), atol=1e-5)
        assert tuple(np.asarray(lines.colors)[0, 0]) == SKILL_RGB["sit"]
        assert len(handle.nodes["skills"]["/skills/targets"].points) == len(clips)
        dd = handle._gui["clips"]
        dd.value = dd.options[-1]
        deadline = __import__("time").monotonic() + 5
        while handle.frame != clips[-1].start and __import__("time").monotonic() < deadline:
            __import__("time").sleep(0.05)
        assert handle.frame == clips[-1].start
    finally:
        handle.stop()
