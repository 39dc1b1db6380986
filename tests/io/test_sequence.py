"""Sequence readers: each input kind, frame selection, bad input, skipped frames, streaming."""

from __future__ import annotations

import gc
import inspect
import tracemalloc
import types
from pathlib import Path

import cv2
import numpy as np
import pytest

from trianflow_vo.errors import InputError
from trianflow_vo.frames import Frame, FrameSkip
from trianflow_vo.io import sequence as seqmod
from trianflow_vo.io.sequence import Prefetcher, Sequence, natural_key, open_sequence

H, W = 24, 40


def img_for(i: int, h: int = H, w: int = W, color: bool = False) -> np.ndarray:
    """A frame whose pixel (0, 0) encodes its index; colour frames have distinct B, G, R."""
    rng = np.random.default_rng(i)
    if color:
        im = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        im[0, 0] = (i % 256, 7, 200)
    else:
        im = rng.integers(0, 256, (h, w), dtype=np.uint8)
        im[0, 0] = i % 256
    return im


def p_line(key, fx, fy, cx, cy):
    return f"{key}: {fx} 0 {cx} 0 0 {fy} {cy} 0 0 0 1 0"


def write_kitti(root: Path, n: int = 10, image_dirs=("image_0",), ext=".png", times=True, calib=True) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    for d in image_dirs:
        (root / d).mkdir()
        for i in range(n):
            cv2.imwrite(str(root / d / f"{i:06d}{ext}"), img_for(i, color=d == "image_2"))
    if calib:
        (root / "calib.txt").write_text(
            "\n".join([p_line("P0", 100, 101, 20, 12), p_line("P1", 100, 101, 20, 12), p_line("P2", 200, 201, 19, 11), p_line("P3", 200, 201, 19, 11)]) + "\n"
        )
    if times:
        (root / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(n)))
    (root / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * n)
    return root


def write_images(folder: Path, names, sizes=None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(names):
        h, w = sizes[k] if sizes else (H, W)
        cv2.imwrite(str(folder / name), img_for(k, h, w))
    return folder


def frames_of(seq):
    return list(seq)


# --------------------------------------------------------------------------- KITTI


def test_kitti_gray_folder(tmp_path):
    root = write_kitti(tmp_path / "00")
    seq = open_sequence(root)
    assert seq.kind == "kitti" and seq.path == root and seq.image_dir == root / "image_0"
    np.testing.assert_array_equal(seq.K, [[100, 0, 20], [0, 101, 12], [0, 0, 1]])
    assert seq.K.dtype == np.float64 and seq.K_source == "calib.txt:P0"
    assert seq.image_size == (H, W) and len(seq) == 10
    assert seq.ground_truth_path() == root / "poses.txt"
    out = frames_of(seq)
    assert [f.index for f in out] == list(range(10))
    for f in out:
        assert isinstance(f, Frame)
        assert f.image.shape == (H, W, 3) and f.image.dtype == np.uint8
        # grayscale expanded: three equal channels, exact (PNG is lossless)
        np.testing.assert_array_equal(f.image[..., 0], img_for(f.index))
        np.testing.assert_array_equal(f.image[..., 0], f.image[..., 2])
        assert f.timestamp == pytest.approx(0.1 * f.index)
        assert f.source == str(root / "image_0" / f"{f.index:06d}.png")


def test_kitti_prefers_image_2_and_its_P2(tmp_path):
    root = write_kitti(tmp_path / "seq", n=4, image_dirs=("image_0", "image_2"), times=False)
    seq = open_sequence(root)
    assert seq.image_dir == root / "image_2" and seq.K_source == "calib.txt:P2"
    np.testing.assert_array_equal(seq.K, [[200, 0, 19], [0, 201, 11], [0, 0, 1]])
    f = next(iter(seq))
    assert tuple(f.image[0, 0]) == (0, 7, 200)  # BGR order preserved
    assert f.timestamp is None


def test_kitti_image_folder_given_directly(tmp_path):
    root = write_kitti(tmp_path / "seq", n=4, image_dirs=("image_2",))
    seq = open_sequence(root / "image_2")
    assert seq.kind == "kitti" and seq.path == root and seq.K[0, 0] == 200


def test_kitti_jpeg_frames(tmp_path):
    root = write_kitti(tmp_path / "seq", n=5, ext=".jpg")
    seq = open_sequence(root)
    out = frames_of(seq)
    assert [type(f) for f in out] == [Frame] * 5
    assert np.abs(out[3].image[..., 0].astype(int) - img_for(3)).mean() < 40  # lossy, but this frame


def test_kitti_calib_override_picks_line_by_folder(tmp_path):
    root = write_kitti(tmp_path / "seq", n=4, image_dirs=("image_2",), calib=False)
    with pytest.raises(InputError) as e:
        open_sequence(root)
    assert "--intrinsics fx,fy,cx,cy" in str(e.value) and "--calib FILE" in str(e.value)
    assert e.value.path == str(root)
    other = tmp_path / "other_calib.txt"
    other.write_text(p_line("P0", 1, 1, 1, 1) + "\n" + p_line("P2", 300, 301, 18, 10) + "\n")
    seq = open_sequence(root, calib=other)
    assert seq.K[0, 0] == 300 and seq.K_source.startswith("--calib")
    seq = open_sequence(root, intrinsics=(50.0, 51.0, 20.0, 12.0))
    np.testing.assert_array_equal(seq.K, [[50, 0, 20], [0, 51, 12], [0, 0, 1]])


def test_kitti_bad_times_and_calib(tmp_path):
    root = write_kitti(tmp_path / "seq", n=4)
    (root / "times.txt").write_text("0.0\n0.1\nabc\n0.3\n")
    with pytest.raises(InputError) as e:
        open_sequence(root)
    assert e.value.path == str(root / "times.txt") and e.value.line == 3
    (root / "times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(InputError, match="2 timestamps for 4 images"):
        open_sequence(root)
    (root / "times.txt").unlink()
    (root / "calib.txt").write_text(p_line("P0", 1, 1, 1, 1)[:-2] + "\n")
    with pytest.raises(InputError) as e:
        open_sequence(root)
    assert str(e.value).startswith(f"{root / 'calib.txt'}:1: ")


def test_kitti_empty_image_folder(tmp_path):
    root = write_kitti(tmp_path / "seq", n=0)
    with pytest.raises(InputError, match="no images") as e:
        open_sequence(root)
    assert e.value.path == str(root / "image_0")


# --------------------------------------------------------------------------- TUM


def write_tum(root: Path, n: int = 6) -> Path:
    (root / "rgb").mkdir(parents=True)
    lines = ["# color images", "# file: 'x.bag'", "# timestamp filename"]
    for i in range(n):
        t = 1305031102.175304 + i / 30.0
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), img_for(i, color=True))
        lines.append(f"{t:.6f} rgb/{t:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    return root


def test_tum_folder_default_intrinsics(tmp_path):
    root = write_tum(tmp_path / "rgbd_dataset_freiburg1_xyz")
    seq = open_sequence(root, stride=2)
    assert seq.kind == "tum" and seq.K_source == "TUM freiburg1 default"
    np.testing.assert_array_equal(seq.K, [[517.3, 0, 318.6], [0, 516.5, 255.3], [0, 0, 1]])
    out = frames_of(seq)
    assert [f.index for f in out] == [0, 2, 4]
    assert [f.timestamp for f in out] == pytest.approx([1305031102.175304 + i / 30.0 for i in (0, 2, 4)], abs=1e-6)
    assert all(f.image[0, 0, 0] == f.index for f in out)


def test_tum_needs_intrinsics_without_freiburg_name(tmp_path):
    root = write_tum(tmp_path / "my_recording")
    with pytest.raises(InputError, match=r"--intrinsics fx,fy,cx,cy or --calib FILE"):
        open_sequence(root)
    assert open_sequence(root, intrinsics=(500, 500, 20, 12)).K[0, 0] == 500


def test_tum_malformed_line_and_missing_file(tmp_path):
    root = write_tum(tmp_path / "rgbd_dataset_freiburg3_x", n=4)
    lines = (root / "rgb.txt").read_text().splitlines()
    (root / "rgb.txt").write_text("\n".join(lines[:5] + ["1305031102.3 rgb/a.png extra"] + lines[5:]) + "\n")
    with pytest.raises(InputError) as e:
        open_sequence(root)
    assert e.value.path == str(root / "rgb.txt") and e.value.line == 6
    # a listed file that does not exist is skipped, not fatal
    (root / "rgb.txt").write_text("\n".join(lines[:5] + ["1305031102.3 rgb/missing.png"] + lines[5:]) + "\n")
    out = frames_of(open_sequence(root))
    assert [type(f).__name__ for f in out] == ["Frame", "Frame", "FrameSkip", "Frame", "Frame"]
    assert out[2].source == str(root / "rgb" / "missing.png") and "cannot read" in out[2].reason


# --------------------------------------------------------------------------- plain image folders


def test_images_natural_sort_and_K_txt(tmp_path):
    names = ["10.png", "2.png", "1.png", "100.png", "11.png", "frame_3.jpg"]
    folder = write_images(tmp_path / "imgs", names)
    (folder / "notes.md").write_text("not an image")
    (folder / "K.txt").write_text("50 0 20\n0 50 12\n0 0 1\n")
    seq = open_sequence(folder)
    assert seq.kind == "images" and seq.K_source == "K.txt" and seq.K[0, 0] == 50
    out = frames_of(seq)
    assert [Path(f.source).name for f in out] == ["1.png", "2.png", "10.png", "11.png", "100.png", "frame_3.jpg"]
    assert [f.index for f in out] == list(range(6))
    # the file written k-th carries k in pixel (0, 0): check a lossless one
    assert out[2].image[0, 0, 0] == names.index("10.png")
    assert all(f.timestamp is None for f in out)
    assert seq.ground_truth_path() is None


def test_natural_key():
    names = ["img10.png", "img2.png", "IMG1.png", "img2a.png", "a.png"]
    assert sorted(names, key=natural_key) == ["a.png", "IMG1.png", "img2.png", "img2a.png", "img10.png"]


def test_images_calib_txt_kitti_style_and_subfolder(tmp_path):
    root = tmp_path / "clip"
    write_images(root / "color", [f"{i:06d}.png" for i in range(5)])
    (root / "calib.txt").write_text(p_line("P0", 585, 585, 320, 240) + "\n")
    (root / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 5)
    seq = open_sequence(root)
    assert seq.kind == "images" and seq.image_dir == root / "color" and seq.K[0, 0] == 585
    assert seq.ground_truth_path() == root / "poses.txt"


def test_images_no_intrinsics_message(tmp_path):
    folder = write_images(tmp_path / "imgs", ["a.png", "b.png"])
    with pytest.raises(InputError) as e:
        open_sequence(folder)
    msg = str(e.value)
    assert msg.startswith(str(folder)) and "--intrinsics fx,fy,cx,cy" in msg and "--calib FILE" in msg


def test_calib_override_with_fx_fy_cx_cy_file(tmp_path):
    folder = write_images(tmp_path / "imgs", ["a.png", "b.png"])
    (folder / "K.txt").write_text("1 0 1\n0 1 1\n0 0 1\n")
    f = tmp_path / "cam.txt"
    f.write_text("400 410 20 12\n")
    seq = open_sequence(folder, calib=f)
    np.testing.assert_array_equal(seq.K, [[400, 0, 20], [0, 410, 12], [0, 0, 1]])
    with pytest.raises(InputError, match="not both"):
        open_sequence(folder, calib=f, intrinsics=(1, 1, 1, 1))
    with pytest.raises(InputError, match="not found") as e:
        open_sequence(folder, calib=tmp_path / "missing.txt")
    assert e.value.path == str(tmp_path / "missing.txt")
    with pytest.raises(InputError, match="positive"):
        open_sequence(folder, intrinsics=(0, 1, 1, 1))


# --------------------------------------------------------------------------- video


def write_video(path: Path, n: int, fourcc: str, fps: float = 10.0) -> Path:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (W * 2, H * 2))
    assert w.isOpened(), f"cannot write {fourcc} video here"
    for i in range(n):
        w.write(np.full((H * 2, W * 2, 3), 10 * i, np.uint8))
    w.release()
    return path


@pytest.mark.parametrize("name, fourcc", [("clip.avi", "MJPG"), ("clip.mp4", "mp4v")])
def test_video(tmp_path, name, fourcc):
    path = write_video(tmp_path / name, 12, fourcc)
    seq = open_sequence(path, intrinsics=(60, 60, 40, 24), start=1, end=11, stride=3)
    assert seq.kind == "video" and seq.image_size == (2 * H, 2 * W) and seq.n_source_frames == 12
    assert len(seq) == 4
    out = frames_of(seq)
    assert [f.index for f in out] == [1, 4, 7, 10]
    for f in out:
        assert isinstance(f, Frame) and f.image.shape == (2 * H, 2 * W, 3)
        assert abs(float(f.image.mean()) - 10 * f.index) < 4, (f.index, f.image.mean())
        assert f.timestamp == pytest.approx(f.index / 10.0, abs=1e-3)
        assert f.source == f"{path}#{f.index}"
    assert seq.ground_truth_path() is None


def test_video_errors(tmp_path):
    path = write_video(tmp_path / "clip.avi", 5, "MJPG")
    with pytest.raises(InputError, match="--intrinsics") as e:
        open_sequence(path)
    assert e.value.path == str(path)
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"\x00not a video" * 50)
    with pytest.raises(InputError, match="cannot be opened") as e:
        open_sequence(bad, intrinsics=(1, 1, 1, 1))
    assert e.value.path == str(bad)
    with pytest.raises(InputError, match="fewer than two"):
        open_sequence(path, intrinsics=(1, 1, 1, 1), start=4)


def test_single_image_is_not_a_sequence(tmp_path):
    write_images(tmp_path, ["one.png"])
    with pytest.raises(InputError, match="single image"):
        open_sequence(tmp_path / "one.png", intrinsics=(1, 1, 1, 1))


# --------------------------------------------------------------------------- selection


@pytest.fixture
def ten_images(tmp_path):
    folder = write_images(tmp_path / "imgs", [f"{i}.png" for i in range(10)])
    (folder / "calib.txt").write_text("50 50 20 12\n")
    return folder


@pytest.mark.parametrize(
    "start, end, stride, expect",
    [
        (0, None, 1, list(range(10))),
        (2, 9, 3, [2, 5, 8]),
        (3, None, 4, [3, 7]),
        (0, 100, 5, [0, 5]),  # end beyond the last frame is clipped
        (8, None, 1, [8, 9]),
    ],
)
def test_selection(ten_images, start, end, stride, expect):
    seq = open_sequence(ten_images, start=start, end=end, stride=stride)
    assert len(seq) == len(expect)
    assert [f.index for f in seq] == expect
    assert all(f.image[0, 0, 0] == f.index for f in seq)  # index = source index


@pytest.mark.parametrize(
    "kw, expect",
    [
        (dict(stride=0), "stride must be"),
        (dict(stride=-2), "stride must be"),
        (dict(start=5, end=5), "start (5) must be before end (5)"),
        (dict(start=7, end=3), "must be before"),
        (dict(start=-1), "start must be >= 0"),
        (dict(start=9), "fewer than two frames selected (1 of 10"),
        (dict(start=20), "fewer than two frames selected (0 of 10"),
        (dict(start=0, end=10, stride=10), "fewer than two"),
    ],
)
def test_bad_selection(ten_images, kw, expect):
    with pytest.raises(InputError) as e:
        open_sequence(ten_images, **kw)
    assert expect in str(e.value) and e.value.path == str(ten_images)


def test_missing_and_empty(tmp_path):
    with pytest.raises(InputError, match="no such file or folder") as e:
        open_sequence(tmp_path / "nope")
    assert e.value.path == str(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no images") as e:
        open_sequence(tmp_path / "empty", intrinsics=(1, 1, 1, 1))
    assert e.value.path == str(tmp_path / "empty")
    (tmp_path / "empty" / "readme.txt").write_text("x")
    with pytest.raises(InputError, match="no images"):
        open_sequence(tmp_path / "empty", intrinsics=(1, 1, 1, 1))
    write_images(tmp_path / "one", ["0.png"])
    with pytest.raises(InputError, match="fewer than two"):
        open_sequence(tmp_path / "one", intrinsics=(1, 1, 1, 1))


# --------------------------------------------------------------------------- bad frames


def truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_truncated_image_is_skipped_and_iteration_continues(tmp_path, ext):
    folder = write_images(tmp_path / "imgs", [f"{i}{ext}" for i in range(5)])
    truncate(folder / f"2{ext}")
    (folder / f"4{ext}").write_bytes(b"")
    seq = open_sequence(folder, intrinsics=(50, 50, 20, 12))
    out = frames_of(seq)
    assert [type(f) for f in out] == [Frame, Frame, FrameSkip, Frame, FrameSkip]
    assert out[2].index == 2 and out[2].source == str(folder / f"2{ext}")
    assert "truncated" in out[2].reason
    assert out[4].source == str(folder / f"4{ext}") and out[4].reason == "empty file"


def test_jpeg_without_end_marker_is_rejected(tmp_path):
    """Some decoders fill a cut-off JPEG with grey instead of failing: the reader checks the end marker."""
    ok, buf = cv2.imencode(".jpg", img_for(1))
    data = buf.tobytes()
    good, cut, padded = tmp_path / "good.jpg", tmp_path / "cut.jpg", tmp_path / "padded.jpg"
    good.write_bytes(data)
    cut.write_bytes(data[:-2])
    padded.write_bytes(data + b"\x00" * 8)
    assert seqmod.decode_image(good)[0] is not None
    assert seqmod.decode_image(padded)[0] is not None
    img, reason = seqmod.decode_image(cut)
    assert img is None and reason == "truncated JPEG (no end-of-image marker)"


def test_first_unreadable_frame_does_not_set_the_size(tmp_path):
    folder = write_images(tmp_path / "imgs", ["0.png", "1.png", "2.png"], sizes=[(10, 10), (H, W), (H, W)])
    truncate(folder / "0.png")
    seq = open_sequence(folder, intrinsics=(50, 50, 20, 12))
    assert seq.image_size == (H, W)
    assert [type(f) for f in seq] == [FrameSkip, Frame, Frame]


def test_all_unreadable(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i in range(3):
        (folder / f"{i}.png").write_bytes(b"garbage")
    with pytest.raises(InputError, match="none of the 3 selected images can be decoded") as e:
        open_sequence(folder, intrinsics=(1, 1, 1, 1))
    assert "0.png" in str(e.value)


def test_mixed_sizes_are_skipped(tmp_path):
    sizes = [(H, W), (H, W), (H + 2, W), (W, H), (H, W)]
    folder = write_images(tmp_path / "imgs", [f"{i}.png" for i in range(5)], sizes=sizes)
    seq = open_sequence(folder, intrinsics=(50, 50, 20, 12))
    out = frames_of(seq)
    assert [type(f) for f in out] == [Frame, Frame, FrameSkip, FrameSkip, Frame]
    assert out[2].reason == f"size {W}x{H + 2} differs from the first frame's {W}x{H}"
    assert out[2].source == str(folder / "2.png") and out[3].source == str(folder / "3.png")


# --------------------------------------------------------------------------- streaming


def test_streaming_300_frames(tmp_path, monkeypatch):
    h, w = 120, 160  # 57.6 kB per decoded frame: 300 frames would be 17 MB
    folder = tmp_path / "long"
    folder.mkdir()
    base = np.random.default_rng(0).integers(0, 256, (h, w), dtype=np.uint8)
    for i in range(300):
        cv2.imwrite(str(folder / f"{i}.png"), base)
    seq = open_sequence(folder, intrinsics=(100, 100, 80, 60))
    assert len(seq) == 300
    assert inspect.isgeneratorfunction(Sequence.__iter__)
    it = iter(seq)
    assert isinstance(it, types.GeneratorType)

    # decoding is lazy: one decode per frame pulled
    calls = []
    real = seqmod.decode_image
    monkeypatch.setattr(seqmod, "decode_image", lambda p: (calls.append(p), real(p))[1])
    it = iter(seq)
    assert calls == []
    next(it)
    next(it)
    assert len(calls) == 2
    it.close()
    monkeypatch.setattr(seqmod, "decode_image", real)

    # memory stays flat when the consumer drops frames
    gc.collect()
    tracemalloc.start()
    n = 0
    for f in seq:
        assert isinstance(f, Frame)
        n += 1
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert n == 300
    assert peak < 1_500_000, f"peak {peak} bytes while streaming (all frames would be {300 * h * w * 3})"


def test_prefetcher_same_frames_in_order(ten_images):
    seq = open_sequence(ten_images, stride=2)
    plain = [(f.index, f.image.tobytes()) for f in seq]
    with Prefetcher(seq, depth=2) as pf:
        pre = [(f.index, f.image.tobytes()) for f in pf]
    assert pre == plain


def test_prefetcher_propagates_errors_and_closes_early():
    def gen():
        yield 1
        yield 2
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        list(Prefetcher(gen()))
    released = []

    def endless():
        try:
            i = 0
            while True:
                yield i
                i += 1
        finally:
            released.append(True)

    pf = Prefetcher(endless(), depth=1)
    first = next(iter(pf))
    pf.close()
    assert first == 0 and not pf._thread.is_alive()
    assert released == [True]  # the source iterator was closed (a video capture would be released)
    with pytest.raises(ValueError):
        Prefetcher([], depth=0)


# --------------------------------------------------------------------------- shipped sample and shared data


def test_shipped_sample(sample_seq):
    seq = open_sequence(sample_seq)
    assert seq.kind == "kitti" and len(seq) == 48 and seq.image_size == (376, 1241)
    assert seq.image_dir.name == "image_0"
    np.testing.assert_allclose(seq.K, [[718.856, 0, 607.1928], [0, 718.856, 185.2157], [0, 0, 1]])
    gt = seq.ground_truth_path()
    assert gt is not None and len(gt.read_text().split("\n")) - 1 == 48
    attribution = (sample_seq / "ATTRIBUTION.txt").read_text()
    assert "CC BY-NC-SA 3.0" in attribution and "Geiger" in attribution
    size = sum(p.stat().st_size for p in sample_seq.rglob("*") if p.is_file())
    assert size < 7_000_000
    f = next(iter(seq))
    assert isinstance(f, Frame) and f.index == 0 and f.image.shape == (376, 1241, 3)


def test_sample_matches_shared_source(sample_seq, shared_data):
    """The JPEG sample is the shared clip's frames 0-47, re-encoded (small error only)."""
    src = open_sequence(shared_data / "kitti00-f0000-0150", end=48)
    sam = open_sequence(sample_seq)
    assert src.image_size == sam.image_size
    np.testing.assert_array_equal(src.K, sam.K)
    for a, b in zip(open_sequence(shared_data / "kitti00-f0000-0150", start=0, end=48, stride=23), open_sequence(sample_seq, stride=23)):
        assert a.index == b.index
        assert np.abs(a.image.astype(int) - b.image.astype(int)).mean() < 3.0
    gt_src = (shared_data / "kitti00-f0000-0150" / "poses.txt").read_text().splitlines()[:48]
    assert sam.ground_truth_path().read_text().splitlines() == gt_src


def test_shared_kitti06_calibration(shared_data):
    seq = open_sequence(shared_data / "kitti06-f0000-0050", stride=3)
    assert seq.K[0, 0] == pytest.approx(707.0912) and seq.image_size == (370, 1226)
    assert len(seq) == 17
