"""KITTI flow PNGs (layout, exact round trip to 1/64 px), ground-truth flow files, the
KITTI flow folder layout and pair lists, with one-line errors naming the file."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from trianflow_vo.errors import InputError
from trianflow_vo.io.flo import write_flo
from trianflow_vo.io.kitti_flow import (
    FlowPair,
    decode_kitti_flow,
    encode_kitti_flow,
    kitti_flow_pairs,
    read_flow_file,
    read_kitti_flow,
    read_pair_list,
    write_kitti_flow,
)


def _flow(h=6, w=9, seed=0, scale=200.0):
    return np.random.default_rng(seed).uniform(-scale, scale, (h, w, 2))


def test_round_trip_exact_on_the_64th_grid(tmp_path):
    flow = np.rint(_flow() * 64) / 64  # representable values
    valid = np.random.default_rng(1).random(flow.shape[:2]) < 0.7
    p = write_kitti_flow(tmp_path / "f.png", flow, valid)
    back, v = read_kitti_flow(p)
    assert back.dtype == np.float32 and back.shape == flow.shape and v.dtype == bool
    np.testing.assert_array_equal(v, valid)
    np.testing.assert_array_equal(back[valid], flow[valid].astype(np.float32))
    assert (back[~valid] == 0).all()
    assert list(tmp_path.iterdir()) == [p]  # no .tmp left


def test_round_trip_of_any_flow_within_half_a_64th():
    flow = _flow(seed=2, scale=500.0)
    back, v = decode_kitti_flow(encode_kitti_flow(flow))
    assert v.all()
    assert np.abs(back - flow).max() <= 0.5 / 64 + 1e-9


def test_file_layout_rgb_u_v_valid(tmp_path):
    """In the file: R = u*64 + 2^15, G = v*64 + 2^15, B = valid (cv2 reads B, G, R)."""
    flow = np.zeros((2, 3, 2))
    flow[0, 0] = (1.0, -0.5)
    flow[1, 2] = (-512.0, 511.984375)
    valid = np.array([[True, True, False], [True, True, True]])
    raw = cv2.imread(str(write_kitti_flow(tmp_path / "f.png", flow, valid)), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.shape == (2, 3, 3)
    assert raw[0, 0].tolist() == [1, 32768 - 32, 32768 + 64]  # B valid, G v, R u
    assert raw[1, 2].tolist() == [1, 65535, 0]
    assert raw[0, 2].tolist() == [0, 0, 0]  # invalid
    assert raw[0, 1].tolist() == [1, 32768, 32768]


def test_decode_hand_made_png(tmp_path):
    raw = np.zeros((1, 3, 3), np.uint16)
    raw[0, 0] = (1, 32768 + 128, 32768 - 64)  # valid, v = +2, u = -1
    raw[0, 1] = (0, 40000, 40000)  # invalid: zeroed
    raw[0, 2] = (7, 32768, 32768 + 1)  # any non-zero B is valid; u = 1/64
    cv2.imwrite(str(tmp_path / "f.png"), raw)
    flow, valid = read_kitti_flow(tmp_path / "f.png")
    assert valid.tolist() == [[True, False, True]]
    np.testing.assert_array_equal(flow[0], np.array([[-1.0, 2.0], [0.0, 0.0], [1 / 64, 0.0]], np.float32))


def test_encode_clips_and_checks():
    flow = np.array([[[600.0, -700.0]]])
    back, _ = decode_kitti_flow(encode_kitti_flow(flow))
    assert back[0, 0].tolist() == [65535 / 64 - 512, -512.0]
    with pytest.raises(ValueError, match="non-finite"):
        encode_kitti_flow(np.array([[[np.nan, 0.0]]]))
    encode_kitti_flow(np.array([[[np.nan, 0.0]]]), np.array([[False]]))  # fine where invalid
    with pytest.raises(ValueError, match=r"\(H, W, 2\)"):
        encode_kitti_flow(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="valid must be"):
        encode_kitti_flow(np.zeros((3, 3, 2)), np.ones((2, 2), bool))


def test_read_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match="nope.png: no such file"):
        read_kitti_flow(tmp_path / "nope.png")
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(InputError, match="empty.png: empty file"):
        read_kitti_flow(tmp_path / "empty.png")
    data = encode_kitti_flow(_flow(h=40, w=50))
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 3])
    with pytest.raises(InputError, match="cut.png: cannot decode the flow PNG"):
        read_kitti_flow(tmp_path / "cut.png")
    cv2.imwrite(str(tmp_path / "u8.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(InputError, match="u8.png: not a KITTI flow PNG: uint8 with 3 channel"):
        read_kitti_flow(tmp_path / "u8.png")
    cv2.imwrite(str(tmp_path / "grey16.png"), np.zeros((4, 4), np.uint16))
    with pytest.raises(InputError, match="grey16.png: not a KITTI flow PNG: uint16 with 1 channel"):
        read_kitti_flow(tmp_path / "grey16.png")
    (tmp_path / "sub.png").mkdir()
    with pytest.raises(InputError, match="sub.png: is a folder"):
        read_kitti_flow(tmp_path / "sub.png")


def test_read_flow_file_png_and_flo(tmp_path):
    flow = np.rint(_flow(seed=3) * 64) / 64
    write_kitti_flow(tmp_path / "a.png", flow)
    f, v = read_flow_file(tmp_path / "a.png")
    assert v.all() and np.array_equal(f, flow.astype(np.float32))
    flo = flow.astype(np.float32)
    flo[0, 0] = (1e10, 1e10)  # Middlebury's unknown flow
    flo[0, 1, 1] = np.nan
    write_flo(tmp_path / "a.flo", flo)
    f, v = read_flow_file(tmp_path / "a.flo")
    assert not v[0, 0] and not v[0, 1] and v.sum() == v.size - 2
    assert (f[0, :2] == 0).all() and np.array_equal(f[v], flo[v])
    with pytest.raises(InputError, match="a.npy: unknown ground-truth flow format"):
        read_flow_file(tmp_path / "a.npy")


# --------------------------------------------------------------------------- layout and lists


def _png(path, seed=0):
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.random.default_rng(seed).integers(0, 255, (8, 10, 3), dtype=np.uint8))
    return path


def _kitti(root, n=2, gt_dirs=("flow_occ",)):
    """A KITTI flow folder with pairs 000010 and (n=2) 000002, written in that order."""
    for i in (10, 2)[:n]:
        for k in ("10", "11"):
            _png(root / "image_2" / f"{i:06d}_{k}.png", i)
        for d in gt_dirs:
            (root / d).mkdir(parents=True, exist_ok=True)
            write_kitti_flow(root / d / f"{i:06d}_10.png", np.zeros((8, 10, 2)))
    return root


def test_kitti_layout_pairs_in_natural_order(tmp_path):
    root = _kitti(tmp_path / "training", gt_dirs=("flow_noc", "flow_occ"))
    pairs, gt_dir = kitti_flow_pairs(root)
    assert gt_dir == root / "flow_occ"  # occ (all pixels) preferred
    assert [p.name for p in pairs] == ["000002_10", "000010_10"]
    assert pairs[0] == FlowPair(root / "image_2/000002_10.png", root / "image_2/000002_11.png",
                                root / "flow_occ/000002_10.png")
    pairs, gt_dir = kitti_flow_pairs(root, root / "flow_noc")
    assert gt_dir == root / "flow_noc" and pairs[1].gt == root / "flow_noc/000010_10.png"
    # the image folder itself works too, ground truth beside it
    pairs, gt_dir = kitti_flow_pairs(root / "image_2")
    assert gt_dir == root / "flow_occ" and len(pairs) == 2


def test_kitti_layout_flo_ground_truth_and_noc_fallback(tmp_path):
    root = _kitti(tmp_path / "t", n=1, gt_dirs=())
    (root / "flow_noc").mkdir()
    write_flo(root / "flow_noc" / "000010_10.flo", np.zeros((8, 10, 2), np.float32))
    pairs, gt_dir = kitti_flow_pairs(root)
    assert gt_dir == root / "flow_noc" and pairs[0].gt.suffix == ".flo"


def test_kitti_layout_errors(tmp_path):
    with pytest.raises(InputError, match="nope: no such folder"):
        kitti_flow_pairs(tmp_path / "nope")
    (tmp_path / "empty" / "image_2").mkdir(parents=True)
    with pytest.raises(InputError, match=r"image_2: no first images \(NNNNNN_10.png\)"):
        kitti_flow_pairs(tmp_path / "empty")
    root = _kitti(tmp_path / "a", gt_dirs=())
    with pytest.raises(InputError, match=r"a: no ground-truth folder \(flow_occ or flow_noc\).*--gt-flow"):
        kitti_flow_pairs(root)
    with pytest.raises(InputError, match="elsewhere: ground-truth flow folder not found"):
        kitti_flow_pairs(root, tmp_path / "elsewhere")
    root = _kitti(tmp_path / "b")
    (root / "image_2" / "000010_11.png").unlink()
    with pytest.raises(InputError, match=r"000010_10.png: no second image 000010_11.png"):
        kitti_flow_pairs(root)
    root = _kitti(tmp_path / "c")
    (root / "flow_occ" / "000002_10.png").unlink()
    with pytest.raises(InputError, match=r"000002_10.png: no ground-truth flow for this image \(looked for "
                                         r"000002_10.png and 000002_10.flo"):
        kitti_flow_pairs(root)


def test_pair_list(tmp_path):
    a, b = _png(tmp_path / "x" / "a.png"), _png(tmp_path / "x" / "b.png")
    write_kitti_flow(tmp_path / "gt.png", np.zeros((8, 10, 2)))
    lst = tmp_path / "pairs.txt"
    lst.write_text(f"# first image, second image, ground truth\n\nx/a.png x/b.png gt.png\n"
                   f"{b} {a} {tmp_path / 'gt.png'}\n")
    pairs = read_pair_list(lst)
    assert pairs == [FlowPair(a, b, tmp_path / "gt.png"), FlowPair(b, a, tmp_path / "gt.png")]
    lst.write_text("x/a.png x/b.png\n")
    with pytest.raises(InputError, match=r"pairs.txt:1: expected 'image1 image2 ground_truth', got 2 field"):
        read_pair_list(lst)
    lst.write_text("# nothing\nx/a.png x/b.png gt.png\nx/a.png x/c.png gt.png\n")
    with pytest.raises(InputError, match=r"pairs.txt:3: .*c.png: no such file"):
        read_pair_list(lst)
    lst.write_text("# only comments\n")
    with pytest.raises(InputError, match="pairs.txt: no pairs"):
        read_pair_list(lst)
    with pytest.raises(InputError, match="missing.txt: no such file"):
        read_pair_list(tmp_path / "missing.txt")
