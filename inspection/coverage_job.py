"""``nsspr-inspect coverage``: where a calibrated model's good scans cover the part, and the good scans to take next.

Reads the model's calibration (its per-location reference holds the good scans' surface), the target surface (the
scans given, registered into the model's frame as ``score`` registers them, or the model's mean shape), plans the
views (:func:`inspection.coverage_views.plan_views`) and writes into the output folder ``coverage.png`` (the
picture), ``coverage.ply`` (the target points coloured as in the picture) and ``coverage.json`` (the plan: every
proposed sensor position, what each covers), atomically; the proposed views are printed.
"""
import json
from pathlib import Path

import numpy as np

from .errors import InspectionError


def coverage_plan(model, data=None, n_views=4, split=None, progress=False):
    """The :class:`inspection.coverage_views.CoveragePlan` of a calibrated model file (its good scans' coverage of
    the scans in ``data``, or of its mean shape when ``data`` is None) with ``n_views`` proposed views.

    Raises
    ------
    InspectionError
        An uncalibrated model, a calibration without a per-location reference or with coverage off (naming the
        file and what to do), or no scans in ``data``.
    """
    from .coverage import COVERAGE_LENGTHSCALES, coverage_radius
    from .coverage_views import mean_shape_targets, plan_views
    from .job import calibrated_inspector
    from .loading import load_scans
    from .model_io import load_model_handle
    from .scoring import registered

    handle = load_model_handle(model)
    if handle.calibration is None:
        raise InspectionError(f"{handle.path}: the model is not calibrated; coverage reads the good scans' surface "
                              f"from its calibration: run `nsspr-inspect calibrate --model {handle.path} --data "
                              f"TRAINING_COLLECTION` first")
    insp = calibrated_inspector(handle)
    if getattr(insp, "parts_", None):
        raise InspectionError(f"{handle.path}: a model of several part types; coverage plans one part at a time")
    if insp.reference_ is None:
        raise InspectionError(f"{handle.path}: its calibration has no per-location reference (the good training "
                              f"scans' surface); calibrate it on its training collection")
    radius = coverage_radius(insp.model, insp.settings_.coverage or COVERAGE_LENGTHSCALES)
    if radius is None:
        raise InspectionError(f"{handle.path}: the model has no kernel lengthscale to measure coverage with")
    standoff = None
    if data is None:
        points, normals = mean_shape_targets(insp.model)
        source = "the model's mean shape (no scans given)"
    else:
        scans, info = load_scans(data, handle.frame, split=split, model_fingerprint=handle.fingerprint,
                                 reading=insp.reading_)
        scans = [s for s in scans if s.normals is not None and len(s.points)]
        if not scans:
            raise InspectionError(f"{data}: no scans with normals to plan coverage for")
        moved = [registered(insp.model, s, insp.settings_.align, getattr(insp, "aligner_", None))[0] for s in scans]
        points = np.vstack([np.asarray(s.points, dtype=np.float64) for s in moved])
        normals = np.vstack([np.asarray(s.normals, dtype=np.float64) for s in moved])
        origins = [np.asarray(s.sensor_origin, dtype=np.float64) for s in moved if s.sensor_origin is not None]
        if origins:  # the scans' own stand-off from the part's centre
            centre = (points.min(0) + points.max(0)) / 2
            standoff = float(np.median([np.linalg.norm(o - centre) for o in origins]))
        source = f"{len(moved)} scans of {data}"
    return plan_views(insp.reference_, points, normals, radius, n_views, standoff=standoff, source=source,
                      progress=progress)


def write_coverage(plan, out):
    """Write ``coverage.png``, ``coverage.ply`` and ``coverage.json`` of ``plan`` into the folder ``out`` (created;
    each file atomically). Returns the folder."""
    from datasets import write_cloud

    from .plots import plot_coverage
    from .report import atomic_write_text

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    plot_coverage(out / "coverage.png", plan)
    colours = np.tile(np.array([200, 200, 200], dtype=np.uint8), (len(plan.points), 1))
    colours[~plan.covered] = (220, 30, 30)
    palette = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [148, 103, 189], [140, 86, 75],
                        [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207], [214, 39, 40]], np.uint8)
    seen = plan.first_view >= 0
    colours[seen] = palette[plan.first_view[seen] % len(palette)]
    write_cloud(out / "coverage.ply", plan.points.astype(np.float32), plan.normals.astype(np.float32), colours)
    atomic_write_text(out / "coverage.json", json.dumps(plan.as_dict(), indent=2) + "\n")
    return out


def describe_plan(plan):
    """The plan in lines a user reads: the coverage, then each proposed view."""
    lines = [f"coverage of {plan.source}: {100 * (1 - plan.uncovered_share):.1f} % of {len(plan.points)} points lie "
             f"on surface the good scans covered (within {plan.radius:.4g} across the surface)"]
    if not plan.views:
        lines.append("no view would cover more: every target point is covered, or none can be seen from outside")
    for k, view in enumerate(plan.views):
        p = ", ".join(f"{v:.4g}" for v in view.position)
        lines.append(f"  view {k + 1}: a good scan with the sensor at ({p}) looking at the part's centre covers "
                     f"{100 * view.share:.1f} % of the uncovered points")
    if plan.views:
        lines.append(f"  after these views {100 * plan.remaining_share:.1f} % of the uncovered points stay uncovered "
                     f"(positions in the model's frame; add the good scans to the training collection and retrain)")
    return lines
