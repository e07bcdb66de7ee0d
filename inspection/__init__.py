"""Turning fitted fields into decisions: one pipeline (``Inspector``, configured by ``InspectionConfig``) from good scans to
verdicts, per-point and per-scan scores, thresholds (conformal or a log-normal tail), reports, the CLI.

Public names are imported lazily so that ``python -m inspection --help`` stays fast.
"""
import importlib

_EXPORTS = {
    "Inspector": "inspection.estimator",
    "NotFittedError": "inspection.estimator",
    "ScanResult": "inspection.estimator",
    "InspectionConfig": "inspection.config",
    "DEFAULT_AGGREGATE": "inspection.config",
    "DEFAULT_PROJECTION": "inspection.config",
    "field_for": "inspection.evidence",
    "gather_evidence": "inspection.evidence",
    "select_scans": "inspection.selection",
    "POINT_SCORES": "inspection.scores",
    "point_scores": "inspection.scores",
    "LocalReference": "inspection.reference",
    "aggregate": "inspection.aggregates",
    "conformal_p_values": "inspection.threshold",
    "conformal_threshold": "inspection.threshold",
    "fit_threshold": "inspection.threshold",
    "Threshold": "inspection.threshold",
    "Calibration": "inspection.calibration",
    "read_calibration": "inspection.calibration",
    "write_calibration": "inspection.calibration",
    "calibrated_inspector": "inspection.job",
    "inspect_scan": "inspection.job",
    "error_row": "inspection.job",
    "load_model_handle": "inspection.model_io",
    "ModelHandle": "inspection.model_io",
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
