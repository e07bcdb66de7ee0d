"""Where good parts have a surface: the samples of a sensor's rays that the free-space test may accuse
(:mod:`autodecoder.scanning.free_space`, "Where good parts have a surface" and "Not where the ray skims past a good
surface")."""
import numpy as np

from datasets.validation import check_points


class SurfaceBand:
    """Where good parts have a surface: the points within ``radius`` of good scans' points (see the module
    docstring, "Where good parts have a surface"), less the samples where a ray skims past that surface on its outer
    side ("Not where the ray skims past a good surface").

    Parameters
    ----------
    points : (n, 3) array, or a :class:`datasets.neighbours.NearestNeighbours` or scipy.spatial.cKDTree over them
        Points of good scans of the part (e.g. the model's training scans), the field's frame. A
        ``NearestNeighbours`` index is used as it is (the caller may already hold one over these points: no second
        build for every scan inspected); otherwise one is built over the points.
    radius : float
        World units (> 0).
    normals : (index, (n2, 3) array), optional
        Good scans' points with unit outward normals: an index with ``query(x, k) -> (distance, rows)`` over n2
        points (:class:`datasets.neighbours.NearestNeighbours`, or a cKDTree) and their normals, row for row. None:
        every sample in the band is tested.
    min_cos : float in [0, 1)
        With ``normals``: a sample outside the nearest good point's tangent plane, on a ray making |cos| <
        ``min_cos`` with its normal, is not tested (0: none is left out for it).
    """

    def __init__(self, points, radius, normals=None, min_cos=0.0):
        from scipy.spatial import cKDTree

        from datasets.neighbours import NearestNeighbours

        if not float(radius) > 0:
            raise ValueError(f"SurfaceBand radius must be > 0 (world units), got {radius!r}")
        self.radius = float(radius)
        if isinstance(points, NearestNeighbours):
            self._index = points
            self.points = check_points(points.data, "surface points")
        else:
            self.points = check_points(points.data if isinstance(points, cKDTree) else points, "surface points")
            self._index = NearestNeighbours(self.points)
        if not 0 <= float(min_cos) < 1:
            raise ValueError(f"SurfaceBand min_cos must be in [0, 1), got {min_cos!r}")
        self.min_cos = float(min_cos)
        self._normals = None
        if normals is not None:
            index, unit = normals
            unit = np.asarray(unit, dtype=np.float64).reshape(-1, 3)
            size = index.n if hasattr(index, "n") else len(index.data)
            length = np.linalg.norm(unit, axis=1)
            if len(unit) != size or not np.isfinite(unit).all() or not (length > 0).all():
                raise ValueError(f"SurfaceBand normals: one finite, non-zero normal per indexed point ({size}), got "
                                 f"{len(unit)}")
            self._normals = (index, unit / length[:, None])

    def contains(self, x):
        """(k, 3) points -> (k,) bool: within ``radius`` of a good scan's point."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        return self._index.nearest_within(x, self.radius)[0]

    def skims(self, x, directions):
        """(k, 3) samples and the (k, 3) unit directions of their rays -> (k,) bool: the sample lies on the outer
        side of the nearest good point's tangent plane and its ray runs along that plane (|cos| < ``min_cos``). All
        False without normals or with ``min_cos`` 0."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        if self._normals is None or self.min_cos <= 0 or len(x) == 0:
            return np.zeros(len(x), dtype=bool)
        index, unit = self._normals
        rows = np.asarray(index.query(x, k=1)[1]).reshape(-1)
        n = unit[rows]
        outside = np.einsum("kj,kj->k", x - np.asarray(index.data)[rows], n) > 0
        along = np.abs(np.einsum("kj,kj->k", np.asarray(directions, dtype=np.float64).reshape(-1, 3), n))
        return outside & (along < self.min_cos)

    def tested(self, x, directions):
        """(k,) bool: the samples a ray tests, :meth:`contains` and not :meth:`skims`."""
        inside = self.contains(x)
        if inside.any():
            inside[inside] = ~self.skims(np.asarray(x, dtype=np.float64).reshape(-1, 3)[inside],
                                         np.asarray(directions, dtype=np.float64).reshape(-1, 3)[inside])
        return inside
