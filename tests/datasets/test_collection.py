"""Tests of the HDF5 scan collection, its frame and the torch dataset over it."""
import hashlib
import pickle

import h5py
import numpy as np
import pytest

from datasets import Frame, Scan, ScanCollection
from datasets import collection as collection_mod


def make_scan(name, n=50, seed=0, split="train", label="good", defect="", labels=False, origin=False, part_id=""):
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return Scan(name=name, points=rng.normal(size=(n, 3)), normals=normals, split=split, label=label,
                defect=defect, part_id=part_id,
                point_labels=(rng.random(n) < 0.2).astype(np.uint8) if labels else None,
                sensor_origin=rng.normal(size=3) if origin else None)


def some_scans():
    return [make_scan("train/good/0", 40, 0),
            make_scan("train/good/1", 70, 1, origin=True, part_id="bracket"),
            make_scan("test/dent/0", 1, 2, split="test", label="defective", defect="dent", labels=True),
            make_scan("test/good/0", 33, 3, split="test", labels=True, origin=True),
            make_scan("val/ü-ñame", 0, 4, split="validation", label="unknown")]


def assert_same_scan(a, b):
    assert a.name == b.name and a.split == b.split and a.label == b.label
    assert a.defect == b.defect and a.part_id == b.part_id
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.normals, b.normals)
    assert a.points.dtype == np.float32 and a.normals.dtype == np.float32
    if a.point_labels is None:
        assert b.point_labels is None
    else:
        np.testing.assert_array_equal(a.point_labels, b.point_labels)
        assert b.point_labels.dtype == np.uint8
    if a.sensor_origin is None:
        assert b.sensor_origin is None
    else:
        np.testing.assert_array_equal(a.sensor_origin, b.sensor_origin)


def sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ---- Frame -----------------------------------------------------------------------------------------------------------
def test_frame_fit_maps_bounding_box_to_unit_cube():
    rng = np.random.default_rng(0)
    p = rng.uniform([10, -5, 100], [14, -3, 101], size=(500, 3))
    f = Frame.fit(p)
    q = f.to_collection(p)
    lo, hi = q.min(0), q.max(0)
    assert np.isclose((hi - lo).max(), 1.0)
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-12)
    np.testing.assert_allclose(f.to_file(q), p, atol=1e-12)
    assert Frame.from_dict(f.as_dict()) == f
    assert Frame.identity().to_collection(p) is not p and np.array_equal(Frame.identity().to_collection(p), p)


def test_frame_apply_moves_points_and_origin_not_normals():
    s = make_scan("a", 20, origin=True)
    f = Frame(center=[1.0, 2.0, 3.0], scale=0.5)
    t = f.apply(s)
    np.testing.assert_allclose(t.points, 0.5 * (s.points.astype(np.float64) - [1, 2, 3]), rtol=1e-6)
    np.testing.assert_allclose(t.sensor_origin, 0.5 * (s.sensor_origin.astype(np.float64) - [1, 2, 3]), rtol=1e-6)
    np.testing.assert_array_equal(t.normals, s.normals)
    assert t is not s and t.name == s.name


@pytest.mark.parametrize("bad", [dict(center=[0, 0], scale=1.0), dict(center=[0, 0, 0], scale=0.0),
                                 dict(center=[0, 0, np.nan], scale=1.0)])
def test_frame_rejects_bad_values(bad):
    with pytest.raises(ValueError, match="Frame"):
        Frame(**bad)


def test_frame_fit_rejects_a_single_point():
    with pytest.raises(ValueError, match="no volume"):
        Frame.fit(np.ones((5, 3)))


# ---- round trips -----------------------------------------------------------------------------------------------------
def test_create_append_read_back_exactly(tmp_path):
    path = tmp_path / "c.h5"
    scans = some_scans()
    frame = Frame([1.0, 2.0, 3.0], 0.25)
    ScanCollection.create(path, scans[:3], frame=frame, provenance={"source": "test", "n": 3})
    ScanCollection.append(path, scans[3:])
    with ScanCollection(path) as c:
        assert len(c) == 5
        assert c.names == [s.name for s in scans]
        for i, s in enumerate(scans):
            assert_same_scan(s, c[i])
        assert_same_scan(scans[-1], c[-1])
        assert [s.name for s in c.read_many([4, 0])] == [scans[4].name, scans[0].name]
        assert [s.name for s in c] == c.names
        assert c.frame == frame
        assert c.provenance == {"source": "test", "n": 3}
        assert c.index_of("test/dent/0") == 2
        with pytest.raises(KeyError, match="nope"):
            c.index_of("nope")
        with pytest.raises(IndexError):
            c[5]
        assert c.select(split="train") == [0, 1]
        assert c.select(split="test", label="good") == [3]
        assert c.select(defect="dent") == [2]
        assert c.select(part_id="bracket") == [1]
        assert c.select(split=["train", "validation"]) == [0, 1, 4]
        meta = c.metadata()
        assert meta[1]["sensor_origin"] is not None and meta[0]["sensor_origin"] is None
        assert [m["n_points"] for m in meta] == [40, 70, 1, 33, 0]
        assert [m["has_labels"] for m in meta] == [False, False, True, True, False]
        c.verify()
    with pytest.raises(ValueError, match="closed"):
        c[0]


def test_schema_readable_with_plain_h5py(tmp_path):
    path = tmp_path / "c.h5"
    scans = some_scans()
    ScanCollection.create(path, scans)
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "nsspr-scan-collection" and f.attrs["format_version"] == 1
        off = f["scans/offsets"][:]
        assert off.dtype == np.int64 and off.shape == (6,)
        i = 1
        np.testing.assert_array_equal(f["points"][off[i]:off[i + 1]], scans[i].points)
        assert f["scans/name"].asstr()[i] == scans[i].name
        assert np.isnan(f["scans/sensor_origin"][0]).all()
        assert f["points"].compression is not None and f["points"].chunks is not None


def test_empty_collection(tmp_path):
    path = tmp_path / "empty.h5"
    ScanCollection.create(path, [])
    with ScanCollection(path) as c:
        assert len(c) == 0 and list(c) == [] and c.select() == []
    ScanCollection.append(path, [make_scan("x", 5)])
    with ScanCollection(path) as c:
        assert c.names == ["x"]


def test_duplicate_names_rejected(tmp_path):
    path = tmp_path / "c.h5"
    with pytest.raises(ValueError, match="duplicate scan name 'a'"):
        ScanCollection.create(path, [make_scan("a"), make_scan("a", seed=1)])
    assert not path.exists() and list(tmp_path.iterdir()) == []
    ScanCollection.create(path, [make_scan("a")])
    before = sha(path)
    with pytest.raises(ValueError, match="duplicate"):
        ScanCollection.append(path, [make_scan("b"), make_scan("a", seed=2)])
    assert sha(path) == before and sorted(p.name for p in tmp_path.iterdir()) == ["c.h5"]


def test_non_finite_points_rejected(tmp_path):
    s = make_scan("a")
    s.points[3, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        ScanCollection.create(tmp_path / "c.h5", [s])


def test_refuses_to_overwrite_unless_asked(tmp_path):
    path = tmp_path / "c.h5"
    ScanCollection.create(path, [make_scan("a")])
    with pytest.raises(FileExistsError, match=str(path)):
        ScanCollection.create(path, [make_scan("b")])
    ScanCollection.create(path, [make_scan("b")], overwrite=True)
    with ScanCollection(path) as c:
        assert c.names == ["b"]


def test_same_input_gives_byte_identical_file(tmp_path):
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    ScanCollection.create(a, some_scans(), provenance={"x": 1})
    ScanCollection.create(b, some_scans(), provenance={"x": 1})
    assert sha(a) == sha(b)


def test_fingerprint_tracks_data_not_provenance(tmp_path):
    def fp(scans, name, **kw):
        ScanCollection.create(tmp_path / name, scans, **kw)
        with ScanCollection(tmp_path / name) as c:
            return c.fingerprint()

    base = fp(some_scans(), "a.h5", provenance={"a": 1})
    assert len(base) == 64 and int(base, 16) >= 0
    assert fp(some_scans(), "b.h5", provenance={"b": 2}) == base
    moved = some_scans()
    moved[1].points[5, 0] += 1e-3
    assert fp(moved, "c.h5") != base
    relabelled = some_scans()
    relabelled[3].label = "defective"
    assert fp(relabelled, "d.h5") != base
    assert fp(some_scans(), "e.h5", frame=Frame([0, 0, 1.0], 1.0)) != base
    assert fp(some_scans()[:4], "f.h5") != base


def test_verify_detects_edited_points(tmp_path):
    path = tmp_path / "c.h5"
    ScanCollection.create(path, some_scans())
    with h5py.File(path, "r+") as f:
        f["points"][0, 0] += 1.0
    with ScanCollection(path) as c, pytest.raises(ValueError, match="train/good/0"):
        c.verify()


# ---- bad files -------------------------------------------------------------------------------------------------------
def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing.h5"):
        ScanCollection(tmp_path / "nothing.h5")


def test_text_file_renamed_h5_rejected(tmp_path):
    path = tmp_path / "notes.h5"
    path.write_text("hello, I am not HDF5\n" * 20)
    with pytest.raises(ValueError, match=r"notes\.h5: not an HDF5 file") as e:
        ScanCollection(path)
    assert e.value.__cause__ is None and e.value.__suppress_context__


def test_other_hdf5_rejected(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["data"] = np.arange(10)
    with pytest.raises(ValueError, match=r"other\.h5: an HDF5 file but not a scan collection"):
        ScanCollection(path)


def test_wrong_version_rejected(tmp_path):
    path = tmp_path / "v2.h5"
    ScanCollection.create(path, [make_scan("a")])
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = 2
    with pytest.raises(ValueError, match=r"v2\.h5: scan collection format version 2 is not supported"):
        ScanCollection(path)


def test_truncated_file_rejected(tmp_path):
    path = tmp_path / "cut.h5"
    ScanCollection.create(path, [make_scan(f"s{i}", 3000, i) for i in range(4)])
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"cut\.h5: truncated") as e:
        ScanCollection(path)
    assert e.value.__suppress_context__


def test_damaged_offsets_rejected(tmp_path):
    path = tmp_path / "bad.h5"
    ScanCollection.create(path, some_scans())
    with h5py.File(path, "r+") as f:
        f["scans/offsets"][2] += 1
    with pytest.raises(ValueError, match=r"bad\.h5: damaged"):
        ScanCollection(path)


# ---- atomicity -------------------------------------------------------------------------------------------------------
class Boom(RuntimeError):
    pass


def test_interrupted_create_and_append_leave_old_file(tmp_path, monkeypatch):
    path = tmp_path / "c.h5"
    ScanCollection.create(path, some_scans()[:2])
    before = sha(path)

    calls = {"n": 0}
    real = collection_mod._content_hash

    def failing(*a):  # fails on the second scan, after the first one's data went to the file
        calls["n"] += 1
        if calls["n"] == 2:
            raise Boom("disk on fire")
        return real(*a)

    monkeypatch.setattr(collection_mod, "_content_hash", failing)
    monkeypatch.setattr(collection_mod, "_WRITE_BATCH_POINTS", 1)  # flush after every scan
    with pytest.raises(Boom):
        ScanCollection.create(path, some_scans()[2:], overwrite=True)
    assert sha(path) == before
    calls["n"] = 0
    with pytest.raises(Boom):
        ScanCollection.append(path, some_scans()[2:])
    assert sha(path) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.h5"]

    def gen():  # a generator that fails half-way: the new file must not appear either
        yield make_scan("x")
        raise Boom("generator died")

    monkeypatch.setattr(collection_mod, "_content_hash", real)
    with pytest.raises(Boom):
        ScanCollection.create(tmp_path / "new.h5", gen())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.h5"]


# ---- streaming and torch ---------------------------------------------------------------------------------------------
def test_iteration_streams_in_batches(tmp_path, monkeypatch):
    # more scans than one write batch, so offsets across batches are exercised
    monkeypatch.setattr(collection_mod, "_WRITE_BATCH_POINTS", 100)
    scans = [make_scan(f"s{i}", 37 + i, i) for i in range(20)]
    path = tmp_path / "c.h5"
    ScanCollection.create(path, iter(scans))
    with ScanCollection(path) as c:
        for a, b in zip(scans, c):
            assert_same_scan(a, b)


def test_scan_dataset(tmp_path):
    import torch

    from datasets import ScanDataset

    path = tmp_path / "c.h5"
    scans = some_scans()
    ScanCollection.create(path, scans)
    ds = ScanDataset(path, split="test")
    assert len(ds) == 2
    item = ds[1]
    assert item["index"].item() == 3 and item["points"].dtype == torch.float32
    np.testing.assert_array_equal(item["points"].numpy(), scans[3].points)
    clone = pickle.loads(pickle.dumps(ds))  # what a DataLoader worker gets: no open handle inside
    assert clone._collection is None and clone[0]["index"].item() == 2
    loader = torch.utils.data.DataLoader(ScanDataset(path, label="good"), batch_size=1, num_workers=0)
    assert [b["index"].item() for b in loader] == [0, 1, 3]
