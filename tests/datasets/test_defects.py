"""Tests of datasets.defects: each defect changes the scanned surface where its labels say and nowhere else."""
import numpy as np
import pytest
import trimesh

from datasets.defects import (DEFECT_KINDS, HEIGHT_RANGE, RADIUS_RANGE, _refine_near, defect_for_view,
                              make_defect, patch_normal, pick_site, pick_spot)
from datasets.point_defects import defect_in_points
from datasets.scanner import VirtualScanner

TOP = np.array([0.1, 0.05, 0.25])  # a point of the top face of the box below
UP = np.array([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def box():
    return trimesh.creation.box(extents=(1.0, 1.0, 0.5))  # 12 big faces: the dent / bump must refine them


def _scan_top(mesh, n_points=2000):
    return VirtualScanner(mesh).scan(np.array([0.3, -0.2, 2.0]), look_at=np.zeros(3), n_points=n_points, seed=0)


@pytest.fixture(scope="module")
def scanned(box):
    """kind -> (Defect, ScanResult of the defective part, labels)."""
    out = {}
    for kind in DEFECT_KINDS:
        defect = make_defect(box, kind, TOP, UP, radius=0.1, height=0.03, shape="sphere", seed=0)
        result = _scan_top(defect.mesh)
        out[kind] = defect, result, defect.region(result.clean_points, result.triangle_ids)
    return out


@pytest.mark.parametrize("kind", DEFECT_KINDS)
def test_defect_changes_the_scan_where_labelled_and_nowhere_else(box, scanned, kind):
    defect, result, labels = scanned[kind]
    assert labels.sum() >= 30
    distance = trimesh.proximity.closest_point(box, result.clean_points)[1]
    diagonal = np.linalg.norm(box.extents)
    assert distance[~labels].max() < 1e-5 * diagonal  # unlabelled: on the undamaged part
    height = (result.clean_points[labels] - TOP) @ UP  # labelled: off it, on the expected side
    if kind == "dent":
        assert height.max() < 1e-9 and height.min() == pytest.approx(-0.03 * diagonal, rel=0.1)
    elif kind == "bump":
        assert height.min() > -1e-9 and height.max() == pytest.approx(0.03 * diagonal, rel=0.1)
    elif kind == "missing":
        assert height.max() < 1e-6 and height.min() < -0.5 * defect.radius
        assert np.linalg.norm(result.clean_points[labels] - TOP, axis=1).max() <= defect.radius * 1.001
    else:
        assert height.min() > -1e-6 and height.max() > 0.5 * defect.radius
    # most labelled points are measurably off the undamaged surface (dent / bump fade out at the rim)
    assert np.median(distance[labels]) > 0.002 * diagonal


@pytest.mark.parametrize("kind", DEFECT_KINDS)
def test_watertight_input_stays_watertight_and_geometry_labels_agree(scanned, kind):
    defect, result, labels = scanned[kind]
    assert defect.mesh.is_watertight
    assert defect.mesh.volume > 0
    by_geometry = defect.region(result.clean_points)
    assert np.mean(by_geometry == labels) > 0.98


def test_refinement_is_conforming_and_resolves_the_radius(box):
    vertices, faces = _refine_near(box.vertices, box.faces, TOP, 0.1, 0.1 / 6.0)
    refined = trimesh.Trimesh(vertices, faces, process=False)
    assert refined.is_watertight and refined.volume == pytest.approx(box.volume)
    corners = vertices[faces]
    near = np.linalg.norm(corners.mean(axis=1) - TOP, axis=1) < 0.1
    edges = np.linalg.norm(corners - np.roll(corners, -1, axis=1), axis=2).max(axis=1)
    assert edges[near].max() <= 0.1 / 6.0


@pytest.mark.parametrize("kind", ["missing", "foreign"])
def test_open_mesh_falls_back_without_booleans(box, kind):
    open_box = box.copy()
    open_box.update_faces(np.flatnonzero(open_box.face_normals[:, 2] > -0.5))  # no bottom
    defect = make_defect(open_box, kind, TOP, UP, radius=0.1, shape="sphere", seed=0)
    result = _scan_top(defect.mesh)
    labels = defect.region(result.clean_points, result.triangle_ids)
    assert labels.sum() >= 30
    distance = trimesh.proximity.closest_point(box, result.clean_points)[1]
    assert np.median(distance[labels]) > 0.02


def test_defect_for_view_picks_a_visible_smooth_spot(box):
    scanner = VirtualScanner(box)
    view = scanner.random_view(seed=1)
    defect = defect_for_view(box, scanner, view, "bump", seed=2)
    preview = scanner.scan(view, n_points=2000, seed=3)
    # on a face the camera sees, away from its edges by about the radius
    assert np.min(np.linalg.norm(preview.clean_points - defect.center, axis=1)) < 0.05
    assert np.sum(defect.normal * (view.camera_position - defect.center)) > 0
    spot, normal = pick_spot(preview, 0.1, seed=4)
    near = np.linalg.norm(preview.clean_points - spot, axis=1) < 0.1
    assert near.sum() > 10 and np.all(preview.normals[near] @ normal > 0.99)  # no edge within the radius


def test_same_seed_same_defect(box):
    a = make_defect(box, "foreign", TOP, UP, seed=5)
    b = make_defect(box, "foreign", TOP, UP, seed=5)
    np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    np.testing.assert_array_equal(a.mesh.faces, b.mesh.faces)


def test_unknown_kind_is_rejected(box):
    with pytest.raises(ValueError, match="scratch"):
        make_defect(box, "scratch", TOP, UP)


def test_defect_size_scales_width_and_depth(box):
    whole = make_defect(box, "dent", TOP, UP, seed=3)
    half = make_defect(box, "dent", TOP, UP, seed=3, size=0.5)
    assert half.radius == pytest.approx(0.5 * whole.radius) and half.height == pytest.approx(0.5 * whole.height)
    with pytest.raises(ValueError, match="size"):
        make_defect(box, "dent", TOP, UP, seed=3, size=0.0)


# ------------------------------------------------------------------------------------------------ defects in points
SENSOR = np.array([0.1, -0.1, 2.0])


@pytest.fixture(scope="module")
def sheet():
    """A flat scan: a 1 x 1 grid of points (spacing 0.005) in z = 0, normals +z, seen from ``SENSOR`` above."""
    u = np.arange(-0.5, 0.5, 0.005)
    points = np.stack([*np.meshgrid(u, u, indexing="ij"), np.zeros((len(u), len(u)))], -1).reshape(-1, 3)
    return points, np.tile(UP, (len(points), 1))


def test_pick_spot_is_pick_site_on_the_scans_points(box):
    preview = _scan_top(box)
    points = preview.to_mesh_frame(preview.clean_points)
    normals = np.asarray(preview.normals) @ preview.pose[:3, :3]
    eye = preview.to_mesh_frame(preview.sensor_origin[None])[0]
    for seed in range(3):
        center, normal = pick_spot(preview, 0.1, seed=seed)
        i = pick_site(points, normals, eye, 0.1, seed=seed)
        np.testing.assert_array_equal(center, points[i])
        np.testing.assert_allclose(normal, normals[i] / np.linalg.norm(normals[i]))


def test_pick_site_keeps_the_whole_disc_on_the_sheet(sheet):
    points, normals = sheet
    for seed in range(5):
        i = pick_site(points, normals, SENSOR, 0.05, seed=seed, min_share=0.9)
        assert np.all(np.abs(points[i, :2]) <= 0.5 - 0.05 + 0.01)  # a disc half over the border has half the points
        assert i == pick_site(points, normals, SENSOR, 0.05, seed=seed, min_share=0.9)  # the same seed, the same site


def test_patch_normal_is_the_mean_of_the_normals_near_the_centre(sheet):
    points, _ = sheet
    # a ridge along x = 0.0025, midway between two columns of points: a disc centred on it holds as many of each side
    tilted = np.where(points[:, :1] > 0.0025, [[0.6, 0.0, 0.8]], [[-0.6, 0.0, 0.8]])
    np.testing.assert_allclose(patch_normal(points, tilted, [0.0025, 0.0, 0.0], 0.0512), UP, atol=1e-12)
    np.testing.assert_allclose(patch_normal(points, tilted, [0.3, 0.0, 0.0], 0.0512), [0.6, 0.0, 0.8], atol=1e-12)


@pytest.mark.parametrize("kind", DEFECT_KINDS)
def test_defect_in_points_moves_only_the_labelled_points_where_its_kind_says(sheet, kind):
    points, normals = sheet
    out, labels, info = defect_in_points(points, normals, SENSOR, kind, diagonal=1.0, seed=7)
    c, n0, radius = np.array(info["center"]), np.array(info["normal"]), info["radius"]
    lab = labels.astype(bool)
    assert info["kind"] == kind and RADIUS_RANGE[0] <= radius <= RADIUS_RANGE[1] and lab.sum() >= 30
    np.testing.assert_allclose(n0, UP, atol=1e-12)
    np.testing.assert_array_equal(out[~lab], points[~lab])  # outside the defect: the scan as measured
    if kind in ("dent", "bump"):
        assert HEIGHT_RANGE[0] <= info["height"] <= HEIGHT_RANGE[1]
        r = np.linalg.norm(points[lab] - c, axis=1)
        assert r.max() < radius and lab.sum() == (np.linalg.norm(points - c, axis=1) < radius).sum()
        sign = 1.0 if kind == "bump" else -1.0
        np.testing.assert_allclose(out[lab] - points[lab], sign * info["height"] * (1 - (r / radius) ** 2)[:, None] ** 2
                                   * UP, atol=1e-15)
        return
    # missing and foreign: each replaced point stays on its sensor ray, behind (missing) or in front of (foreign)
    # where it was
    before, after = points[lab] - SENSOR, out[lab] - SENSOR
    np.testing.assert_allclose(np.cross(before, after), 0.0, atol=1e-12)
    if kind == "missing":  # on the removed ball's far wall, beneath the sheet
        assert info["depth"] == radius
        np.testing.assert_allclose(np.linalg.norm(out[lab] - c, axis=1), radius, rtol=1e-9)
        assert np.all(out[lab, 2] < 0)
    else:  # on the object's visible side, above the sheet
        assert info["shape"] in ("sphere", "box") and np.all(out[lab, 2] > 0)
        assert np.all(np.linalg.norm(after, axis=1) < np.linalg.norm(before, axis=1))


def test_defect_in_points_same_seed_same_defect_and_its_size(sheet):
    points, normals = sheet
    a = defect_in_points(points, normals, SENSOR, "foreign", 1.0, noise=1e-3, seed=3)
    b = defect_in_points(points, normals, SENSOR, "foreign", 1.0, noise=1e-3, seed=3)
    np.testing.assert_array_equal(a[0], b[0])
    assert a[2] == b[2]
    whole = defect_in_points(points, normals, SENSOR, "dent", 1.0, seed=4)[2]
    half = defect_in_points(points, normals, SENSOR, "dent", 1.0, seed=4, size=0.5)[2]
    assert half["radius"] == pytest.approx(0.5 * whole["radius"]) and half["height"] == pytest.approx(
        0.5 * whole["height"])
    with pytest.raises(ValueError, match="scratch"):
        defect_in_points(points, normals, SENSOR, "scratch", 1.0)
    with pytest.raises(ValueError, match="size"):
        defect_in_points(points, normals, SENSOR, "dent", 1.0, size=0)


def test_bad_input_to_the_point_defects_is_one_clear_error(sheet):
    """An empty cloud, normals not one per point, a radius or part size that is not a length, a negative noise, or a
    centre with no point near: a ValueError saying which, never a numpy traceback or a silent number."""
    points, normals = sheet
    with pytest.raises(ValueError, match="pick_site: points"):
        pick_site(np.zeros((0, 3)), np.zeros((0, 3)), SENSOR, 0.05)
    with pytest.raises(ValueError, match="one normal per point"):
        pick_site(points, normals[:-1], SENSOR, 0.05)
    with pytest.raises(ValueError, match="a radius > 0"):
        pick_site(points, normals, SENSOR, 0.0)
    for diagonal in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="diagonal must be a finite length > 0"):
            defect_in_points(points, normals, SENSOR, "dent", diagonal, seed=0)
    with pytest.raises(ValueError, match="noise >= 0"):
        defect_in_points(points, normals, SENSOR, "missing", 1.4, noise=-0.001, seed=0)
    with pytest.raises(ValueError, match="no normal within"):
        patch_normal(points, normals, [5.0, 5.0, 5.0], 0.01)
