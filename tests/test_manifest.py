"""Session manifest: strict loading, validation and the TOML round trip."""

from __future__ import annotations

from pathlib import Path

import pytest

from embodmocap.errors import InputError
from embodmocap.io.manifest import (
    ContactMarker,
    ManifestError,
    SceneEntry,
    SequenceEntry,
    SessionManifest,
    ViewEntry,
    load_manifest,
    validate_manifest,
    write_manifest,
)

GOOD = """\
version = 1
body_model = "body_model.npz"
[scenes.room]
capture = "captures/room"
indoor = false
[scenes.room.markers]
door = [1.5, -2, 0.25]
[sequences.seq0]
scene = "room"
contacts = [{frame = 120, xyz = [1.0, 2.0, 0.0]}, {frame = 300, marker = "door"}]
note = "first take"
[sequences.seq0.views.v1]
capture = "captures/seq0/v1"
sync_frame = 57
keypoints = "perception/seq0/v1/keypoints"
masks = "perception/seq0/v1/masks"
body_prior = "perception/seq0/v1/body_prior.npz"
[sequences.seq0.views.v2]
capture = "captures/seq0/v2"
"""

FOLDERS = (
    "captures/room", "captures/seq0/v1", "captures/seq0/v2",
    "perception/seq0/v1/keypoints", "perception/seq0/v1/masks",
)


@pytest.fixture
def session(tmp_path: Path) -> Path:
    for folder in FOLDERS:
        (tmp_path / folder).mkdir(parents=True)
    (tmp_path / "perception/seq0/v1/body_prior.npz").write_bytes(b"x")
    (tmp_path / "body_model.npz").write_bytes(b"x")
    (tmp_path / "session.toml").write_text(GOOD)
    return tmp_path


def _load_with(session: Path, text: str) -> ManifestError:
    (session / "session.toml").write_text(text)
    with pytest.raises(ManifestError) as info:
        load_manifest(session / "session.toml")
    assert isinstance(info.value, InputError)
    assert str(session / "session.toml") in str(info.value)
    return info.value


def test_load_resolves_everything(session: Path) -> None:
    m = load_manifest(session)  # the folder works as well as the file
    assert m.root == session
    assert m.version == 1 and m.gender == "neutral"
    assert m.body_model == session / "body_model.npz"
    room = m.scenes["room"]
    assert room.capture == session / "captures/room" and room.indoor is False
    assert room.markers == {"door": (1.5, -2.0, 0.25)}
    seq = m.sequences["seq0"]
    assert seq.scene == "room" and seq.note == "first take" and not seq.failed and not seq.optim_scale
    assert seq.subframe_sync and not seq.sync_force  # the defaults: sub-frame part applied, nothing forced
    assert seq.contacts == (
        ContactMarker(120, (1.0, 2.0, 0.0)),
        ContactMarker(300, (1.5, -2.0, 0.25), marker="door"),
    )
    v1, v2 = seq.views["v1"], seq.views["v2"]
    assert v1.sync_frame == 57 and v2.sync_frame is None
    assert v1.keypoints == session / "perception/seq0/v1/keypoints"
    assert v1.body_prior == session / "perception/seq0/v1/body_prior.npz"
    assert v2.capture == session / "captures/seq0/v2" and v2.masks is None
    assert validate_manifest(m) == []


def test_round_trip(session: Path, tmp_path: Path) -> None:
    m = load_manifest(session / "session.toml")
    out = session / "session.toml"
    out.unlink()
    assert write_manifest(m) == out
    text = out.read_text()
    assert str(session) not in text  # paths inside the session are stored relative
    again = load_manifest(out)
    assert again == m
    # The session folder can move: relative paths follow it.
    moved = tmp_path.parent / (tmp_path.name + "_moved")
    session.rename(moved)
    assert load_manifest(moved).scenes["room"].capture == moved / "captures/room"


def test_round_trip_of_a_built_manifest_with_outside_path(tmp_path: Path) -> None:
    outside = tmp_path / "elsewhere" / "room"
    outside.mkdir(parents=True)
    root = tmp_path / "sess"
    for v in ("v1", "v2"):
        (root / "cap" / v).mkdir(parents=True)
    m = SessionManifest(
        root=root,
        scenes={"room": SceneEntry("room", outside, indoor=True, markers={"7": [0, 1, 2]})},
        sequences={
            "s": SequenceEntry(
                name="s", scene="room",
                views={v: ViewEntry(capture=Path("cap") / v) for v in ("v1", "v2")},
                contacts=[ContactMarker(5, [0, 1, 2], marker="7"), ContactMarker(9, (3, 4, 5))],
                optim_scale=True, failed=True, note="n", subframe_sync=False, sync_force=True,
            )
        },
        gender="female",
    )
    assert m.sequences["s"].views["v1"].capture == root / "cap/v1"  # relative resolved at build
    assert validate_manifest(m) == []
    path = write_manifest(m)
    assert str(outside) in path.read_text()  # outside the root: absolute
    assert load_manifest(path) == m
    assert [s.name for s in m.active_sequences()] == [] and len(m.active_sequences(force=True)) == 1


@pytest.mark.parametrize(
    "old, new, key",
    [
        ("version = 1\n", "version = 1\ncolour = 3\n", "colour: unknown key"),
        ("indoor = false\n", "indoor = false\nfloor = 0\n", "scenes.room.floor: unknown key"),
        ("sync_frame = 57\n", "sync_frame = 57\nfps = 30\n", "sequences.seq0.views.v1.fps: unknown key"),
        ('note = "first take"\n', 'note = "first take"\nextra = 1\n', "sequences.seq0.extra: unknown key"),
        ("{frame = 120, xyz", "{frame = 120, when = 3, xyz", "sequences.seq0.contacts[0].when: unknown key"),
    ],
)
def test_unknown_keys(session: Path, old: str, new: str, key: str) -> None:
    err = _load_with(session, GOOD.replace(old, new, 1))
    assert any(p.startswith(key) for p in err.problems), err.problems
    assert "allowed:" in str(err)


def test_missing_capture_folder(session: Path) -> None:
    err = _load_with(session, GOOD.replace("captures/seq0/v2", "captures/nope"))
    assert err.problems == [f"sequences.seq0.views.v2.capture: capture does not exist: {session / 'captures/nope'} "
                            "(the folder the phone app exported, or a Record3D .r3d file)"]


def test_missing_perception_and_body_model(session: Path) -> None:
    (session / "body_model.npz").unlink()
    err = _load_with(session, GOOD.replace("v1/masks", "v1/maskz"))
    keys = sorted(p.split(":")[0] for p in err.problems)
    assert keys == ["body_model", "sequences.seq0.views.v1.masks"]


def test_unknown_scene(session: Path) -> None:
    err = _load_with(session, GOOD.replace('scene = "room"', 'scene = "kitchen"'))
    assert len(err.problems) == 1
    assert err.problems[0].startswith("sequences.seq0.scene: unknown scene 'kitchen'")


@pytest.mark.parametrize(
    "old, new, key, expected",
    [
        ("sync_frame = 57", 'sync_frame = "57"', "sequences.seq0.views.v1.sync_frame", "an integer"),
        ("indoor = false", 'indoor = "no"', "scenes.room.indoor", "a boolean"),
        ("version = 1", "version = true", "version", "an integer"),
        ("[1.5, -2, 0.25]", "[1.5, -2]", "scenes.room.markers.door", "a list of 3 finite numbers"),
        ('capture = "captures/room"', "capture = 3", "scenes.room.capture", "a path string"),
        ('note = "first take"', 'note = "first take"\nsubframe_sync = "no"', "sequences.seq0.subframe_sync", "a boolean"),
        ('note = "first take"', 'note = "first take"\nsync_force = 1', "sequences.seq0.sync_force", "a boolean"),
    ],
)
def test_wrong_types(session: Path, old: str, new: str, key: str, expected: str) -> None:
    err = _load_with(session, GOOD.replace(old, new, 1))
    assert any(p.startswith(f"{key}: expected {expected}") for p in err.problems), err.problems
    # A scene that failed to parse must not make its sequence report an unknown scene too.
    assert not any("unknown scene" in p for p in err.problems)


def test_three_views(session: Path) -> None:
    err = _load_with(session, GOOD + '[sequences.seq0.views.v3]\ncapture = "captures/seq0/v1"\n')
    assert any(p.startswith("sequences.seq0.views.v3: unknown view") for p in err.problems)


def test_one_view_and_missing_required(session: Path) -> None:
    text = GOOD.split("[sequences.seq0.views.v2]")[0].replace('scene = "room"\n', "")
    err = _load_with(session, text)
    assert "sequences.seq0.scene: missing required key" in err.problems


def test_all_problems_reported_at_once(session: Path) -> None:
    text = (
        GOOD.replace("version = 1", "version = 2\nwho = 1")
        .replace("captures/room", "captures/none")
        .replace('marker = "door"', 'marker = "window"')
        .replace("sync_frame = 57", "sync_frame = -3")
    )
    err = _load_with(session, text)
    keys = sorted(p.split(":")[0] for p in err.problems)
    assert keys == [
        "scenes.room.capture",
        "sequences.seq0.contacts[1].marker",
        "sequences.seq0.views.v1.sync_frame",
        "version",
        "who",
    ]
    assert str(err).count("\n  - ") == 5


def test_contact_needs_exactly_one_of_xyz_or_marker(session: Path) -> None:
    err = _load_with(session, GOOD.replace('{frame = 300, marker = "door"}', '{frame = 300, marker = "door", xyz = [0, 0, 0]}'))
    assert any(p.startswith("sequences.seq0.contacts[1]: give exactly one") for p in err.problems)


def test_bad_names_and_gender(session: Path) -> None:
    err = _load_with(session, 'gender = "robot"\n' + GOOD.replace("[sequences.seq0]", '[sequences.".."]')
                     .replace("sequences.seq0.views", 'sequences."..".views'))
    keys = sorted(p.split(":")[0] for p in err.problems)
    assert keys == ["gender", "sequences..."]


def test_not_toml_and_missing_file(session: Path) -> None:
    (session / "session.toml").write_text("version = = 1\n")
    with pytest.raises(InputError, match="not valid TOML"):
        load_manifest(session / "session.toml")
    with pytest.raises(InputError, match="session manifest not found"):
        load_manifest(session / "other.toml")


def test_loading_does_not_modify_the_file(session: Path) -> None:
    before = (session / "session.toml").read_bytes()
    load_manifest(session)
    assert (session / "session.toml").read_bytes() == before


def test_synthesised_into_a_relative_folder_the_manifest_finds_everything(tmp_path, monkeypatch):
    """`embodmocap demo` writes to the relative folder demo_out: every path in its manifest must
    resolve inside that folder (not inside demo_out/demo_out)."""
    from embodmocap.io.manifest import validate_manifest
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    monkeypatch.chdir(tmp_path)
    synthesize(SynthConfig(seconds=1.0, scene_seconds=1.0, fps=10, width=160, height=120, depth_width=64,
                           depth_height=48), "rel")
    m = load_manifest(tmp_path / "rel" / "session.toml")
    assert validate_manifest(m) == []
    assert m.scenes["scene0"].capture == tmp_path / "rel" / "captures" / "scene0"
    assert 'capture = "captures/scene0"' in (tmp_path / "rel" / "session.toml").read_text()
