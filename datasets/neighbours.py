"""The k nearest neighbours of every point of a scan at once.

A scan's inspection asks, for each of its points, for the nearest points of a reference cloud (the good scans'
surface, their values) or of the scan itself (its stray points). At full resolution (30,000 points and more) these
queries were the largest share of a scan's time with ``scipy.spatial.cKDTree``; ``pykdtree`` answers the same exact
queries in about half the time (docs/results.md#at-the-line-seconds-per-scan-issue-30). It runs on the OpenMP
threads the process allows: one where torch is limited to one thread (``torch.set_num_threads(1)`` limits the same
OpenMP runtime), as ``score --jobs`` workers are.

Trees that need more than k nearest neighbours (radius searches) stay
``cKDTree``.
"""
import numpy as np


class NearestNeighbours:
    """An exact k-nearest-neighbour index over a fixed cloud.

    Parameters
    ----------
    points : (n, 3) array
        Finite (ValueError otherwise); copied as float64 (the distances are then float64 too).
    """

    def __init__(self, points):
        from pykdtree.kdtree import KDTree

        self.data = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        if len(self.data) == 0:
            raise ValueError("NearestNeighbours needs at least one point")
        if not np.isfinite(self.data).all():  # pykdtree would answer with arbitrary neighbours
            raise ValueError("NearestNeighbours needs finite points (NaN or inf among them)")
        self._tree = KDTree(self.data)

    def __getstate__(self):  # the tree is rebuilt from the points (pykdtree's trees do not pickle)
        return {"data": self.data}

    def __setstate__(self, state):
        self.__init__(state["data"])

    @property
    def n(self):
        """Number of indexed points."""
        return len(self.data)

    def query(self, x, k):
        """The ``k`` nearest indexed points of each query point, nearest first.

        Parameters
        ----------
        x : (m, 3) array
        k : int, 1 <= k <= n

        Returns
        -------
        distance : (m, k) float64 array
            Euclidean, the points' units.
        index : (m, k) intp array
            Rows of ``data``.
        """
        k = int(k)
        if not 1 <= k <= self.n:
            raise ValueError(f"k must be in [1, {self.n}] (the indexed points), got {k}")
        x = np.ascontiguousarray(np.asarray(x, dtype=np.float64).reshape(-1, 3))
        if not np.isfinite(x).all():
            raise ValueError("NearestNeighbours.query needs finite query points (NaN or inf among them)")
        if len(x) == 0:
            return np.zeros((0, k)), np.zeros((0, k), dtype=np.intp)
        distance, index = self._tree.query(x, k=k)
        return distance.reshape(len(x), k), index.reshape(len(x), k).astype(np.intp)

    def nearest_within(self, x, bound):
        """The nearest indexed point of each query point, where one lies within ``bound``.

        The same neighbours as ``scipy.spatial.cKDTree.query(x, distance_upper_bound=bound)`` (the registration's
        ICP correspondences, :mod:`datasets.registration`), in about two thirds of the time (docs/results_archive.md,
        "Speed").

        Parameters
        ----------
        x : (m, 3) array
            Finite query points.
        bound : float
            Largest distance (the points' units) at which a neighbour counts.

        Returns
        -------
        found : (m,) bool
            Which query points have an indexed point within ``bound``.
        index : (m,) intp array
            Its row of ``data`` where ``found``; ``n`` (no such row) elsewhere.
        """
        x = np.ascontiguousarray(np.asarray(x, dtype=np.float64).reshape(-1, 3))
        if not np.isfinite(x).all():
            raise ValueError("NearestNeighbours.nearest_within needs finite query points (NaN or inf among them)")
        if len(x) == 0:
            return np.zeros(0, bool), np.zeros(0, dtype=np.intp)
        distance, index = self._tree.query(x, k=1, distance_upper_bound=float(bound))
        return np.isfinite(distance.reshape(-1)), index.reshape(-1).astype(np.intp)
