"""The similarity transform between a cloud's own coordinates ("world") and the model's unit-cube frame."""
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Normalization:
    """x_model = scale * (x_world - center): the cloud's bounding box centred at 0 with its longest side 1.

    Normals are unchanged by a uniform scale and a translation. A field value (a length) scales with ``scale``:
    f_world = f_model / scale, variances with scale^2.
    """

    center: np.ndarray  # (3,)
    scale: float

    @classmethod
    def fit(cls, points):
        """The transform that maps ``points`` (n, 3) into [-0.5, 0.5]^3 with the longest side of length 1."""
        lo, hi = points.min(0), points.max(0)
        extent = float((hi - lo).max())
        if not np.isfinite(extent) or extent <= 0:
            raise ValueError("the points span no volume: cannot normalise a cloud whose bounding box is a point")
        return cls(center=((lo + hi) / 2).astype(np.float64), scale=1.0 / extent)

    @classmethod
    def identity(cls):
        return cls(center=np.zeros(3), scale=1.0)

    def to_model(self, x):
        """World points (..., 3) -> model frame."""
        return (np.asarray(x, dtype=np.float64) - self.center) * self.scale

    def to_world(self, x):
        """Model-frame points (..., 3) -> world."""
        return np.asarray(x, dtype=np.float64) / self.scale + self.center

    def as_dict(self):
        return {"center": [float(c) for c in self.center], "scale": float(self.scale)}

    @classmethod
    def from_dict(cls, d):
        return cls(center=np.asarray(d["center"], dtype=np.float64), scale=float(d["scale"]))
