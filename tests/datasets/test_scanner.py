"""Tests of datasets.scanner: hits on the surface, normals towards the camera, exact counts, noise along the ray."""
import numpy as np
import pytest
import trimesh

from datasets.scanner import VirtualScanner, random_view


@pytest.fixture(scope="module")
def box():
    mesh = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    mesh.apply_translation((10.0, -3.0, 1.0))  # away from the origin: the scanner must not assume a centred part
    return mesh


@pytest.fixture(scope="module")
def scanner(box):
    return VirtualScanner(box)


def _surface_distance(mesh, points):
    return trimesh.proximity.closest_point(mesh, points)[1]


def test_hits_lie_on_the_surface_with_camera_facing_unit_normals(box, scanner):
    result = scanner.scan(scanner.random_view(seed=1), n_points=700, seed=2)
    assert result.points.shape == (700, 3) and result.points.dtype == np.float32
    assert result.normals.shape == (700, 3) and result.normals.dtype == np.float32
    assert result.triangle_ids.shape == (700,)
    assert _surface_distance(box, result.points).max() < 1e-4
    np.testing.assert_allclose(np.linalg.norm(result.normals, axis=1), 1.0, atol=1e-5)
    assert np.all(np.sum(result.normals * (result.sensor_origin - result.points), axis=1) > 0)
    # the normal is the hit triangle's (up to sign)
    face_normals = box.face_normals[result.triangle_ids]
    np.testing.assert_allclose(np.abs(np.sum(face_normals * result.normals, axis=1)), 1.0, atol=1e-5)


def test_depth_noise_is_along_the_ray_with_the_requested_std(scanner):
    view = scanner.random_view(seed=3)
    clean = scanner.scan(view, n_points=3000, seed=4)
    noisy = scanner.scan(view, n_points=3000, noise=0.01, seed=4)
    np.testing.assert_array_equal(clean.triangle_ids, noisy.triangle_ids)  # same pixels: subset drawn before noise
    rays = clean.points.astype(np.float64) - clean.sensor_origin
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    offset = noisy.points.astype(np.float64) - clean.points
    along = np.sum(offset * rays, axis=1)
    across = np.linalg.norm(offset - along[:, None] * rays, axis=1)
    assert across.max() < 1e-5
    assert abs(along.std() - 0.01) < 0.001 and abs(along.mean()) < 0.001
    np.testing.assert_allclose(noisy.clean_points, clean.clean_points)


def test_exact_count_when_the_resolution_is_too_low(box, scanner):
    result = scanner.scan(scanner.random_view(seed=5), resolution=(8, 6), n_points=400, seed=0)
    assert len(result.points) == 400
    assert len(np.unique(result.points, axis=0)) == 400  # raised the resolution, did not repeat points
    assert _surface_distance(box, result.points).max() < 1e-4


def test_same_seed_same_scan(scanner):
    a = scanner.scan(scanner.random_view(seed=6), n_points=300, noise=0.01, seed=7)
    b = scanner.scan(scanner.random_view(seed=6), n_points=300, noise=0.01, seed=7)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.normals, b.normals)


def test_invisible_part_raises(scanner):
    eye = scanner.center + np.array([0.0, 0.0, 5.0])
    with pytest.raises(ValueError, match="not visible"):
        scanner.scan(eye, look_at=eye + np.array([0.0, 0.0, 1.0]), n_points=10)


def test_random_view_distance_scales_with_the_part_and_looks_at_it():
    for size in (0.01, 1.0, 500.0):
        view = random_view(np.ones(3), (1.5, 2.0), (-20, 70), size=size, seed=0)
        distance = np.linalg.norm(view.camera_position - np.ones(3))
        assert 1.5 * size <= distance <= 2.0 * size
        elevation = np.degrees(np.arcsin((view.camera_position[2] - 1.0) / distance))
        assert -20 <= elevation <= 70
        np.testing.assert_array_equal(view.look_at, np.ones(3))
        np.testing.assert_array_equal(view.pose, np.eye(4))


def test_jittered_pose_is_rigid_and_scans_the_moved_part(box, scanner):
    view = scanner.random_view(jitter_deg=30.0, jitter_translation=0.1, seed=8)
    rotation = view.pose[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    assert not np.allclose(view.pose, np.eye(4))
    result = scanner.scan(view, n_points=500, seed=9)
    moved = box.copy()
    moved.apply_transform(view.pose)
    assert _surface_distance(moved, result.points).max() < 1e-4
    assert _surface_distance(box, result.to_mesh_frame(result.points)).max() < 1e-4
    assert np.all(np.sum(result.normals * (result.sensor_origin - result.points), axis=1) > 0)


def test_pinhole_rays_all_leave_the_sensor_origin(scanner):
    result = scanner.scan(scanner.random_view(seed=5), n_points=300, seed=6)
    np.testing.assert_allclose(result.ray_origins, np.broadcast_to(result.sensor_origin, (300, 3)))


def test_line_scanner_sweeps_parallel_fans_along_one_axis(box, scanner):
    """A line scanner's rays leave a head that moves along a line through the recorded origin, perpendicular to the
    optical axis; each line is a fan in the plane of the axis and the sweep's normal, so its rays are parallel along
    the sweep, and every return lies on the part where its own ray meets it first."""
    view = scanner.random_view(seed=7)
    result = scanner.scan(view, n_points=800, seed=8, sensor="line")
    assert _surface_distance(box, result.points).max() < 1e-4
    start = result.ray_origins
    forward = scanner.center - view.camera_position
    forward /= np.linalg.norm(forward)
    sweep = start - result.sensor_origin
    assert np.abs(sweep @ forward).max() < 1e-9  # the head moves across the optical axis
    spread = np.linalg.svd(sweep - sweep.mean(0), compute_uv=False)
    assert spread[0] > 0.1 * scanner.diagonal and spread[1] < 1e-6 * scanner.diagonal  # along one line
    # every ray lies in the plane of the optical axis and the fan: its direction is square to the sweep
    axis = np.linalg.svd(sweep - sweep.mean(0))[2][0]
    rays = result.clean_points - start
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    assert np.abs(rays @ axis).max() < 1e-6
    # the recorded origin sees the returns from elsewhere than the rays that made them: not one centre
    from_origin = result.clean_points - result.sensor_origin
    from_origin /= np.linalg.norm(from_origin, axis=1, keepdims=True)
    assert np.degrees(np.arccos(np.clip(np.sum(from_origin * rays, axis=1), -1, 1))).max() > 5.0
    with pytest.raises(ValueError, match="sensor"):
        scanner.scan(view, n_points=10, sensor="fisheye")


def test_written_origin_keeps_to_its_stand_off_and_tilt_ranges():
    from datasets.scanner import written_origin

    center, origin = np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 13.0])
    np.testing.assert_allclose(written_origin(origin, center, seed=0), origin)
    axis = origin - center
    for seed in range(50):
        w = written_origin(origin, center, (0.5, 3.0), 5.0, seed=seed) - center
        factor = np.linalg.norm(w) / np.linalg.norm(axis)
        angle = np.degrees(np.arccos(np.clip(w @ axis / np.linalg.norm(w) / np.linalg.norm(axis), -1, 1)))
        assert 0.5 - 1e-9 <= factor <= 3.0 + 1e-9 and angle <= 5.0 + 1e-9
