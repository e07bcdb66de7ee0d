"""A scan's evidence, computed once: its projected field and what every point score and the ray score read from it.

:func:`gather_evidence` projects one scan into the model (or takes the fixed field) and reads, once, the quantities
the per-location point scores compare (:func:`inspection.reference.field_quantity`), the grazing factor of the sensor's
rays (:func:`autodecoder.scanning.sensor.grazing_factor`) and the stray returns
(:func:`datasets.outliers.stray_points`). The scores (:mod:`inspection.scores`) and the ray score
(:mod:`inspection.ray_evidence`) are computed from a :class:`ScanEvidence` without projecting again.
"""
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from datasets.validation import points_and_normals


@dataclass
class ScanEvidence:
    """One scan under the model.

    Attributes
    ----------
    name : str
    points : (m, 3) float64 array
        Model frame.
    field : stochastic field
        The scan's projected field (or the fixed field).
    origin : (3,) array or None
        The sensor origin (None when the scan records none).
    value, variance : (m,) arrays or None
        For the per-location point scores: the compared quantity and the field's variance in its units.
    grazing : (m,) array or None
        The grazing factor of the sensor's rays at each point (the origin estimated from the normals when the scan
        records none; None without normals or without a per-location point score).
    stray : (m,) bool array
        Isolated returns off the surface their neighbours define.
    normals : (m, 3) float64 array or None
        The scan's normals.
    """

    name: str
    points: np.ndarray
    field: object
    origin: object = None
    value: np.ndarray = None
    variance: np.ndarray = None
    grazing: np.ndarray = None
    stray: np.ndarray = None
    normals: np.ndarray = None


def kept_points(stray, count):
    """Which of a scan's ``count`` points its score counts: (count,) bool, every point but its stray returns.

    A stray point (a lone return off the surface, :func:`datasets.outliers.stray_points`) is not a defect unless
    many points agree, so a scan's score aggregates the others, and the calibration fits what good scans' scores
    count (the term variances, the reach of :func:`inspection.calibrating.uncovered_points`) on the same points.
    When every point is stray (or none was looked for: ``stray`` None) every point counts: a score needs points.
    The maps keep every point's own score either way.

    Parameters
    ----------
    stray : (count,) bool array or None
        :attr:`ScanEvidence.stray`.
    count : int
        The scan's number of points.
    """
    if stray is None:
        return np.ones(count, dtype=bool)
    stray = np.asarray(stray, dtype=bool).reshape(-1)
    if len(stray) != count:
        raise ValueError(f"kept_points: {count} points but {len(stray)} stray flags")
    return np.ones(count, dtype=bool) if stray.all() else ~stray


@contextmanager
def stage(timings, name):
    """Adds the wall time of the block to ``timings[name]`` (seconds; a dict, or None: nothing is timed). The
    inspection's per-scan stages (:func:`gather_evidence`, :func:`inspection.scoring.score_evidence`) are timed this
    way for the latency benchmark."""
    if timings is None:
        yield
        return
    t0 = time.perf_counter()
    try:
        yield
    finally:
        timings[name] = timings.get(name, 0.0) + time.perf_counter() - t0


def scan_name(scan, index):
    """A scan's own name, or ``'scan #<index>'`` for one without (a bare array)."""
    return getattr(scan, "name", None) or f"scan #{index}"


def sensor_origin(scan, name, required=False):
    """The scan's sensor origin (3,), None when it records none (``required``: a ValueError naming the scan)."""
    origin = getattr(scan, "sensor_origin", None)
    if origin is None:
        if not required:
            return None
        raise ValueError(f"{name}: no sensor origin, and the ray score needs where the sensor was (store it with the "
                         f"scan: synthetic scans have it, scanner files take a <stem>.json sidecar "
                         f"{{\"sensor_origin\": [x, y, z]}}), or inspect without rays")
    origin = np.asarray(origin, dtype=np.float64).reshape(-1)
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise ValueError(f"{name}: sensor origin must be 3 finite numbers, got {origin.tolist()}")
    return origin


def field_for(model, points, normals=None, options=None):
    """The stochastic field that explains one scan under ``model``.

    ``model`` may be a latent model (``model.project(points, normals)`` -> a projection with ``.field``, e.g.
    :func:`autodecoder.load_model`'s), a fixed field (anything with ``mean``/``variance``, e.g. a ``fit_cloud``
    field: every scan is scored against the same surface), or a callable ``(points, normals) -> field``.
    ``options`` (dict) go to ``model.project`` (e.g. ``{"steps": 60}``).
    """
    if hasattr(model, "project"):
        projection = model.project(points, normals, **(options or {}))
        return getattr(projection, "field", projection)
    if hasattr(model, "mean") and hasattr(model, "variance"):
        return model
    if callable(model):
        out = model(points, normals)
        return getattr(out, "field", out)
    raise TypeError(f"model must have .project(points, normals), .mean/.variance, or be callable; "
                    f"got {type(model).__name__}")


def gather_evidence(model, scan, index=0, quantity=None, projection=None, need_origin=False, exclude_own_code=False,
                    timings=None):
    """Project one scan and read what the scores need.

    Parameters
    ----------
    model : latent model, field or callable
        See :func:`field_for`.
    scan : Scan, (points, normals) or (m, 3) array
        In the model's frame.
    index : int
        The scan's position in its batch (names a scan without a name).
    quantity : {'distance'} or None
        The per-location reference's quantity (:func:`inspection.reference.field_quantity`); None: not read.
    projection : dict, optional
        ``model.project`` options.
    need_origin : bool
        The scan must record a valid sensor origin (the ray score).
    exclude_own_code : bool
        A training scan of a latent model is projected without starting from its own trained code (cross-fitting).
    timings : dict, optional
        Receives the seconds of each stage (:func:`stage`): ``'load'`` (points, normals, origin), ``'projection'``,
        ``'field'`` (the compared quantity and its variance), ``'grazing'``, ``'stray'``.

    Returns
    -------
    ScanEvidence
    """
    from autodecoder.scanning.sensor import grazing_factor, view_origin_from_normals
    from datasets.outliers import stray_points

    from .reference import field_quantity

    with stage(timings, "load"):
        points, normals = points_and_normals(scan)
        name = scan_name(scan, index)
        if points.ndim != 2 or points.shape[-1] != 3 or len(points) == 0:
            raise ValueError(f"{name}: a scan needs (m >= 1, 3) points, got shape {points.shape}")
        origin = sensor_origin(scan, name, required=need_origin)
    options = dict(projection or {})
    train_names = getattr(model, "train_names", None)
    if exclude_own_code and train_names and name in train_names:
        options["exclude"] = (train_names.index(name),)
    part = getattr(scan, "part_id", "")
    if part and getattr(model, "train_part_ids", None):  # a latent model: start from the part's codes
        options["part_id"] = part
    with stage(timings, "projection"):
        field = field_for(model, points, normals, options)
    value = variance = grazing = None
    if quantity is not None:
        with stage(timings, "field"):
            value, variance = field_quantity(field, points, quantity, with_variance=True)
        if normals is not None:
            with stage(timings, "grazing"):
                # no sensor origin (a public layout's test scan): the view estimated from the normals, for the
                # grazing term alone
                seen_from = origin if origin is not None else view_origin_from_normals(points, normals)
                grazing = grazing_factor(points, normals, seen_from)
    points = np.asarray(points, dtype=np.float64)
    with stage(timings, "stray"):
        stray = stray_points(points)
    return ScanEvidence(name, points, field, origin, value, variance, grazing, stray,
                        None if normals is None else np.asarray(normals, dtype=np.float64))
