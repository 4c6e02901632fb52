"""Import of release-style XLSX/CSV sheets into a session manifest."""

from __future__ import annotations

import csv
import logging
from pathlib import Path

import openpyxl
import pytest

from embodmocap.errors import InputError
from embodmocap.io.manifest import ContactMarker, load_manifest
from embodmocap.io.sheet_import import import_sheet, import_sheet_cli

HEADER = ["scene_folder", "seq_name", "in_door", "v1_start", "v2_start", "character", "skills",
          "keyframes", "FAILED", "note", "contacts", "optim_scale", "vertical"]


def _make_folders(root: Path, scene_folder: str, seqs: list[str]) -> None:
    (root / scene_folder).mkdir(parents=True, exist_ok=True)
    for seq in seqs:
        for raw in ("raw1", "raw2"):
            (root / scene_folder / seq / raw).mkdir(parents=True, exist_ok=True)


def _write_xlsx(path: Path, sheets: dict[str, list[list[object]]]) -> Path:
    book = openpyxl.Workbook()
    book.remove(book.active)
    for title, rows in sheets.items():
        ws = book.create_sheet(title)
        for row in rows:
            ws.append(row)
    book.save(path)
    return path


def _write_csv(path: Path, rows: list[list[object]], delimiter: str = ",") -> Path:
    with open(path, "w", newline="", encoding="utf-8-sig") as f:
        csv.writer(f, delimiter=delimiter).writerows(rows)
    return path


def _row(scene: str, seq: str, **cells: object) -> list[object]:
    values = {"scene_folder": scene, "seq_name": seq, **cells}
    return [values.get(h, values.get(h.lower())) for h in HEADER]


@pytest.fixture
def xlsx_session(tmp_path: Path) -> tuple[Path, Path]:
    root = tmp_path / "session"
    _make_folders(root, "data/0618livingroom", ["seq0", "seq1"])
    _make_folders(root, "data/0619garden", ["seq0"])
    sheets = {
        "day1": [
            HEADER,
            _row("data/0618livingroom", "seq0", in_door=True, v1_start=57, v2_start="-", FAILED="FALSE",
                 note="good", contacts="[[120, [1.0, 2.0, 0.0]], [300, 1]]", optim_scale="1.0", vertical="TRUE"),
            [None] * len(HEADER),  # a blank row in the middle is skipped
            _row("data/0618livingroom", "seq1", in_door="TRUE", v1_start=61.0, v2_start="63",
                 FAILED="TRUE", contacts="[]", optim_scale=False),
        ],
        "day2": [
            HEADER,
            _row("data/0619garden", "seq0", in_door="False", v1_start=-1, v2_start=None, FAILED="0",
                 note="dot not visible", contacts="[[10, 0]]", optim_scale="0"),
        ],
        "contact": [
            ["scene", "contacts"],
            ["data/0618livingroom", "[[0.5, 0.5, 0.0], [3.0, -1.0, 0.0]]"],
            ["data/0619garden", "[(9, 8, 0)]"],
        ],
    }
    return _write_xlsx(tmp_path / "seq_info.xlsx", sheets), root


def test_xlsx_import(xlsx_session: tuple[Path, Path]) -> None:
    sheet, root = xlsx_session
    m = import_sheet(sheet, root)
    assert m.root == root
    # The `contact` sheet does not become pseudo-sequences; the same seq_name in two scenes
    # gets the scene name as prefix.
    assert list(m.scenes) == ["0618livingroom", "0619garden"]
    assert list(m.sequences) == ["0618livingroom_seq0", "seq1", "0619garden_seq0"]

    room, garden = m.scenes["0618livingroom"], m.scenes["0619garden"]
    assert room.capture == root / "data/0618livingroom" and room.indoor is True
    assert garden.indoor is False
    assert room.markers == {"0": (0.5, 0.5, 0.0), "1": (3.0, -1.0, 0.0)}
    assert garden.markers == {"0": (9.0, 8.0, 0.0)}

    s0 = m.sequences["0618livingroom_seq0"]
    assert s0.scene == "0618livingroom"
    assert s0.views["v1"].capture == root / "data/0618livingroom/seq0/raw1"
    assert s0.views["v2"].capture == root / "data/0618livingroom/seq0/raw2"
    assert (s0.views["v1"].sync_frame, s0.views["v2"].sync_frame) == (57, None)
    assert s0.contacts == (ContactMarker(120, (1.0, 2.0, 0.0)), ContactMarker(300, (3.0, -1.0, 0.0), marker="1"))
    assert s0.optim_scale is True and s0.failed is False and s0.note == "good"

    s1 = m.sequences["seq1"]
    assert (s1.views["v1"].sync_frame, s1.views["v2"].sync_frame) == (61, 63)
    assert s1.failed is True and s1.optim_scale is False and s1.contacts == ()

    g = m.sequences["0619garden_seq0"]
    assert g.failed is True  # v1_start = -1: the release skips the row
    assert g.note == "dot not visible; skipped: v1_start = -1 in the sheet"
    assert g.views["v1"].sync_frame is None
    assert g.contacts == (ContactMarker(10, (9.0, 8.0, 0.0), marker="0"),)


def test_cli_writes_loadable_manifest(xlsx_session: tuple[Path, Path]) -> None:
    sheet, root = xlsx_session
    before = sheet.read_bytes()
    path = import_sheet_cli(sheet, root)
    assert path == root / "session.toml"
    assert load_manifest(path) == import_sheet(sheet, root)
    assert sheet.read_bytes() == before
    with pytest.raises(InputError, match="already exists"):
        import_sheet_cli(sheet, root)
    path.write_text("old")
    import_sheet_cli(sheet, root, force=True)
    assert load_manifest(path).sequences["seq1"].failed


def test_cli_check_refuses_missing_folders(tmp_path: Path) -> None:
    sheet = _write_csv(tmp_path / "s.csv", [HEADER, _row("scene", "seq0")])
    with pytest.raises(InputError, match="capture does not exist") as info:
        import_sheet_cli(sheet, tmp_path / "sess")
    assert "sequences.seq0.views.v1.capture" in str(info.value)
    assert not (tmp_path / "sess" / "session.toml").exists()
    assert import_sheet_cli(sheet, tmp_path / "sess", check=False).is_file()


def test_views_recorded_as_r3d_files_import_and_pass_the_check(tmp_path: Path) -> None:
    """Record3D phones: each view a .r3d file, named by the capture pattern, passes the folder check."""
    root = tmp_path / "sess"
    (root / "hall" / "seq0").mkdir(parents=True)
    for v in ("v1", "v2"):
        (root / "hall" / "seq0" / f"{v}.r3d").write_bytes(b"PK")  # the check looks for the file only
    sheet = _write_csv(tmp_path / "s.csv", [HEADER, _row("hall", "seq0")])
    path = import_sheet_cli(sheet, root, capture_pattern="{scene_folder}/{seq_name}/{view}.r3d")
    views = load_manifest(path).sequences["seq0"].views
    assert views["v2"].capture == root / "hall" / "seq0" / "v2.r3d"
    # A video named as a view is refused with what a capture is.
    (root / "hall" / "seq0" / "v1.mp4").write_bytes(b"")
    with pytest.raises(InputError, match=r"v1.mp4 is a file, not a capture"):
        import_sheet_cli(sheet, tmp_path / "sess", capture_pattern="{scene_folder}/{seq_name}/{view}.mp4", force=True)


def test_csv_import_with_pattern_and_contact_csv(tmp_path: Path) -> None:
    root = tmp_path / "s"
    rows = [
        HEADER,
        _row("/abs/room", "take1", in_door="true", v1_start="10", v2_start="12.0", FAILED="",
             contacts='[[5, 0], [6, [0, 0, 1]]]', note="multi\nline"),
        _row("/abs/room", "take2", in_door="FALSE", v1_start="-", v2_start="", FAILED="False"),
    ]
    sheet = _write_csv(tmp_path / "seq.csv", rows, delimiter=";")
    contact = _write_csv(tmp_path / "contact.csv", [["scene", "contacts"], ["room", "[[1, 2, 3]]"]])
    m = import_sheet(sheet, root, capture_pattern="rec/{scene}/{seq_name}_{view}", contact_sheet=contact)
    t1 = m.sequences["take1"]
    assert m.scenes["room"].capture == Path("/abs/room")
    assert m.scenes["room"].indoor is True  # from the first row (the second disagrees: warning)
    assert t1.views["v2"].capture == root / "rec/room/take1_v2"
    assert (t1.views["v1"].sync_frame, t1.views["v2"].sync_frame) == (10, 12)
    assert t1.contacts == (ContactMarker(5, (1.0, 2.0, 3.0), marker="0"), ContactMarker(6, (0.0, 0.0, 1.0)))
    assert t1.note == "multi\nline" and t1.failed is False
    t2 = m.sequences["take2"]
    assert (t2.views["v1"].sync_frame, t2.views["v2"].sync_frame) == (None, None)


def test_indoor_disagreement_warns(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    rows = [HEADER, _row("room", "a", in_door="TRUE"), _row("room", "b", in_door="FALSE")]
    with caplog.at_level(logging.WARNING):
        m = import_sheet(_write_csv(tmp_path / "s.csv", rows), tmp_path)
    assert m.scenes["room"].indoor is True
    assert "in_door" in caplog.text and "row 3" in caplog.text


@pytest.mark.parametrize(
    "text",
    [
        "__import__('os').system('touch HACKED')",
        "[[1, __import__('os').getcwd()]]",
        "[(lambda: 1)()]",
        "open('x')",
    ],
)
def test_contacts_code_is_rejected(tmp_path: Path, text: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    sheet = _write_csv(tmp_path / "s.csv", [HEADER, _row("room", "seq0", contacts=text)])
    with pytest.raises(InputError) as info:
        import_sheet(sheet, tmp_path)
    assert "row 2, column 'contacts'" in str(info.value) and str(sheet) in str(info.value)
    assert not (tmp_path / "HACKED").exists()


@pytest.mark.parametrize(
    "cells, column",
    [
        ({"v1_start": "abc"}, "v1_start"),
        ({"v2_start": -5}, "v2_start"),
        ({"v1_start": 3.5}, "v1_start"),
        ({"FAILED": "maybe"}, "FAILED"),
        ({"in_door": "indoors"}, "in_door"),
        ({"optim_scale": 2}, "optim_scale"),
        ({"contacts": "[[1, 2, 3]]"}, "contacts"),
        ({"contacts": "[[-1, [0, 0, 0]]]"}, "contacts"),
        ({"contacts": "{'a': 1}"}, "contacts"),
        ({"contacts": "[[1, 4]]"}, "contacts"),  # id form without any contact sheet
        ({"seq_name": None}, "seq_name"),
    ],
)
def test_bad_cells_name_sheet_row_column(tmp_path: Path, cells: dict[str, object], column: str) -> None:
    good = _row("room", "ok")
    bad = _row("room", "seq0", **cells)
    sheet = _write_xlsx(tmp_path / "s.xlsx", {"Sheet1": [HEADER, good, bad]})
    with pytest.raises(InputError) as info:
        import_sheet(sheet, tmp_path)
    message = str(info.value)
    assert str(sheet) in message
    assert f"sheet 'Sheet1', row 3, column '{column}'" in message


def test_all_bad_cells_are_listed(tmp_path: Path) -> None:
    rows = [HEADER, _row("room", "a", v1_start="x"), _row("room", "b", FAILED="?", contacts="[")]
    with pytest.raises(InputError) as info:
        import_sheet(_write_csv(tmp_path / "s.csv", rows), tmp_path)
    lines = str(info.value).splitlines()
    assert "3 bad cells" in lines[0]
    assert [line.split(": ")[0].strip("- ") for line in lines[1:]] == [
        "row 2, column 'v1_start'", "row 3, column 'FAILED'", "row 3, column 'contacts'",
    ]


def test_other_bad_sheets(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no sequence rows"):
        import_sheet(_write_csv(tmp_path / "e.csv", [HEADER]), tmp_path)
    dup = [HEADER, _row("room", "a"), _row("room", "a")]
    with pytest.raises(InputError, match="row 3: sequence 'a' of scene 'room' already at row 2"):
        import_sheet(_write_csv(tmp_path / "d.csv", dup), tmp_path)
    clash = [HEADER, _row("x/room", "a"), _row("y/room", "b")]
    with pytest.raises(InputError, match="share the name 'room'"):
        import_sheet(_write_csv(tmp_path / "c.csv", clash), tmp_path)
    with pytest.raises(InputError, match="placeholders"):
        import_sheet(_write_csv(tmp_path / "p.csv", [HEADER, _row("r", "a")]), tmp_path, capture_pattern="{nope}")
    with pytest.raises(InputError, match="unsupported sheet type"):
        import_sheet(_write_csv(tmp_path / "p.ods", [HEADER]), tmp_path)
    contact_bad = {"Sheet1": [HEADER, _row("room", "a")], "contact": [["scene", "contacts"], ["room", "[[1, 2]]"]]}
    with pytest.raises(InputError, match="sheet 'contact', row 2, column 'contacts'"):
        import_sheet(_write_xlsx(tmp_path / "k.xlsx", contact_bad), tmp_path)
