"""Video probe / random-access reader / atomic writer round trips."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.io.video import VideoReader, VideoWriter, probe_video


def smooth_frames(n: int, w: int = 96, h: int = 64, seed: int = 0) -> list[np.ndarray]:
    """Smooth random colour images (H.264 reproduces them closely), each frame different."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        small = rng.uniform(40, 215, (h // 16, w // 16, 3)).astype(np.float32)
        out.append(np.clip(cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR), 0, 255).astype(np.uint8))
    return out


@pytest.fixture(scope="module")
def video(tmp_path_factory) -> tuple[Path, list[np.ndarray]]:
    frames = smooth_frames(90)
    path = tmp_path_factory.mktemp("video") / "clip.mp4"
    with VideoWriter(path, 30.0, 96, 64) as w:
        for f in frames:
            w.write(f)
    return path, frames


def test_probe_reads_size_rate_count_and_timestamps(video):
    path, frames = video
    info = probe_video(path)
    assert (info.num_frames, info.width, info.height, info.codec) == (90, 96, 64, "h264")
    assert info.fps == pytest.approx(30.0)
    np.testing.assert_allclose(info.timestamps_s, np.arange(90) / 30.0, atol=1e-6)


def test_frames_round_trip_close(video):
    path, frames = video
    with VideoReader(path) as r:
        assert len(r) == 90
        errs = [np.abs(r.read(i).astype(int) - frames[i]).mean() for i in range(len(r))]
        wrong = np.abs(r.read(1).astype(int) - frames[0]).mean()
    # yuv420p halves chroma resolution: on these tiny colourful frames that alone costs ~3 levels.
    assert max(errs) < 4.0 and wrong > 4 * max(errs)


def test_far_jump_without_key_frame_decodes_forward(video):
    """A jump far ahead seeks only when a key frame lies in the gap: the seek would land on the key
    frame before the target, and with none in the gap that is at or before the frames already
    decoded (decoding them again). The clip's only key frame is its first."""
    path, _ = video
    seeks = []

    class Counting(VideoReader):
        def _seek(self, index: int) -> None:
            seeks.append(index)
            super()._seek(index)

    with VideoReader(path) as r:
        seq = [r.read(i) for i in range(90)]
    with Counting(path) as r:
        assert r._key_at_or_before(80) == 0
        for i in (3, 70, 89):  # jumps of 67 and 19 frames, no key frame after 0
            np.testing.assert_array_equal(r.read(i), seq[i])
        assert seeks == [3]  # the first read opens the decoder; the jump decodes on
        np.testing.assert_array_equal(r.read(10), seq[10])  # backwards: a seek
        assert seeks == [3, 10]


def test_random_access_equals_sequential(video):
    path, _ = video
    with VideoReader(path) as r:
        seq = [r.read(i) for i in range(90)]
    order = [5, 4, 89, 0, 60, 61, 10, 88, 30, 30]
    with VideoReader(path) as r:
        for i in order:
            np.testing.assert_array_equal(r.read(i), seq[i])
        with pytest.raises(IndexError):
            r.read(90)


def test_odd_size_rejected_and_nothing_written(tmp_path):
    with pytest.raises(ValueError, match="even"):
        VideoWriter(tmp_path / "odd.mp4", 30, 95, 64)
    assert not list(tmp_path.iterdir())


def test_writer_is_atomic(tmp_path):
    path = tmp_path / "a.mp4"
    w = VideoWriter(path, 30, 32, 32)
    w.write(np.zeros((32, 32, 3), np.uint8))
    assert not path.exists()  # only the temp file exists until close
    w.close()
    assert path.exists() and probe_video(path).num_frames == 1
    with pytest.raises(RuntimeError):
        with VideoWriter(tmp_path / "b.mp4", 30, 32, 32) as w2:
            w2.write(np.zeros((32, 32, 3), np.uint8))
            raise RuntimeError("interrupted")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mp4"]


def test_truncated_and_fake_videos_raise_input_error(video, tmp_path):
    path, _ = video
    data = path.read_bytes()
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError) as e:
        probe_video(cut)
    assert e.value.path == cut
    fake = tmp_path / "fake.mp4"
    fake.write_text("not a video")
    with pytest.raises(InputError) as e:
        VideoReader(fake)
    assert e.value.path == fake
    with pytest.raises(InputError):
        probe_video(tmp_path / "missing.mp4")


def test_display_rotation_is_reported(tmp_path):
    import av

    path = tmp_path / "rot.mov"
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=30)
        s.width, s.height, s.pix_fmt = 32, 16, "yuv420p"
        s.set_display_rotation(-90)
        f = av.VideoFrame.from_ndarray(np.zeros((16, 32, 3), np.uint8), format="rgb24")
        for p in s.encode(f):
            c.mux(p)
        for p in s.encode():
            c.mux(p)
    info = probe_video(path)
    assert info.rotation_deg == -90 and (info.width, info.height) == (32, 16)
