"""Middlebury ``.flo`` files: layout, round trip, one-line errors."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from trianflow_vo.errors import InputError
from trianflow_vo.io.flo import FLO_MAGIC, decode_flo, encode_flo, read_flo, write_flo


def _flow(h=5, w=7, seed=0):
    return np.random.default_rng(seed).normal(0, 10, (h, w, 2)).astype(np.float32)


def test_round_trip_is_exact(tmp_path):
    flow = _flow()
    flow[0, 0] = [np.inf, -0.0]
    p = write_flo(tmp_path / "a.flo", flow)
    back = read_flo(p)
    assert back.dtype == np.float32 and back.shape == flow.shape
    np.testing.assert_array_equal(back, flow)
    assert back.flags.writeable
    assert list(tmp_path.iterdir()) == [p]  # no .tmp left behind


def test_layout_magic_little_endian_width_height_interleaved(tmp_path):
    flow = _flow(h=3, w=4)
    data = write_flo(tmp_path / "a.flo", flow).read_bytes()
    assert len(data) == 12 + 3 * 4 * 2 * 4
    assert data[:4] == b"PIEH"
    assert struct.unpack("<f", data[:4])[0] == FLO_MAGIC == 202021.25
    assert struct.unpack("<ii", data[4:12]) == (4, 3)  # width first, then height
    u00, v00, u01 = struct.unpack("<fff", data[12:24])
    assert (u00, v00, u01) == (flow[0, 0, 0], flow[0, 0, 1], flow[0, 1, 0])
    last_v = struct.unpack("<f", data[-4:])[0]
    assert last_v == flow[2, 3, 1]


def test_float64_is_stored_as_float32():
    flow = _flow().astype(np.float64)
    np.testing.assert_array_equal(decode_flo(encode_flo(flow)), flow.astype(np.float32))


def test_overwrite_replaces(tmp_path):
    p = tmp_path / "a.flo"
    write_flo(p, _flow(seed=1))
    write_flo(p, _flow(h=2, w=2, seed=2))
    np.testing.assert_array_equal(read_flo(p), _flow(h=2, w=2, seed=2))


@pytest.mark.parametrize("shape", [(4, 4), (4, 4, 3), (0, 4, 2)])
def test_bad_shape(shape, tmp_path):
    with pytest.raises(ValueError):
        write_flo(tmp_path / "a.flo", np.zeros(shape, np.float32))
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("mangle, words", [
    (lambda d: b"XXXX" + d[4:], "magic"),
    (lambda d: d[:8], "header"),
    (lambda d: d[:-4], "expected"),
    (lambda d: d[:4] + struct.pack("<ii", -1, 3) + d[12:], "invalid size"),
])
def test_bad_files_one_line_naming_the_file(mangle, words, tmp_path):
    p = tmp_path / "bad.flo"
    p.write_bytes(mangle(encode_flo(_flow(h=3, w=4))))
    with pytest.raises(InputError) as e:
        read_flo(p)
    msg = str(e.value)
    assert "\n" not in msg and str(p) in msg and words in msg


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_flo(tmp_path / "nope.flo")
