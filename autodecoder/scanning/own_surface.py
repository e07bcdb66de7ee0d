"""The surface a scan saw, from its points alone: their spacing, where that surface stops around each point (a
hole's rim, a silhouette), and which rays pass through it.

:mod:`autodecoder.scanning.free_space` leaves untested a ray that passes through the scan's own surface before its
point (its module docstring, "Rays that pass through the scan's own surface"): had the sensor looked along it, that
surface would have hidden the point, so the sensor origin it was drawn from is wrong there.
"""
import math

import numpy as np

BOUNDARY_NEIGHBOURS = 10  # surface_sides: the neighbours whose directions must surround a point inside a surface
BOUNDARY_GAP = 0.5 * math.pi  # and the widest gap between those directions there (radians)


def median_spacing(tree, sample=2048, seed=0):
    """The median distance of a point to its nearest other point, over a seeded sample of the points of a
    scipy.spatial.cKDTree (world units; 0 for fewer than 2 points)."""
    n = int(tree.n)
    if n < 2:
        return 0.0
    rows = np.arange(n) if n <= sample else np.random.default_rng(seed).choice(n, sample, replace=False)
    return float(np.median(tree.query(tree.data[rows], k=2)[0][:, 1]))


def surface_sides(observed, rows=None, k=BOUNDARY_NEIGHBOURS, max_gap=BOUNDARY_GAP):
    """The surface the scan saw around each observed point: its unit normal (either sign) and where it stops.

    A point is on the surface's border (a hole's rim, a silhouette, the edge of the view) when the directions to its
    ``k`` nearest neighbours, in their principal plane, leave a gap wider than ``max_gap`` radians (the usual angle
    criterion of point-cloud boundary detection); the surface stops in the direction of that gap's middle.

    Parameters
    ----------
    observed : scipy.spatial.cKDTree
        Over the scan's points.
    rows : (r,) int array, optional
        Only these points (default all n); the arrays returned have one row per point asked for.

    Returns
    -------
    sides : (n, 3) float64 array
        Zero for a point inside the surface; for one on its border, the unit direction in its tangent plane in which
        the surface stops.
    normals : (n, 3) float64 array
        The least direction of its neighbours (zero with fewer than 4 points).
    """
    data = np.asarray(observed.data, dtype=np.float64)
    pts = data if rows is None else data[np.asarray(rows, dtype=np.int64)]
    n = len(pts)
    k = min(int(k), len(data) - 1)
    out = np.zeros((n, 3))
    if k < 3 or n == 0:
        return out, np.zeros((n, 3))
    idx = observed.query(pts, k=k + 1)[1][:, 1:]
    offsets = data[idx] - pts[:, None, :]  # (n, k, 3)
    centred = offsets - offsets.mean(1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    u, v = vectors[:, :, 2], vectors[:, :, 1]  # the principal plane (the normal is the least direction)
    angles = np.sort(np.arctan2(np.einsum("nkj,nj->nk", offsets, v), np.einsum("nkj,nj->nk", offsets, u)), axis=1)
    gaps = np.diff(np.concatenate([angles, angles[:, :1] + 2 * np.pi], axis=1), axis=1)
    widest = gaps.argmax(axis=1)
    border = gaps[np.arange(n), widest] > max_gap
    middle = angles[np.arange(n), widest] + 0.5 * gaps[np.arange(n), widest]
    out[border] = (np.cos(middle)[:, None] * u + np.sin(middle)[:, None] * v)[border]
    return out, vectors[:, :, 0]


def passes_through(observed, origin, directions, t_from, t_to, radius, sides=True, max_samples=4096):
    """Whether rays pass through the scan's own surface between ``t_from`` and ``t_to`` (the module docstring's
    "rays that pass through the scan's own surface"): between a sample and the next the ray crosses the tangent
    plane of the sample's nearest observed point, within ``radius`` of that point and on the side of it where the
    surface the scan saw goes on (``sides``: a ray that passes a hole's rim or a silhouette beside it passes the
    surface's border, not through it; one that runs along a surface without crossing it does not count).

    Parameters
    ----------
    observed : scipy.spatial.cKDTree
        Over the scan's points (world frame).
    origin : (3,) array
    directions : (B, 3) array
        Unit directions.
    t_from, t_to : (B,) arrays
        The part of each ray checked (world units from ``origin``; nothing where t_to <= t_from).
    radius : float
        World units (> 0); the samples are spaced at most ``radius`` / 2 apart (at most ``max_samples`` per ray).
    sides : bool
        Whether the side of a border point matters (:func:`surface_sides`, computed for the points met only); False:
        every sample within ``radius`` of an observed point counts.

    Returns
    -------
    (B,) bool
    """
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    t_from, t_to = np.asarray(t_from, dtype=np.float64).reshape(-1), np.asarray(t_to, dtype=np.float64).reshape(-1)
    out = np.zeros(len(directions), dtype=bool)
    rays = np.flatnonzero(t_to > t_from)
    if len(rays) == 0:
        return out
    counts = np.minimum(max_samples, np.ceil(2.0 * (t_to[rays] - t_from[rays]) / radius).astype(int) + 1)
    owner = np.repeat(np.arange(len(rays)), counts)
    start = np.cumsum(counts) - counts
    u = (np.arange(counts.sum()) - start[owner]) / np.maximum(counts[owner] - 1, 1)  # 0 .. 1 along each ray
    t = t_from[rays][owner] + u * (t_to[rays] - t_from[rays])[owner]
    x = origin + t[:, None] * directions[rays][owner]
    distance, nearest = observed.query(x, k=1, distance_upper_bound=radius)
    near = np.isfinite(distance)
    if sides and near.any():  # beside a border point, only on the side where the surface goes on
        rows = np.flatnonzero(near)
        met, which = np.unique(nearest[rows], return_inverse=True)
        border = surface_sides(observed, met)[0][which]
        near[rows] = np.einsum("ij,ij->i", x[rows] - observed.data[nearest[rows]], border) <= 0.0
    out[rays] = np.logical_or.reduceat(near, start)
    return out
