"""cmax.io.atomic: small outputs appear under their final name only when complete."""
import numpy as np
import pytest

from cmax.io.atomic import save_npz_atomic, write_text_atomic


def test_text_written_whole_and_no_partial_left(tmp_path):
    path = write_text_atomic(tmp_path / "summary.json", "{\"a\": 1}\n")
    assert path.read_text() == "{\"a\": 1}\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]


def test_npz_keeps_the_given_name(tmp_path):
    depth = np.arange(6, dtype=np.float32).reshape(2, 3)
    path = save_npz_atomic(tmp_path / "depth.bin", depth=depth)  # numpy alone would write depth.bin.npz
    assert sorted(p.name for p in tmp_path.iterdir()) == ["depth.bin"]
    with np.load(path) as data:
        np.testing.assert_array_equal(data["depth"], depth)


class _Unwritable:
    def __array__(self, dtype=None, copy=None):
        raise RuntimeError("disk full")


def test_failed_write_leaves_the_old_file(tmp_path):
    path = write_text_atomic(tmp_path / "out.npz", "old")
    with pytest.raises(RuntimeError, match="disk full"):
        save_npz_atomic(path, depth=_Unwritable())
    assert path.read_text() == "old"
