"""Turning fitted fields into decisions: per-point and per-scan scores, thresholds from good scans (conformal or a log-normal tail), reports, the CLI.

Public names are imported lazily so that ``python -m inspection --help`` stays fast.
"""
import importlib

_EXPORTS = {
    "Inspector": "inspection.estimator",
    "NotFittedError": "inspection.estimator",
    "field_for": "inspection.estimator",
    "DEFAULT_AGGREGATE": "inspection.estimator",
    "DEFAULT_PROJECTION": "inspection.estimator",
    "point_scores": "inspection.scores",
    "LocalReference": "inspection.scores",
    "aggregate": "inspection.scores",
    "conformal_p_values": "inspection.threshold",
    "conformal_threshold": "inspection.threshold",
    "fit_threshold": "inspection.threshold",
    "Threshold": "inspection.threshold",
    "Calibration": "inspection.calibration",
    "read_calibration": "inspection.calibration",
    "write_calibration": "inspection.calibration",
    "load_model": "inspection.model_io",
    "save_reference_field": "inspection.model_io",
    "Aligner": "inspection.align",
    "ray_evidence": "inspection.ray_evidence",
    "Combination": "inspection.combine",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'inspection' has no attribute {name!r}")
