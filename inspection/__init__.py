"""Turning fitted fields into decisions: scores, calibrated thresholds, reports."""
