"""The nearest-neighbour baseline every inspection benchmark prints beside the toolkit's scores."""
import numpy as np


def nn_baseline(train_points, scans, top=5.0):
    """Per scan: each point's distance to the nearest training point, and the scan score = the mean of the worst
    ``top`` % of them.

    Parameters
    ----------
    train_points : (n, 3) array
        The good training scans' points, in the scans' frame.
    scans : sequence of objects with ``points`` (m_i, 3)
    top : float in (0, 100]

    Returns
    -------
    list of (float, (m_i,) array)
        (scan score, per-point distances) per scan.
    """
    from scipy.spatial import cKDTree

    tree = cKDTree(train_points)
    out = []
    for s in scans:
        d = tree.query(s.points, k=1, workers=2)[0]
        k = max(1, int(np.ceil(top / 100 * len(d))))
        out.append((float(np.sort(d)[-k:].mean()), d))
    return out
