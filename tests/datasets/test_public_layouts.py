"""Tests of the public benchmarks' layouts (Real3D-AD, Anomaly-ShapeNet, MVTec 3D-AD) and of template views.

Each layout is rebuilt in miniature in tmp_path (a few hundred points a cloud, PCDs written as ASCII PCD text, TIFFs
and PNGs written here) and imported as a user would.
"""
import hashlib

import numpy as np
import pytest

from datasets import ScanCollection
from datasets.__main__ import main
from datasets.importer import import_tree
from datasets.layouts import LAYOUTS, detect_layout
from datasets.templates import render_views


# ---- small replicas ------------------------------------------------------------------------------------------------
def sphere(n, center=(0.0, 0.0, 0.0), radius=1.0, turn=0.0):
    """Fibonacci points (n, 3) on a sphere and their outward normals; ``turn`` rotates the spiral about z."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5 ** 0.5) * i + turn
    normals = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)
    return np.asarray(center) + radius * normals, normals


def write_pcd(path, points):
    """An ASCII PCD file as scanners' software writes it (header, then one 'x y z' line a point)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    header = ["# .PCD v0.7 - Point Cloud Data file format", "VERSION 0.7", "FIELDS x y z", "SIZE 4 4 4",
              "TYPE F F F", "COUNT 1 1 1", f"WIDTH {len(points)}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0",
              f"POINTS {len(points)}", "DATA ascii"]
    body = "\n".join(f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in points)
    path.write_text("\n".join(header) + "\n" + body + "\n")


def hashes(root):
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*")) if p.is_file()}


def partial(points, direction):
    """The half of a cloud facing ``direction`` (a partial scan)."""
    return points[points @ np.asarray(direction, dtype=float) > 0]


R3D_RADIUS = 12.0  # mm


def make_real3d(root):
    """airplane/: 4 templates, test 2 good (one a 'temp' file) and 2 defective with gt/<stem>.txt."""
    for k in range(4):
        write_pcd(root / "train" / f"{k + 1}_template.pcd", sphere(400, radius=R3D_RADIUS, turn=0.3 * k)[0])
    write_pcd(root / "test" / "10_good.pcd", partial(sphere(500, radius=R3D_RADIUS)[0], (0, 0, 1)))
    write_pcd(root / "test" / "11_good_temp.pcd", sphere(100, radius=R3D_RADIUS)[0])  # not a sample
    truth = {}
    for stem, direction in (("12_bulge", (1, 0, 0)), ("13_sink_cut", (0, 1, 0))):
        pts = partial(sphere(480, radius=R3D_RADIUS)[0], direction)
        write_pcd(root / "test" / f"{stem}.pcd", pts[::2])  # a decimated copy: the loader reads the txt instead
        labels = (pts @ np.asarray(direction, float) > 0.9 * R3D_RADIUS).astype(int)
        (root / "gt").mkdir(exist_ok=True)
        np.savetxt(root / "gt" / f"{stem}.txt", np.column_stack([pts, labels]), fmt=["%.6f"] * 3 + ["%d"])
        truth[stem] = (pts, labels)
    return truth


def make_shapenet(root, comma=True):
    """pcd/ashtray0/: 4 templates, positive0 (good), bulge0 (comma GT, rows shuffled), concavity1 (space GT)."""
    rng = np.random.default_rng(1)
    for k in range(4):
        write_pcd(root / "train" / f"ashtray0_template{k}.pcd", sphere(400, radius=0.5, turn=0.2 * k)[0])
    write_pcd(root / "test" / "positive0.pcd", partial(sphere(400, radius=0.5)[0], (0, 0, 1)))
    truth = {}
    for stem, direction, sep in (("bulge0", (1, 0, 0), "," if comma else " "), ("concavity1", (0, -1, 0), " ")):
        pts = partial(sphere(420, radius=0.5)[0], direction)
        write_pcd(root / "test" / f"{stem}.pcd", pts)
        labels = (pts @ np.asarray(direction, float) > 0.42).astype(int)
        order = rng.permutation(len(pts))
        (root / "GT").mkdir(exist_ok=True)
        np.savetxt(root / "GT" / f"{stem}.txt", np.column_stack([pts, labels])[order], delimiter=sep,
                   fmt=["%.6f"] * 3 + ["%d"])
        truth[stem] = labels
    return truth


GRID, PIXEL, TABLE_Z = 60, 0.001, 0.40  # 60 x 60 pixels of 1 mm, table 0.4 m from the camera (metres)


def mvtec_grid(seed=0, dome_radius=0.015, speck=True):
    """An organised cloud (GRID, GRID, 3) float32 in metres: a table plane at z = TABLE_Z (slightly tilted), a dome
    rising towards the camera in the middle, a 3 x 3 pixel speck floating 20 mm above the table, some pixels without
    a point (zeros). Returns the grid and the (GRID, GRID) bool map of the dome's pixels that stand >= 8 mm off the
    table (the object's points that must survive)."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:GRID, 0:GRID].astype(float)
    x, y = (u - GRID / 2) * PIXEL, (v - GRID / 2) * PIXEL
    table = TABLE_Z + 0.05 * x + 0.02 * y  # the table is not square to the camera
    r2 = x**2 + y**2
    height = np.sqrt(np.clip(dome_radius**2 - r2, 0, None))
    z = table - height
    if speck:
        z[5:8, 45:48] = table[5:8, 45:48] - 0.02
    grid = np.stack([x, y, z], axis=2).astype(np.float32)
    missing = rng.random((GRID, GRID)) < 0.03
    grid[missing] = 0.0
    tilt = np.sqrt(1 + 0.05**2 + 0.02**2)  # perpendicular distance = vertical offset / tilt
    object_pixels = (height / tilt >= 0.008) & ~missing
    return grid, object_pixels, missing, height / tilt


def make_mvtec(root):
    import tifffile
    from PIL import Image

    files = {}
    for split, kind, seed in (("train", "good", 0), ("train", "good", 1), ("validation", "good", 2),
                              ("test", "good", 3), ("test", "crack", 4)):
        grid, obj, missing, height = mvtec_grid(seed)
        name = f"{seed:03d}"
        path = root / split / kind / "xyz" / f"{name}.tiff"
        path.parent.mkdir(parents=True, exist_ok=True)
        tifffile.imwrite(path, grid, photometric="rgb")
        (root / split / kind / "rgb").mkdir(exist_ok=True)
        Image.fromarray(np.zeros((GRID, GRID, 3), np.uint8)).save(root / split / kind / "rgb" / f"{name}.png")
        mask = None
        if kind != "good":
            mask = np.zeros((GRID, GRID), np.uint8)
            mask[26:34, 30:36] = 255  # a crack on the dome
            (root / split / kind / "gt").mkdir(exist_ok=True)
            Image.fromarray(mask).save(root / split / kind / "gt" / f"{name}.png")
        files[f"{split}/{kind}/{name}"] = (grid, obj, missing, height, mask)
    return files


# ---- Real3D-AD -----------------------------------------------------------------------------------------------------
def test_real3d_splits_labels_units_and_untouched_files(tmp_path):
    root = tmp_path / "airplane"
    truth = make_real3d(root)
    before = hashes(root)
    assert detect_layout(root) == "real3d-ad"
    s = import_tree(root, tmp_path / "a.h5", views=3, validation_views=2, progress=False)
    assert hashes(root) == before  # the user's files are only read
    assert s["layout"] == "real3d-ad" and s["units"] == "mm" and s["voxel"] is None  # small clouds: no downsampling
    with ScanCollection(tmp_path / "a.h5") as c:
        scans = {x.name: x for x in c}
        frame = c.frame
    assert sorted(n for n in scans if n.startswith("train/")) == \
        sorted(f"train/{k}_template/view_{i:03d}" for k in range(1, 5) for i in range(3))
    assert len([n for n in scans if n.startswith("validation/")]) == 8
    tests = {n: x for n, x in scans.items() if x.split == "test"}
    assert sorted(tests) == ["test/bulge/12_bulge", "test/good/10_good", "test/sink/13_sink_cut"]  # 'temp' skipped
    good = tests["test/good/10_good"]
    assert good.label == "good" and good.point_labels is not None and not good.point_labels.any()
    for stem, defect in (("12_bulge", "bulge"), ("13_sink_cut", "sink")):
        scan = tests[f"test/{defect}/{stem}"]
        pts, labels = truth[stem]
        assert scan.label == "defective" and scan.defect == defect
        # the txt is the labelled cloud: its points, in its order, with its labels, back in millimetres
        np.testing.assert_allclose(frame.to_file(scan.points), pts, atol=1e-4 * R3D_RADIUS)
        np.testing.assert_array_equal(scan.point_labels, labels)
    views = [x for x in scans.values() if x.split != "test"]
    assert all(x.sensor_origin is not None and x.label == "good" for x in views)
    # millimetres in the file: the collection frame maps the 24 mm sphere to the unit cube
    assert frame.scale == pytest.approx(1 / (2 * R3D_RADIUS), rel=0.05)


def test_test_scans_without_origin_are_oriented_like_the_templates(tmp_path):
    from scipy.spatial import cKDTree

    from datasets.layouts import orient_like_templates

    root = tmp_path / "airplane"
    make_real3d(root)
    s = import_tree(root, tmp_path / "a.h5", views=2, validation_views=1, progress=False)
    assert s["oriented_by_templates"] == s["n_without_origin"] == 3
    with ScanCollection(tmp_path / "a.h5") as c:
        for scan in c.read_many(c.select(split="test")):
            outward = c.frame.to_file(scan.points) / R3D_RADIUS  # the sphere is centred at the origin
            assert np.mean(np.einsum("ij,ij->i", scan.normals, outward) > 0) > 0.95
    # the rule itself: a scan whose normals all point inward is turned outward; one in another pose is left alone
    tp, tn = sphere(2000, radius=R3D_RADIUS)
    templates = (cKDTree(tp), tn, 0.5)
    cap = tp[tp[:, 2] > 4.0]
    inward = -cap / R3D_RADIUS
    fixed, on = orient_like_templates(cap, inward, templates)
    assert on and np.allclose(fixed, -inward)
    moved, on = orient_like_templates(cap + 100.0, inward, templates)
    assert not on and np.array_equal(moved, inward)


def test_a_flipped_patch_of_a_test_scan_takes_the_templates_sign():
    # the propagation along a partial scan can flip a patch beyond a crease: each point on the templates then takes
    # the sign of its nearest template normals; a point off the templates (a foreign object) keeps the scan's sign
    from scipy.spatial import cKDTree

    from datasets.layouts import orient_like_templates

    tp, tn = sphere(3000, radius=R3D_RADIUS, turn=0.3)
    templates = (cKDTree(tp), tn, 0.5)
    cap = tp[tp[:, 2] > 2.0][::2] * 1.001  # not the template points themselves
    outward = cap / np.linalg.norm(cap, axis=1, keepdims=True)  # the truth, independent of the templates' normals
    patch = cap[:, 0] > 3.0
    assert 0.1 < patch.mean() < 0.4
    normals = np.where(patch[:, None], -outward, outward)
    foreign = np.array([[0.0, 0.0, 2.0 * R3D_RADIUS]])  # far above the cap; its normal points down, as the scan gave it
    pts = np.vstack([cap, foreign])
    fixed, on = orient_like_templates(pts, np.vstack([normals, [[0.0, 0.0, -1.0]]]), templates)
    assert on
    np.testing.assert_allclose(fixed[:-1], outward)
    np.testing.assert_allclose(fixed[-1], [0.0, 0.0, -1.0])
    # the whole-scan sign comes first: the same scan with every normal inverted gives the same result
    fixed2, _ = orient_like_templates(pts, -np.vstack([normals, [[0.0, 0.0, 1.0]]]), templates)
    np.testing.assert_allclose(fixed2[:-1], outward)


def test_real3d_missing_ground_truth_names_the_file(tmp_path):
    root = tmp_path / "car"
    make_real3d(root)
    (root / "gt" / "12_bulge.txt").unlink()
    with pytest.raises(ValueError, match=r"12_bulge\.pcd.*without its ground truth.*12_bulge\.txt"):
        import_tree(root, tmp_path / "c.h5", progress=False)
    assert not (tmp_path / "c.h5").exists()


def test_downsampling_keeps_labels_and_reports_the_voxel(tmp_path):
    root = tmp_path / "airplane"
    truth = make_real3d(root)
    s = import_tree(root, tmp_path / "a.h5", views=2, validation_views=1, max_points=60, progress=False)
    assert s["voxel_auto"] and s["voxel"] > 0
    with ScanCollection(tmp_path / "a.h5") as c:
        scan = c[c.names.index("test/bulge/12_bulge")]
        assert c.provenance["voxel"] == s["voxel"]
    pts, labels = truth["12_bulge"]
    assert len(scan) < len(pts)
    # each voxel's label is the max of its points' labels: the defect survives, and only where the truth has it
    assert scan.point_labels.sum() > 0
    assert scan.point_labels.mean() >= labels.mean() * 0.8


# ---- Anomaly-ShapeNet ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("comma", [True, False])
def test_shapenet_ground_truth_matched_by_coordinates(tmp_path, comma):
    root = tmp_path / "pcd" / "ashtray0"
    truth = make_shapenet(root, comma=comma)
    before = hashes(root)
    assert detect_layout(root) == "anomaly-shapenet"
    s = import_tree(root, tmp_path / "s.h5", views=2, validation_views=1, progress=False)
    assert hashes(root) == before
    assert s["units"] == "unit scale"
    with ScanCollection(tmp_path / "s.h5") as c:
        scans = {x.name: x for x in c}
    assert scans["test/good/positive0"].label == "good" and not scans["test/good/positive0"].point_labels.any()
    for stem, defect in (("bulge0", "bulge"), ("concavity1", "concavity")):
        scan = scans[f"test/{defect}/{stem}"]
        assert scan.label == "defective" and scan.defect == defect
        # the GT rows were shuffled: the labels must follow the .pcd's own point order
        np.testing.assert_array_equal(scan.point_labels, truth[stem])
    assert sum(x.split == "train" for x in scans.values()) == 8
    assert sum(x.split == "validation" for x in scans.values()) == 4


def test_shapenet_mismatched_ground_truth_says_which_file_and_how_many(tmp_path):
    root = tmp_path / "pcd" / "ashtray0"
    make_shapenet(root)
    gt = root / "GT" / "bulge0.txt"
    table = np.loadtxt(gt, delimiter=",")
    table[:7, :3] += 0.05  # seven rows moved far from any point of the cloud
    np.savetxt(gt, table, delimiter=",", fmt=["%.6f"] * 3 + ["%d"])
    with pytest.raises(ValueError, match=r"bulge0\.txt: 7 of the \d+ points of .*bulge0\.pcd"):
        import_tree(root, tmp_path / "s.h5", progress=False)
    assert not (tmp_path / "s.h5").exists()


# ---- MVTec 3D-AD ---------------------------------------------------------------------------------------------------
def test_mvtec_table_plane_removed_labels_on_the_grid(tmp_path):
    root = tmp_path / "bagel"
    files = make_mvtec(root)
    before = hashes(root)
    assert detect_layout(root) == "mvtec3d"
    s = import_tree(root, tmp_path / "m.h5", progress=False)
    assert hashes(root) == before
    assert s["units"] == "m" and s["voxel"] is None
    with ScanCollection(tmp_path / "m.h5") as c:
        scans = {x.name: x for x in c}
        frame = c.frame
        assert c.provenance["table_plane"] == "removed"
    assert {n: x.split for n, x in scans.items()} == {"train/good/000": "train", "train/good/001": "train",
                                                       "validation/good/002": "validation",
                                                       "test/good/003": "test", "test/crack/004": "test"}
    for name, (grid, obj, missing, height, mask) in files.items():
        scan = scans[name]
        pts = frame.to_file(scan.points)  # metres again
        valid = ~missing
        # exactly the dome's pixels that stand clear of the table's 5 mm band survive: no table, no speck
        expected = valid & (height >= 0.005)
        assert len(pts) == expected.sum()
        np.testing.assert_allclose(np.sort(pts[:, 2]), np.sort(grid[expected][:, 2]), atol=1e-6)
        assert obj.sum() <= len(pts)
        np.testing.assert_allclose(scan.sensor_origin, frame.to_collection(np.zeros(3)), atol=1e-6)
        # normals face the sensor at the origin
        assert np.all(np.einsum("ij,ij->i", scan.normals, -pts) > 0)
        if scan.split == "test":
            want = np.zeros_like(expected) if mask is None else (mask > 0)
            np.testing.assert_array_equal(np.sort(scan.point_labels), np.sort(want[expected].astype(np.uint8)))
            assert (scan.label == "defective") == (mask is not None)
    crack = scans["test/crack/004"]
    assert crack.defect == "crack" and crack.point_labels.sum() > 0


def test_mvtec_keep_plane_keeps_every_point(tmp_path):
    root = tmp_path / "bagel"
    files = make_mvtec(root)
    assert main(["import", str(root), "--out", str(tmp_path / "m.h5"), "--keep-plane", "--layout", "mvtec3d"]) == 0
    with ScanCollection(tmp_path / "m.h5") as c:
        for name, (grid, obj, missing, height, mask) in files.items():
            assert len(c[c.names.index(name)]) == (~missing).sum()  # every pixel with a point: table included
        assert c.provenance["table_plane"] == "kept"


def test_mvtec_mask_of_the_wrong_size_names_the_file(tmp_path):
    from PIL import Image

    root = tmp_path / "bagel"
    make_mvtec(root)
    Image.fromarray(np.zeros((30, 30), np.uint8)).save(root / "test" / "crack" / "gt" / "004.png")
    with pytest.raises(ValueError, match=r"004\.png: mask of 30 x 30 pixels, but its point map is 60 x 60"):
        import_tree(root, tmp_path / "m.h5", progress=False)


# ---- errors --------------------------------------------------------------------------------------------------------
def test_unknown_layout_names_the_known_ones(tmp_path, capsys):
    root = tmp_path / "airplane"
    make_real3d(root)
    with pytest.raises(ValueError, match="unknown layout 'kitti'.*real3d-ad.*anomaly-shapenet.*mvtec3d"):
        import_tree(root, tmp_path / "x.h5", layout="kitti")
    empty = tmp_path / "empty"
    (empty / "stuff").mkdir(parents=True)
    assert main(["import", str(empty), "--out", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err
    assert all(name in err for name in LAYOUTS)


def test_cli_prints_layout_and_voxel(tmp_path, capsys):
    root = tmp_path / "airplane"
    make_real3d(root)
    assert main(["import", str(root), "--out", str(tmp_path / "a.h5"), "--views", "2", "--validation-views", "1",
                 "--max-points", "60"]) == 0
    out = capsys.readouterr().out
    assert "layout real3d-ad (mm); voxel" in out and "from the training clouds' spacing" in out


def test_calibration_uses_the_validation_views(tmp_path):
    """The trainer trains on the templates' training views and holds the validation views back (no template is)."""
    from autodecoder.latent.collection_split import split_training_scans

    root = tmp_path / "airplane"
    make_real3d(root)
    import_tree(root, tmp_path / "a.h5", views=3, validation_views=2, progress=False)
    with ScanCollection(tmp_path / "a.h5") as c:
        train, calibration = split_training_scans(c)
        names = c.names
    assert sorted(names[i] for i in train) == sorted(n for n in names if n.startswith("train/"))
    assert sorted(calibration) == sorted(n for n in names if n.startswith("validation/"))
    assert {n.split("/")[1] for n in calibration} == {f"{k}_template" for k in range(1, 5)}


# ---- template views ------------------------------------------------------------------------------------------------
def test_template_views_are_partial_visible_seeded_and_face_their_sensor():
    center = np.array([3.0, -1.0, 2.0])
    pts, nrm = sphere(3000, center=center, radius=2.0)
    views = render_views("t", pts, nrm, n_train=4, n_validation=2, seed=5)
    again = render_views("t", pts, nrm, n_train=4, n_validation=2, seed=5)
    other = render_views("t", pts, nrm, n_train=4, n_validation=2, seed=6)
    assert [v.split for v in views] == ["train"] * 4 + ["validation"] * 2
    index = {tuple(p): i for i, p in enumerate(pts)}
    for v, w, o in zip(views, again, other):
        np.testing.assert_array_equal(v.points, w.points)
        np.testing.assert_array_equal(v.sensor_origin, w.sensor_origin)
        assert not np.allclose(v.sensor_origin, o.sensor_origin)
        origin = v.sensor_origin.astype(np.float64)
        # at 2 bounding-box diagonals from the bounding box's centre
        box_center = (pts.min(0) + pts.max(0)) / 2
        assert np.linalg.norm(origin - box_center) == pytest.approx(2 * np.linalg.norm(np.ptp(pts, axis=0)), rel=1e-5)
        # from the template's surface: every view point is a template point
        assert v.points.dtype == np.float64  # file units kept exact until the collection frame is applied
        idx = np.array([index[tuple(p)] for p in v.points])
        # partial, and what a sphere's geometry says is visible: a sphere point p is seen from o iff
        # (p - c) . (o - p) > 0 (o lies outside p's tangent plane)
        seen = np.einsum("ij,ij->i", pts - center, origin - pts) > 0
        assert 0.3 * len(pts) < len(v) < 0.7 * len(pts)
        assert seen[idx].mean() > 0.98 and np.isin(np.flatnonzero(seen), idx).mean() > 0.9
        # normals (from the template's, outward) face the sensor
        assert np.all(np.einsum("ij,ij->i", v.normals, origin - v.points) > 0)
        np.testing.assert_allclose(v.normals, nrm[idx], atol=1e-6)


def test_table_plane_removal_on_a_large_map_uses_a_subset_and_agrees():
    """Over 5000 points DBSCAN runs on a seeded subset; the object's pixels must still be exactly those off the
    table's band, and the floating speck must still go."""
    from datasets.layouts import _CLUSTER_SUBSAMPLE, remove_table_plane

    n, pixel = 120, 0.0005  # 14,400 pixels of 0.5 mm
    v, u = np.mgrid[0:n, 0:n].astype(float)
    x, y = (u - n / 2) * pixel, (v - n / 2) * pixel
    table = TABLE_Z + 0.03 * x
    height = np.sqrt(np.clip(0.024**2 - x**2 - y**2, 0, None))
    z = table - height
    z[3:7, 110:114] = table[3:7, 110:114] - 0.02  # 16 points floating 20 mm above the table
    grid = np.stack([x, y, z], axis=2)
    keep = remove_table_plane(grid, seed=0)
    off_table = height / np.sqrt(1 + 0.03**2) >= 0.005
    assert off_table.sum() > _CLUSTER_SUBSAMPLE  # the subset path is taken
    np.testing.assert_array_equal(keep, off_table)
    np.testing.assert_array_equal(remove_table_plane(grid, seed=0), keep)  # seeded
