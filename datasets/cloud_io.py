"""Reading scanner point-cloud files (PLY, PCD, XYZ/PTS/TXT, NPY, NPZ; organised TIFF point maps) and writing PLY."""
import logging
from pathlib import Path

import numpy as np

from .atomic import atomic_path

log = logging.getLogger(__name__)

CLOUD_SUFFIXES = (".ply", ".pcd", ".xyz", ".pts", ".txt", ".npy", ".npz")
_TEXT_SUFFIXES = (".xyz", ".pts", ".txt")


def is_cloud_file(path):
    """Whether a folder's entry is read as a point cloud: a visible name (not starting with a dot: a scanner's
    temporary file, a desktop's metadata) with one of :data:`CLOUD_SUFFIXES`. The one rule every command that takes
    a folder of scans (``import``, ``score`` / ``calibrate --data FOLDER``, ``watch``) sorts its files by; whether
    the file is a regular file is left to the caller (it may vanish between a listing and a look)."""
    path = Path(path)
    return not path.name.startswith(".") and path.suffix.lower() in CLOUD_SUFFIXES


def read_cloud(path):
    """Points and (if the file has them) normals of a point-cloud file, in the file's own units.

    Parameters
    ----------
    path : str or Path
        ``.ply`` / ``.pcd`` (read with open3d), ``.xyz`` / ``.pts`` / ``.txt`` (whitespace or comma separated columns:
        3 = xyz, 6 or more = xyz + normals when columns 4-6 are unit vectors, otherwise the extra columns, e.g.
        intensity and colour, are ignored; a first line holding only a point count is skipped), ``.npy`` ((N, 3) or
        (N, 6) = xyz + normals), ``.npz`` (keys ``points`` or ``xyz``, optional ``normals``).

    Returns
    -------
    points : (N, 3) float64 array
        May contain non-finite rows (the importer drops them); N >= 1.
    normals : (N, 3) float64 array or None
        As stored (not re-normalised); None when the file has none.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    ValueError
        Unknown extension, empty or unreadable file, wrong array shapes; the message names the file.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in CLOUD_SUFFIXES:
        raise ValueError(f"{path}: unknown point-cloud extension {path.suffix!r} (known: {', '.join(CLOUD_SUFFIXES)})")
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if not path.is_file():
        raise ValueError(f"{path}: not a regular file")
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: empty file")
    try:
        if suffix in (".ply", ".pcd"):
            points, normals = _read_open3d(path)
        elif suffix in _TEXT_SUFFIXES:
            points, normals = _read_text(path)
        else:
            points, normals = _read_numpy(path, suffix)
    except ValueError as e:
        msg = str(e)
        raise ValueError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
    except (OSError, EOFError, KeyError) as e:  # unreadable: permissions, a corrupt zip, a missing npz key
        raise ValueError(f"{path}: cannot read ({type(e).__name__}: {e})") from None
    if len(points) == 0:
        raise ValueError(f"{path}: contains no points")
    return points, normals


def _read_open3d(path):
    import open3d as o3d

    # open3d reports failures as printed warnings and an empty cloud, not exceptions: silence it and check the result
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        pcd = o3d.io.read_point_cloud(str(path))
    points = np.asarray(pcd.points, dtype=np.float64)
    if len(points) == 0:
        raise ValueError(f"{path}: open3d read no points (empty or not a valid {path.suffix.lower()[1:]} file)")
    normals = np.asarray(pcd.normals, dtype=np.float64) if pcd.has_normals() else None
    if normals is not None and not np.any(normals):  # some writers emit all-zero normal properties
        normals = None
    return points, normals


def _read_text(path):
    with open(path, "r", errors="replace") as f:
        head = [line for _, line in zip(range(50), f)]
    data_lines = [ln for ln in head if ln.strip() and not ln.lstrip().startswith(("#", "//"))]
    if not data_lines:
        raise ValueError("no data lines")
    skip = 0
    first = data_lines[0].replace(",", " ").split()
    if len(first) == 1:  # a .pts header: the point count alone on the first line
        skip = head.index(data_lines[0]) + 1
    sample = data_lines[1] if skip and len(data_lines) > 1 else data_lines[0]  # a row of numbers, not the count
    delimiter = "," if "," in sample else None
    try:
        table = np.loadtxt(path, dtype=np.float64, comments=("#", "//"), delimiter=delimiter, skiprows=skip,
                           ndmin=2)
    except ValueError as e:
        raise ValueError(f"not a table of numbers ({e})") from None
    return _split_columns(table, path)


def _split_columns(table, path):
    if table.ndim != 2 or table.shape[0] == 0:
        raise ValueError("contains no points")
    cols = table.shape[1]
    if cols < 3:
        raise ValueError(f"has {cols} columns, expected 3 (xyz) or 6 (xyz + normals)")
    points = table[:, :3]
    if cols < 6:
        return points, None
    normals = table[:, 3:6]
    norms = np.linalg.norm(normals, axis=1)
    finite = np.isfinite(norms)
    if cols == 6 or (finite.any() and np.mean(np.abs(norms[finite] - 1) < 0.1) > 0.9):
        return points, normals
    log.info("%s: columns 4-6 are not unit vectors; read as xyz without normals", path)
    return points, None


def _read_numpy(path, suffix):
    if suffix == ".npy":
        arr = np.load(path, allow_pickle=False)
        if arr.ndim != 2 or arr.shape[1] not in (3, 6):
            raise ValueError(f"array of shape {arr.shape}, expected (N, 3) xyz or (N, 6) xyz + normals")
        arr = arr.astype(np.float64)
        return arr[:, :3], (arr[:, 3:6] if arr.shape[1] == 6 else None)
    with np.load(path, allow_pickle=False) as z:
        key = "points" if "points" in z.files else "xyz" if "xyz" in z.files else None
        if key is None:
            raise ValueError(f"npz has keys {z.files}, expected 'points' or 'xyz' (and optionally 'normals')")
        points = np.asarray(z[key], dtype=np.float64)
        normals = np.asarray(z["normals"], dtype=np.float64) if "normals" in z.files else None
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"'{key}' has shape {points.shape}, expected (N, 3)")
    if normals is not None and normals.shape != points.shape:
        raise ValueError(f"'normals' has shape {normals.shape}, expected {points.shape} like '{key}'")
    return points, normals


def read_organized_cloud(path):
    """An organised point cloud stored as an H x W x 3 float TIFF (MVTec 3D-AD's ``xyz/NNN.tiff``), read with tifffile.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    grid : (H, W, 3) float64 array
        One point per pixel, in the file's units (metres for MVTec 3D-AD); NaN where the sensor returned no point:
        the pixel holds (0, 0, 0) or a non-finite value. (The MVTec 3D-AD baselines drop a pixel with ANY zero
        coordinate, ``np.all(pc != 0, axis=1)``; a real point can have x = 0 exactly, so only all three count here.)

    Raises
    ------
    ValueError
        Not a readable TIFF, or not H x W x 3; the message names the file.
    """
    import tifffile

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        grid = np.asarray(tifffile.imread(path), dtype=np.float64)
    except Exception as e:  # tifffile raises many types for corrupt or foreign files
        raise ValueError(f"{path}: cannot read as a TIFF point map ({type(e).__name__}: {e})") from None
    if grid.ndim != 3 or grid.shape[2] != 3:
        raise ValueError(f"{path}: expected an H x W x 3 organised point cloud, got an array of shape {grid.shape}")
    grid[~np.all(np.isfinite(grid), axis=2) | np.all(grid == 0, axis=2)] = np.nan
    return grid


def write_cloud(path, points, normals=None, colors=None, scalars=None):
    """Write a binary little-endian PLY file (plyfile) atomically (:func:`datasets.atomic.atomic_path`).

    Parameters
    ----------
    path : str or Path
        Must end in ``.ply``; parent folders are created.
    points : (N, 3) float array
        Written as float32, or float64 when given as float64 (keeps scanner precision).
    normals : (N, 3) float array, optional
    colors : (N, 3) array, optional
        Floats in [0, 1] (rounded to 8-bit) or uint8 in [0, 255].
    scalars : dict of str -> (N,) array, optional
        Further per-vertex properties (e.g. a defect region id), each written with its array's dtype (int32 for
        integers, float32 for floats).

    Returns
    -------
    Path
    """
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise ValueError(f"{path}: write_cloud writes PLY only, got extension {path.suffix!r}")
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{path}: points must be (N, 3), got {points.shape}")
    ftype = "<f8" if points.dtype == np.float64 else "<f4"
    fields = [("x", ftype), ("y", ftype), ("z", ftype)]
    columns = [points]
    if normals is not None:
        normals = np.asarray(normals)
        if normals.shape != points.shape:
            raise ValueError(f"{path}: normals {normals.shape} must match points {points.shape}")
        fields += [("nx", ftype), ("ny", ftype), ("nz", ftype)]
        columns.append(normals)
    if colors is not None:
        colors = np.asarray(colors)
        if colors.shape != points.shape:
            raise ValueError(f"{path}: colors {colors.shape} must match points {points.shape}")
        if colors.dtype != np.uint8:
            colors = colors.astype(np.float64)
            if not np.all(np.isfinite(colors)) or colors.min(initial=0) < 0 or colors.max(initial=0) > 1:
                raise ValueError(f"{path}: float colors must be finite and in [0, 1]")
            colors = np.round(colors * 255).astype(np.uint8)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    extra = {}
    for name, values in (scalars or {}).items():
        values = np.asarray(values).reshape(-1)
        if len(values) != len(points) or not str(name).isidentifier():
            raise ValueError(f"{path}: scalar property {name!r} needs a plain name and one value per point "
                             f"({len(points)}), got {len(values)}")
        extra[name] = values.astype("<i4" if np.issubdtype(values.dtype, np.integer) else "<f4")
        fields.append((name, extra[name].dtype.str))
    body = np.empty(len(points), dtype=fields)
    names = [f[0] for f in fields]
    for k, name in enumerate(names[: 3 * len(columns)]):
        body[name] = columns[k // 3][:, k % 3]
    if colors is not None:
        for k, name in enumerate(("red", "green", "blue")):
            body[name] = colors[:, k]
    for name, values in extra.items():
        body[name] = values
    from plyfile import PlyData, PlyElement

    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(body, "vertex")], text=False, byte_order="<").write(str(tmp))
    return path
