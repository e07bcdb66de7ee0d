"""Tests of scanner-file reading/writing, tree import, export and the `python -m datasets` command line."""
import hashlib
import json

import numpy as np
import pytest

from datasets import Frame, ScanCollection, read_cloud, write_cloud
from datasets.__main__ import main
from datasets.importer import import_tree
from datasets.ingest import voxel_downsample

FORMATS = ("ply", "pcd", "xyz", "txt", "pts", "npy", "npz")
CENTER, RADIUS = np.array([5.0, -2.0, 30.0]), 2.0


def sphere(n=800, center=CENTER, radius=RADIUS):
    """Fibonacci points on a sphere (N, 3) and their outward unit normals (N, 3)."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5 ** 0.5) * i
    normals = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)
    return center + radius * normals, normals


def write_any(path, points, normals=None, **npz_extra):
    """Write a cloud in the format its extension names (with normals when given)."""
    ext = path.suffix[1:]
    path.parent.mkdir(parents=True, exist_ok=True)
    table = points if normals is None else np.hstack([points, normals])
    if ext == "ply":
        write_cloud(path, points, normals)
    elif ext == "pcd":
        import open3d as o3d

        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        if normals is not None:
            pcd.normals = o3d.utility.Vector3dVector(normals)
        assert o3d.io.write_point_cloud(str(path), pcd)
    elif ext in ("xyz", "txt"):
        np.savetxt(path, table, delimiter="," if ext == "txt" else " ")
    elif ext == "pts":
        np.savetxt(path, table, header=str(len(points)), comments="")
    elif ext == "npy":
        np.save(path, table)
    elif ext == "npz":
        arrays = {"points": points, **npz_extra}
        if normals is not None:
            arrays["normals"] = normals
        np.savez(path, **arrays)
    return path


def sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def make_tree(root, n=300):
    """A small MVTec-3D-AD style tree: 2 train, 1 validation, 2 test/good, 2 test/dent (with ground truth)."""
    rng = np.random.default_rng(0)
    for k, ext in enumerate(("ply", "xyz")):
        p, nrm = sphere(n + 10 * k)
        write_any(root / "train" / "good" / f"{k:03d}.{ext}", p, nrm if k == 0 else None)
    write_any(root / "validation" / "good" / "000.npy", *sphere(n))
    for k, ext in enumerate(("pcd", "npz")):
        write_any(root / "test" / "good" / f"{k:03d}.{ext}", *sphere(n, center=CENTER + 1))
    for k in range(2):
        p, nrm = sphere(n + k, center=CENTER + 3, radius=3.0)
        write_any(root / "test" / "dent" / f"{k:03d}.txt", p, nrm)
        gt = (rng.random(len(p)) < 0.1).astype(int)
        (root / "ground_truth" / "dent").mkdir(parents=True, exist_ok=True)
        np.savetxt(root / "ground_truth" / "dent" / f"{k:03d}.txt", gt, fmt="%d")
    return root


# ---- reading and writing files ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("ext", FORMATS)
@pytest.mark.parametrize("with_normals", [True, False])
def test_read_cloud_each_format(tmp_path, ext, with_normals):
    p, n = sphere(200)
    path = write_any(tmp_path / f"c.{ext}", p, n if with_normals else None)
    points, normals = read_cloud(path)
    np.testing.assert_allclose(points, p, atol=1e-5)
    if with_normals:
        np.testing.assert_allclose(normals, n, atol=1e-5)
    else:
        assert normals is None


def test_read_text_with_extra_columns_that_are_not_normals(tmp_path):
    p, _ = sphere(50)
    extra = np.hstack([p, np.full((50, 1), 0.3), np.full((50, 3), 200.0)])  # x y z intensity r g b
    np.savetxt(tmp_path / "scan.pts", extra)
    points, normals = read_cloud(tmp_path / "scan.pts")
    np.testing.assert_allclose(points, p)
    assert normals is None


def test_write_cloud_colors(tmp_path):
    import open3d as o3d

    p, n = sphere(100)
    colors = np.random.default_rng(0).random((100, 3))
    path = write_cloud(tmp_path / "sub" / "c.ply", p.astype(np.float32), n, colors)
    pcd = o3d.io.read_point_cloud(str(path))
    np.testing.assert_allclose(np.asarray(pcd.colors), colors, atol=0.5 / 255 + 1e-9)
    np.testing.assert_allclose(np.asarray(pcd.points), p, atol=1e-5)
    assert [q.name for q in path.parent.iterdir()] == ["c.ply"]  # no temporary file left behind
    with pytest.raises(ValueError, match=r"c2\.ply: float colors must be finite and in \[0, 1\]"):
        write_cloud(tmp_path / "c2.ply", p, colors=colors * 2)
    with pytest.raises(ValueError, match="PLY only"):
        write_cloud(tmp_path / "c.xyz", p)


@pytest.mark.parametrize("name, content, message", [
    ("empty.ply", b"", "empty file"),
    ("empty.xyz", b"", "empty file"),
    ("junk.ply", b"this is not a ply file\n", "open3d read no points"),
    ("words.xyz", b"a b c\nd e f\n", "not a table of numbers"),
    ("two.xyz", b"1 2\n3 4\n", "2 columns"),
    ("cloud.obj", b"v 0 0 0\n", "unknown point-cloud extension"),
])
def test_read_cloud_errors_name_the_file(tmp_path, name, content, message):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(ValueError, match=message) as e:
        read_cloud(path)
    assert str(path) in str(e.value)


def test_read_cloud_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.ply"):
        read_cloud(tmp_path / "nope.ply")


# ---- import ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("ext", FORMATS)
@pytest.mark.parametrize("with_normals", [True, False])
def test_import_flat_folder_each_format(tmp_path, ext, with_normals):
    p, n = sphere(800)
    write_any(tmp_path / "in" / f"ball.{ext}", p, n if with_normals else None)
    out = tmp_path / "c.h5"
    import_tree(tmp_path / "in", out, progress=False)
    with ScanCollection(out) as c:
        assert c.names == ["ball"]
        scan = c[0]
        assert (scan.split, scan.label, scan.defect) == ("test", "unknown", "")
        np.testing.assert_allclose(c.frame.to_file(scan.points), p, atol=1e-5)
        np.testing.assert_allclose(np.linalg.norm(scan.normals, axis=1), 1, atol=1e-5)
        agree = np.einsum("ij,ij->i", scan.normals, n) > 0
        assert agree.mean() > 0.98, f"{ext}: {agree.mean():.3f} of estimated normals point outward"
        if with_normals:
            np.testing.assert_allclose(scan.normals, n, atol=1e-5)


@pytest.mark.parametrize("how", ["sidecar", "npz"])
def test_estimated_normals_face_the_sensor(tmp_path, how):
    # the inside of a dome seen from its centre (a cup's interior): the surface faces the sensor, so the outward
    # normals point toward the centre, the opposite of what "away from the centroid" would pick
    p, n = sphere(3000)
    dome = p[:, 2] > CENTER[2] + 0.5
    p, facing = p[dome], -n[dome]
    origin = CENTER
    if how == "npz":
        write_any(tmp_path / "in" / "cup.npz", p, sensor_origin=origin)
    else:
        write_any(tmp_path / "in" / "cup.xyz", p)
        (tmp_path / "in" / "cup.json").write_text(json.dumps({"sensor_origin": origin.tolist()}))
    import_tree(tmp_path / "in", tmp_path / "c.h5", progress=False)
    with ScanCollection(tmp_path / "c.h5") as c:
        scan = c[0]
        np.testing.assert_allclose(c.frame.to_file(scan.sensor_origin), origin, rtol=1e-5)
        assert (np.einsum("ij,ij->i", scan.normals, facing) > 0).mean() > 0.98


def test_a_sidecar_with_the_view_direction_alone_puts_the_origin_far_along_it(tmp_path):
    """{"view_direction": [x, y, z]} (a line scanner's sweep, a stand-off nobody wrote down): the origin lies
    VIEW_DIRECTION_DISTANCE bounding-box diagonals from the cloud's centre along the direction, so its rays to the
    part are parallel within a third of a degree, and the normals face it; a zero or malformed direction is one error
    naming the sidecar."""
    from datasets.importer import VIEW_DIRECTION_DISTANCE

    p, n = sphere(3000)
    cap = p[:, 2] > CENTER[2] + 0.3  # the top of a ball, seen from above
    p, outward = p[cap], n[cap]
    write_any(tmp_path / "in" / "top.xyz", p)
    (tmp_path / "in" / "top.json").write_text(json.dumps({"view_direction": [0.0, 0.0, 5.0]}))
    import_tree(tmp_path / "in", tmp_path / "c.h5", progress=False)
    with ScanCollection(tmp_path / "c.h5") as c:
        scan = c[0]
        origin = c.frame.to_file(scan.sensor_origin)
    lo, hi = p.min(0), p.max(0)
    expected = (lo + hi) / 2 + [0.0, 0.0, VIEW_DIRECTION_DISTANCE * np.linalg.norm(hi - lo)]
    np.testing.assert_allclose(origin, expected, rtol=1e-5)
    rays = (origin - p) / np.linalg.norm(origin - p, axis=1, keepdims=True)
    assert np.degrees(np.arccos(rays[:, 2].min())) < 0.35
    assert (np.einsum("ij,ij->i", scan.normals, outward) > 0).mean() > 0.98
    for bad in ({"view_direction": [0, 0, 0]}, {"view_direction": [1, 2]}, {"view": 1}):
        (tmp_path / "in" / "top.json").write_text(json.dumps(bad))
        with pytest.raises(ValueError, match="top.json"):
            import_tree(tmp_path / "in", tmp_path / "d.h5", progress=False)


def test_import_tree(tmp_path):
    root = make_tree(tmp_path / "tree")
    out = tmp_path / "c.h5"
    summary = import_tree(root, out, progress=False)
    assert summary["n_scans"] == 7
    with ScanCollection(out) as c:
        assert c.names == ["train/good/000", "train/good/001", "validation/good/000", "test/dent/000",
                           "test/dent/001", "test/good/000", "test/good/001"]
        assert c.select(split="train", label="good") == [0, 1]
        assert c.select(split="test", label="defective", defect="dent") == [3, 4]
        assert c.select(split="validation") == [2]
        # frame fixed from the training scans only (test spheres are bigger and elsewhere)
        train_points = np.concatenate([read_cloud(root / "train/good/000.ply")[0],
                                       read_cloud(root / "train/good/001.xyz")[0]])
        expected = Frame.fit(train_points)
        np.testing.assert_allclose(c.frame.center, expected.center, atol=1e-9)
        assert np.isclose(c.frame.scale, expected.scale)
        train = np.concatenate([c[i].points for i in (0, 1)])
        assert np.isclose(np.ptp(train, axis=0).max(), 1.0, atol=1e-6)
        # ground truth: the dent scans get the file's labels, good test scans all zeros, train none
        gt = np.loadtxt(root / "ground_truth/dent/001.txt").astype(np.uint8)
        np.testing.assert_array_equal(c[4].point_labels, gt)
        assert c[5].point_labels is not None and not c[5].point_labels.any()
        assert c[0].point_labels is None
        assert c.provenance["frame_fitted_on"] == "train" and c.provenance["files"] == 7


def test_points_subset_is_seeded_and_file_is_byte_identical(tmp_path):
    root = make_tree(tmp_path / "tree")
    a, b, other = tmp_path / "a.h5", tmp_path / "b.h5", tmp_path / "other.h5"
    import_tree(root, a, n_points=100, seed=3, progress=False)
    import_tree(root, b, n_points=100, seed=3, progress=False)
    import_tree(root, other, n_points=100, seed=4, progress=False)
    assert sha(a) == sha(b)
    assert sha(a) != sha(other)
    with ScanCollection(a) as c:
        assert all(len(s) == 100 for s in c)
        # labels follow their points through the subset
        pts, _ = read_cloud(root / "test/dent/000.txt")
        gt = np.loadtxt(root / "ground_truth/dent/000.txt")
        s = c[c.index_of("test/dent/000")]
        orig = c.frame.to_file(s.points)
        idx = [int(np.argmin(np.linalg.norm(pts - q, axis=1))) for q in orig]
        np.testing.assert_array_equal(s.point_labels, gt[idx])


def test_voxel_downsampling_keeps_labels():
    p = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [1.5, 0.1, 0.1]])
    n = np.array([[0, 0, 1.0], [0, 1.0, 0], [1.0, 0, 0]])
    q, m, lab = voxel_downsample(p, n, np.array([0, 1, 0], np.uint8), 1.0)
    np.testing.assert_allclose(q, [[0.15, 0.15, 0.15], [1.5, 0.1, 0.1]])
    np.testing.assert_allclose(m[0], [0, 2 ** -0.5, 2 ** -0.5])
    np.testing.assert_array_equal(lab, [1, 0])


def test_import_with_voxel(tmp_path):
    root = make_tree(tmp_path / "tree")
    import_tree(root, tmp_path / "c.h5", voxel=0.5, progress=False)
    with ScanCollection(tmp_path / "c.h5") as c:
        assert all(0 < len(s) < 300 for s in c)
        assert c[3].point_labels is not None and len(c[3].point_labels) == len(c[3])


def test_nonfinite_points_dropped_and_logged(tmp_path, caplog):
    p, n = sphere(400)
    p[:7] = np.nan
    p[7, 2] = np.inf
    write_any(tmp_path / "in" / "ball.npy", p, n)
    with caplog.at_level("INFO", logger="datasets.importer"):
        summary = import_tree(tmp_path / "in", tmp_path / "c.h5", progress=False)
    assert summary["n_dropped"] == 8
    assert any("dropped 8 of 400" in r.message for r in caplog.records)
    with ScanCollection(tmp_path / "c.h5") as c:
        assert len(c[0]) == 392


# ---- bad inputs: one clear error naming the file, nothing written ----------------------------------------------------
def _bad_tree(tmp_path, case):
    root = tmp_path / "tree"
    p, n = sphere(200)
    write_any(root / "train" / "good" / "ok.ply", p, n)
    bad = root / "test" / "dent"
    bad.mkdir(parents=True)
    if case == "empty":
        (bad / "x.ply").write_bytes(b"")
    elif case == "zero_points":
        np.save(bad / "x.npy", np.zeros((0, 3)))
    elif case == "one_point":
        (bad / "x.xyz").write_text("1 2 3\n")
    elif case == "all_nan":
        np.savetxt(bad / "x.xyz", np.full((50, 3), np.nan))
    elif case == "gt_mismatch":
        write_any(bad / "x.xyz", p)
        (root / "ground_truth" / "dent").mkdir(parents=True)
        np.savetxt(root / "ground_truth" / "dent" / "x.txt", np.zeros(10), fmt="%d")
        return root, root / "ground_truth" / "dent" / "x.txt"
    return root, next(bad.iterdir())


BAD_CASES = {"empty": "empty file", "zero_points": "contains no points", "one_point": "1 finite point",
             "all_nan": "no finite points", "gt_mismatch": "10 labels for the 200 points"}
# (a file that is not a point cloud, a mesh or a README beside the clouds, is skipped and named, not an error:
# tests/datasets/test_folder_of_scans.py)


@pytest.mark.parametrize("case", list(BAD_CASES))
def test_bad_inputs_give_one_clear_error_and_write_nothing(tmp_path, case, capsys):
    root, culprit = _bad_tree(tmp_path, case)
    out = tmp_path / "c.h5"
    with pytest.raises(ValueError, match=BAD_CASES[case]) as e:
        import_tree(root, out, progress=False)
    assert str(culprit) in str(e.value)
    assert not out.exists() and not list(tmp_path.glob(".*.tmp"))
    assert main(["import", str(root), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and str(culprit) in err and "Traceback" not in err
    assert not out.exists()


def test_folder_without_scans(tmp_path, capsys):
    (tmp_path / "in").mkdir()
    assert main(["import", str(tmp_path / "in"), "--out", str(tmp_path / "c.h5")]) == 2
    assert "no point-cloud files found" in capsys.readouterr().err
    assert main(["import", str(tmp_path / "missing"), "--out", str(tmp_path / "c.h5")]) == 2
    assert "missing: no such folder" in capsys.readouterr().err
    assert not (tmp_path / "c.h5").exists()


def test_existing_output_needs_overwrite(tmp_path, capsys):
    write_any(tmp_path / "in" / "a.npy", *sphere(100))
    out = tmp_path / "in" / "c.h5"  # inside the imported folder: skipped, not an "unknown extension"
    assert main(["import", str(tmp_path / "in"), "--out", str(out)]) == 0
    assert main(["import", str(tmp_path / "in"), "--out", str(out)]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["import", str(tmp_path / "in"), "--out", str(out), "--overwrite", "--points", "50"]) == 0


# ---- command line: info and export -----------------------------------------------------------------------------------
def test_cli_import_info_export_roundtrip(tmp_path, capsys):
    root = make_tree(tmp_path / "tree")
    out = tmp_path / "c.h5"
    assert main(["import", str(root), "--out", str(out), "--points", "150"]) == 0
    printed = capsys.readouterr().out
    assert "7 scans" in printed and "dent" in printed

    assert main(["info", str(out)]) == 0
    info = capsys.readouterr().out
    assert "7 scans" in info and "test        defective   dent" in info
    assert "points per scan: min 150, median 150, max 150" in info and "fingerprint" in info

    exported = tmp_path / "exported"
    assert main(["export", str(out), str(exported)]) == 0
    assert (exported / "train/good/000.ply").is_file() and (exported / "ground_truth/dent/001.txt").is_file()
    points, _ = read_cloud(exported / "test/dent/001.ply")
    assert len(points) == 150
    import open3d as o3d

    colors = np.asarray(o3d.io.read_point_cloud(str(exported / "test/dent/001.ply")).colors)
    with ScanCollection(out) as c:
        red = colors[:, 1] < 0.5
        np.testing.assert_array_equal(red, c[c.index_of("test/dent/001")].point_labels > 0)

    again = tmp_path / "again.h5"
    assert main(["import", str(exported), "--out", str(again)]) == 0
    with ScanCollection(out) as a, ScanCollection(again) as b:
        assert a.names == b.names
        assert [m["label"] for m in a.metadata()] == [m["label"] for m in b.metadata()]
        np.testing.assert_array_equal(a[3].point_labels, b[3].point_labels)

    assert main(["export", str(out), str(exported)]) == 2  # not empty
    assert "not empty" in capsys.readouterr().err
    assert main(["info", str(tmp_path / "nothing.h5")]) == 2
    assert "nothing.h5" in capsys.readouterr().err


def test_cli_info_on_a_foreign_file(tmp_path, capsys):
    (tmp_path / "x.h5").write_text("not hdf5")
    assert main(["info", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err
    assert err.strip() == f"error: {tmp_path / 'x.h5'}: not an HDF5 file"
