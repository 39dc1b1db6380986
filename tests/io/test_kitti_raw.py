"""KITTI raw drives (vo/io/kitti_raw.py, open_sequence kind "kitti_raw") and random frame access
(Sequence.files / read_frame / FrameReader, added to vo/io/sequence.py beside the raw reader)."""

from __future__ import annotations

import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest

from trianflow_vo.errors import InputError
from trianflow_vo.frames import Frame, FrameSkip
from trianflow_vo.io import kitti_raw
from trianflow_vo.io.sequence import FrameReader, open_sequence

H, W = 24, 40

# the layout (and the numbers of the first lines) of a real calib_cam_to_cam.txt (2011_09_26)
REAL_HEAD = """calib_time: 09-Jan-2012 13:57:47
corner_dist: 9.950000e-02
S_00: 1.392000e+03 5.120000e+02
K_00: 9.842439e+02 0.000000e+00 6.900000e+02 0.000000e+00 9.808141e+02 2.331966e+02 0.000000e+00 0.000000e+00 1.000000e+00
D_00: -3.728755e-01 2.037299e-01 2.219027e-03 1.383707e-03 -7.233722e-02
R_00: 1.000000e+00 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00
T_00: 2.573699e-16 -1.059758e-16 1.614870e-16
S_rect_00: 1.242000e+03 3.750000e+02
R_rect_00: 9.999239e-01 9.837760e-03 -7.445048e-03 -9.869795e-03 9.999421e-01 -4.278459e-03 7.402527e-03 4.351614e-03 9.999631e-01
P_rect_00: 7.215377e+02 0.000000e+00 6.095593e+02 0.000000e+00 0.000000e+00 7.215377e+02 1.728540e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00
S_rect_02: 1.242000e+03 3.750000e+02
P_rect_02: 7.215377e+02 0.000000e+00 6.095593e+02 4.485728e+01 0.000000e+00 7.215377e+02 1.728540e+02 2.163791e-01 0.000000e+00 0.000000e+00 1.000000e+00 2.745884e-03
"""


def p_rect(cam: str, fx, fy, cx, cy, tx=0.0) -> str:
    return f"P_rect_{cam}: {fx:e} 0 {cx:e} {tx:e} 0 {fy:e} {cy:e} 0 0 0 1 0"


def synthetic_calib(path: Path) -> Path:
    """Distinct K per camera (a real file has the same K for all four), at W x H."""
    lines = ["calib_time: 09-Jan-2012 13:57:47", "corner_dist: 9.950000e-02"]
    for cam, f in (("00", 30.0), ("01", 31.0), ("02", 50.0), ("03", 51.0)):
        lines += [f"S_{cam}: 1.392000e+03 5.120000e+02", f"K_{cam}: 1 0 2 0 1 3 0 0 1",
                  f"S_rect_{cam}: {W}.0 {H}.0", p_rect(cam, f, f + 1, 19.5 + int(cam), 11.5, tx=-3.0)]
    path.write_text("\n".join(lines) + "\n")
    return path


def frame_img(i: int, color=True) -> np.ndarray:
    rng = np.random.default_rng(i)
    im = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    im[0, 0] = (i, 7, 200)
    return im if color else im[..., 0].copy()


def stamp(i: int) -> str:
    return f"2011-09-26 13:02:{25 + i // 10:02d}.{(i % 10) * 100000000 + 123:09d}"


def write_drive(date_dir: Path, drive: str, n: int = 5, cams=("image_02",), times=True) -> Path:
    d = date_dir / f"{date_dir.name}_drive_{drive}"
    for cam in cams:
        (d / cam / "data").mkdir(parents=True)
        for i in range(n):
            cv2.imwrite(str(d / cam / "data" / f"{i:010d}.png"), frame_img(i, color=cam in ("image_02", "image_03")))
        if times:
            (d / cam / "timestamps.txt").write_text("".join(stamp(i) + "\n" for i in range(n)))
    return d


@pytest.fixture
def raw_root(tmp_path) -> Path:
    root = tmp_path / "raw"
    for date, drives in (("2011_09_26", ("0001_sync", "0002_sync", "0009_extract")), ("2011_09_28", ("0016_sync",))):
        (root / date).mkdir(parents=True)
        synthetic_calib(root / date / kitti_raw.CALIB_NAME)
        for dr in drives:
            write_drive(root / date, dr)
    return root


# ------------------------------------------------------------------------------------ calibration file


def test_real_cam_to_cam_layout(tmp_path):
    f = tmp_path / kitti_raw.CALIB_NAME
    f.write_text(REAL_HEAD)
    entries = kitti_raw.read_cam_to_cam(f)
    assert "calib_time" not in entries  # not numbers
    assert entries["corner_dist"][0].tolist() == [0.0995] and entries["P_rect_02"][1] == 12
    K, size = kitti_raw.rect_intrinsics(f, "02")
    np.testing.assert_allclose(K, [[721.5377, 0, 609.5593], [0, 721.5377, 172.854], [0, 0, 1]])
    assert size == (375, 1242)
    # P_rect_02's fourth column (the baseline) is not part of K: same K as camera 00
    np.testing.assert_array_equal(kitti_raw.rect_intrinsics(f, "00")[0], K)


def test_rect_intrinsics_per_camera(tmp_path):
    f = synthetic_calib(tmp_path / kitti_raw.CALIB_NAME)
    K2, size = kitti_raw.rect_intrinsics(f, "02")
    np.testing.assert_array_equal(K2, [[50, 0, 21.5], [0, 51, 11.5], [0, 0, 1]])
    assert size == (H, W)
    K0, _ = kitti_raw.rect_intrinsics(f, "00")
    assert K0[0, 0] == 30 and K0[0, 2] == 19.5


@pytest.mark.parametrize("text, match, line", [
    ("calib_time: 09-Jan-2012 13:57:47\nS_rect_02: 40 24\n",
     r"no P_rect_02: line \(rectified projections found: none\)", None),
    ("P_rect_00: 1 0 2 0 0 1 3 0 0 0 1 0\n", r"found: P_rect_00\)", None),
    ("calib_time: x\nP_rect_02: 1 0 2 0 0 1 3 0 0 0 1\n", "needs 12 numbers, got 11", 2),
    ("P_rect_02: 0 0 2 0 0 1 3 0 0 0 1 0\n", "focal lengths must be positive", 1),
    ("P_rect_02: 1 0 2 0 0 1 3 0 0 0 2 0\n", "not K", 1),
    ("corner_dist: 1\nthis line has no key\n", "expected 'key: values'", 2),
    ("P_rect_02: 1 0 2 0 0 1 3 0 0 0 1 0\nP_rect_02: 1 0 2 0 0 1 3 0 0 0 1 0\n", "given twice", 2),
])
def test_rect_intrinsics_errors_name_file_and_line(tmp_path, text, match, line):
    f = tmp_path / "calib_cam_to_cam.txt"
    f.write_text(text)
    with pytest.raises(InputError, match=match) as e:
        kitti_raw.rect_intrinsics(f, "02")
    assert e.value.path == str(f) and e.value.line == line


def test_read_timestamps(tmp_path):
    f = tmp_path / "timestamps.txt"
    f.write_text("2011-09-26 13:02:25.594360375\n2011-09-26 13:02:25.698040000\n\n2011-09-26 13:03:00.000000000\n")
    t = kitti_raw.read_timestamps(f)
    assert len(t) == 3
    assert t[0] == pytest.approx(1317042145.594360375, abs=1e-6)  # 2011-09-26 13:02:25 UTC
    np.testing.assert_allclose(np.diff(t), [0.103679625, 34.30196], atol=1e-6)
    f.write_text("2011-09-26 13:02:25.5\n2011-13-26 13:02:25.5\n")
    with pytest.raises(InputError) as e:
        kitti_raw.read_timestamps(f)
    assert e.value.line == 2
    f.write_text("13:02:25.5\n")
    with pytest.raises(InputError, match="malformed timestamp") as e:
        kitti_raw.read_timestamps(f)
    assert e.value.line == 1


# ------------------------------------------------------------------------------------ layout


def test_find_drives_drive_date_root(raw_root):
    d26, d28 = raw_root / "2011_09_26", raw_root / "2011_09_28"
    drive1 = d26 / "2011_09_26_drive_0001_sync"
    assert kitti_raw.find_drives(drive1) == [drive1]
    assert kitti_raw.find_drives(d26) == [drive1, d26 / "2011_09_26_drive_0002_sync"]  # no _extract
    assert [p.name for p in kitti_raw.find_drives(raw_root)] == [
        "2011_09_26_drive_0001_sync", "2011_09_26_drive_0002_sync", "2011_09_28_drive_0016_sync"]
    assert kitti_raw.find_drives(drive1 / "image_02") == []
    assert kitti_raw.drive_name(drive1) == "2011_09_26_drive_0001"
    assert kitti_raw.camera_of(drive1 / "image_02" / "data") == "02"
    with pytest.raises(ValueError):
        kitti_raw.camera_of(drive1)


def test_open_sequence_drive(raw_root):
    drive = raw_root / "2011_09_26" / "2011_09_26_drive_0001_sync"
    seq = open_sequence(drive)
    assert seq.kind == "kitti_raw" and seq.path == drive and seq.image_dir == drive / "image_02" / "data"
    np.testing.assert_array_equal(seq.K, [[50, 0, 21.5], [0, 51, 11.5], [0, 0, 1]])
    assert seq.K_source == "calib_cam_to_cam.txt:P_rect_02"
    assert seq.image_size == (H, W) and len(seq) == 5 and seq.ground_truth_path() is None
    assert seq.timestamp(3) - seq.timestamp(0) == pytest.approx(0.3, abs=1e-6)
    frames = list(seq)
    assert all(isinstance(f, Frame) for f in frames)
    np.testing.assert_array_equal(frames[2].image, frame_img(2))
    sel = open_sequence(drive, start=1, stride=2)
    assert [f.index for f in sel] == [1, 3]


def test_open_sequence_grey_camera_and_overrides(tmp_path):
    date = tmp_path / "2011_09_26"
    date.mkdir()
    calib = synthetic_calib(date / kitti_raw.CALIB_NAME)
    drive = write_drive(date, "0005_sync", cams=("image_00",), times=False)
    seq = open_sequence(drive)
    assert seq.image_dir == drive / "image_00" / "data" and seq.K[0, 0] == 30 and seq.timestamp(0) is None
    assert seq.K_source == "calib_cam_to_cam.txt:P_rect_00"
    np.testing.assert_array_equal(open_sequence(drive, intrinsics=(9, 8, 7, 6)).K, [[9, 0, 7], [0, 8, 6], [0, 0, 1]])
    # --calib with a cam_to_cam file: the projection of the drive's camera (P_rect_00 = "P0")
    assert open_sequence(drive, calib=calib).K[0, 0] == 30


def test_open_sequence_drive_errors(raw_root, tmp_path):
    drive = raw_root / "2011_09_26" / "2011_09_26_drive_0001_sync"
    (raw_root / "2011_09_26" / kitti_raw.CALIB_NAME).unlink()
    with pytest.raises(InputError, match=r"no calib_cam_to_cam.txt in the date folder 2011_09_26/.*--intrinsics") as e:
        open_sequence(drive)
    assert e.value.path == str(drive)
    with pytest.raises(InputError, match=r"unrectified KITTI raw drive \(_extract\)"):
        open_sequence(raw_root / "2011_09_26" / "2011_09_26_drive_0009_extract", intrinsics=(1, 1, 1, 1))
    # timestamps that do not match the images
    d28 = raw_root / "2011_09_28" / "2011_09_28_drive_0016_sync"
    (d28 / "image_02" / "timestamps.txt").write_text(stamp(0) + "\n")
    with pytest.raises(InputError, match="1 timestamps for 5 images"):
        open_sequence(d28)
    # an empty camera folder
    date = tmp_path / "2011_10_03"
    date.mkdir()
    synthetic_calib(date / kitti_raw.CALIB_NAME)
    (date / "2011_10_03_drive_0027_sync" / "image_02" / "data").mkdir(parents=True)
    with pytest.raises(InputError, match="no images .* KITTI raw camera folder"):
        open_sequence(date / "2011_10_03_drive_0027_sync")


def test_calib_inside_the_drive_folder(tmp_path):
    date = tmp_path / "flat"
    date.mkdir()
    drive = write_drive(date, "0001_sync")
    synthetic_calib(drive / kitti_raw.CALIB_NAME)
    assert open_sequence(drive).K[0, 0] == 50


# ------------------------------------------------------------------------------------ random access


def test_files_and_read_frame_images(raw_root):
    drive = raw_root / "2011_09_26" / "2011_09_26_drive_0002_sync"
    bad = drive / "image_02" / "data" / "0000000003.png"
    bad.write_bytes(bad.read_bytes()[:40])
    seq = open_sequence(drive, start=1, stride=2)
    assert seq.files == tuple(sorted((drive / "image_02" / "data").glob("*.png")))
    fr = seq.read_frame(4)  # any source index, not only the selected ones
    assert isinstance(fr, Frame) and fr.index == 4 and fr.timestamp == seq.timestamp(4)
    np.testing.assert_array_equal(fr.image, frame_img(4))
    skip = seq.read_frame(3)
    assert isinstance(skip, FrameSkip) and skip.source == str(bad) and "cannot decode" in skip.reason
    for i in (-1, 5, 1.0, True):
        with pytest.raises(IndexError):
            seq.read_frame(i)


def test_read_frame_other_size_is_a_skip(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i}.png"), frame_img(i))
    cv2.imwrite(str(folder / "3.png"), np.zeros((H + 2, W, 3), np.uint8))
    seq = open_sequence(folder, intrinsics=(1, 1, 1, 1))
    assert "differs from the first frame" in seq.read_frame(3).reason


def write_video(path: Path, n: int, fourcc: str) -> Path:
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10.0, (64, 48))
    if not wr.isOpened():
        pytest.skip(f"no {fourcc} encoder in this OpenCV build")
    for i in range(n):
        im = np.random.default_rng(i).integers(0, 256, (48, 64, 3), dtype=np.uint8)
        im[:16, :16] = 8 * i
        wr.write(im)
    wr.release()
    return path


@pytest.mark.parametrize("name, fourcc", [("clip.avi", "MJPG"), ("clip.mp4", "mp4v")])
def test_video_random_access_matches_iteration(tmp_path, name, fourcc):
    seq = open_sequence(write_video(tmp_path / name, 30, fourcc), intrinsics=(50, 50, 32, 24))
    assert seq.files is None
    ref = {f.index: f.image for f in seq}
    assert sorted(ref) == list(range(30))
    order = [0, 1, 2, 5, 4, 29, 3, 3, 27, 10, 11, 0]  # forward grabs, seeks backwards and far ahead
    with FrameReader(seq) as reader:
        for i in order:
            fr = reader.read(i)
            assert isinstance(fr, Frame) and fr.index == i and fr.source.endswith(f"#{i}")
            np.testing.assert_array_equal(fr.image, ref[i], err_msg=f"frame {i}")
        # a reader pickled with an open capture (as into a spawned worker) opens its own
        clone = pickle.loads(pickle.dumps(reader))
        assert clone._cap is None
        np.testing.assert_array_equal(clone.read(7).image, ref[7])
        clone.close()
    np.testing.assert_array_equal(seq.read_frame(13).image, ref[13])


def test_video_reading_past_the_end_is_a_skip(tmp_path):
    seq = open_sequence(write_video(tmp_path / "clip.avi", 6, "MJPG"), intrinsics=(50, 50, 32, 24))
    seq.n_source_frames = 8  # a container that claims more frames than it holds
    with FrameReader(seq) as reader:
        skip = reader.read(7)
        assert isinstance(skip, FrameSkip) and "video ended before frame 7" in skip.reason
        assert isinstance(reader.read(2), Frame)  # still usable afterwards


def _read_in_child(reader, index, queue):
    fr = reader.read(index)
    reader.close()
    queue.put(None if not isinstance(fr, Frame) else fr.image)


def test_video_reader_inherited_through_fork(tmp_path):
    """A reader whose capture is open in the parent works in a forked child (which opens its own)."""
    import multiprocessing as mp

    seq = open_sequence(write_video(tmp_path / "clip.mp4", 12, "mp4v"), intrinsics=(50, 50, 32, 24))
    ref = {f.index: f.image for f in seq}
    reader = FrameReader(seq)
    np.testing.assert_array_equal(reader.read(2).image, ref[2])  # capture open here
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_read_in_child, args=(reader, 9, q))
    p.start()
    p.join(timeout=60)
    if p.is_alive():
        p.kill()
        pytest.fail("the forked child hung reading the video")
    assert p.exitcode == 0
    np.testing.assert_array_equal(q.get(timeout=5), ref[9])
    np.testing.assert_array_equal(reader.read(3).image, ref[3])  # the parent's capture still works
    reader.close()
