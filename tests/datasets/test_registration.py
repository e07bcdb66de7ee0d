"""datasets.registration's scaled motion (a product family's members brought to one size) and its transforms:
against known stretches and closed forms. (The rigid motion is tested through inspection.align in
tests/inspection/test_align.py.)"""
import numpy as np
import pytest

from datasets.scan import Scan


def _part(stretch=1.0, n=6000, seed=0, name="part"):
    """Points and outward normals of an L-shaped solid (two boxes, so that every axis has features along it)
    stretched by ``stretch`` along x about the origin, sampled evenly over its surface."""
    import trimesh

    a = trimesh.creation.box((0.8, 0.3, 0.2))
    b = trimesh.creation.box((0.2, 0.3, 0.5))
    b.apply_translation((0.3, 0.0, 0.15))
    mesh = trimesh.boolean.union([a, b], engine="manifold") if hasattr(trimesh.boolean, "union") else a
    mesh.apply_scale((stretch, 1.0, 1.0))
    points, faces = trimesh.sample.sample_surface_even(mesh, n, seed=seed)
    return Scan(name, points.astype(np.float32), mesh.face_normals[faces].astype(np.float32))


def test_a_stretched_part_is_registered_back_to_the_targets_size():
    """A copy of the part 15 % longer along x (other samples of its surface) is moved onto the part: the linear
    part of the transform is diag(1 / 1.15, 1, 1) within 1 %, and the moved points lie on the part."""
    from datasets.registration import Aligner

    target, source = _part(1.0, seed=0), _part(1.15, seed=1)
    aligner = Aligner(target.points, target.normals, motion="scaled")
    T = aligner.transform(source.points)
    np.testing.assert_allclose(T[:3, :3], np.diag([1 / 1.15, 1.0, 1.0]), atol=0.01)
    moved = source.points @ T[:3, :3].T + T[:3, 3]
    ok, distances = aligner.plane_distances(moved, 3 * aligner.spacing)
    assert ok.mean() > 0.95 and np.median(distances) < 0.2 * aligner.spacing


def test_the_rigid_motion_leaves_the_size_alone():
    """The default (rigid) motion's transform is a rotation: its linear part is orthonormal even for a stretched
    scan (sizes are the scaled motion's business)."""
    from datasets.registration import Aligner

    target, source = _part(1.0, seed=0), _part(1.1, seed=1)
    T = Aligner(target.points, target.normals).transform(source.points)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)


def test_apply_transform_moves_normals_by_the_inverse_transpose():
    """Under a stretch a plane's normal turns: points of the plane x + y = 0 stretched by 2 along x lie on the plane
    x / 2 + y = 0, whose unit normal is (1, 2, 0) / sqrt(5); the moved normals are that one, unit length."""
    from datasets.registration import apply_transform

    rng = np.random.default_rng(0)
    u, z = rng.normal(size=(50, 1)), rng.normal(size=(50, 1))
    points = np.c_[u, -u, z]
    normals = np.tile([1.0, 1.0, 0.0], (50, 1)) / np.sqrt(2)
    T = np.diag([2.0, 1.0, 1.0, 1.0])
    T[:3, 3] = (0.3, -0.2, 0.1)
    moved, turned = apply_transform(T, points, normals)
    np.testing.assert_allclose(moved, points * [2, 1, 1] + [0.3, -0.2, 0.1])
    np.testing.assert_allclose(turned, np.tile([1.0, 2.0, 0.0], (50, 1)) / np.sqrt(5), atol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", moved[1:] - moved[:1], turned[1:]), 0.0, atol=1e-12)


def test_a_group_of_sizes_is_brought_to_one_size():
    """Scans of members 0.85-1.15 times as long are registered onto each other: afterwards every scan's x scale
    times its member's length is the same common length (within 2 %), and the common length is about their
    average (within 5 %): the group's size does not drift."""
    from datasets.registration import register_group

    stretches = [0.85, 0.9, 0.95, 1.05, 1.1, 1.15]
    scans = [_part(s, n=3000, seed=i, name=f"scan{i}") for i, s in enumerate(stretches)]
    moved = register_group(scans, motion="scaled")
    common = np.array([m.extra["align"][0, 0] * s for m, s in zip(moved, stretches)])
    assert np.ptp(common) / common.mean() < 0.02, common
    assert abs(common.mean() - 1.0) < 0.05, common


def test_moved_by_composes_a_second_registration():
    """A scan registered twice records its total motion: the second transform after the first."""
    from datasets.registration import moved_by

    scan = _part(1.0, n=200)
    A, B = np.diag([1.1, 1.0, 0.9, 1.0]), np.eye(4)
    B[:3, 3] = (0.1, 0.0, 0.0)
    twice = moved_by(moved_by(scan, A), B)
    np.testing.assert_allclose(twice.extra["align"], B @ A)
    np.testing.assert_allclose(twice.points, scan.points @ (B @ A)[:3, :3].T + (B @ A)[:3, 3], atol=1e-6)


def test_an_unknown_motion_is_refused():
    from datasets.registration import Aligner

    with pytest.raises(ValueError, match="motion"):
        Aligner(np.random.default_rng(0).normal(size=(50, 3)), motion="similarity")
