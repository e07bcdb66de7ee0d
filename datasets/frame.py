"""The similarity transform between a scanner file's coordinates and a collection's frame."""
from dataclasses import dataclass, field, replace

import numpy as np


@dataclass(frozen=True)
class Frame:
    """x_collection = scale * (x_file - center): a uniform scale after a translation.

    Normals are unchanged (no rotation, positive scale). A length in the collection frame is ``scale`` times the same
    length in file units, so a field value maps back as f_file = f_collection / scale and a variance as / scale**2.

    Attributes
    ----------
    center : (3,) float64 array
        Point of the file frame that becomes the origin, in file units.
    scale : float
        Collection units per file unit (> 0).
    """

    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0

    def __post_init__(self):
        # frozen: set through object.__setattr__ so the stored center is always a fresh read-only float64 copy
        center = np.array(self.center, dtype=np.float64).reshape(-1)
        if center.shape != (3,) or not np.all(np.isfinite(center)):
            raise ValueError(f"Frame center must be 3 finite numbers, got {self.center!r}")
        scale = float(self.scale)
        if not np.isfinite(scale) or scale <= 0:
            raise ValueError(f"Frame scale must be a finite number > 0, got {self.scale!r}")
        center.flags.writeable = False
        object.__setattr__(self, "center", center)
        object.__setattr__(self, "scale", scale)

    @classmethod
    def identity(cls):
        """The frame that changes nothing (center 0, scale 1)."""
        return cls(np.zeros(3), 1.0)

    @classmethod
    def fit(cls, points):
        """The frame that maps the bounding box of ``points`` to a cube centred at 0 whose longest side is 1.

        The box is exact (CAD vertices, clean samples); scanner data is fitted on the points that survive
        :func:`datasets.outliers.stray_points` (the importer does), so isolated returns off the part leave the frame
        as it would be without them.

        Parameters
        ----------
        points : (N, 3) array
            Points in file units; non-finite rows are ignored.

        Returns
        -------
        Frame
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        p = p[np.all(np.isfinite(p), axis=1)]
        if len(p) == 0:
            raise ValueError("Frame.fit: no finite points to fit a frame to")
        lo, hi = p.min(0), p.max(0)
        extent = float((hi - lo).max())
        if extent <= 0:
            raise ValueError("Frame.fit: the points span no volume (their bounding box is a single point)")
        return cls((lo + hi) / 2, 1.0 / extent)

    def to_collection(self, x):
        """File-frame points (..., 3) -> collection frame, float64."""
        return (np.asarray(x, dtype=np.float64) - self.center) * self.scale

    def to_file(self, x):
        """Collection-frame points (..., 3) -> file frame, float64."""
        return np.asarray(x, dtype=np.float64) / self.scale + self.center

    def apply(self, scan):
        """The scan moved from file frame into this frame (points and sensor origin; normals unchanged; the
        per-point deviation, a length, times ``scale``).

        Parameters
        ----------
        scan : Scan
            In file units.

        Returns
        -------
        Scan
            A new scan; ``scan`` is not modified.
        """
        origin = None if scan.sensor_origin is None else self.to_collection(scan.sensor_origin)
        deviation = None if scan.point_deviation is None else scan.point_deviation.astype(np.float64) * self.scale
        return replace(scan, points=self.to_collection(scan.points), normals=scan.normals.copy(),
                       sensor_origin=origin, extra=dict(scan.extra), point_deviation=deviation)

    def as_dict(self):
        """JSON-ready ``{"center": [x, y, z], "scale": s}``."""
        return {"center": [float(c) for c in self.center], "scale": float(self.scale)}

    @classmethod
    def from_dict(cls, d):
        """Inverse of :meth:`as_dict`."""
        return cls(np.asarray(d["center"], dtype=np.float64), float(d["scale"]))

    def __eq__(self, other):
        if not isinstance(other, Frame):
            return NotImplemented
        return self.scale == other.scale and bool(np.array_equal(self.center, other.center))

    def __hash__(self):
        return hash((self.scale, tuple(self.center)))

    def __repr__(self):
        return f"Frame(center={self.as_dict()['center']}, scale={self.scale!r})"
