"""Partial training views of complete template clouds: what a depth sensor would see of each from around it.

Real3D-AD and Anomaly-ShapeNet give 4 complete (360 degree) clouds per class for training and test on partial scans.
The latent model is a space of partial scans, so each template is turned into partial views: the points that open3d's
hidden-point removal (Katz, Tal and Basri 2007, "Direct visibility of point sets") keeps from a sensor position, with
that position recorded as the view's sensor origin. Views for training and held-back views for calibration come from
different sensor positions of the same templates, so no template has to be held back.
"""
import numpy as np

from .scan import Scan

# Radius of hidden-point removal's spherical flip, in template diameters. open3d's tutorial uses 100, which is exact
# on noise-free points but on a template with scanner noise keeps far less than a ray caster sees; 1000 keeps most
# of it, and the few points beyond the silhouette that a larger radius lets through are removed by the back-face
# test in render_views (docs/results.md#rendered-template-views-against-ray-casting).
HPR_RADIUS_FACTOR = 1000.0
MIN_VIEW_POINTS = 3


def sensor_positions(center, diagonal, n, seed, distance=2.0):
    """``n`` sensor positions uniformly distributed in direction around ``center``, ``distance`` diagonals from it.

    Parameters
    ----------
    center : (3,) float array
    diagonal : float > 0
        The template's bounding-box diagonal, in its units.
    n : int >= 0
    seed : int, sequence of int or numpy Generator
    distance : float > 0

    Returns
    -------
    (n, 3) float64 array, in the template's units.
    """
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(center, dtype=np.float64) + distance * float(diagonal) * d


def visible_points(points, origin):
    """Indices of the points of a complete cloud visible from ``origin`` (open3d hidden-point removal).

    Parameters
    ----------
    points : (N, 3) float array
    origin : (3,) float array, same units, outside the cloud

    Returns
    -------
    (M,) int64 array, sorted.
    """
    import open3d as o3d

    pts = np.asarray(points, dtype=np.float64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    diameter = float(np.linalg.norm(np.ptp(pts, axis=0)))
    _, idx = pcd.hidden_point_removal(np.asarray(origin, dtype=np.float64), HPR_RADIUS_FACTOR * diameter)
    return np.unique(np.asarray(idx, dtype=np.int64))


def render_views(name, points, normals, n_train, n_validation, seed=0, distance=2.0):
    """Partial views of one complete template cloud, as scans in the template's units.

    Parameters
    ----------
    name : str
        The template's name (its file stem); views are named ``train/<name>/view_000``, ``validation/<name>/...``.
    points : (N, 3) float array
        The complete template, in its file units.
    normals : (N, 3) float array
        Unit outward normals of the template. A view keeps the visible points whose normal faces its sensor (a depth
        sensor sees the outside of a surface and returns nothing from a back face), so every view's normals face
        its sensor.
    n_train, n_validation : int >= 0
        Views for training (split 'train') and held-back views for calibration (split 'validation', which the
        trainer and the calibration treat as not trained on), from different sensor positions.
    seed : int
        The sensor positions follow from (seed, name): the same seed gives the same views.
    distance : float
        Sensor distance from the template's bounding-box centre, in bounding-box diagonals.

    Returns
    -------
    list of Scan
        Label 'good', ``sensor_origin`` set, points float64 in file units (the collection frame is applied later).

    Raises
    ------
    ValueError
        A view that sees fewer than 3 points (names the template and the view).
    """
    import zlib

    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    lo, hi = points.min(0), points.max(0)
    center, diagonal = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    rng = np.random.default_rng([int(seed), zlib.crc32(name.encode())])
    origins = sensor_positions(center, diagonal, n_train + n_validation, rng, distance)
    scans = []
    for k, origin in enumerate(origins):
        split, i = ("train", k) if k < n_train else ("validation", k - n_train)
        idx = visible_points(points, origin)
        # hidden-point removal also keeps points just beyond the silhouette; a sensor gets no return where it would
        # see the back of the surface, so those go (by the template's outward normals)
        idx = idx[np.einsum("ij,ij->i", normals[idx], origin - points[idx]) > 0]
        if len(idx) < MIN_VIEW_POINTS:
            raise ValueError(f"template {name!r}: view {split} {i} from {origin.tolist()} sees {len(idx)} points")
        p, n = points[idx], normals[idx]
        scan = Scan(name=f"{split}/{name}/view_{i:03d}", points=p, normals=n, split=split, label="good",
                    sensor_origin=origin, extra={"template": name})
        scan.points = p  # keep file-unit precision until the frame is applied (as the importer does)
        scans.append(scan)
    return scans
