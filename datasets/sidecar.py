"""A scanner file's sidecar: where the sensor was, as ``<stem>.json`` (or an ``.npz``'s ``sensor_origin``) says.

A sidecar holds ``{"sensor_origin": [x, y, z]}`` in the file's units, or ``{"view_direction": [x, y, z]}`` for a
scanner whose stand-off nobody wrote down: the origin is then put ``VIEW_DIRECTION_DISTANCE`` bounding-box diagonals
from the cloud's centre along that direction (near-parallel rays, :mod:`datasets.importer`'s module docstring).
Read by the importers of every layout (:mod:`datasets.importer`, :mod:`datasets.layouts`).
"""
import json

import numpy as np

SIDECAR_SUFFIX = ".json"
VIEW_DIRECTION_DISTANCE = 100.0  # bounding-box diagonals: a sidecar's view direction as a far origin


def read_sensor_origin(path, points):
    """Sensor origin (3,) in file units from an npz key or a ``<stem>.json`` sidecar (a ``view_direction`` becomes
    a far origin beyond the cloud ``points``: module docstring), or None."""
    if path.suffix.lower() == ".npz":
        with np.load(path, allow_pickle=False) as z:
            if "sensor_origin" in z.files:
                return check_origin(z["sensor_origin"], path)
    sidecar = path.with_suffix(SIDECAR_SUFFIX)
    if sidecar.is_file():
        expected = '{"sensor_origin": [x, y, z]} or {"view_direction": [x, y, z]}'
        try:
            record = json.loads(sidecar.read_text())
            if "sensor_origin" in record:
                return check_origin(record["sensor_origin"], sidecar)
            direction = check_origin(record["view_direction"], sidecar, "view_direction")
        except (json.JSONDecodeError, KeyError, TypeError, AttributeError) as e:
            raise ValueError(f"{sidecar}: expected {expected} ({e})") from None
        length = float(np.linalg.norm(direction))
        if not length > 0:
            raise ValueError(f"{sidecar}: view_direction must not be zero")
        lo, hi = points.min(0), points.max(0)
        diagonal = max(float(np.linalg.norm(hi - lo)), 1e-12)
        return (lo + hi) / 2 + VIEW_DIRECTION_DISTANCE * diagonal * direction / length
    return None


def check_origin(value, where, what="sensor_origin"):
    """``value`` as a (3,) float64 origin (or direction), or a ValueError naming ``where`` and ``what``."""
    o = np.asarray(value, dtype=np.float64).reshape(-1)
    if o.shape != (3,) or not np.all(np.isfinite(o)):
        raise ValueError(f"{where}: {what} must be 3 finite numbers, got {value!r}")
    return o
