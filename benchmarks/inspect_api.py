"""The benchmarks' one door into the inspection package: every suite that calibrates, scores or reads a scored run
goes through these functions, so a change of the inspection API is met here once.

Written against ``inspection.job.calibrate`` / ``inspection.run.score`` (what ``python -m inspection calibrate`` and
``score`` run) with an ``inspection.config.InspectionConfig``, the per-scan job's
``inspection.job.calibrated_inspector`` (a model file's calibrated inspector, as ``score`` builds it) and the files
``score`` writes (``scores.csv``, ``summary.json``).
"""
import shutil
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from benchmarks import metrics
from benchmarks.metrics import read_scores  # noqa: F401 (the suites read a scored run's rows through this door)

# the lines of the inspection's own output a benchmark repeats: what calibration did and any note on the threshold
_ECHOED = ("note:", "threshold basis", "calibrated on", "part ", "the rays weighed")


def model_info(model_path):
    """What a benchmark needs to know of a trained model: ``train_names``, ``heldback_names``, ``kind``,
    ``train_seconds`` and ``epoch`` (None where the checkpoint does not say)."""
    from inspection.model_io import load_model_handle

    handle = load_model_handle(model_path)
    info = getattr(handle.model, "info", None) or {}
    return {"train_names": list(handle.train_names), "heldback_names": list(handle.heldback_names),
            "kind": handle.kind, "train_seconds": info.get("train_seconds"),
            "epoch": getattr(handle.model, "epoch", None)}


def point_score_names():
    """The point scores the inspection package offers (its registry), in its order."""
    from inspection.scores import POINT_SCORES

    return list(POINT_SCORES)


def defaults():
    """The inspection's defaults: ``alpha``, ``aggregate``, ``point_score`` (the point score the command line picks
    on a model's training collection), ``combination`` (the ray rule), ``projection`` (the options of a latent
    model's ``project`` / ``project_many`` that inspection uses)."""
    from inspection.combine import RULE
    from inspection.config import DEFAULT_AGGREGATE, DEFAULT_PROJECTION, InspectionConfig

    config = InspectionConfig()
    # point score 'auto': 'joint' where the model's training scans give the reference (its training collection)
    return {"alpha": config.alpha, "aggregate": DEFAULT_AGGREGATE, "point_score": "joint", "combination": RULE,
            "projection": dict(DEFAULT_PROJECTION)}


def registered_onto(scans, good_scans):
    """``scans`` each registered onto the union of ``good_scans`` by the inspection's registration
    (``inspection.align.Aligner``): a baseline given the scans as aligned as the toolkit's are."""
    from inspection.align import Aligner

    aligner = Aligner.from_scans(good_scans)
    return [aligner.align_scan(s) for s in scans]


def in_common_frame(model_path, scans):
    """``scans`` registered onto the model's common frame (the pose of training scans placed by hand, or a family's
    size: ``LatentModel.normalise``, a training scan onto the others), as the toolkit registers them before it scores
    them; None when the model has no such frame. A baseline given the scans as aligned as the toolkit's are."""
    from inspection.model_io import load_model_handle

    model = load_model_handle(model_path).model
    if getattr(model, "family", None) is None:
        return None
    return [model.normalise(s) for s in scans]


def calibrate_and_score(model_path, data_path, out_dir, *, rays=None, point_score=None, aggregate=None,
                        alpha=None, align=None, maps="flagged", progress=False, echo=print, folds=True):
    """The README's path on an uncalibrated copy of a model: ``python -m inspection calibrate`` on the model's training
    collection (timed: ``calibration_seconds`` in the summary returned; with no settings exactly what ``score`` does
    by itself on an uncalibrated model), then ``python -m inspection score``.

    Parameters
    ----------
    model_path : str or Path
        A trained model; it is copied to ``out_dir/model.pt`` (the calibration is written into the copy).
    data_path : str or Path
        The model's training collection; its test split is scored.
    out_dir : str or Path
        The run's folder: ``model.pt`` and ``results/`` (scores.csv, summary.json, plots, maps).
    rays : bool, optional
        Calibrate with (True) or without (False) the ray score; None: the inspection's own choice.
    point_score, aggregate, alpha : optional
        Calibration settings; None: the inspection's defaults.
    align : bool, optional
        Calibrate and score with ``--align`` (True: every scan, the calibration scans included, registered onto the
        training scans first) or ``--no-align`` (False); None: the inspection's default (registered when the
        training scans' poses spread).
    maps : {'flagged', 'all', 'none'}
    folds : bool
        False: the copy is the model without its fold models (as trained with ``--calibration-folds 0``), so that it
        calibrates on the held-back scans and the training scans cross-fitted.
    echo : callable (str) -> None, optional
        Receives the inspection's lines on calibration and threshold notes (None: silent).

    Returns
    -------
    dict
        summary.json's content, and ``calibration_seconds``.
    """
    from inspection.config import InspectionConfig
    from inspection.job import calibrate, describe_calibration
    from inspection.run import score

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    copy = out_dir / "model.pt"
    shutil.copyfile(model_path, copy)  # uncalibrated: the cached model stays as trained
    if not folds:
        _drop_folds(copy)
    lines = []
    settings = {k: v for k, v in dict(rays=rays, point_score=point_score, aggregate=aggregate, alpha=alpha,
                                      align=align).items() if v is not None}
    t0 = time.perf_counter()
    insp, info = calibrate(copy, data_path, config=InspectionConfig(**settings), progress=progress)
    calibration_seconds = time.perf_counter() - t0
    lines += describe_calibration(insp, info)
    summary = score(copy, data_path, out_dir / "results", split="test", progress=progress, maps=maps,
                    echo=lines.append, overwrite=True)
    summary["calibration_seconds"] = calibration_seconds
    if echo is not None:
        for line in lines:
            if line.startswith(_ECHOED) or "not calibrated" in line:
                echo(line)
    return summary


def parse_point_scores(text):
    """``'joint,distance,nll:mean'`` -> [('joint', None), ('distance', None), ('nll', 'mean')]: point scores, each
    with an aggregate after a colon (None: the default aggregate). Unknown point scores are a SystemExit."""
    from inspection.aggregates import check_aggregate

    out = []
    for spec in (t.strip() for t in text.split(",") if t.strip()):
        name, _, agg = spec.partition(":")
        if name not in point_score_names():
            raise SystemExit(f"--point-scores: unknown point score {name!r}; known: {point_score_names()}")
        if agg:
            check_aggregate(agg)
        out.append((name, agg or None))
    return out


def point_score_runs(model_path, data_path, work_dir, specs, align=None, progress=False):
    """The same model calibrated and scored with each point score of ``specs`` (:func:`parse_point_scores`) alone:
    no ray score, folds off, no maps; one run folder each under ``work_dir``. Returns {spec text: figures of
    :func:`summary_figures` plus ``oracle``}."""
    out = {}
    for name, agg in specs:
        text = name + (f":{agg}" if agg else "")
        run_dir = Path(work_dir) / f"alone_{name}_{agg or 'default'}"
        summary = calibrate_and_score(model_path, data_path, run_dir, rays=False, point_score=name, aggregate=agg,
                                      align=align, maps="none", progress=progress, folds=False, echo=None)
        scored = read_scores(run_dir / "results")
        out[text] = {**summary_figures(summary), "oracle": metrics.oracle_flagged(scored["score"], scored["label"])}
    return out


def scoring_seconds(model_path, data_path, out_dir, jobs_list=(1, 2), progress=False):
    """Throughput of ``python -m inspection score --jobs N``: an uncalibrated copy of a model calibrated once (the
    defaults, on its training collection), then its test split scored with ``--maps none`` once per N.

    Returns
    -------
    dict
        ``scans`` (scored per run), ``calibration_seconds``, and per N (str) ``{"seconds", "scans_per_second",
        "scores"}`` with ``scores`` the scores.csv rows' scores (equal across N: the runs must agree).
    """
    from inspection.job import calibrate
    from inspection.run import score

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    copy = out_dir / "model.pt"
    shutil.copyfile(model_path, copy)
    t0 = time.perf_counter()
    calibrate(copy, data_path, progress=progress)
    figures = {"calibration_seconds": time.perf_counter() - t0, "jobs": {}}
    for jobs in jobs_list:
        t0 = time.perf_counter()
        score(copy, data_path, out_dir / f"jobs{jobs}", split="test", progress=progress, maps="none",
              echo=lambda line: None, overwrite=True, jobs=int(jobs))
        seconds = time.perf_counter() - t0
        scores = read_scores(out_dir / f"jobs{jobs}")["score"].tolist()
        figures["scans"] = len(scores)
        figures["jobs"][str(jobs)] = {"seconds": seconds, "scans_per_second": len(scores) / seconds,
                                      "scores": scores}
    return figures


def score_calibrated(model_path, data_path, out_dir, *, good_folder=None, maps="none", progress=False):
    """Another collection's test split scored by a calibrated model, as ``python -m inspection score`` does: the model
    is copied to ``out_dir/model.pt`` (its calibration with it) and ``results/`` written there. The collection must lie
    in the model's frame (another test sensor's scans imported as the training collection's were).

    With ``good_folder``, the copy is first given that folder's scanner files (good scans of the inspection's own
    sensor, none a scan it trained on) as ``python -m inspection calibrate --model M --data FOLDER`` does: they set
    the threshold's level (:meth:`inspection.Inspector.fit_level`).

    Returns
    -------
    dict
        summary.json's content.
    """
    from inspection.job import calibrate
    from inspection.run import score

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    copy = out_dir / "model.pt"
    shutil.copyfile(model_path, copy)
    if good_folder is not None:
        calibrate(copy, good_folder, progress=progress, echo=lambda line: None)
    return score(copy, data_path, out_dir / "results", split="test", progress=progress, maps=maps,
                 echo=lambda line: None, overwrite=True)


def calibration_gap(run_dir):
    """How far a scored run's good test scans lie from the scans that calibrated its threshold: the mean log score
    of the good test scans (``good_test_mean_log``), each calibration role's (``<role>_mean_log``: held-back,
    fold, cross-fitted) and the difference (``minus_<role>``; positive: the test scans score higher than what set
    the threshold), from ``run_dir/results/scores.csv`` and ``run_dir/model.pt``."""
    from benchmarks.metrics import GOOD

    scored = read_scores(Path(run_dir) / "results")
    good = scored["score"][(scored["label"] == GOOD) & np.isfinite(scored["score"])]
    test = float(np.log(good).mean())
    gap = {"good_test_mean_log": test}
    for role, values in calibration_scores(Path(run_dir) / "model.pt").items():
        if len(values):
            gap[f"{role}_mean_log"] = float(np.log(values).mean())
            gap[f"minus_{role}"] = test - float(np.log(values).mean())
    return gap


def _drop_folds(model_path):
    """Remove the fold models from a model file (a copy), atomically."""
    from autodecoder.latent.folds import FOLDS_KEY
    from autodecoder.latent.model import read_checkpoint, save_checkpoint

    state = read_checkpoint(model_path)
    if state.pop(FOLDS_KEY, None) is not None:
        save_checkpoint(state, model_path)


def outside_family_figures(results_dir):
    """What the family's range decided in a scored run (:mod:`inspection.family_range`), from its scores.csv:
    :func:`benchmarks.metrics.verdicts_turned` with the reason that rule gives (None for a run without reasons)."""
    from inspection.family_range import OUTSIDE_FAMILY

    return metrics.verdicts_turned(read_scores(results_dir), OUTSIDE_FAMILY)


def summary_figures(summary):
    """The figures of a summary: ``auroc`` (overall and per defect type), ``point_auroc``, ``flagged`` (fractions
    of defective and good test scans above the threshold; ``good_rejected``, the fraction of good ones whose verdict
    is 'defective' rather than 'uncertain', ``defective_told`` the fraction of defective ones whose verdict is
    'defective', each None for a summary written before verdicts were counted),
    ``threshold`` (value, basis, predicted false-alarm rate and its interval;
    None for a model of several parts, thresholded per part), ``point_score``, ``aggregate``, ``rays``,
    ``seconds_per_scan``, ``calibration_seconds`` (when timed), ``alpha``."""
    metrics = summary["metrics"]
    confusion = metrics.get("confusion_matrix", {})
    decision = summary.get("decision")
    threshold = None
    told = metrics.get("verdicts", {}).get("good")
    rejected = told["defective"] / sum(told.values()) if told and sum(told.values()) else None
    told_bad = metrics.get("verdicts", {}).get("defective")
    found = told_bad["defective"] / sum(told_bad.values()) if told_bad and sum(told_bad.values()) else None
    if decision is not None:
        threshold = {"value": decision.get("value"), "basis": decision.get("basis"),
                     "predicted_far": decision.get("predicted_far"), "far_interval": decision.get("far_interval")}
    return {"auroc": {"overall": metrics.get("auroc"), **metrics.get("auroc_per_defect", {})},
            "point_auroc": metrics.get("point_auroc"),
            "flagged": {"defective": metrics.get("detection_rate"), "good": metrics.get("false_alarm_rate"),
                        "n_good": confusion.get("tn", 0) + confusion.get("fp", 0), "good_rejected": rejected,
                        "defective_told": found},
            "threshold": threshold, "point_score": summary.get("point_score"), "aggregate": summary.get("aggregate"),
            "rays": summary.get("rays") is not None, "seconds_per_scan": summary.get("seconds_per_scan"),
            "calibration_seconds": summary.get("calibration_seconds"),
            "alpha": summary.get("alpha")}


def point_maps(model_path, data_path, split="test", fields=False, neighbours=()):
    """Per-point scores of a collection's scans under a calibrated model (``inspection.Inspector`` with the model's
    stored calibration, as ``score`` computes them).

    Returns
    -------
    scans : list of datasets.Scan
    results : list of dict
        Per scan: ``score`` (float), ``point_scores`` ((m_i,) array: the points' own scores), ``map`` ((m_i,)
        array: the anomaly map's values, :func:`inspection.maps.map_values`), with ``neighbours`` (a sequence of
        patch sizes) ``maps`` ({patch size: (m_i,) array}, the same map at each) and ``patch_maps`` (the same
        without the rays' evidence) and, with ``fields``, ``field``
        (the projected stochastic field).
    """
    from datasets import ScanCollection

    from inspection.maps import map_values

    insp = _inspector(model_path)
    with ScanCollection(data_path) as c:
        scans = c.read_many(c.select(split=split))
    results = []
    for s in scans:
        r = insp.inspect(s)
        settings = insp.for_scan(s).settings_
        one = {"score": float(r.score), "point_scores": np.asarray(r.full(r.point_scores)),
               "map": r.full(map_values(settings, r.scored(s), r)[0])}
        if neighbours:
            one["maps"] = {k: r.full(map_values(settings, r.scored(s), r, k)[0]) for k in neighbours}
            one["patch_maps"] = {k: r.full(map_values(settings, r.scored(s), r, k, rays=False)[0])
                                 for k in neighbours}
        if fields:
            one["field"] = r.field
        results.append(one)
    return scans, results


def patch_map(points, values):
    """``values`` (m,) of a scan's ``points`` as the toolkit's anomaly maps show its residuals: each point's root mean
    square over its patch of nearest points (:func:`inspection.maps.patch_residuals`, the maps' patch size)."""
    from inspection.maps import patch_residuals

    return patch_residuals(points, values)


def map_neighbours():
    """The anomaly maps' default patch size, in points (``inspection.maps.MAP_NEIGHBOURS``)."""
    from inspection.maps import MAP_NEIGHBOURS

    return MAP_NEIGHBOURS


def calibration_settings(model_path):
    """How a calibrated model scores: ``point_score``, ``aggregate``, ``noise`` (the floor used: the calibration's or
    the model's own), ``lengthscale`` (the model's kernel lengthscale), ``alpha``."""
    from inspection import load_model_handle

    handle = load_model_handle(model_path)
    cal = handle.calibration
    settings = _inspector(model_path).settings_
    return {"point_score": settings.point_score, "aggregate": settings.aggregate, "alpha": cal.alpha,
            "noise": settings.noise if settings.noise is not None else handle.model.noise,
            "lengthscale": handle.model.lengthscale}


def calibration_scores(model_path):
    """The calibrated model's good calibration scores by role: ``{'held-back': (n_h,), 'fold': (n_f,),
    'cross-fitted': (n_c,)}``."""
    from inspection import read_calibration

    cal = read_calibration(model_path)
    roles = np.array(cal.roles or ["held-back"] * len(cal.scores))
    scores = np.asarray(cal.scores, dtype=np.float64)
    return {role: scores[roles == role] for role in ("held-back", "fold", "cross-fitted")}


def points_alone_threshold(model_path):
    """The threshold the calibrated model's point score alone would have: the same calibration scans' point scores
    (those its combination with the rays stored; the calibration scores themselves without rays) through the same
    threshold rule at the same alpha, what ``calibrate --no-rays`` gives on the same scans. A float."""
    from inspection import read_calibration
    from inspection.threshold import fit_threshold

    cal = read_calibration(model_path)
    rays = (cal.extra or {}).get("rays")
    points = cal.scores if not rays else rays["components"]["points"]
    return float(fit_threshold(points, cal.alpha, cal.roles or None).value)


def _inspector(model_path):
    """The Inspector of a calibrated model, with its stored calibration (the per-scan job's, as ``score`` builds
    it)."""
    from inspection import calibrated_inspector, load_model_handle

    return calibrated_inspector(load_model_handle(model_path))


def fit_inspector(model_path, data_path, progress=False):
    """``inspection.Inspector(model).fit(collection)`` at the defaults: a calibrated inspector of a trained model on
    its training collection (not written to the model file)."""
    from datasets import ScanCollection
    from inspection import Inspector, load_model_handle

    handle = load_model_handle(model_path)
    with ScanCollection(data_path) as c:
        return Inspector(handle.model, verbose=progress).fit(c)


@contextmanager
def every_point_scored():
    """Within it every scan is scored on all its points (``inspection.resolution.SAMPLE_BELOW`` 0), as before dense
    scans were thinned to the training density: the latency suite's "before"."""
    from inspection import resolution

    kept, resolution.SAMPLE_BELOW = resolution.SAMPLE_BELOW, 0.0
    try:
        yield
    finally:
        resolution.SAMPLE_BELOW = kept


def timed_inspect(inspector, scan):
    """One scan through ``inspector.inspect``: (score, the scored points' scores (k,), timings): the seconds of its
    stages (``Inspector.inspect``'s: sample, load, projection, field, grazing, stray, reference, aggregate, rays,
    combine), ``total`` (the call), ``map`` (then the anomaly map of every point, what a PLY map shows) and
    ``points_scored``."""
    from inspection.maps import map_values

    timings = {}
    t0 = time.perf_counter()
    result = inspector.inspect(scan, timings=timings)
    timings["total"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    result.full(map_values(inspector.for_scan(scan).settings_, result.scored(scan), result)[0])
    timings["map"] = time.perf_counter() - t0
    timings["points_scored"] = len(result.point_scores)
    return float(result.score), np.asarray(result.point_scores), timings


def defect_projection(model_path, data_path, split="test"):
    """How far a calibrated model's projection follows a defect: :func:`field_terms_by_code` of the scans of
    ``split`` under the model file's stored calibration.

    Raises
    ------
    ValueError
        A model calibrated with alignment or a product family's model (their scans are moved before projection,
        which this measurement does not do), or one without a per-location reference.
    """
    from datasets import ScanCollection

    insp = _inspector(model_path)
    if insp.settings_.align or getattr(insp.model, "family", None) is not None or insp.reference_ is None:
        raise ValueError(f"{model_path}: calibrated with alignment, a family's model, or no reference: not measured")
    with ScanCollection(data_path) as c:
        scans = c.read_many(c.select(split=split))
    return field_terms_by_code(insp, scans)


def field_terms_by_code(inspector, scans):
    """Every scan of ``scans`` scored with the field's term alone (``'distance'``, z_d) twice, once with the code
    projected from the whole scan (what the inspection does) and once with the code projected from the scan's good
    points alone (its ``point_labels`` == 0: a projection no defect can pull, which a scan does not come with), the
    field read at every point each time against the fitted ``inspector``'s per-location reference; beside it the same
    field term without the field's own variance in its denominator (``no_variance``: the reference's spread, the noise
    and the grazing term alone, the stochastic field's knowledge of where it is unsure left out) and the good points'
    term alone (``'surface'``, z_s). Each aggregated as the inspector aggregates (stray points left out),
    without the rays. The scans must lie in the model's frame (no alignment, no family sizing).

    Returns
    -------
    list of dict
        Per scan: ``name``, ``label``, ``defect``, ``own``, ``clean``, ``no_variance``, ``surface`` (per-scan scores; for a
        good scan, or one without labelled points, ``clean`` is ``own``), and for a defective scan with labelled
        points ``defect_own`` / ``defect_clean``: the median z_d at its defect points under each code.
    """
    from inspection.aggregates import aggregate
    from inspection.evidence import field_for, gather_evidence, kept_points
    from inspection.reference import REFERENCE_QUANTITY, field_quantity
    from inspection.scores import noise_floor, reference_scores

    settings, reference = inspector.settings_, inspector.reference_
    out = []
    for s in scans:
        ev = gather_evidence(inspector.model, s, quantity=REFERENCE_QUANTITY, projection=settings.projection)
        noise = noise_floor(ev.field, settings.noise)

        def field_term(value, variance):
            return reference_scores(reference, "distance", ev.points, value, variance, noise, ev.grazing, ev.normals)

        keep = kept_points(ev.stray, len(ev.points))
        own = field_term(ev.value, ev.variance)
        surface = reference_scores(reference, "surface", ev.points, ev.value, ev.variance, noise, ev.grazing,
                                   ev.normals)
        one = {"name": s.name, "label": s.label, "defect": s.defect, "own": aggregate(own[keep], settings.aggregate),
               "surface": aggregate(surface[keep], settings.aggregate),
               "no_variance": aggregate(field_term(ev.value, np.zeros_like(ev.variance))[keep], settings.aggregate)}
        one["clean"] = one["own"]
        labels = s.point_labels
        if s.label != "good" and labels is not None and np.any(labels) and np.count_nonzero(labels == 0) >= 3:
            good = np.asarray(labels) == 0
            field = field_for(inspector.model, ev.points[good], None if ev.normals is None else ev.normals[good],
                              settings.projection)
            clean = field_term(*field_quantity(field, ev.points, REFERENCE_QUANTITY, with_variance=True))
            one["clean"] = aggregate(clean[keep], settings.aggregate)
            one["defect_own"], one["defect_clean"] = float(np.median(own[~good])), float(np.median(clean[~good]))
        out.append(one)
    return out


def coverage_figures(run_dir, data_path):
    """What a scored run's calibrated model (``run_dir/model.pt``) says of coverage (issue 48): ``on_covered``
    {defective test scan name: whether at least half of its labelled defect points lie on surface the good scans
    covered, at the default coverage radius (:func:`inspection.coverage.covered_points`)}, and the run's
    ``threshold``, ``far_interval``, ``alpha`` and ``heldback_names``."""
    from datasets import ScanCollection
    from inspection import calibrated_inspector, load_model_handle
    from inspection.coverage import COVERAGE_LENGTHSCALES, coverage_radius, covered_points

    handle = load_model_handle(Path(run_dir) / "model.pt")
    insp = calibrated_inspector(handle)
    radius = coverage_radius(insp.model, COVERAGE_LENGTHSCALES)
    on_covered = {}
    with ScanCollection(data_path) as c:
        for scan in c.read_many(c.select(split="test", label="defective")):
            mask = np.zeros(0, bool) if scan.point_labels is None else scan.point_labels.astype(bool)
            if mask.any():
                covered = covered_points(insp.reference_, scan.points[mask], scan.normals[mask], radius)
                on_covered[str(scan.name)] = bool(covered.mean() >= 0.5)
    return {"on_covered": on_covered, "threshold": float(insp.threshold_),
            "far_interval": [float(v) for v in insp.decision_threshold_.far_interval], "alpha": float(insp.alpha),
            "heldback_names": list(handle.heldback_names)}


def proposed_views(model_path, data_path, n_views, split="test"):
    """The sensor positions (n, 3), model frame, that ``nsspr-inspect coverage`` proposes for the scans of ``split``
    of ``data_path`` under the calibrated model file (:func:`inspection.coverage_job.coverage_plan`)."""
    from inspection.coverage_job import coverage_plan

    plan = coverage_plan(model_path, data_path, n_views, split=split)
    return np.array([v.position for v in plan.views]).reshape(-1, 3)


def candidate_directions(n):
    """(n, 3) unit vectors evenly over the sphere: the candidate view directions of the coverage planner
    (:func:`inspection.coverage_views.sphere_directions`)."""
    from inspection.coverage_views import sphere_directions

    return sphere_directions(n)


def default_folds(n_train):
    """The fold models the trainer adds by default to a model of ``n_train`` training scans of one part
    (:func:`autodecoder.latent.folds.default_folds`)."""
    from autodecoder.latent.folds import default_folds as folds

    return folds(n_train)


def scan_regions(model_path, data_path, out_dir, split="test", progress=False):
    """Every scan of ``split`` of a model's training collection, calibrated the README's way on a copy of the model
    (``out_dir/model.pt``), with its anomaly map and defect regions (:mod:`inspection.regions`) whatever its verdict.

    Returns
    -------
    list of dict
        Per scan: ``name``, ``label``, ``defect``, ``verdict``, ``points`` (m, 3, model frame), ``point_labels``
        (m,) or None, ``point_deviation`` (m,) or None (the truth, in the scans' file units), ``areas`` (m,) (each
        point's area as the regions measure it, file units), ``map`` (m,), ``region_ids`` (m,) (-1: none; None: no
        region level) and ``regions`` (``DefectRegion.row()`` dicts, file units).
    """
    from datasets import ScanCollection
    from inspection.job import calibrate, inspect_scan
    from inspection.regions import point_areas

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    model = out_dir / "model.pt"
    if not model.exists():
        shutil.copyfile(model_path, out_dir / "model.tmp.pt")
        calibrate(out_dir / "model.tmp.pt", data_path, progress=progress)
        (out_dir / "model.tmp.pt").replace(model)
    insp = _inspector(model)
    runs = []
    with ScanCollection(data_path) as c:
        scale = float(c.frame.scale)
        for i, scan in enumerate(s for s in c if s.split == split):
            out = inspect_scan(insp, scan, i, maps="all", maps_dir=out_dir / "maps")
            deviation = getattr(scan, "point_deviation", None)
            runs.append({"name": scan.name, "label": scan.label, "defect": scan.defect,
                         "verdict": out["row"]["verdict"], "points": np.asarray(scan.points, dtype=np.float64),
                         "point_labels": scan.point_labels,
                         "point_deviation": None if deviation is None else np.asarray(deviation) / scale,
                         "areas": point_areas(scan.points) / scale ** 2, "map": out.get("point_map"),
                         "region_ids": out.get("region_ids"), "regions": out.get("defects", [])})
    return runs
