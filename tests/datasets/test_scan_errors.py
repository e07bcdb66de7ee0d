"""Crafted collection files, each a valid collection with one promise of docs/collection_format.md broken: reading
names the file, the scan's stored name and its index (ScanReadError), the other scans stay readable, and the
`python -m datasets` command line answers every user mistake with one line on stderr and exit status 2."""
import pickle
import re
import shutil
import tempfile

import h5py
import numpy as np
import pytest

from datasets import Scan, ScanCollection, ScanReadError
from datasets.__main__ import main
from datasets.collection import _content_hash
from datasets.validation import check_oriented_cloud

N_POINTS = 200
NAMES = [f"test_bump_{i:03d}" for i in range(5)]


def sphere_scan(name, i, labels=False):
    rng = np.random.default_rng(i)
    d = rng.normal(size=(N_POINTS, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return Scan(name=name, points=d, normals=d, split="test", label="defective", defect="bump",
                point_labels=(rng.random(N_POINTS) < 0.2).astype(np.uint8) if labels else None)


@pytest.fixture(scope="module")
def valid(tmp_path_factory):
    """A valid small collection written by the library; tests edit copies of it."""
    path = tmp_path_factory.mktemp("valid") / "tree.h5"
    ScanCollection.create(path, [sphere_scan(n, i, labels=i % 2 == 1) for i, n in enumerate(NAMES)])
    return path


def crafted(valid, tmp_path, edit, name="tree.h5"):
    """A copy of ``valid`` with ``edit(h5, rows)`` applied (rows(i): scan i's slice of the point arrays)."""
    path = tmp_path / name
    shutil.copyfile(valid, path)
    with h5py.File(path, "r+") as f:
        off = f["scans/offsets"][()]
        edit(f, lambda i: slice(int(off[i]), int(off[i + 1])))
    return path


def rehash(f, i, rows):
    """Store scan i's content hash as the writer would, so that only the promise under test is broken."""
    labels = f["point_labels"][rows(i)] if f["scans/has_labels"][i] else None
    f["scans/content_sha256"][i] = _content_hash(f["points"][rows(i)], f["normals"][rows(i)], labels).encode()


def nan_in_third_scan(f, rows):
    pts = f["points"][rows(2)]
    pts[10:60, 1] = np.nan
    f["points"][rows(2)] = pts
    rehash(f, 2, rows)


def moved_point(f, rows):
    r = rows(3)
    f["points"][r.start + 7, 0] += 1e-3


def assert_names_scan(err, path, index):
    assert isinstance(err, ScanReadError) and isinstance(err, ValueError)
    assert err.path == str(path) and err.scan_name == NAMES[index] and err.index == index
    assert str(err).startswith(f"{path}: scan {NAMES[index]!r} (#{index}): ")


def read_error(c, i, index=None):
    """The ScanReadError of reading ``c[i]``, checked to name the file, the scan and its index."""
    with pytest.raises(ScanReadError) as e:
        c[i]
    assert_names_scan(e.value, c.path, i if index is None else index)
    return e.value


# ---- one broken promise each: the error names the file, the scan's own name and its index ----------------------------
def test_nan_points_name_the_file_and_the_scan(valid, tmp_path):
    path = crafted(valid, tmp_path, nan_in_third_scan)
    with ScanCollection(path) as c:
        err = read_error(c, 2)
        assert str(err).startswith(f"{path}: scan 'test_bump_002' (#2): points has 50 rows with NaN or Inf")
        with pytest.raises(ScanReadError, match=r"\(#2\)"):
            c.read_many([0, 1, 2, 3])  # the default still raises, for the scan at fault
        for i in (0, 1, 3, 4):
            assert c[i].name == NAMES[i]


def test_non_finite_normals(valid, tmp_path):
    def edit(f, rows):
        f["normals"][rows(4).start] = [np.inf, 0, 0]
        rehash(f, 4, rows)

    with ScanCollection(crafted(valid, tmp_path, edit)) as c:
        err = read_error(c, -1, index=4)  # a negative index is reported as the scan's index in the collection
    assert "normals has 1 rows with NaN or Inf" in str(err)


def test_moved_point_fails_its_stored_hash(valid, tmp_path):
    path = crafted(valid, tmp_path, moved_point)
    with ScanCollection(path) as c:
        assert read_error(c, 3).problem == ("content does not match its stored content_sha256: the file was "
                                            "modified or damaged")
        with pytest.raises(ScanReadError, match="test_bump_003"):
            c.verify()
        assert c[2].name == NAMES[2]


def test_hash_covers_labels_and_normals(valid, tmp_path):
    def flip_label(f, rows):
        f["point_labels"][rows(1).start] ^= 1

    def turn_normal(f, rows):
        f["normals"][rows(0).start] = [0, 0, 1]

    for i, edit in ((1, flip_label), (0, turn_normal)):
        with ScanCollection(crafted(valid, tmp_path, edit, f"{edit.__name__}.h5")) as c:
            assert "content_sha256" in read_error(c, i).problem


def test_edit_with_matching_hash_reads(valid, tmp_path):
    """The check compares with the stored hash: a point moved and its hash updated reads back as edited."""
    def edit(f, rows):
        moved_point(f, rows)
        rehash(f, 3, rows)

    with ScanCollection(crafted(valid, tmp_path, edit)) as c, ScanCollection(valid) as ref:
        np.testing.assert_allclose(c[3].points[7, 0], ref[3].points[7, 0] + 1e-3, rtol=1e-6)
        c.verify()


@pytest.mark.parametrize("case, message, index", [
    ("short_normals", r"normals \(190, 3\) must match points \(200, 3\)", 4),
    ("short_labels", r"190 point labels for 200 points", 3),
    ("bad_split", r"split must be one of .* got 'bogus'", 1),
    ("points_2_columns", r"points must be an \(n, 3\) array, got shape \(200, 2\)", 0),
])
def test_wrong_shapes_and_values(valid, tmp_path, case, message, index):
    def edit(f, rows):
        if case == "short_normals":
            f["normals"].resize(f["normals"].shape[0] - 10, axis=0)
        elif case == "short_labels":
            # scans 1 and 3 carry labels: cut into scan 3's rows (scan 4, after it, has none)
            f["point_labels"].resize(f["point_labels"].shape[0] - N_POINTS - 10, axis=0)
        elif case == "bad_split":
            f["scans/split"][1] = "bogus"
        else:
            points = f["points"][()]
            del f["points"]
            f["points"] = points[:, :2]

    path = crafted(valid, tmp_path, edit)
    with ScanCollection(path) as c:
        scans, failed = c.read_many(range(len(c)), errors="collect")
    assert failed, "no scan failed"
    assert_names_scan(failed[0], path, index)
    assert failed[0].problem == str(failed[0]).split(": ", 2)[2]
    assert re.search(message, failed[0].problem), failed[0].problem


def test_damaged_chunk_is_a_scan_error(tmp_path):
    path = tmp_path / "big.h5"
    big = [Scan(name=f"s{i}", points=np.random.default_rng(i).normal(size=(5000, 3)),
                normals=np.tile([0.0, 0.0, 1.0], (5000, 1))) for i in range(3)]
    ScanCollection.create(path, big)
    with h5py.File(path, "r") as f:
        chunk = f["points"].id.get_chunk_info(3)  # rows 12288-16383: scan 2 only (rows 10000-14999)
    data = bytearray(path.read_bytes())
    data[chunk.byte_offset:chunk.byte_offset + chunk.size] = bytes(chunk.size)
    path.write_bytes(bytes(data))
    with ScanCollection(path) as c:
        scans, failed = c.read_many([0, 1, 2], errors="collect")
    assert [s.name for s in scans] == ["s0", "s1"]
    assert [(e.scan_name, e.index) for e in failed] == [("s2", 2)]
    assert "cannot be read" in failed[0].problem


# ---- per-scan reading: score what can be read, report the rest -------------------------------------------------------
def test_read_many_collects_errors_in_order(valid, tmp_path):
    def edit(f, rows):
        nan_in_third_scan(f, rows)
        moved_point(f, rows)

    path = crafted(valid, tmp_path, edit)
    with ScanCollection(path) as c:
        scans, failed = c.read_many([4, 3, 0, 2], errors="collect")
        assert [s.name for s in scans] == [NAMES[4], NAMES[0]]
        assert [(e.scan_name, e.index) for e in failed] == [(NAMES[3], 3), (NAMES[2], 2)]
        assert all(e.path == str(path) for e in failed)
        assert c.read_many([], errors="collect") == ([], [])
        with pytest.raises(ValueError, match="errors must be 'raise' or 'collect', got 'ignore'"):
            c.read_many([0], errors="ignore")
        with pytest.raises(IndexError):  # not a problem of one scan: raised whatever `errors` says
            c.read_many([0, 99], errors="collect")
    with ScanCollection(valid) as c:
        scans, failed = c.read_many(range(len(c)), errors="collect")
        assert [s.name for s in scans] == NAMES and failed == []
        assert [s.name for s in c.read_many([1, 0])] == NAMES[1::-1]


def test_scan_read_error_fields_message_and_pickle():
    e = ScanReadError("points has 1 rows with NaN or Inf", "a/tree.h5", "x/007", 6)
    assert str(e) == "a/tree.h5: scan 'x/007' (#6): points has 1 rows with NaN or Inf"
    again = pickle.loads(pickle.dumps(e))  # e.g. from a worker process
    assert (again.path, again.scan_name, again.index, str(again)) == ("a/tree.h5", "x/007", 6, str(e))
    assert str(ScanReadError("bad", index=2)) == "scan #2: bad"
    assert str(ScanReadError("bad", scan_name="n")) == "scan 'n': bad"
    assert str(ScanReadError("bad")) == "bad"


def test_check_oriented_cloud_raises_scan_read_error():
    pts = np.random.default_rng(0).normal(size=(20, 3))
    with pytest.raises(ScanReadError, match=r"^t\.h5: scan 'a' \(#3\): normals are missing") as e:
        check_oriented_cloud(pts, None, path="t.h5", scan_name="a", index=3)
    assert (e.value.path, e.value.scan_name, e.value.index) == ("t.h5", "a", 3)
    bad = pts.copy()
    bad[0] = np.nan
    with pytest.raises(ScanReadError, match=r"^scan 3: points has 1 rows with NaN or Inf") as e:
        check_oriented_cloud(bad, pts, name="scan 3")  # the free-form label of callers that have no name
    assert e.value.scan_name is None
    with pytest.raises(ScanReadError, match="2 normals have zero length"):
        check_oriented_cloud(pts, np.vstack([np.zeros((2, 3)), pts[2:]]))


# ---- command line: one line on stderr, exit status 2 -----------------------------------------------------------------
def one_error_line(capsys):
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    return err.strip()


def test_cli_corrupt_collection(valid, tmp_path, capsys):
    path = crafted(valid, tmp_path, moved_point)
    assert main(["export", str(path), str(tmp_path / "out")]) == 2
    assert one_error_line(capsys) == (f"error: {path}: scan 'test_bump_003' (#3): content does not match its stored "
                                      f"content_sha256: the file was modified or damaged")
    with h5py.File(path, "r+") as f:
        f["scans/has_labels"].resize(2, axis=0)
    for argv in (["info", str(path)], ["export", str(path), str(tmp_path / "out2")]):
        assert main(argv) == 2
        assert one_error_line(capsys) == f"error: {path}: damaged scan collection (offsets, counts and per-scan " \
                                         f"arrays disagree)"


@pytest.mark.parametrize("argv, expected", [
    (["import", "{tmp}/in", "--out", "{tmp}/c.h5", "--points", "many"], "argument --points: invalid int value"),
    (["import", "{tmp}/in", "--out", "{tmp}/c.h5", "--layout", "nope"], "argument --layout: invalid choice"),
    (["import", "{tmp}/in", "--out", "{tmp}/c.h5", "--voxel", "-1"], "voxel size must be > 0"),
    (["import", "{tmp}/missing", "--out", "{tmp}/c.h5"], "{tmp}/missing: no such folder"),
    (["import", "{tmp}/in", "--out", "{tmp}/no/c.h5"], "{tmp}/no: output folder does not exist"),
    (["import", "{tmp}/in", "--out", "{tmp}/ro/c.h5"], "{tmp}/ro/c.h5: cannot write a file in {tmp}/ro"),
    (["import", "{tmp}/in", "--out", "{tmp}/valid.h5"], "{tmp}/valid.h5: already exists"),
    (["info", "{tmp}/nothing.h5"], "{tmp}/nothing.h5: no such scan collection"),
    (["info", "{tmp}/in/a.npy"], "{tmp}/in/a.npy: not an HDF5 file"),
    (["info"], "the following arguments are required: collection"),
    (["bogus"], "argument command: invalid choice: 'bogus'"),
    (["export", "{tmp}/valid.h5", "{tmp}/in"], "{tmp}/in: not empty"),
    (["export", "{tmp}/valid.h5", "{tmp}/in/a.npy"], "{tmp}/in/a.npy: Not a directory"),
    (["synth", "--mesh", "builtin", "--out", "{tmp}/s.h5", "--points", "0"], "--points must be an integer >= 1"),
    (["synth", "--mesh", "builtin", "--out", "{tmp}/s.h5", "--noise", "inf"], "--noise must be >= 0"),
    (["synth", "--mesh", "builtin", "--out", "{tmp}/s.h5", "--jitter", "nan"], "--jitter must be between 0 and 180"),
    (["synth", "--mesh", "{tmp}/none.obj", "--out", "{tmp}/s.h5"], "mesh file '{tmp}/none.obj' not found"),
    (["synth", "--mesh", "builtin", "--out", "{tmp}/ro/s.h5"], "{tmp}/ro/s.h5: cannot write a file in {tmp}/ro"),
    (["synth", "--mesh", "builtin", "--out", "{tmp}/valid.h5"], "{tmp}/valid.h5: already exists"),
])
def test_cli_user_mistakes_give_one_line_and_status_2(valid, tmp_path, monkeypatch, capsys, argv, expected):
    (tmp_path / "in").mkdir()
    np.save(tmp_path / "in" / "a.npy", sphere_scan("a", 0).points)
    shutil.copyfile(valid, tmp_path / "valid.h5")
    (tmp_path / "ro").mkdir()

    def read_only(*args, **kwargs):  # a read-only folder, also when the tests run as root
        raise PermissionError(13, "Permission denied", str(tmp_path / "ro" / ".x.tmp"))

    real_mkstemp = tempfile.mkstemp
    monkeypatch.setattr(tempfile, "mkstemp", lambda *a, dir=None, **k: (
        read_only() if str(dir) == str(tmp_path / "ro") else real_mkstemp(*a, dir=dir, **k)))
    before = sorted(p.name for p in tmp_path.rglob("*"))
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    assert expected.format(tmp=tmp_path) in one_error_line(capsys)
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing written


def test_cli_help_still_exits_0(capsys):
    assert main(["--help"]) == 0 and "usage" in capsys.readouterr().out
