"""`embodmocap.data.FrameDataset` over a training export: items equal the export's files, a
DataLoader with 2 workers reads a whole session, clip mode gives consecutive frames, filters, and a
bad or missing folder is one clear error."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from embodmocap.data import FrameDataset
from embodmocap.errors import InputError
from embodmocap.export.training import export_training
from embodmocap.io.layout import SessionLayout
from embodmocap.io.smpl_file import read_smpl_npz, write_smpl_npz
from stage4_session import SYNTH
from training_session import training_export  # noqa: F401  (fixture)


def _labels(out: Path, view: str) -> dict:
    with np.load(out / "seq0" / view / "labels.npz") as z:
        return {k: z[k] for k in z.files}


def test_an_item_is_the_exported_frame(training_export):
    out = training_export["out"]
    ds = FrameDataset(out)
    T = training_export["info"]["T"]
    assert len(ds) == 2 * T
    item = ds[T + 3]  # view 2, frame 3
    assert (item["sequence"], item["view"], int(item["frame"])) == ("seq0", "v2", 3)
    d = out / "seq0" / "v2"
    bgr = cv2.imread(str(d / "rgb" / "000003.jpg"))
    assert item["rgb"].shape == (3, SYNTH.height, SYNTH.width) and item["rgb"].dtype == torch.uint8
    assert torch.equal(item["rgb"], torch.from_numpy(bgr[:, :, ::-1].transpose(2, 0, 1).copy()))
    assert torch.equal(item["depth"], torch.from_numpy(np.load(d / "depth.npy")[3].astype(np.float32) / 1000))
    mask = np.unpackbits(np.load(d / "masks.npy")[3], axis=-1, count=SYNTH.width).astype(bool)
    assert torch.equal(item["mask"], torch.from_numpy(mask)) and mask.any()
    lab = _labels(out, "v2")
    for key in ("T_world_cam", "global_orient", "body_pose", "transl", "joints_cam", "keypoints", "keypoints_fit"):
        assert torch.allclose(item[key], torch.from_numpy(lab[key][3]).float()), key
    assert torch.allclose(item["K"], torch.from_numpy(lab["K"]).float())
    assert torch.allclose(item["K_depth"], torch.from_numpy(lab["K_depth"]).float())
    assert torch.allclose(item["betas"], torch.from_numpy(lab["betas"]).float())
    assert bool(item["valid"]) and bool(item["smpl_valid"]) and bool(item["in_sync"]) and bool(item["depth_present"])


def test_dataloader_with_two_workers_reads_the_whole_session(training_export):
    out = training_export["out"]
    ds = FrameDataset(out)
    loader = torch.utils.data.DataLoader(ds, batch_size=5, shuffle=True, num_workers=2,
                                         generator=torch.Generator().manual_seed(0))
    seen = {}
    for batch in loader:
        assert batch["rgb"].shape[1:] == (3, SYNTH.height, SYNTH.width)
        for i, (seq, view, t) in enumerate(zip(batch["sequence"], batch["view"], batch["frame"].tolist())):
            seen[(seq, view, t)] = (batch["joints_cam"][i], batch["rgb"][i, :, 100, 100])
    T = training_export["info"]["T"]
    assert sorted(seen) == [("seq0", v, t) for v in ("v1", "v2") for t in range(T)]
    for v in ("v1", "v2"):
        lab = _labels(out, v)
        rgb = cv2.imread(str(out / "seq0" / v / "rgb" / "000004.jpg"))[100, 100, ::-1]
        assert torch.allclose(seen[("seq0", v, 4)][0], torch.from_numpy(lab["joints_cam"][4]).float())
        assert seen[("seq0", v, 4)][1].tolist() == rgb.tolist()


def test_clip_mode_returns_consecutive_frames(training_export):
    out = training_export["out"]
    T = training_export["info"]["T"]
    clips = FrameDataset(out, clip=4)
    assert len(clips) == 2 * (T // 4)
    frames = FrameDataset(out)
    for i in range(len(clips)):
        c = clips[i]
        assert c["rgb"].shape == (4, 3, SYNTH.height, SYNTH.width) and c["depth"].shape[0] == 4
        f = c["frame"].tolist()
        assert f == list(range(f[0], f[0] + 4))
        # Frame j of the clip is the single-frame item of that frame.
        one = frames[(T if c["view"] == "v2" else 0) + f[2]]
        assert torch.equal(c["rgb"][2], one["rgb"]) and torch.equal(c["depth"][2], one["depth"])
        assert torch.equal(c["mask"][2], one["mask"]) and torch.equal(c["transl"][2], one["transl"])
    overlapping = FrameDataset(out, clip=4, stride=1, views=["v1"])
    assert [int(overlapping[i]["frame"][0]) for i in range(len(overlapping))] == list(range(T - 3))
    batch = next(iter(torch.utils.data.DataLoader(clips, batch_size=2, num_workers=2)))
    assert batch["rgb"].shape == (2, 4, 3, SYNTH.height, SYNTH.width)


def test_invalid_frames_are_left_out_unless_asked(training_export, tmp_path):
    session = tmp_path / "session"
    shutil.copytree(training_export["session"], session, symlinks=True)
    sl = SessionLayout(session).sequence("seq0")
    params, frames = read_smpl_npz(sl.smpl_world)
    valid = np.ones(len(frames), bool)
    valid[5] = False
    write_smpl_npz(sl.smpl_world, params, frames, valid)
    out = export_training(session, out=tmp_path / "export")
    T = len(frames)
    ds = FrameDataset(out, views=["v1"])
    assert sorted(int(ds[i]["frame"]) for i in range(len(ds))) == [t for t in range(T) if t != 5]
    everything = FrameDataset(out, views=["v1"], require_valid=False)
    assert len(everything) == T and not bool(everything[5]["valid"])
    clips = FrameDataset(out, clip=3, stride=1, views=["v1"])
    starts = [int(clips[i]["frame"][0]) for i in range(len(clips))]
    assert starts == [s for s in range(T - 2) if not s <= 5 < s + 3]


def test_filters_and_what_to_load(training_export):
    out = training_export["out"]
    T = training_export["info"]["T"]
    ds = FrameDataset(out, views=["v2"], load_rgb=False, load_depth=False, load_mask=False)
    assert len(ds) == T and {ds[i]["view"] for i in range(len(ds))} == {"v2"}
    assert not {"rgb", "depth", "mask"} & set(ds[0])
    assert len(FrameDataset(out, sequences=["other"])) == 0


def test_missing_or_bad_folder_is_one_clear_error(training_export, tmp_path):
    with pytest.raises(InputError, match="not found") as err:
        FrameDataset(tmp_path / "nowhere")
    assert str(tmp_path / "nowhere") in str(err.value) and "--to training" in str(err.value)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no manifest.json"):
        FrameDataset(tmp_path / "empty")
    bad = tmp_path / "bad"
    shutil.copytree(training_export["out"], bad)
    index = json.loads((bad / "manifest.json").read_text())
    (bad / "manifest.json").write_text(json.dumps(dict(index, format="something/9")))
    with pytest.raises(InputError, match="something/9"):
        FrameDataset(bad)
    (bad / "manifest.json").write_text(json.dumps(index))
    (bad / "seq0" / "v2" / "depth.npy").unlink()
    with pytest.raises(InputError) as err:
        FrameDataset(bad)
    assert "depth.npy" in str(err.value)
    shutil.copy(training_export["out"] / "seq0" / "v2" / "depth.npy", bad / "seq0" / "v2" / "depth.npy")
    (bad / "seq0" / "v1" / "rgb" / "000002.jpg").unlink()
    with pytest.raises(InputError, match="JPEG frames"):
        FrameDataset(bad)
