"""Checks of user input (point clouds, normals, query points) with one clear message each."""
import numpy as np


def check_points(points, name="points", min_points=1):
    """A finite (n, 3) float array with n >= ``min_points``, or a ValueError saying what is wrong."""
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must be an (n, 3) array, got shape {arr.shape}")
    if len(arr) < min_points:
        raise ValueError(f"{name} has {len(arr)} points; at least {min_points} needed")
    if not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
    bad = ~np.isfinite(arr).all(1)
    if bad.any():
        raise ValueError(f"{name} has {int(bad.sum())} rows with NaN or Inf (of {len(arr)}); drop them first")
    return arr.astype(np.float64)


def check_oriented_cloud(points, normals, min_points=10):
    """Validated points (n, 3) and unit normals (n, 3); raises ValueError with the problem."""
    points = check_points(points, "points", min_points)
    if normals is None:
        raise ValueError("normals are missing: an oriented point cloud needs one outward normal per point "
                         "(estimate them, e.g. datasets' importer does)")
    normals = check_points(normals, "normals", min_points)
    if normals.shape != points.shape:
        raise ValueError(f"points {points.shape} and normals {normals.shape} must have the same shape")
    length = np.linalg.norm(normals, axis=1)
    if (length < 1e-8).any():
        raise ValueError(f"{int((length < 1e-8).sum())} normals have zero length")
    return points, normals / length[:, None]
