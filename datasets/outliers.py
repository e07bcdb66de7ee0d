"""Stray points of a scan: isolated returns off the surface that the scan's other points define."""
import numpy as np

from .local_planes import smallest_eigenpairs
from .neighbours import NearestNeighbours

STRAY_NEIGHBOURS = 8  # the local plane of a point is fitted to this many nearest neighbours (the point excluded)
STRAY_FACTOR = 3.0  # a point this many local spacings off that plane is stray
_CHUNK = 100_000  # points per block of neighbourhood arrays


def stray_points(points, k=STRAY_NEIGHBOURS, factor=STRAY_FACTOR):
    """Which points lie off the surface their neighbours define, by more than a few of the local point spacings.

    A point is stray when its distance to the least-squares plane of its ``k`` nearest neighbours (itself excluded)
    exceeds ``factor`` times the local spacing, the median nearest-neighbour distance of those neighbours. Both
    lengths come from the data, so the rule holds in any units and at any resolution. A neighbourhood is judged by
    its own spacing, not the cloud's, so a sparse patch (a grazing surface, a thin ridge) is not stray for being
    sparse; a cluster of more than about ``k`` agreeing points is a surface, not a stray point.

    Why not a global k-NN distance rule (open3d's ``remove_statistical_outlier``): on a real range scan the spacing
    varies several-fold with the viewing angle, and a global threshold either flags the grazing surfaces or misses
    points a few millimetres off a dense one.

    Parameters
    ----------
    points : (N, 3) float array
        Finite, any units.
    k : int >= 3
    factor : float > 0

    Returns
    -------
    (N,) bool array
        True for stray points. All False when N <= k (too few points to judge).
    """
    if k < 3:
        raise ValueError(f"stray_points: k must be >= 3 (a plane needs 3 points), got {k}")
    if not factor > 0:
        raise ValueError(f"stray_points: factor must be > 0, got {factor}")
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) <= k:
        return np.zeros(len(p), dtype=bool)
    tree = NearestNeighbours(p)
    # one query for every point's k + 1 nearest (itself among them): its second distance is the point's nearest
    # other point (0 for duplicates), the same number a query of 2 gives
    dist, neighbours = tree.query(p, k + 1)
    nn = dist[:, 1]  # (N,)
    positive = nn[nn > 0]
    floor = 0.1 * float(np.median(positive)) if len(positive) else 0.0  # stands in for a spacing of 0 (duplicates)
    out = np.empty(len(p), dtype=bool)
    for start in range(0, len(p), _CHUNK):  # chunks keep the (n, k, 3) neighbourhoods of a large scan small
        q_idx = np.arange(start, min(start + _CHUNK, len(p)))
        idx = neighbours[q_idx]
        # the query returns the point itself first, unless an exact duplicate came first: drop whichever is itself
        first_other = idx[:, 0] != q_idx
        nb = np.where(first_other[:, None], idx[:, :k], idx[:, 1:])  # (n, k)
        q = p[nb]  # (n, k, 3)
        centre = q.mean(axis=1)
        d = q - centre[:, None]
        _, normal = smallest_eigenpairs(np.matmul(d.transpose(0, 2, 1), d))  # the plane's normal
        off = np.abs(np.einsum("ni,ni->n", p[q_idx] - centre, normal))
        spacing = np.median(nn[nb], axis=1)
        out[q_idx] = off > factor * np.maximum(spacing, floor)
    return out
