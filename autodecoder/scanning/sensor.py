"""Sensor geometry of a range scan: how the sensor's rays meet the surface, where it stood, and its pinhole image.

A range scan is seen from one sensor origin: the angle between each ray and the surface sets how noisy a return is
(:func:`grazing_factor`), a one-view scan's normals face the sensor (:func:`view_origin_from_normals`), and the
directions from the origin to the returns form a pinhole image whose enclosed gaps are rays that returned nothing
(:func:`image_holes`). Inspection's point and ray scores read these; they hold no model.
"""
import logging

import numpy as np

log = logging.getLogger(__name__)

# cos^2 of the angle between the sensor's ray and the surface normal is floored here (about 87 degrees) so that the
# grazing factor 1 / cos^2 - 1 stays finite at silhouettes
GRAZING_COS2_FLOOR = 0.0025
MAX_OFF_AXIS_COS = 0.087  # cos 85 deg: wider views are not one pinhole image
MAX_GRID_CELLS = 400_000  # image_holes' grid is coarsened beyond this many cells


def grazing_factor(points, normals, origin):
    """1 / cos^2(theta) - 1 at each point, theta the angle between the sensor's ray and the surface normal.

    A range sensor's error grows where its ray grazes the surface: near silhouettes and sharp edges a depth error
    moves a point off the part's edge, and real sensors' spots smear there. The reference scores model it as noise
    that grows with this factor (:class:`inspection.reference.LocalReference`). The scan's own normals are used (exact for synthetic
    scans, estimated on import for scanner files): the projected field's gradient, which rounds sharp edges, finds
    far fewer of the grazing points that set good scans' scores (docs/results.md#how-each-step-contributed).
    cos^2 is floored at ``GRAZING_COS2_FLOOR``.

    Parameters
    ----------
    points : (m, 3) array
    normals : (m, 3) array
        Unit normals (either orientation: the factor depends on cos^2).
    origin : (3,) array
        The sensor position, in the same frame as the points.

    Returns
    -------
    (m,) float64 array >= 0 (0 where the ray meets the surface head-on)
    """
    points = np.asarray(points, dtype=np.float64)
    rays = points - np.asarray(origin, dtype=np.float64).reshape(1, 3)
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
    normals = np.asarray(normals, dtype=np.float64)
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    cos2 = np.sum(rays * normals, axis=1) ** 2
    return 1.0 / np.maximum(cos2, GRAZING_COS2_FLOOR) - 1.0


# sensor distance of an estimated viewpoint (view_origin_from_normals), in the scan's bounding-box diagonals
ESTIMATED_VIEW_DISTANCE = 2.0


def view_origin_from_normals(points, normals, distance=ESTIMATED_VIEW_DISTANCE):
    """A stand-in sensor origin for a scan that records none, for :func:`grazing_factor` only.

    Every normal a sensor sees faces it, so the mean of a one-view scan's outward normals points roughly at the
    sensor: the origin is put ``distance`` bounding-box diagonals from the scan's centroid along it. A rough
    direction (how rough, and what the grazing term it gives is worth:
    docs/results.md#training-from-4-complete-templates-benchmarksfour_templatespy), good enough for a noise term
    that grows smoothly with the angle; not a sensor origin for the ray score, which needs the real one.

    Parameters
    ----------
    points, normals : (m, 3) arrays
        Normals oriented outward (their mean decides the side; a scan whose normals cancel out gets an arbitrary
        direction, and the grazing factor is then as good as any).

    Returns
    -------
    (3,) float64 array
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    w = normals.mean(0)
    norm = float(np.linalg.norm(w))
    w = w / norm if norm > 1e-12 else np.array([0.0, 0.0, 1.0])
    diagonal = float(np.linalg.norm(np.ptp(points, axis=0))) if len(points) else 0.0
    return points.mean(0) + distance * max(diagonal, 1e-12) * w


def image_holes(points, origin, gap=2.0):
    """Directions of the holes in a scan's image: where the sensor returned nothing although returns surround it.

    Parameters
    ----------
    points : (m, 3) array
        The scan's points, in the same frame as ``origin``.
    origin : (3,) array
        The sensor position.
    gap : float
        A grid cell is empty when it is farther than ``gap`` x s from every return (s: the returns' mean spacing).

    Returns
    -------
    directions : (E, 3) float64 array
        Unit directions of the hole cells (E = 0 when there are none, or the view is not one pinhole image).
    uv : (E, 2) float64 array
        Their image coordinates.
    points_uv : (m, 2) float64 array or None
        The returns' image coordinates (None when the view was skipped).
    pitch : float
        The mean spacing s of the returns in the image (image units; 0 when skipped).
    """
    from scipy import ndimage
    from scipy.spatial import ConvexHull, Delaunay, QhullError, cKDTree

    empty = (np.zeros((0, 3)), np.zeros((0, 2)), None, 0.0)
    d = np.asarray(points, dtype=np.float64) - np.asarray(origin, dtype=np.float64)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    axis = d.mean(0)
    if len(d) < 16 or np.linalg.norm(axis) == 0:
        return empty
    axis /= np.linalg.norm(axis)
    if (d @ axis).min() < MAX_OFF_AXIS_COS:
        log.info("image_holes: the returns span more than one pinhole view; no missing-return rays")
        return empty
    helper = np.eye(3)[np.argmin(np.abs(axis))]
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    uv = np.c_[d @ e1, d @ e2] / (d @ axis)[:, None]  # (m, 2) gnomonic image coordinates
    try:
        hull = ConvexHull(uv)
    except QhullError:  # the returns lie on a line in the image: no area to hold a hole
        return empty
    # the mean spacing of the returns over their hull, not the nearest-neighbour distance: a sensor that keeps a
    # random part of its pixels (or drops some) has returns one pixel apart and gaps of several pixels everywhere
    pitch = float(np.sqrt(hull.volume / len(uv)))
    if not pitch > 0:
        return empty
    tree = cKDTree(uv)
    lo, hi = uv.min(0) - pitch, uv.max(0) + pitch
    shape = np.ceil((hi - lo) / pitch).astype(int) + 1
    if np.prod(shape) > MAX_GRID_CELLS:
        # a few far-flung returns make the image huge: coarsen the grid, not the memory
        pitch *= float(np.sqrt(np.prod(shape) / MAX_GRID_CELLS))
        shape = np.ceil((hi - lo) / pitch).astype(int) + 1
    gu, gv = (lo[i] + pitch * np.arange(shape[i]) for i in range(2))
    grid = np.stack(np.meshgrid(gu, gv, indexing="ij"), -1).reshape(-1, 2)
    is_empty = tree.query(grid, k=1, distance_upper_bound=gap * pitch)[0] == np.inf
    inside = Delaunay(uv[hull.vertices]).find_simplex(grid) >= 0
    labels, n = ndimage.label(is_empty.reshape(shape))
    labels = labels.reshape(-1)
    # empty regions that reach outside the hull of the returns are background around the silhouette
    open_labels = np.unique(labels[is_empty & ~inside])
    hole = is_empty & inside & ~np.isin(labels, open_labels)
    if not hole.any():
        return (*empty[:2], uv, pitch)
    h_uv = grid[hole]
    dirs = axis + h_uv[:, :1] * e1 + h_uv[:, 1:] * e2
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True), h_uv, uv, pitch
