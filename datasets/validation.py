"""Checks of user input (point clouds, normals, query points) with one clear message each; the one reader of
'a scan' as the APIs accept it (a :class:`datasets.scan.Scan`, a (points, normals) pair or an (n, 3) array)."""
import numpy as np


class ScanReadError(ValueError):
    """One scan cannot be read or used; the others from the same source may be fine.

    Raised for problems of a single scan: NaN or Inf values, wrong array shapes, missing or zero normals where an
    oriented cloud is required, content that does not match the hash stored with it. A caller that handles many
    scans catches it per scan, reports it and goes on with the others (e.g.
    ``ScanCollection.read_many(indices, errors="collect")``). Problems of a whole file (not HDF5, another format
    version, inconsistent offsets) raise a plain ``ValueError``.

    The message reads ``"<path>: scan '<scan_name>' (#<index>): <problem>"``; parts that are unknown (None) are left
    out.

    Attributes
    ----------
    problem : str
        What is wrong, without the location.
    path : str or None
        The file the scan is stored in.
    scan_name : str or None
        The scan's own (stored) name.
    index : int or None
        The scan's index in its collection.
    """

    def __init__(self, problem, path=None, scan_name=None, index=None):
        self.problem = problem
        self.path = None if path is None else str(path)
        self.scan_name = scan_name
        self.index = None if index is None else int(index)
        where = [] if self.path is None else [self.path]
        if scan_name is not None:
            where.append(f"scan {scan_name!r}" + ("" if index is None else f" (#{self.index})"))
        elif index is not None:
            where.append(f"scan #{self.index}")
        super().__init__(": ".join([*where, problem]))

    def __reduce__(self):  # pickles (multiprocessing workers) with its attributes
        return type(self), (self.problem, self.path, self.scan_name, self.index)


def _points_problem(arr, min_points=1):
    """What makes ``arr`` not a finite (n, 3) numeric array with n >= ``min_points`` (a phrase to follow the
    array's name), or None."""
    if arr.ndim != 2 or arr.shape[1] != 3:
        return f"must be an (n, 3) array, got shape {arr.shape}"
    if len(arr) < min_points:
        return f"has {len(arr)} points; at least {min_points} needed"
    if not np.issubdtype(arr.dtype, np.number):
        return f"must be numeric, got dtype {arr.dtype}"
    finite = np.isfinite(arr)
    if not finite.all():  # the per-row count only then: .all(1) costs ten times more than .all()
        return f"has {int((~finite.all(1)).sum())} rows with NaN or Inf (of {len(arr)}); drop them first"
    return None


def check_points(points, name="points", min_points=1):
    """A finite (n, 3) float array with n >= ``min_points``, or a ValueError saying what is wrong."""
    arr = np.asarray(points)
    problem = _points_problem(arr, min_points)
    if problem:
        raise ValueError(f"{name} {problem}")
    return arr.astype(np.float64)


def check_oriented_cloud(points, normals, min_points=10, name="", *, path=None, scan_name=None, index=None):
    """Validated points (n, 3) float64 and unit normals (n, 3) float64; raises :class:`ScanReadError` with the problem.

    ``name`` (e.g. ``"scan 3"``) starts every problem, so that an error about one of many clouds says which;
    ``path``, ``scan_name`` and ``index`` (the scan's file, stored name and index in it, when known) are passed on to
    the error, which names them too.
    """
    where = f"{name}: " if name else ""

    def fail(problem):
        raise ScanReadError(where + problem, path, scan_name, index)

    points = np.asarray(points)
    problem = _points_problem(points, min_points)
    if problem:
        fail(f"points {problem}")
    if normals is None:
        fail("normals are missing: an oriented point cloud needs one outward normal per point "
             "(estimate them, e.g. datasets' importer does)")
    normals = np.asarray(normals)
    problem = _points_problem(normals, min_points)
    if problem:
        fail(f"normals {problem}")
    if normals.shape != points.shape:
        fail(f"points {points.shape} and normals {normals.shape} must have the same shape")
    points, normals = points.astype(np.float64), normals.astype(np.float64)
    length = np.linalg.norm(normals, axis=1)
    if (length < 1e-8).any():
        fail(f"{int((length < 1e-8).sum())} normals have zero length")
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
