"""datasets.atomic: files and folders appear whole or not at all, with the permissions a plain open() gives."""
import os
import stat

import numpy as np
import pytest

from datasets import read_cloud, write_cloud
from datasets.atomic import atomic_directory, atomic_path


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_atomic_path_writes_whole_file_with_open_permissions(tmp_path):
    target = tmp_path / "sub" / "out.txt"
    with atomic_path(target) as tmp:
        assert tmp.parent == target.parent and tmp.name.startswith(".") and tmp.exists()
        assert not target.exists()  # nothing at the destination until the block ends
        tmp.write_text("hello")
    assert target.read_text() == "hello"
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    assert stat.S_IMODE(target.stat().st_mode) == stat.S_IMODE(plain.stat().st_mode) == 0o666 & ~_umask()
    assert sorted(p.name for p in target.parent.iterdir()) == ["out.txt"]


def test_atomic_path_interrupted_keeps_previous_file_and_leaves_nothing(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(target) as tmp:
            tmp.write_text("half of the new")
            raise KeyboardInterrupt
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_atomic_path_keeps_suffix_for_writers_that_choose_a_format_by_it(tmp_path):
    with atomic_path(tmp_path / "fig.png", suffix=".png") as tmp:
        assert tmp.suffix == ".png"
        tmp.write_bytes(b"\x89PNG")
    assert (tmp_path / "fig.png").read_bytes() == b"\x89PNG"


def test_atomic_directory_replaces_whole_folder_or_nothing(tmp_path):
    out = tmp_path / "tree"
    with atomic_directory(out) as tmp:
        (tmp / "a.txt").write_text("1")
    assert sorted(p.name for p in out.iterdir()) == ["a.txt"]
    assert stat.S_IMODE(out.stat().st_mode) == 0o777 & ~_umask()
    with pytest.raises(RuntimeError):
        with atomic_directory(out) as tmp:
            (tmp / "b.txt").write_text("2")
            raise RuntimeError("interrupted")
    assert sorted(p.name for p in out.iterdir()) == ["a.txt"]  # the old tree, untouched
    with atomic_directory(out) as tmp:
        (tmp / "c.txt").write_text("3")
    assert sorted(p.name for p in out.iterdir()) == ["c.txt"]  # replaced whole, not merged
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tree"]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_ply_written_by_plyfile_reads_back_exactly_with_open3d(tmp_path, dtype):
    """write_cloud (plyfile) and read_cloud (open3d) are independent implementations of PLY: a round trip through
    both must give the same numbers (float64 kept as float64)."""
    rng = np.random.default_rng(0)
    p = rng.normal(size=(50, 3)).astype(dtype)
    n = rng.normal(size=(50, 3))
    n = (n / np.linalg.norm(n, axis=1, keepdims=True)).astype(dtype)
    path = write_cloud(tmp_path / "c.ply", p, n)
    q, m = read_cloud(path)
    np.testing.assert_array_equal(q, p.astype(np.float64))
    np.testing.assert_array_equal(m, n.astype(np.float64))
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert "binary_little_endian" in header and ("double x" if dtype == np.float64 else "float x") in header
