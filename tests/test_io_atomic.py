"""cmax.io.atomic: small outputs appear under their final name only when complete."""
import os

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


def test_output_appears_only_at_commit_and_leaves_no_lock(tmp_path):
    from cmax.io.atomic import AtomicOutput

    output = AtomicOutput(tmp_path / "a.bin")
    output.write(b"abc")
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == sorted(["a.bin.lock", output.temp.name]) and output.temp.name.startswith("a.bin.")
    assert output.commit().read_bytes() == b"abc"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin"]
    with pytest.raises(ValueError, match="committed"):
        output.commit()


def test_abort_keeps_the_old_file_and_a_target_made_meanwhile_is_not_replaced(tmp_path):
    from cmax.io.atomic import AtomicOutput

    (tmp_path / "a.bin").write_bytes(b"old")
    output = AtomicOutput(tmp_path / "a.bin", overwrite=True)
    output.write(b"new")
    output.abort()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin"] and (tmp_path / "a.bin").read_bytes() == b"old"
    output = AtomicOutput(tmp_path / "b.bin")
    output.write(b"mine")
    (tmp_path / "b.bin").write_bytes(b"someone else's")  # appeared while writing
    with pytest.raises(FileExistsError):
        output.commit()
    assert (tmp_path / "b.bin").read_bytes() == b"someone else's"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "b.bin"]


def test_a_target_made_while_h5_writer_or_write_with_writes_is_a_file_exists_error_and_kept(tmp_path):
    """The writers that name the target in their errors (``H5Writer.close``, ``write_with``), when a file appears
    at the target while they write (was: ``OSError: [Errno None] ... exists ...``, not a FileExistsError, so a
    caller catching that missed it): ``FileExistsError`` in the refusal's own words; the file kept, no temporary
    or lock left."""
    from cmax.events import Events
    from cmax.io import H5Writer
    from cmax.io.atomic import write_with

    writer = H5Writer(tmp_path / "a.h5", 10, 10)
    writer.append(Events(np.array([1]), np.array([2]), np.array([5]), np.array([1]), 10, 10))
    (tmp_path / "a.h5").write_bytes(b"mine")                  # appeared while writing
    with pytest.raises(FileExistsError, match=r"a.h5 exists .*nothing was written under this name") as caught:
        writer.close()
    assert "Errno" not in str(caught.value)

    def fill(output) -> None:
        output.write(b"new")
        (tmp_path / "b.bin").write_bytes(b"someone else's")

    with pytest.raises(FileExistsError, match="b.bin exists") as caught:
        write_with(tmp_path / "b.bin", fill, overwrite=False)
    assert "Errno" not in str(caught.value)
    assert (tmp_path / "a.h5").read_bytes() == b"mine" and (tmp_path / "b.bin").read_bytes() == b"someone else's"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.h5", "b.bin"]


def test_temporaries_of_a_killed_writer_are_removed_by_the_next_one_only(tmp_path):
    from cmax.io.atomic import temporaries

    stale = tmp_path / "a.bin.0123456789abcdef.partial"
    stale.write_bytes(b"half")
    other = tmp_path / "b.bin.0123456789abcdef.partial"  # another output's: not touched
    other.write_bytes(b"half")
    odd = tmp_path / "a.bin.backup.partial"  # not a name the writers draw: not touched
    odd.write_bytes(b"keep")
    assert temporaries(tmp_path / "a.bin") == [stale]
    write_text_atomic(tmp_path / "a.bin", "done")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "a.bin.backup.partial", other.name]


def test_a_replaced_file_keeps_its_permissions(tmp_path):
    """--overwrite of a 0600 file (a private recording, a checkpoint) came back 0644 (less umask)."""
    import stat as stat_module

    from cmax.io.atomic import write_text_atomic

    path = tmp_path / "private.txt"
    write_text_atomic(path, "first")
    os.chmod(path, 0o600)
    write_text_atomic(path, "second")
    assert path.read_text() == "second" and stat_module.S_IMODE(path.stat().st_mode) == 0o600


def test_a_file_named_like_a_lock_that_holds_data_is_refused_not_removed(tmp_path):
    """A user's ``data.h5.lock`` (holding data) was taken as the lock of ``data.h5`` and deleted on release."""
    from cmax.io.atomic import PathLock, lock_path

    user = lock_path(tmp_path / "data.h5")
    user.write_text("important")
    with pytest.raises(FileExistsError, match="holds data, so it is not a lock file of cmax"):
        PathLock(user, tmp_path / "data.h5")
    assert user.read_text() == "important"
    empty = lock_path(tmp_path / "other.h5")
    empty.touch()                                   # a killed writer's leftover: empty, reused and removed
    with PathLock(empty, tmp_path / "other.h5"):
        pass
    assert not empty.exists()
