"""Checks of user input (point clouds, normals, query points) with one clear message each; the one reader of
'a scan' as the APIs accept it (a :class:`datasets.scan.Scan`, a (points, normals) pair or an (n, 3) array)."""
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


def check_oriented_cloud(points, normals, min_points=10, name=""):
    """Validated points (n, 3) float64 and unit normals (n, 3) float64; raises ValueError with the problem.

    ``name`` (e.g. ``"scan 3"``) starts every message, so that an error about one of many scans says which.
    """
    where = f"{name}: " if name else ""
    points = check_points(points, f"{where}points", min_points)
    if normals is None:
        raise ValueError(f"{where}normals are missing: an oriented point cloud needs one outward normal per point "
                         "(estimate them, e.g. datasets' importer does)")
    normals = check_points(normals, f"{where}normals", min_points)
    if normals.shape != points.shape:
        raise ValueError(f"{where}points {points.shape} and normals {normals.shape} must have the same shape")
    length = np.linalg.norm(normals, axis=1)
    if (length < 1e-8).any():
        raise ValueError(f"{where}{int((length < 1e-8).sum())} normals have zero length")
    return points, normals / length[:, None]


def points_and_normals(scan):
    """(points, normals or None) of anything the APIs accept as a scan, unchecked.

    Parameters
    ----------
    scan : Scan, (points, normals) pair, or (n, 3) array
        Anything with ``points`` (and optionally ``normals``) attributes counts as a scan; a pair's normals may be
        None.

    Returns
    -------
    points : ndarray
    normals : ndarray or None
    """
    if hasattr(scan, "points"):
        normals = getattr(scan, "normals", None)
        return np.asarray(scan.points), None if normals is None else np.asarray(normals)
    if isinstance(scan, (tuple, list)) and len(scan) == 2:
        return np.asarray(scan[0]), None if scan[1] is None else np.asarray(scan[1])
    return np.asarray(scan), None
