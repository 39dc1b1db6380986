"""Training data layer (train/data.py): sources, pairs, resize + K, flip, bad frames, exclusions,
static filter and its cache, fingerprint, DataLoader workers; synthetic data first, then real."""

from __future__ import annotations

import json
import pickle
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from trianflow_vo.errors import ConfigError, InputError
from trianflow_vo.io import kitti_raw
from trianflow_vo.train import data as D
from trianflow_vo.train.data import (PairDataset, StaticFilter, collate_pairs, eigen_test_scenes, fingerprint,
                                     has_ground_truth, open_training_sources)

H, W = 24, 40
FX, FY, CX, CY = 50.0, 40.0, 19.5, 11.5


def frame(i: int, shift: int = 0) -> np.ndarray:
    """A textured colour frame; ``shift`` moves the texture right by that many pixels."""
    rng = np.random.default_rng(1000 + i)
    tex = cv2.GaussianBlur(rng.integers(0, 256, (H, W + 64, 3), dtype=np.uint8), (3, 3), 0)
    im = np.ascontiguousarray(tex[:, 32 - shift: 32 - shift + W])
    im[..., 0] = np.clip(im[..., 0].astype(int) // 2, 0, 255)  # B differs from G and R
    return im


def write_images(folder: Path, n: int, ext=".png", frames=None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        cv2.imwrite(str(folder / f"{i:06d}{ext}"), frame(i) if frames is None else frames[i])
    return folder


def calib_line(key: str) -> str:
    return f"{key}: {FX} 0 {CX} 0 0 {FY} {CY} 0 0 0 1 0"


def write_raw_drive(root: Path, date: str, drive: str, n: int = 6, calib=True) -> Path:
    d = root / date / f"{date}_drive_{drive}_sync"
    write_images(d / "image_02" / "data", n)
    if calib:
        (root / date / kitti_raw.CALIB_NAME).write_text(
            "calib_time: 09-Jan-2012 13:57:47\nS_rect_02: 40 24\n" + calib_line("P_rect_02") + "\n")
    return d


def write_odometry(seq_dir: Path, n: int = 6) -> Path:
    write_images(seq_dir / "image_2", n)
    (seq_dir / "calib.txt").write_text("\n".join(calib_line(f"P{c}") for c in range(4)) + "\n")
    return seq_dir


def write_tum(folder: Path, n: int = 6) -> Path:
    write_images(folder / "rgb", n)
    (folder / "rgb.txt").write_text("# ts file\n" + "".join(f"{i * 0.1:.6f} rgb/{i:06d}.png\n" for i in range(n)))
    (folder / "groundtruth.txt").write_text("".join(f"{i * 0.1:.6f} 0 0 0 0 0 0 1\n" for i in range(n)))
    return folder


def write_video(path: Path, n: int) -> Path:
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, H))
    assert wr.isOpened(), "cannot write MJPG video here"
    for i in range(n):
        wr.write(frame(i))
    wr.release()
    return path


@pytest.fixture
def raw(tmp_path) -> Path:
    root = tmp_path / "raw"
    write_raw_drive(root, "2011_09_26", "0001")
    write_raw_drive(root, "2011_09_26", "0002")  # an Eigen test drive
    write_raw_drive(root, "2011_09_28", "0016", n=4)
    return root


# ------------------------------------------------------------------------------------ sources


def test_sources_of_every_format(tmp_path, raw):
    odo = write_odometry(tmp_path / "odo" / "sequences" / "00")
    write_odometry(tmp_path / "odo" / "sequences" / "01", n=3)
    (tmp_path / "odo" / "poses").mkdir()
    (tmp_path / "odo" / "poses" / "00.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 6)
    tum = write_tum(tmp_path / "rgbd_dataset_freiburg1_xyz")
    imgs = write_images(tmp_path / "clip", 5)
    (imgs / "K.txt").write_text(f"{FX} {FY} {CX} {CY}\n")
    (imgs / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 5)
    video = write_video(tmp_path / "v.avi", 7)

    srcs = open_training_sources([raw], intrinsics=None)
    assert [s.name for s in srcs] == ["2011_09_26_drive_0001_sync", "2011_09_26_drive_0002_sync",
                                      "2011_09_28_drive_0016_sync"]
    assert {s.kind for s in srcs} == {"kitti_raw"} and not any(has_ground_truth(s) for s in srcs)
    np.testing.assert_array_equal(srcs[0].K, [[FX, 0, CX], [0, FY, CY], [0, 0, 1]])
    assert [s.name for s in open_training_sources([raw / "2011_09_28"])] == ["2011_09_28_drive_0016_sync"]
    # the odometry dataset root, its sequences/ folder and one sequence
    for p in (tmp_path / "odo", tmp_path / "odo" / "sequences"):
        assert [s.name for s in open_training_sources([p])] == ["00", "01"]
    (s00,) = open_training_sources([odo])
    assert s00.kind == "kitti" and s00.ground_truth_path == tmp_path / "odo" / "poses" / "00.txt"
    (t,) = open_training_sources([tum])
    assert t.kind == "tum" and t.ground_truth_path == tum / "groundtruth.txt" and has_ground_truth(t)
    (c,) = open_training_sources([imgs])
    assert c.kind == "images" and c.ground_truth_path == imgs / "poses.txt"
    (v,) = open_training_sources([video], intrinsics=(FX, FY, CX, CY))
    assert v.kind == "video" and v.name == "v.avi" and v.ground_truth_path is None
    # a sequence reached twice is kept once; order follows the arguments
    both = open_training_sources([raw / "2011_09_28", raw])
    assert [s.name for s in both] == ["2011_09_28_drive_0016_sync", "2011_09_26_drive_0001_sync",
                                      "2011_09_26_drive_0002_sync"]


def test_source_errors_name_the_path(tmp_path, raw):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no images") as e:
        open_training_sources([empty])
    assert e.value.path == str(empty)
    (raw / "2011_09_28" / kitti_raw.CALIB_NAME).unlink()
    drive = raw / "2011_09_28" / "2011_09_28_drive_0016_sync"
    with pytest.raises(InputError, match=r"no camera intrinsics .*--intrinsics fx,fy,cx,cy or --calib FILE") as e:
        open_training_sources([raw])
    assert e.value.path == str(drive)
    assert open_training_sources([drive], intrinsics=(1, 2, 3, 4))[0].K[0, 0] == 1  # how to give it works
    notes = tmp_path / "notes.txt"
    notes.write_text("hello")
    with pytest.raises(InputError, match="not a video file") as e:
        open_training_sources([notes])
    assert e.value.path == str(notes)
    with pytest.raises(InputError, match="no such file or folder"):
        open_training_sources([tmp_path / "missing"])
    with pytest.raises(InputError, match="no training data given"):
        open_training_sources([])
    ext = tmp_path / "x" / "2011_09_30"
    (ext / "2011_09_30_drive_0016_extract" / "image_02" / "data").mkdir(parents=True)
    with pytest.raises(InputError, match="only unrectified"):
        open_training_sources([ext])


# ------------------------------------------------------------------------------------ pairs, images, K


def test_pair_counts_gap_1_and_2(raw):
    srcs = open_training_sources([raw])  # 6 + 6 + 4 frames
    ds1 = PairDataset(srcs, size=(H, W), gap=1)
    assert len(ds1) == 5 + 5 + 3
    assert ds1.pair(0) == (0, 0, 1) and ds1.pair(5) == (1, 0, 1) and ds1.pair(12) == (2, 2, 3)
    ds2 = PairDataset(srcs, size=(H, W), gap=2)
    assert len(ds2) == 4 + 4 + 2 and ds2.pair(9) == (2, 1, 3)
    assert len(PairDataset(srcs, size=(H, W), gap=5)) == 1 + 1 + 0
    with pytest.raises(IndexError):
        ds1.get(13)
    with pytest.raises(ConfigError, match="data.gap"):
        PairDataset(srcs, gap=0)
    with pytest.raises(ConfigError, match="data.size"):
        PairDataset(srcs, size=(0, 64))


def test_resize_and_K_scaling_known_numbers(raw):
    srcs = open_training_sources([raw])
    ds = PairDataset(srcs, size=(36, 80), gap=2)  # x2 in width, x1.5 in height
    it = ds.get(1, flip=False)
    assert set(it) == {"img1", "img2", "K", "K_inv", "index", "flipped"} and it["index"] == 1
    assert it["img1"].shape == (3, 36, 80) and it["img1"].dtype == torch.float32
    K = it["K"].numpy()
    np.testing.assert_allclose(K, [[2 * FX, 0, 2 * CX], [0, 1.5 * FY, 1.5 * CY], [0, 0, 1]], rtol=1e-6)
    np.testing.assert_allclose(it["K_inv"].numpy() @ K, np.eye(3), atol=1e-6)
    # pair 1 is frames (1, 3) of the first drive: BGR, bilinear resize, / 255
    for key, i in (("img1", 1), ("img2", 3)):
        want = cv2.resize(frame(i), (80, 36), interpolation=cv2.INTER_LINEAR).transpose(2, 0, 1) / 255.0
        np.testing.assert_allclose(it[key].numpy(), want, atol=1e-6)
    assert float(it["img1"].min()) >= 0 and float(it["img1"].max()) <= 1


def test_flip_mirrors_images_and_cx_exactly(raw):
    ds = PairDataset(open_training_sources([raw]), size=(H, W))  # no resize: source pixels
    a, b = ds.get(3, flip=False), ds.get(3, flip=True)
    assert b["flipped"] and not a["flipped"]
    for key in ("img1", "img2"):
        np.testing.assert_array_equal(b[key].numpy(), a[key].numpy()[:, :, ::-1])
        # pixel check: column x of the flipped image is column W - 1 - x of the original
        np.testing.assert_array_equal(b[key].numpy()[:, 5, 3], a[key].numpy()[:, 5, W - 1 - 3])
    Kf = b["K"].numpy().astype(np.float64)
    assert Kf[0, 2] == W - 1 - CX and Kf[0, 0] == FX and Kf[1, 1] == FY and Kf[1, 2] == CY
    # geometry: a point projecting to u projects to W - 1 - u in the mirrored camera/scene
    X = np.array([0.7, -0.2, 3.0])
    u = a["K"].numpy().astype(np.float64) @ X
    uf = Kf @ (X * [-1, 1, 1])
    assert uf[0] / uf[2] == pytest.approx(W - 1 - u[0] / u[2]) and uf[1] / uf[2] == pytest.approx(u[1] / u[2])
    np.testing.assert_allclose(b["K_inv"].numpy() @ b["K"].numpy(), np.eye(3), atol=1e-6)
    # a single bright pixel lands where cx' says: at the image centre column mirrored
    K_skew = np.array([[FX, 2.0, CX], [0, FY, CY], [0, 0, 1]])
    np.testing.assert_allclose(D.flip_intrinsics(K_skew, W), [[FX, -2.0, W - 1 - CX], [0, FY, CY], [0, 0, 1]])


def test_flips_are_deterministic_and_touch_no_global_rng(raw):
    srcs = open_training_sources([raw])
    a = PairDataset(srcs, size=(H, W), flip=True, seed=3)
    b = PairDataset(srcs, size=(H, W), flip=True, seed=3)
    c = PairDataset(srcs, size=(H, W), flip=True, seed=4)
    np_state, torch_state = np.random.get_state()[1].copy(), torch.random.get_rng_state().clone()
    fa = [a[k]["flipped"] for k in range(len(a))]
    assert fa == [b[k]["flipped"] for k in range(len(b))] == [a.flip_for(k) for k in range(len(a))]
    np.testing.assert_array_equal(np.random.get_state()[1], np_state)
    assert torch.equal(torch.random.get_rng_state(), torch_state)
    many = [a.flip_for(k, e) for e in range(20) for k in range(len(a))]  # 260 coins
    assert 80 < sum(many) < 180
    assert many != [c.flip_for(k, e) for e in range(20) for k in range(len(c))]
    assert [a[(k, 5)]["flipped"] for k in range(len(a))] == [a.flip_for(k, 5) for k in range(len(a))]
    assert not any(PairDataset(srcs, size=(H, W), flip=False)[k]["flipped"] for k in range(13))


def test_bad_frame_gives_none_and_collate_counts_it(raw):
    bad = raw / "2011_09_26" / "2011_09_26_drive_0001_sync" / "image_02" / "data" / "000002.png"
    bad.write_bytes(bad.read_bytes()[:50])
    ds = PairDataset(open_training_sources([raw]), size=(H, W))
    assert ds[1] is None and ds[2] is None and ds[0] is not None and ds[3] is not None  # pairs (1,2), (2,3)
    assert str(bad) in ds.skip_reason(1) and ds.skip_reason(0) is None
    batch, skipped = collate_pairs([ds[k] for k in range(5)])
    assert skipped == 2 and batch["img1"].shape == (3, 3, H, W) and batch["K"].shape == (3, 3, 3)
    assert batch["index"].tolist() == [0, 3, 4] and batch["flipped"].dtype == torch.bool
    assert collate_pairs([None, None]) == (None, 2)
    bad.unlink()  # a file vanishing after the listing is a bad sample too
    assert ds[1] is None


def test_exclusion_by_name_pattern_and_eigen_list(raw):
    srcs = open_training_sources([raw])
    names = lambda ds: [s.name for s in ds.sources]  # noqa: E731
    ds = PairDataset(srcs, size=(H, W), exclude=["2011_09_26_drive_0002_sync"])
    assert names(ds) == ["2011_09_26_drive_0001_sync", "2011_09_28_drive_0016_sync"] and len(ds) == 8
    assert ds.excluded_sources == [("2011_09_26_drive_0002_sync", "2011_09_26_drive_0002_sync")]
    assert names(PairDataset(srcs, size=(H, W), exclude=["2011_09_26_drive_0002"])) == names(ds)  # Eigen form
    assert names(PairDataset(srcs, size=(H, W), exclude=["2011_09_26_*"])) == ["2011_09_28_drive_0016_sync"]
    by_date = PairDataset(srcs, size=(H, W), exclude=["2011_09_28/*"])  # <date>/<drive>
    assert names(by_date) == ["2011_09_26_drive_0001_sync", "2011_09_26_drive_0002_sync"]
    eig = PairDataset(srcs, size=(H, W), exclude=eigen_test_scenes())
    assert names(eig) == names(ds) and len(eig.unused_exclusions) == 27
    typo = PairDataset(srcs, size=(H, W), exclude=["2011_09_26_drive_0003"])
    assert len(typo.sources) == 3 and typo.unused_exclusions == ["2011_09_26_drive_0003"]


def test_eigen_test_scenes_list():
    scenes = eigen_test_scenes()
    assert len(scenes) == 28 and len(set(scenes)) == 28
    assert all(re.fullmatch(r"2011_\d\d_\d\d_drive_\d{4}", s) for s in scenes)
    assert {"2011_09_26_drive_0002", "2011_09_26_drive_0117", "2011_10_03_drive_0047"} <= set(scenes)


# ------------------------------------------------------------------------------------ static filter


MH, MW = 48, 80  # DIS needs a few more pixels than the other tests' frames


def smooth_frame(shift: int) -> np.ndarray:
    """A smooth texture (DIS tracks it exactly) moved right by ``shift`` pixels."""
    rng = np.random.default_rng(5)
    tex = cv2.GaussianBlur(rng.integers(0, 256, (MH, MW + 80), dtype=np.uint8), (9, 9), 0)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX)
    return cv2.cvtColor(np.ascontiguousarray(tex[:, 40 - shift: 40 - shift + MW]), cv2.COLOR_GRAY2BGR)


@pytest.fixture
def moving(tmp_path) -> Path:
    """Frames moving 6 px per frame, except frame 3 == frame 2 (a stop)."""
    shifts = [0, 6, 12, 12, 18, 24]
    frames = [smooth_frame(s) for s in shifts]
    folder = write_images(tmp_path / "moving", len(frames), frames=frames)
    (folder / "K.txt").write_text(f"{FX} {FY} {CX} {CY}\n")
    return folder


def test_median_flow_of_a_known_shift():
    a = cv2.cvtColor(smooth_frame(0), cv2.COLOR_BGR2GRAY)
    b = cv2.cvtColor(smooth_frame(6), cv2.COLOR_BGR2GRAY)
    assert D.median_flow_px(a, b) == pytest.approx(6.0, abs=0.3)
    assert D.median_flow_px(a, b, sx=2.0, sy=3.0) == pytest.approx(12.0, abs=0.6)  # a pure x shift
    assert D.median_flow_px(b, a) == pytest.approx(6.0, abs=0.3)
    assert D.median_flow_px(a, a) < 0.05


def test_static_filter_drops_the_duplicate_and_reuses_its_cache(moving, tmp_path, monkeypatch):
    srcs = open_training_sources([moving])
    cache = tmp_path / "cache"
    calls = []
    real = D.median_flow_px
    monkeypatch.setattr(D, "median_flow_px", lambda *a, **k: calls.append(1) or real(*a, **k))
    progress = []
    ds = PairDataset(srcs, size=(MH * 2, MW * 2), static_filter=StaticFilter(1.0, cache, scale=0.5,
                                                                          progress=lambda *a: progress.append(a)))
    assert len(calls) == 5 and progress[-1] == ("moving", 5, 5)
    assert len(ds) == 4 and ds.n_static == 1
    assert [ds.pair(k)[1:] for k in range(4)] == [(0, 1), (1, 2), (3, 4), (4, 5)]  # (2, 3) dropped
    (f,) = cache.glob("static-moving-*.json")
    doc = json.loads(f.read_text())
    assert doc["pairs"] == [[i, i + 1] for i in range(5)]
    # medians in training pixels (x2 of the source): about 12, and ~0 for the stop
    med = np.array(doc["median_px"])
    assert med[2] < 0.1 and np.all(np.abs(med[[0, 1, 3, 4]] - 12) < 0.6)
    calls.clear()
    again = PairDataset(srcs, size=(MH * 2, MW * 2), static_filter=StaticFilter(1.0, cache, scale=0.5))
    assert calls == [] and [again.pair(k) for k in range(len(again))] == [ds.pair(k) for k in range(len(ds))]
    # another threshold reuses the medians; another size recomputes
    assert len(PairDataset(srcs, size=(MH * 2, MW * 2), static_filter=StaticFilter(50.0, cache, scale=0.5))) == 0
    assert calls == []
    PairDataset(srcs, size=(MH, MW), static_filter=StaticFilter(1.0, cache, scale=0.5))
    assert len(calls) == 5
    # a corrupt cache is recomputed, not fatal
    f.write_text("{not json")
    calls.clear()
    assert len(PairDataset(srcs, size=(MH * 2, MW * 2), static_filter=StaticFilter(1.0, cache, scale=0.5))) == 4
    assert len(calls) == 5 and json.loads(f.read_text())["pairs"]


def test_static_filter_keeps_unreadable_pairs_and_checks_settings(moving, tmp_path):
    bad = moving / "000003.png"
    bad.write_bytes(b"")
    srcs = open_training_sources([moving])
    ds = PairDataset(srcs, size=(MH * 2, MW * 2), static_filter=StaticFilter(1.0, None, scale=0.5))
    assert len(ds) == 5 and ds.n_static == 0 and ds[2] is None  # (2, 3) cannot be judged: kept, then skipped at load
    with pytest.raises(ConfigError, match="static_threshold_px"):
        StaticFilter(-1.0)
    with pytest.raises(ConfigError):
        StaticFilter(1.0, scale=0.0)


# ------------------------------------------------------------------------------------ fingerprint


def test_fingerprint_tracks_data_and_settings(raw, tmp_path, moving):
    srcs = open_training_sources([raw])
    base = fingerprint(PairDataset(srcs, size=(H, W)))
    assert re.fullmatch(r"[0-9a-f]{16}", base)
    assert fingerprint(PairDataset(open_training_sources([raw]), size=(H, W))) == base
    others = [
        PairDataset(srcs, size=(H, 2 * W)),
        PairDataset(srcs, size=(H, W), gap=2),
        PairDataset(srcs, size=(H, W), exclude=["nothing-matches"]),
        PairDataset(srcs[:2], size=(H, W)),
        PairDataset(srcs, size=(H, W), static_filter=StaticFilter(0.0, None, scale=0.5)),
    ]
    fps = [fingerprint(d) for d in others]
    assert base not in fps and len(set(fps)) == len(fps)
    # moved elsewhere: same data, same fingerprint
    shutil.copytree(raw, tmp_path / "moved")
    assert fingerprint(PairDataset(open_training_sources([tmp_path / "moved"]), size=(H, W))) == base
    # a frame rewritten with other content (another file size) changes it
    f = raw / "2011_09_28" / "2011_09_28_drive_0016_sync" / "image_02" / "data" / "000001.png"
    cv2.imwrite(str(f), np.zeros((H, W, 3), np.uint8))
    assert fingerprint(PairDataset(open_training_sources([raw]), size=(H, W))) != base
    # the static filter's decisions are part of it
    m = open_training_sources([moving])
    assert (fingerprint(PairDataset(m, size=(H, W), static_filter=StaticFilter(1.0, None, scale=0.5)))
            != fingerprint(PairDataset(m, size=(H, W), static_filter=StaticFilter(100.0, None, scale=0.5))))


# ------------------------------------------------------------------------------------ video, workers, memory


def test_video_pairs_match_decoded_frames(tmp_path):
    video = write_video(tmp_path / "v.avi", 7)
    (src,) = open_training_sources([video], intrinsics=(FX, FY, CX, CY))
    frames = {f.index: f.image for f in src.sequence}
    ds = PairDataset([src], size=(H, W), gap=3)
    assert len(ds) == 4
    for k in (3, 0, 2):  # out of order: seeks
        it = ds.get(k, flip=False)
        np.testing.assert_allclose(it["img1"].numpy(), frames[k].transpose(2, 0, 1) / 255.0, atol=1e-6)
        np.testing.assert_allclose(it["img2"].numpy(), frames[k + 3].transpose(2, 0, 1) / 255.0, atol=1e-6)


def test_dataloader_workers_and_pickling(tmp_path, raw):
    video = write_video(tmp_path / "v.avi", 7)
    srcs = open_training_sources([raw]) + open_training_sources([video], intrinsics=(FX, FY, CX, CY))
    ds = PairDataset(srcs, size=(H, W), flip=True, seed=1)
    main = [ds[k] for k in range(len(ds))]  # opens the video capture in this process
    clone = pickle.loads(pickle.dumps(ds))
    assert all(r._cap is None for r in clone._readers)
    loader = torch.utils.data.DataLoader(ds, batch_size=4, num_workers=1, collate_fn=collate_pairs,
                                         multiprocessing_context="fork", timeout=60)
    got = []
    for batch, skipped in loader:
        assert skipped == 0
        got += [{k: batch[k][j] for k in ("img1", "img2", "K")} | {"index": int(batch["index"][j])}
                for j in range(len(batch["index"]))]
    assert [g["index"] for g in got] == list(range(len(ds)))
    for g, m in zip(got, main):
        for k in ("img1", "img2", "K"):
            assert torch.equal(g[k], m[k])


def test_dataset_holds_file_names_not_images(tmp_path):
    folder = write_images(tmp_path / "many", 200, ext=".jpg")
    (folder / "K.txt").write_text(f"{FX} {FY} {CX} {CY}\n")
    ds = PairDataset(open_training_sources([folder]), size=(H, W))
    assert len(ds) == 199
    assert len(pickle.dumps(ds)) < 200 * 300  # names only: one frame alone is 24*40*3 = 2880 bytes


# ------------------------------------------------------------------------------------ real data


def test_real_kitti_clip(shared_data):
    clip = shared_data / "kitti00-f0000-0150"
    if not clip.is_dir():
        pytest.skip(f"{clip} not found")
    (src,) = open_training_sources([clip])
    assert src.kind == "kitti" and src.image_size == (376, 1241) and has_ground_truth(src)
    ds = PairDataset([src], size=(128, 416), flip=True)
    assert len(ds) == 150
    it = ds.get(75, flip=False)
    # KITTI 00 P0: fx = fy = 718.856, cx = 607.1928, cy = 185.2157 at 1241 x 376
    np.testing.assert_allclose(it["K"].numpy(), [[718.856 * 416 / 1241, 0, 607.1928 * 416 / 1241],
                                                 [0, 718.856 * 128 / 376, 185.2157 * 128 / 376], [0, 0, 1]], rtol=1e-6)
    img = it["img1"].numpy()
    assert img.shape == (3, 128, 416) and 0.05 < img.mean() < 0.95
    np.testing.assert_array_equal(img[0], img[2])  # image_0 is grey: B = G = R
    flipped = ds.get(75, flip=True)
    assert float(flipped["K"][0, 2]) == pytest.approx(415 - 607.1928 * 416 / 1241, abs=1e-4)
    # consecutive frames of a driving car are not static: a threshold of 1 px keeps the first pairs
    head = open_training_sources([clip])[0]
    head.sequence.end = 6  # the first 6 frames only, to stay fast
    kept = PairDataset([head], size=(128, 416), static_filter=StaticFilter(1.0, None))
    assert len(kept) == 5 and kept.n_static == 0
