"""Real-scan-like data through the importer: stray points found and reported, the frame unmoved by them, normals of a
noisy view facing its sensor. Own small data (a range view of a sphere, metres, range noise along the rays); the
tests on the real Stanford range scans skip when ``../shared/realscans`` is absent."""
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from datasets import Frame, ScanCollection, write_cloud
from datasets.__main__ import main
from datasets.importer import import_tree
from datasets.normals import estimate_normals
from datasets.outliers import stray_points

REALSCANS = Path(__file__).resolve().parents[2] / "shared" / "realscans" / "bunny"
# these two checks need real scanner data, which the repository does not ship: the project's shared folder beside
# the checkout has it (developers' machines and CI); the same properties are tested on synthetic range views above
NEEDS_REAL_SCANS = pytest.mark.skipif(
    not REALSCANS.is_dir(), reason=f"needs the real Stanford range scans (shared data, not in the repository) at "
                                   f"{REALSCANS}; the synthetic-view tests in this file cover the same rules")
RADIUS = 0.05  # metres
SENSOR = np.array([0.0, 0.02, 0.3])


def range_view(noise=2e-4, grid=70, seed=0, center=np.zeros(3)):
    """A pinhole range view of a sphere: hit points (N, 3) with Gaussian range noise along each ray, their true
    outward normals (N, 3) and the cosine between normal and ray to the sensor (grazing at the silhouette)."""
    rng = np.random.default_rng(seed)
    u = np.linspace(-1.0, 1.0, grid) * 1.05 * RADIUS / np.linalg.norm(SENSOR - center)
    dx, dy = np.meshgrid(u, u)
    dirs = np.stack([dx.ravel(), dy.ravel(), -np.ones(dx.size)], axis=1)
    dirs = dirs - np.array([0.0, (SENSOR - center)[1] / (SENSOR - center)[2], 0.0])  # look at the centre
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    oc = SENSOR - center
    b = dirs @ oc
    disc = b * b - (oc @ oc - RADIUS ** 2)
    hit = disc > 0
    t = -b[hit] - np.sqrt(disc[hit])
    clean = SENSOR + t[:, None] * dirs[hit]
    normals = (clean - center) / RADIUS
    points = clean + rng.normal(0.0, noise, len(t))[:, None] * dirs[hit]
    cos = np.einsum("ij,ij->i", normals, -dirs[hit])
    return points, normals, cos


def with_strays(points, seed=0, far=True):
    """The view with spurious returns: points on sensor rays 8-20 mm in front of the surface (5-13 spacings),
    and (``far``) one return 10 cm off the part. Returns (points, stray mask)."""
    rng = np.random.default_rng(seed)
    picks = points[rng.choice(len(points), 5, replace=False)]
    d = picks - SENSOR
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    extra = [picks - rng.uniform(0.008, 0.02, (5, 1)) * d]
    if far:
        extra.append(np.array([[0.1, 0.0, 0.02]]))
    extra = np.concatenate(extra)
    out = np.concatenate([points, extra])
    mask = np.zeros(len(out), bool)
    mask[len(points):] = True
    order = rng.permutation(len(out))
    return out[order], mask[order]


def test_stray_points_finds_spurious_returns_not_the_surface():
    points, normals, cos = range_view()
    cloud, truth = with_strays(points)
    found = stray_points(cloud)
    np.testing.assert_array_equal(found, truth)
    # the sparse, grazing silhouette is part of the clean view and nothing there is flagged
    assert (cos < 0.3).sum() > 50 and not stray_points(points).any()


def test_stray_points_is_unit_free_chunk_free_and_validates(monkeypatch):
    import datasets.outliers

    cloud, truth = with_strays(range_view()[0])
    found = stray_points(cloud)
    np.testing.assert_array_equal(stray_points(cloud * 1000.0), found)  # metres or millimetres
    monkeypatch.setattr(datasets.outliers, "_CHUNK", 333)
    np.testing.assert_array_equal(stray_points(cloud), found)  # blocks of a large scan give the same answer
    assert not stray_points(cloud[:5]).any()  # too few points to judge
    with pytest.raises(ValueError, match="k must be"):
        stray_points(cloud, k=2)


def _tree(root, strays):
    """Four training views of a sphere seen from different sides (strays in two of them) and one test view."""
    for k in range(5):
        points = range_view(seed=k, center=np.array([0.01 * k, 0.0, 0.0]))[0]
        if strays and k in (1, 3):
            points = with_strays(points, seed=k)[0]
        split = "train" if k < 4 else "test"
        path = root / split / "good" / f"{k:03d}.ply"
        write_cloud(path, points)
        path.with_suffix(".json").write_text(json.dumps({"sensor_origin": SENSOR.tolist()}))
    return root


def test_frame_is_unmoved_by_stray_points(tmp_path):
    import_tree(_tree(tmp_path / "clean", False), tmp_path / "clean.h5", progress=False)
    import_tree(_tree(tmp_path / "stray", True), tmp_path / "stray.h5", progress=False)
    with ScanCollection(tmp_path / "clean.h5") as a, ScanCollection(tmp_path / "stray.h5") as b:
        fa, fb = a.frame, b.frame
        stray_box = Frame.fit(np.concatenate([b.frame.to_file(b[i].points) for i in b.select(split="train")]))
        assert b.provenance["stray_points"]["total"] == 12 and a.provenance["stray_points"]["total"] == 0
        assert len(b[1]) == len(a[1]) + 6  # kept in the scans
    # tolerance: 0.1 % of the part's extent (the boxes differ only where noise reaches the box's faces)
    assert abs(fb.scale / fa.scale - 1) < 1e-3
    assert np.abs(fb.center - fa.center).max() * fa.scale < 1e-3
    # ... while the plain bounding box of the same points moves far outside that tolerance
    assert abs(stray_box.scale / fa.scale - 1) > 0.1


def test_info_reports_strays_and_drop_strays_removes_them(tmp_path, capsys):
    root = _tree(tmp_path / "tree", True)
    before = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in root.rglob("*.ply")}
    assert main(["import", str(root), "--out", str(tmp_path / "c.h5")]) == 0
    assert "12 stray points found" in capsys.readouterr().out
    assert main(["info", str(tmp_path / "c.h5")]) == 0
    out = capsys.readouterr().out
    assert "stray points at import" in out and ": 12 in 2 scans, at most 6 in one" in out
    assert main(["import", str(root), "--out", str(tmp_path / "d.h5"), "--drop-strays"]) == 0
    with ScanCollection(tmp_path / "c.h5") as c, ScanCollection(tmp_path / "d.h5") as d:
        assert c.frame == d.frame
        assert [len(s) for s in c] == [len(s) + 6 * (i in (1, 3)) for i, s in enumerate(d)]
        assert not any(stray_points(d.frame.to_file(s.points)).any() for s in d)
    assert before == {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in root.rglob("*.ply")}  # untouched


def test_normals_of_a_noisy_view_face_its_sensor():
    import open3d as o3d

    points, truth, cos = range_view(noise=4e-4)
    normals = estimate_normals(points, SENSOR)
    agree = np.einsum("ij,ij->i", normals, truth)
    assert np.median(agree) > np.cos(np.radians(10))
    # open3d's per-point test toward the camera on the same unoriented estimates, as the reference
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.normals = o3d.utility.Vector3dVector(normals)
    pcd.orient_normals_towards_camera_location(SENSOR)
    per_point = np.einsum("ij,ij->i", np.asarray(pcd.normals), truth)
    assert (per_point < 0).sum() >= 5  # grazing noise flips some under the per-point test ...
    assert (agree < 0).sum() <= 0.3 * (per_point < 0).sum()  # ... and the neighbour vote fixes most of them
    assert np.all(agree[cos > 0.3] > 0)  # where the view decides, every normal faces the sensor


# ---- the real Stanford range scans (skipped without ../shared/realscans) -------------------------------------------
@NEEDS_REAL_SCANS
def test_real_view_normals_face_its_sensor_and_few_points_are_stray():
    from scipy.spatial import cKDTree

    from datasets import read_cloud

    full, _ = read_cloud(REALSCANS / "bun000.ply")  # identity pose in bun.conf; the scanner looks down -z
    sensor = full.mean(0) + np.array([0.0, 0.0, 1.0])
    # reference: full-resolution normals (10x denser), signed by the sensor and then by their 20 neighbours' sum
    ref = estimate_normals(full, sensor)
    ref = ref[cKDTree(full).query(full, 20)[1]].sum(1)
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    keep = np.random.default_rng(0).choice(len(full), 4000, replace=False)
    normals = estimate_normals(full[keep], sensor)
    agree = np.einsum("ij,ij->i", normals, ref[keep])
    assert np.mean(agree > 0) > 0.995 and np.median(agree) > np.cos(np.radians(10))
    assert stray_points(full[keep]).mean() < 0.005


@NEEDS_REAL_SCANS
def test_real_view_stray_return_is_found():
    from datasets import read_cloud

    points, _ = read_cloud(REALSCANS / "ear_back.ply")  # one return ~8 cm off the bunny (by the other nine views)
    far = np.argmax(np.linalg.norm(points - np.median(points, axis=0), axis=1))
    found = stray_points(points)
    assert found[far] and found.mean() < 0.005
