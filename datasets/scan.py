"""One scan as data: an oriented partial point cloud with its metadata (the unit every part of the toolkit passes)."""
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

SPLITS = ("train", "validation", "test")
LABELS = ("good", "defective", "unknown")


@dataclass
class Scan:
    """An oriented point cloud of one part, with what is known about it.

    Attributes
    ----------
    name : str
        Unique name within a collection (e.g. ``"test/dent/007"``).
    points : (N, 3) float32 array
        Positions, in the collection's frame once stored in a collection.
    normals : (N, 3) float32 array
        Unit outward normals.
    split : {'train', 'validation', 'test'}
    label : {'good', 'defective', 'unknown'}
    defect : str
        Defect type ('' for good or unknown parts), e.g. 'dent', 'bump', 'missing', 'foreign'.
    part_id : str
        Which part (CAD model) this is a scan of; '' when there is one part.
    point_labels : (N,) uint8 array, optional
        Per-point ground truth, 1 where the point lies on a defect.
    sensor_origin : (3,) float32 array, optional
        Where the sensor was, in the same frame as ``points``.
    extra : dict
        Anything else (a pose, a defect's centre); not stored in a collection.
    point_deviation : (N,) float32 array, optional
        Per-point ground truth of how far each point lies off the good part's surface: its signed distance to it,
        in the same units as ``points`` (a length: a frame's scale scales it), positive outside (material added: a
        bump, a foreign object), negative inside (a dent, a missing pit), 0 on points no defect touched. None when
        unknown (real scans). Like ``point_labels``, every copy, subset or move of a scan carries it.
    """

    name: str
    points: np.ndarray
    normals: np.ndarray
    split: str = "train"
    label: str = "good"
    defect: str = ""
    part_id: str = ""
    point_labels: Optional[np.ndarray] = None
    sensor_origin: Optional[np.ndarray] = None
    extra: dict = field(default_factory=dict)
    point_deviation: Optional[np.ndarray] = None  # last, so that positional construction stays as it was

    def __post_init__(self):
        self.points = np.ascontiguousarray(self.points, dtype=np.float32)
        self.normals = np.ascontiguousarray(self.normals, dtype=np.float32)
        where = f"scan {self.name!r}"
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ValueError(f"{where}: points must be (N, 3), got {self.points.shape}")
        if self.normals.shape != self.points.shape:
            raise ValueError(f"{where}: normals {self.normals.shape} must match points {self.points.shape}")
        if self.split not in SPLITS:
            raise ValueError(f"{where}: split must be one of {SPLITS}, got {self.split!r}")
        if self.label not in LABELS:
            raise ValueError(f"{where}: label must be one of {LABELS}, got {self.label!r}")
        if self.point_labels is not None:
            self.point_labels = np.ascontiguousarray(self.point_labels, dtype=np.uint8).reshape(-1)
            if len(self.point_labels) != len(self.points):
                raise ValueError(f"{where}: {len(self.point_labels)} point labels for {len(self.points)} points")
        if self.point_deviation is not None:
            self.point_deviation = np.ascontiguousarray(self.point_deviation, dtype=np.float32).reshape(-1)
            if len(self.point_deviation) != len(self.points):
                raise ValueError(f"{where}: {len(self.point_deviation)} point deviations for {len(self.points)} "
                                 f"points")
            bad = int(np.count_nonzero(~np.isfinite(self.point_deviation)))
            if bad:
                raise ValueError(f"{where}: {bad} point deviations are NaN or Inf (of {len(self.points)})")
        if self.sensor_origin is not None:
            self.sensor_origin = np.asarray(self.sensor_origin, dtype=np.float32).reshape(3)

    def __len__(self):
        return len(self.points)
