"""Tests of the per-point deviation (``Scan.point_deviation``): each point's true signed offset from the good part's
surface, made by the synthesis and by the defects in real points, carried by every copy and move of a scan, stored
in a collection (unhashed: the fingerprint stays the scans'), and read from a tree's ``<stem>.deviation.txt``."""
from dataclasses import replace

import h5py
import numpy as np
import pytest
import trimesh

import datasets.synth as synth
from datasets import Frame, Scan, ScanCollection, write_cloud
from datasets.defects import DEFECT_KINDS, make_defect
from datasets.importer import export_collection, import_tree
from datasets.ingest import _without
from datasets.point_defects import defect_in_points
from datasets.registration import moved_by
from datasets.scanner import VirtualScanner
from datasets.validation import ScanReadError

HALF = np.array([1.5, 1.0, 0.5])  # the box's half extents
TOP = np.array([0.1, 0.05, 0.5])  # a point of its top face
UP = np.array([0.0, 0.0, 1.0])
SMALL = dict(n_train=1, n_test_good=1, n_test_defective=1, n_points=1500, progress=False)


@pytest.fixture(scope="module")
def box():
    return trimesh.creation.box(extents=2 * HALF)


def box_sdf(p):
    """The box's exact signed distance (positive outside) at points (n, 3) of its own frame: a closed form, not the
    mesh."""
    q = np.abs(p) - HALF
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def scan_of(n=6, deviation=None, name="test/dent/000", labels=True):
    rng = np.random.default_rng(n)
    return Scan(name=name, points=rng.normal(size=(n, 3)), normals=np.tile(UP, (n, 1)), split="test",
                label="defective", defect="dent", point_labels=np.ones(n, np.uint8) if labels else None,
                point_deviation=deviation)


# ---- the mesh synthesis ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["dent", "bump"])
def test_a_dent_lies_inside_the_good_part_and_a_bump_outside_by_its_height(box, kind):
    defect = make_defect(box, kind, TOP, UP, radius=0.1, height=0.03, seed=0)
    result = VirtualScanner(defect.mesh).scan(np.array([0.3, -0.2, 3.0]), look_at=TOP, n_points=6000, seed=0,
                                              noise=0.01)
    labels = defect.region(result.clean_points, result.triangle_ids)
    deviation = synth._point_deviation(box, result, labels, defect)
    on = labels.astype(bool)
    assert on.sum() >= 100 and np.all(deviation[~on] == 0)
    # on the flat top face the good surface is the plane z = 0.5: the deviation is the noise-free hit's height (up to
    # the refined mesh's piecewise-linear version of the profile)
    np.testing.assert_allclose(deviation[on], (result.clean_points[on] - TOP) @ UP, atol=0.03 * abs(defect.height))
    sign = np.sign(defect.height)
    assert sign == (1 if kind == "bump" else -1) and np.all(sign * deviation[on] > -1e-9)
    assert np.abs(deviation).max() == pytest.approx(abs(defect.height), rel=0.03)


def test_a_dent_deeper_than_a_thin_wall_is_measured_from_its_own_face():
    """Both faces of a sheet move (pressed sheet metal): the dented face's points lie nearer the far face's old place
    than their own, and the truth is still the depth they were pressed by."""
    import trimesh

    sheet = trimesh.creation.box(extents=(1.0, 1.0, 0.01))  # 0.01 thick, a dent 0.03 deep
    top = np.array([0.0, 0.0, 0.005])
    defect = make_defect(sheet, "dent", top, UP, radius=0.15, height=0.03, seed=0)
    result = VirtualScanner(defect.mesh).scan(np.array([0.1, -0.1, 2.0]), look_at=top, n_points=6000, seed=0,
                                              noise=0.0)
    labels = defect.region(result.clean_points, result.triangle_ids)
    on = labels.astype(bool)
    deviation = synth._point_deviation(sheet, result, labels, defect)
    np.testing.assert_allclose(deviation[on], (result.clean_points[on] - top) @ UP, atol=0.03 * 0.03)
    assert np.all(deviation[on] <= 1e-9) and deviation[on].min() <= -0.95 * 0.03
    nearest = -trimesh.proximity.signed_distance(sheet, result.clean_points[on])
    # what the distance to the nearest face would have said: far less, the far face's old place being near
    assert np.median(np.abs(nearest)) < 0.5 * np.median(np.abs(deviation[on]))


def test_synthesised_deviations_are_the_distance_to_the_good_part_in_the_collection_frame(box):
    """Noise-free scans in a random pose: every point's deviation, scaled back to file units, is the signed distance
    of the point (moved back into the part's frame) to the box (exact for missing and foreign; within 3 % of the depth
    for the profiles of dents and bumps); good test scans all 0, training None."""
    scans, frame = synth.synthesise(box, seed=5, noise=0.0, jitter_deg=20.0, jitter_translation=0.05, **SMALL)
    assert frame.scale != pytest.approx(1.0)
    for scan in scans:
        if scan.split == "train":
            assert scan.point_deviation is None
            continue
        assert scan.point_deviation.dtype == np.float32 and len(scan.point_deviation) == len(scan)
        if scan.label == "good":
            assert not scan.point_deviation.any()
            continue
        pose = scan.extra["pose"]
        in_part = (frame.to_file(scan.points) - pose[:3, 3]) @ pose[:3, :3]
        truth = box_sdf(in_part)
        # a dent's or a bump's truth is the analytic profile, which the refined mesh follows piecewise linearly
        close = 2e-5 if scan.defect in ("missing", "foreign") else 0.03 * np.abs(truth).max()
        np.testing.assert_allclose(scan.point_deviation / frame.scale, truth, atol=close)
        on = scan.point_labels.astype(bool)
        assert np.all(scan.point_deviation[~on] == 0)
        outward = scan.defect in ("bump", "foreign")
        assert np.median(scan.point_deviation[on]) * (1 if outward else -1) > 0.002


def test_recording_the_deviation_changes_no_scan_and_not_the_fingerprint(box, tmp_path, monkeypatch):
    recorded, frame = synth.synthesise(box, seed=4, jitter_deg=10.0, **SMALL)
    monkeypatch.setattr(synth, "_point_deviation", lambda mesh, result, labels, defect=None: np.zeros(len(labels)))
    plain, _ = synth.synthesise(box, seed=4, jitter_deg=10.0, **SMALL)
    assert any(s.point_deviation is not None and s.point_deviation.any() for s in recorded)
    for a, b in zip(recorded, plain, strict=True):
        assert a.name == b.name
        for key in ("points", "normals", "point_labels", "sensor_origin"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    fingerprints = []
    for name, scans in (("recorded", recorded), ("plain", plain),
                        ("none", [replace(s, point_deviation=None) for s in recorded])):
        ScanCollection.create(tmp_path / f"{name}.h5", scans, frame=frame)
        with ScanCollection(tmp_path / f"{name}.h5") as c:
            fingerprints.append(c.fingerprint())
    assert len(set(fingerprints)) == 1


# ---- a scan's copies and moves ----------------------------------------------------------------------------------
def test_a_scan_checks_its_deviations():
    with pytest.raises(ValueError, match=r"scan 'test/dent/000': 5 point deviations for 6 points"):
        scan_of(deviation=np.zeros(5))
    with pytest.raises(ValueError, match=r"scan 'test/dent/000': 1 point deviations are NaN or Inf"):
        scan_of(deviation=[0, 0, np.nan, 0, 0, 0])
    assert scan_of(deviation=[0, 1, 2, 3, 4, 5]).point_deviation.dtype == np.float32


def test_moves_and_subsets_carry_the_deviation_as_a_length():
    deviation = np.array([0.5, -1.0, 0.0, 2.0, 0.25, -0.125])
    scan = scan_of(deviation=deviation)
    moved = Frame(center=[1.0, 2.0, 3.0], scale=0.25).apply(scan)
    np.testing.assert_array_equal(moved.point_deviation, 0.25 * deviation)
    np.testing.assert_array_equal(scan.point_deviation, deviation)  # the input is left as it was
    assert Frame.identity().apply(scan_of()).point_deviation is None
    kept = _without(scan, np.array([True, False, False, True, False, False]))
    np.testing.assert_array_equal(kept.point_deviation, deviation[[1, 2, 4, 5]])
    # a rotation leaves it, a similarity scales it, a stretch along the normal (z) scales it by the stretch
    c, s = np.cos(0.3), np.sin(0.3)
    rotation = np.array([[c, -s, 0, 1], [s, c, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    np.testing.assert_allclose(moved_by(scan, rotation).point_deviation, deviation, rtol=1e-6)
    similar = rotation.copy()
    similar[:3, :3] *= 3.0
    np.testing.assert_allclose(moved_by(scan, similar).point_deviation, 3.0 * deviation, rtol=1e-6)
    np.testing.assert_allclose(moved_by(scan, np.diag([5.0, 0.5, 2.0, 1.0])).point_deviation, 2.0 * deviation,
                               rtol=1e-6)


# ---- the collection file ------------------------------------------------------------------------------------------
def test_deviations_round_trip_through_a_collection_unhashed(tmp_path):
    deviation = np.array([0.5, -1.0, 0.0, 2.0, 0.25, -0.125], np.float32)
    scans = [scan_of(deviation=deviation), scan_of(n=4, name="test/good/000"), scan_of(n=5, name="train/good/000",
                                                                                       labels=False)]
    ScanCollection.create(tmp_path / "a.h5", scans)
    ScanCollection.create(tmp_path / "b.h5", [replace(s, point_deviation=None) for s in scans])
    with ScanCollection(tmp_path / "a.h5") as a, ScanCollection(tmp_path / "b.h5") as b:
        np.testing.assert_array_equal(a[0].point_deviation, deviation)
        assert a[1].point_deviation is None and a[2].point_deviation is None
        assert [m["has_deviation"] for m in a.metadata()] == [True, False, False]
        assert a.fingerprint() == b.fingerprint()
        assert [m["has_deviation"] for m in b.metadata()] == [False] * 3
    with h5py.File(tmp_path / "a.h5", "r+") as f:  # a deviation is checked on read, though not hashed
        f["point_deviation"][2] = np.nan
    with ScanCollection(tmp_path / "a.h5") as a, pytest.raises(ScanReadError, match="NaN or Inf"):
        a[0]


def test_a_file_written_before_the_deviations_reads_none_and_takes_appended_ones(tmp_path):
    path = tmp_path / "old.h5"
    deviation = np.array([1.0, -2.0, 0.0, 0.5], np.float32)
    ScanCollection.create(path, [scan_of(n=5, name="test/dent/000"), scan_of(n=3, name="test/good/000")])
    with ScanCollection(path) as c:
        before = c.fingerprint()
    with h5py.File(path, "r+") as f:  # what a file of the first version 1 writers holds
        del f["point_deviation"], f["scans/has_deviation"]
    with ScanCollection(path) as c:
        assert c.fingerprint() == before and [s.point_deviation for s in c] == [None, None]
        assert [m["has_deviation"] for m in c.metadata()] == [False, False]
    ScanCollection.append(path, [scan_of(n=4, name="test/dent/001", deviation=deviation)])
    with ScanCollection(path) as c:
        assert [s.point_deviation is None for s in c] == [True, True, False]
        np.testing.assert_array_equal(c[2].point_deviation, deviation)
        np.testing.assert_array_equal(c[0].points, scan_of(n=5).points)
    with h5py.File(path, "r") as f:
        assert f["point_deviation"].shape == (12,) and f["scans/has_deviation"][()].tolist() == [0, 0, 1]
        assert f["point_deviation"].compression == f["point_labels"].compression
    with h5py.File(path, "r+") as f:  # one of the two without the other: damaged
        del f["scans/has_deviation"]
    with pytest.raises(ValueError, match=r"old\.h5: damaged scan collection .*has_deviation"):
        ScanCollection(path)


# ---- defects made in a scan's own points -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sheet():
    """A flat scan: a 1 x 1 grid of points (spacing 0.005) in z = 0, normals +z, seen from ``SENSOR`` above."""
    u = np.arange(-0.5, 0.5, 0.005)
    points = np.stack([*np.meshgrid(u, u, indexing="ij"), np.zeros((len(u), len(u)))], -1).reshape(-1, 3)
    return points, np.tile(UP, (len(points), 1))


SENSOR = np.array([0.1, -0.1, 2.0])


@pytest.mark.parametrize("kind", DEFECT_KINDS)
def test_defect_in_points_deviation_is_the_displacement_along_the_normal(sheet, kind):
    points, normals = sheet
    noise = 1e-3
    out, labels, info, deviation = defect_in_points(points, normals, SENSOR, kind, 1.0, noise=noise, seed=7,
                                                    with_deviation=True)
    without = defect_in_points(points, normals, SENSOR, kind, 1.0, noise=noise, seed=7)
    np.testing.assert_array_equal(out, without[0])  # the deviation draws nothing
    np.testing.assert_array_equal(labels, without[1])
    assert info == without[2]
    on = labels.astype(bool)
    assert on.sum() >= 30 and np.all(deviation[~on] == 0)
    if kind in ("dent", "bump"):  # closed form: the profile of the mesh defects
        r = np.linalg.norm(points[on] - info["center"], axis=1)
        sign = 1.0 if kind == "bump" else -1.0
        np.testing.assert_allclose(deviation[on], sign * info["height"] * (1 - (r / info["radius"]) ** 2) ** 2,
                                   rtol=1e-9, atol=1e-15)
        return
    # missing / foreign: the replaced point's height over the sheet, before the range noise added along its ray
    exact = defect_in_points(points, normals, SENSOR, kind, 1.0, noise=0.0, seed=7, with_deviation=True)
    np.testing.assert_allclose(exact[3][on], exact[0][on, 2], atol=1e-12)
    np.testing.assert_allclose(deviation, exact[3], atol=1e-12)
    assert 0 < np.abs(deviation[on] - out[on, 2]).max() < 6 * noise
    assert np.all(deviation[on] < 0) if kind == "missing" else np.all(deviation[on] > 0)


# ---- the importer ---------------------------------------------------------------------------------------------------
def sphere(n=600, center=(500.0, -200.0, 3000.0), radius=200.0):
    """Fibonacci points on a sphere (n, 3), in millimetres far from the origin, and their unit normals."""
    i = np.arange(n) + 0.5
    phi, theta = np.arccos(1 - 2 * i / n), np.pi * (1 + 5 ** 0.5) * i
    normals = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)
    return np.asarray(center) + radius * normals, normals


def deviation_tree(root):
    """train/good (2), test/good (1), test/dent/d0 with its labels and, as its deviations, a tracer: each point's x
    (file units), which a row that moves, a subset or a voxel mean keeps equal to its point's x."""
    for name, shift in (("train/good/t0", 0.0), ("train/good/t1", 5.0), ("test/good/g0", 2.0),
                        ("test/dent/d0", 1.0)):
        points, normals = sphere()
        write_cloud(root / f"{name}.ply", points + shift, normals)
    points = sphere()[0] + 1.0
    truth = root / "ground_truth" / "dent"
    truth.mkdir(parents=True)
    np.savetxt(truth / "d0.txt", (points[:, 2] > 3150).astype(int), fmt="%d")
    np.savetxt(truth / "d0.deviation.txt", points[:, 0], fmt="%.9g")
    return truth / "d0.deviation.txt"


@pytest.mark.parametrize("reading", [{}, {"n_points": 250}, {"voxel": 40.0}])
def test_the_importer_reads_deviations_through_the_frame(tmp_path, reading):
    deviation_tree(tmp_path / "tree")
    import_tree(tmp_path / "tree", tmp_path / "c.h5", progress=False, **reading)
    with ScanCollection(tmp_path / "c.h5") as c:
        scans = {s.name: s for s in c}
        frame = c.frame
    assert frame.scale < 0.01  # millimetres to a unit box: a deviation not scaled would be off by 400 times
    dent = scans["test/dent/d0"]
    np.testing.assert_allclose(dent.point_deviation / frame.scale, frame.to_file(dent.points)[:, 0], rtol=1e-6)
    assert not scans["test/good/g0"].point_deviation.any()  # known good, in a tree that records deviations
    assert scans["train/good/t0"].point_deviation is None
    if not reading:  # and back out to a tree, in file units
        export_collection(tmp_path / "c.h5", tmp_path / "out", file_frame=True)
        written = np.loadtxt(tmp_path / "out" / "ground_truth" / "dent" / "d0.deviation.txt")
        np.testing.assert_allclose(written, np.loadtxt(tmp_path / "tree/ground_truth/dent/d0.deviation.txt"),
                                   rtol=1e-6)


@pytest.mark.parametrize("content", ["short", "words", "columns", "nan"])
def test_a_malformed_deviation_file_is_one_error_naming_it(tmp_path, content):
    path = deviation_tree(tmp_path / "tree")
    values = np.loadtxt(path)
    text = {"short": "\n".join(map(str, values[:-1])), "words": "0.5\nabc\n" * 300,
            "columns": "\n".join(f"{v} 0" for v in values), "nan": "\n".join(["nan"] + list(map(str, values[1:])))}
    path.write_text(text[content] + "\n")
    with pytest.raises(ValueError) as error:
        import_tree(tmp_path / "tree", tmp_path / "c.h5", progress=False)
    assert str(path) in str(error.value)
    if content == "short":
        assert "599 deviations for the 600 points" in str(error.value)
    assert not (tmp_path / "c.h5").exists()


def test_a_deviation_file_is_never_a_label_file(tmp_path):
    deviation_tree(tmp_path / "tree")
    import_tree(tmp_path / "tree", tmp_path / "c.h5", progress=False)
    with ScanCollection(tmp_path / "c.h5") as c:
        assert not [n for n in c.names if "deviation" in n]
    # a cloud named after another's deviation file, which would be its label file too: refused, naming both
    points, normals = sphere()
    write_cloud(tmp_path / "tree" / "test" / "dent" / "d0.deviation.ply", points, normals)
    with pytest.raises(ValueError, match=r"d0\.deviation\.txt: the per-point deviations of the cloud 'd0' or the "
                                         r"labels of .*d0\.deviation\.ply\?"):
        import_tree(tmp_path / "tree", tmp_path / "d.h5", progress=False)
