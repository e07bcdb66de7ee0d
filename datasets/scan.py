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
        if self.sensor_origin is not None:
            self.sensor_origin = np.asarray(self.sensor_origin, dtype=np.float32).reshape(3)

    def __len__(self):
        return len(self.points)
