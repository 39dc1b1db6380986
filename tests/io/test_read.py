"""trianflow_vo.io.read: one-line errors naming the file, shared by the flow and depth readers."""

import pytest

from trianflow_vo.errors import InputError
from trianflow_vo.io.depth_png import read_depth_png
from trianflow_vo.io.flo import read_flo
from trianflow_vo.io.kitti_flow import read_kitti_flow
from trianflow_vo.io.read import read_bytes


def test_read_bytes_returns_the_file_and_names_it_when_it_cannot(tmp_path):
    f = tmp_path / "a.bin"
    f.write_bytes(b"\x00\x01")
    assert read_bytes(f) == b"\x00\x01"
    with pytest.raises(InputError, match="no such file") as missing:
        read_bytes(tmp_path / "none.bin")
    assert "none.bin" in str(missing.value)
    with pytest.raises(InputError, match="is a folder, expected a file") as folder:
        read_bytes(tmp_path)
    assert str(tmp_path) in str(folder.value)


@pytest.mark.parametrize("reader", [read_flo, read_kitti_flow, read_depth_png])
def test_every_reader_names_a_folder_given_for_a_file(tmp_path, reader):
    with pytest.raises(InputError, match="is a folder, expected a file"):
        reader(tmp_path)
