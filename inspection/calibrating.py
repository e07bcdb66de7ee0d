"""The calibration procedure: from a model, good scans and the settings to the fitted state an inspector scores with.

:func:`calibrate` is what :meth:`inspection.Inspector.fit` (and so ``nsspr-inspect calibrate``) runs. For each part
type of the model (:func:`inspection.selection.model_parts`; one for most models):

1. the good scans are sorted into calibration, reference and surface scans (:func:`inspection.selection.select_scans`)
   and the 'auto' settings decided (:meth:`inspection.config.InspectionConfig.decided`, :func:`fit_alignment`);
2. with registration, the training scans are moved into one common pose, the target of every later registration;
3. the per-location reference is built from the training scans, each projected as a new scan is
   (:func:`fit_reference`);
4. the calibration scans are the held-back scans, plus the training scans scored out of sample: by the fold models
   that never saw them (:func:`fold_evidence`), else cross-fitted (projected without their own code, compared with
   the reference without their points);
5. on these scans' residuals the reference's noise model (:func:`fit_noise_model_on`) and the joint score's term
   variances (:func:`fit_term_variances_on`) are fitted, and they are scored (:mod:`inspection.scoring`); with rays
   the rays are weighed on them (:func:`calibration_scores`).

It returns an :class:`inspection.calibration.FittedState` per part type: the threshold drawn from its scores is the
estimator's (:mod:`inspection.threshold`, at the estimator's ``alpha``).
"""
from dataclasses import dataclass, replace

import numpy as np

from datasets.validation import points_and_normals

from .calibration import FittedState
from .coverage import decide_coverage
from .evidence import kept_points, scan_name
from .loading import reading_of
from .member_surface import fit_member_spread
from .reference import REFERENCE_QUANTITY, LocalReference, fit_noise_model
from .regions import good_map_maxima
from .scores import POINT_SCORES, WEIGHED_SCORES, fit_term_variances, noise_floor, reference_terms
from .scoring import aligned, scan_evidence, score_evidence, sized, thinned
from .selection import model_parts, select_scans

# points of the good scans' own surface kept in a reference (LocalReference.surface), at most: every training scan of
# a 64-view template collection (~180,000 points) or of 32 synthetic scans of 4,000 points fits
SURFACE_MAX_POINTS = 240000
# a training scan scored against the reference without its own points takes the field's term for the good points'
# term at its points farther from the other good scans' surface than this quantile of the held-back scans' points
# are from all of them (uncovered_points)
COVERAGE_QUANTILE = 0.99


@dataclass
class CalibrationFit:
    """What :func:`calibrate` returns.

    Attributes
    ----------
    state : FittedState or None
        The model's calibration (None for a model of several part types).
    parts : dict of str -> FittedState, or None
        A model of several part types: each part's calibration, on its own good scans.
    reading : dict or None
        How the collection calibrated on had read its scanner files (:func:`inspection.loading.reading_of`).
    fingerprint : str
        That collection's fingerprint ('' for scans given as a list).
    """

    state: FittedState = None
    parts: dict = None
    reading: dict = None
    fingerprint: str = ""


def calibrate(model, good_scans, config, reference_scans=None, split=None, cross_fit=True, verbose=False):
    """Calibrate ``model`` on good scans: the procedure of the module docstring.

    Parameters
    ----------
    model : latent model, field or callable
        :func:`inspection.evidence.field_for`; scans in its frame.
    good_scans : datasets.ScanCollection or sequence of Scan (or (m, 3) arrays)
        Good scans. A collection: its good scans, and its training scans count as the model's only when it is the
        model's training collection (same fingerprint); a sequence: scans named like the model's training scans are
        taken to be them.
    config : InspectionConfig
        The settings (validated here).
    reference_scans : sequence of Scan, optional
        Good scans for the per-location reference instead of the training scans among ``good_scans``.
    split : str, optional
        Calibrate on this split's good scans only.
    cross_fit : bool
        Also calibrate on the training scans (by the fold models, else cross-fitted).
    verbose : bool
        Progress bars.

    Returns
    -------
    CalibrationFit
    """
    config = config.validated()
    scans, training_given, origins_everywhere = _good_scans(good_scans, model)
    # a public layout's collection: its good scans are views rendered from clean templates
    provenance = getattr(good_scans, "provenance", None)
    rendered = isinstance(provenance, dict) and bool(provenance.get("template_views"))
    fit = CalibrationFit(reading=reading_of(good_scans),  # files scored later are read the same way
                         fingerprint=good_scans.fingerprint() if hasattr(good_scans, "fingerprint") else "")
    parts = model_parts(model)
    if not parts:
        selection = select_scans(model, scans, reference_scans, split, None, training_given)
        fit.state = calibrate_selection(model, selection, config, origins_everywhere, cross_fit, rendered, verbose)
        return fit
    fit.parts = {}
    for part in parts:
        selection = select_scans(model, scans, reference_scans, split, part, training_given)
        if not selection.calibration:
            raise ValueError(f"no good calibration scans of part {part!r} (the model was trained on parts {parts} "
                             f"and calibrates each on its own scans)")
        fit.parts[part] = calibrate_selection(model, selection, config, origins_everywhere, cross_fit, rendered,
                                              verbose, f" {part}")
    return fit


def calibrate_selection(model, selection, config, origins_everywhere, cross_fit=True, rendered=False, verbose=False,
                        desc=""):
    """The :class:`FittedState` of one part type from its good scans sorted into their roles (``selection``, an
    :class:`inspection.selection.ScanSelection`): steps 1-5 of the module docstring. ``config`` validated;
    ``origins_everywhere``: every scan of the good scans' source records a sensor origin (rays 'auto');
    ``rendered``: the good scans are views rendered from clean templates (``level_rendered``); ``desc`` names
    the part in the progress bars."""
    settings = _decided(model, selection, config, origins_everywhere)
    selection = _sized_selection(model, selection)
    settings, selection, aligner, note = fit_alignment(settings, selection, verbose)
    needs_reference = POINT_SCORES[settings.point_score].reference
    level_rendered = rendered or all(isinstance(getattr(s, "extra", None), dict) and bool(s.extra.get("template"))
                                     for s in selection.calibration)
    reference, crossed = None, []
    if needs_reference:
        reference, crossed = fit_reference(model, _progress(selection.reference, verbose, f"reference{desc}"),
                                           selection.surface, settings)
    calibration = (thinned(model, s)[0] for s in _progress(selection.calibration, verbose, f"calibrate{desc}"))
    held = [scan_evidence(model, aligned(aligner, s)[0] if settings.align is True else s, i, settings, reference)
            for i, s in enumerate(calibration)]  # dense scans at the training density, as new scans are scored
    coverage, uncovered_share = decide_coverage(settings.coverage, reference, held)
    settings = replace(settings, coverage=coverage)
    folded = fold_evidence(model, selection, settings, verbose, desc) if cross_fit else None
    if folded is not None:  # the fold models' out-of-sample scores replace the cross-fitted ones
        crossed, crossed_references, role = folded[0], folded[1], "fold"
    else:  # training scans cross-fitted: scored by the main model against the reference without their points
        crossed = crossed if cross_fit and needs_reference else []
        crossed_references = [reference.without(j) for j in range(len(crossed))]
        role = "cross-fitted"
    if settings.rays and any(g.origin is None for g in crossed):
        crossed, crossed_references = [], []
    goods = held + crossed
    references = [reference] * len(held) + crossed_references
    uncovered = [None] * len(held)
    if needs_reference:
        kappa, lam = fit_noise_model_on(goods, references, settings.noise)
        for reference_j in references:
            reference_j.variance_scale, reference_j.grazing_scale = kappa, lam
        if crossed:
            uncovered += uncovered_points(held, reference, crossed, crossed_references)
    terms = [None] * len(goods)
    if settings.point_score in WEIGHED_SCORES:
        terms = fit_term_variances_on(goods, references, uncovered, settings.noise)
    results = [score_evidence(good, reference_j, settings, uncovered=out, terms=t, surface=reference)
               for good, reference_j, out, t in zip(goods, references, uncovered, terms)]
    how = selection.how
    if crossed:
        how += (f" and {len(crossed)} training scans scored by fold models that never saw them" if role == "fold"
                else f" and {len(crossed)} training scans cross-fitted")
    if uncovered_share is not None and coverage:
        how += (f"; scored over covered surface (the held-back scans have {100 * uncovered_share:.1f} % of their "
                f"points where no training scan saw the surface)")
    scores, combination = calibration_scores(results, settings)
    maxima = good_map_maxima(results, references, settings, combination) if needs_reference else None
    return FittedState(settings, scores, [g.name for g in goods], ["held-back"] * len(held) + [role] * len(crossed),
                       how, reference, combination, aligner, note, level_rendered, maxima)


def _decided(model, selection, config, origins_everywhere):
    """``config`` with 'auto' decided for this selection (:meth:`InspectionConfig.decided`), after checking that
    the selection can calibrate it: calibration scans, the reference scans its point score needs, sensor origins
    on every calibration scan with rays (a ValueError saying what to give otherwise)."""
    if not selection.calibration:
        held = list(getattr(model, "calibration_names", None) or [])
        hint = (f"the model's held-back scans (e.g. {held[0]!r}) are not among them: pass the training collection "
                f"itself or include them" if held else "give good scans it did not train on (a validation split)")
        raise ValueError(f"no good scans the model did not train on to calibrate with; {hint}")
    reference = selection.reference
    if config.point_score != "auto" and POINT_SCORES[config.point_score].reference and not reference:
        raise ValueError(f"point_score {config.point_score!r} needs the model's training scans (among the good "
                         f"scans, or as reference_scans) for its per-location reference")
    with_origins = all(getattr(s, "sensor_origin", None) is not None for s in [*selection.calibration, *reference])
    settings = config.decided(model, bool(reference), with_origins and origins_everywhere)
    if settings.rays:
        missing = [scan_name(s, i) for i, s in enumerate(selection.calibration)
                   if getattr(s, "sensor_origin", None) is None]
        if missing:
            raise ValueError(f"{len(missing)} of {len(selection.calibration)} calibration scans have no sensor "
                             f"origin (e.g. {missing[0]!r}); the ray score needs where the sensor was (scanner "
                             f"files: a <stem>.json sidecar {{\"sensor_origin\": [x, y, z]}}); calibrate "
                             f"without rays")
    return settings


def _sized_selection(model, selection):
    """Every scan of ``selection`` through :func:`inspection.scoring.sized` (each scan once, the same copy wherever
    it is used)."""
    if getattr(model, "family", None) is None:
        return selection
    moved = {}
    for s in [*selection.calibration, *selection.reference, *selection.surface]:
        if id(s) not in moved:
            moved[id(s)] = sized(model, s)
    return replace(selection, calibration=[moved[id(s)] for s in selection.calibration],
                   reference=[moved[id(s)] for s in selection.reference],
                   surface=[moved[id(s)] for s in selection.surface])


def fit_alignment(settings, selection, verbose=False):
    """Decide ``align='auto'`` (the training scans' pose spread, :func:`inspection.align.pose_spread`) and, when
    scans are registered, move the training scans into one common pose (each registered onto the others,
    :func:`inspection.align.register_group`): the target of every later registration and the scans the
    per-location reference is built from.

    Returns
    -------
    settings : InspectionConfig
        With ``align`` True or False.
    selection : ScanSelection
        With its reference and surface scans registered (as given without registration).
    aligner : inspection.align.Aligner or None
        The registration target (with registration).
    note : str
        One line when 'auto' decided to register ('' otherwise).
    """
    note = ""
    reference = selection.reference
    if settings.align == "auto":
        from datasets.registration import registration_ticks

        from .align import AUTO_RATIO, pose_spread

        with registration_ticks("pose: placed by hand?", verbose and bool(reference)) as tick:
            spread = pose_spread(reference, tick=tick) if reference else 1.0
        settings = replace(settings, align=bool(spread > AUTO_RATIO))
        if settings.align is True:
            note = (f"the training scans' poses spread (registered onto the others, their residuals fall by a "
                    f"median {100 * (1 - 1 / spread):.0f} %): every scan is registered first (calibrate --no-align "
                    f"turns it off)")
    if settings.align is not True:
        return settings, selection, None, note
    if not reference:
        raise ValueError("align=True registers every scan onto the model's good training scans: include them "
                         "among the good scans (calibrate on the model's training collection)")
    from datasets.registration import registration_ticks

    from .align import Aligner, register_group

    surface = selection.surface or reference
    with registration_ticks("common pose", verbose) as tick:
        moved = dict(zip(map(id, surface), register_group(surface, tick=tick)))
    selection = replace(selection, reference=[moved.get(id(s), s) for s in reference],
                        surface=[moved[id(s)] for s in surface])
    return settings, selection, Aligner.from_scans(selection.surface), note


def fit_reference(model, scans, surface_scans, settings, max_points=60000, seed=0):
    """The per-location reference of good scans, each projected as a test scan would be (a training scan without
    starting from its own trained code), with the points and normals of ``surface_scans`` (empty: the projected
    scans themselves) as the good scans' own surface (:meth:`LocalReference.surface`).

    Returns
    -------
    reference : LocalReference
        Its points subsampled to ``max_points`` (seeded), with how much the good scans' members differ in shape
        (:func:`inspection.member_surface.fit_member_spread`); its noise model and term variances not yet fitted.
    evidence : list of ScanEvidence
        The scans' evidence (for cross-fitting).
    """
    goods = [scan_evidence(model, s, i, settings, exclude_own_code=True) for i, s in enumerate(scans)]
    if not goods:
        raise ValueError("the per-location reference needs at least one good scan, got none")
    reference = LocalReference.from_values([(g.points, g.value) for g in goods], max_points=max_points, seed=seed,
                                           quantity=REFERENCE_QUANTITY)
    names = [g.name for g in goods]
    if not surface_scans:  # the projected scans themselves, each its own owner
        surface_scans = [_Named(g.name, g.points, g.normals) for g in goods]
    reference.surface_points, reference.surface_owners, reference.surface_normals = _surface_points(
        surface_scans, names, seed)
    reference.member_spread = fit_member_spread(reference, goods, seed)
    return reference, goods


def fold_evidence(model, selection, settings, verbose=False, desc=""):
    """The training scans' evidence under the model's fold models (:mod:`autodecoder.latent.folds`): each
    reference scan projected by the fold model that never trained on it, and compared with that fold model's
    per-location reference over every other reference scan (all of them projected by the fold model, as the
    model's own reference is by the model, the scored scan's points left out). Nothing in such a score has seen
    the scan: it is scored as a new scan is, by a model trained on fewer scans, against a reference of one scan
    fewer. (A fold model's reference over its own training scans alone rests on fewer scans and scored good
    scans higher than the main model scores new ones: docs/results.md, issue 27.)

    Returns (evidence list, reference per evidence; None for a point score without one), or None when the model has
    no fold models or none of the scans they score is among the reference scans."""
    folds = list(getattr(model, "calibration_folds", None) or [])
    if not folds or not selection.reference:
        return None
    names = [getattr(s, "name", None) for s in selection.reference]
    needs_reference = POINT_SCORES[settings.point_score].reference
    goods, references = [], []
    for j, fold in enumerate(folds):
        scored = [i for i, n in enumerate(names) if n in set(fold.scored_names)]
        if not scored:
            continue
        if set(fold.model.train_names) & {names[i] for i in scored}:  # read_folds refuses such a file
            raise ValueError(f"calibration fold {j + 1} was trained on a scan it scores")
        if needs_reference:
            reference, evidence = fit_reference(fold.model,
                                                _progress(selection.reference, verbose, f"fold {j + 1}{desc}"),
                                                selection.surface, settings)
            references += [reference.without(i) for i in scored]
        else:  # (with align, the reference scans come registered onto each other)
            evidence = {i: scan_evidence(fold.model, selection.reference[i], i, settings) for i in scored}
            references += [None] * len(scored)
        goods += [evidence[i] for i in scored]
    return (goods, references) if goods else None


def fit_noise_model_on(goods, references, noise=None):
    """The reference's noise model, (``variance_scale``, ``grazing_scale``):
    :func:`inspection.reference.fit_noise_model` on the residuals of good scans' evidence (``goods``) against the
    reference each is scored with (the grazing term only when every one of them has a grazing factor); ``noise``: the
    settings' noise floor (:func:`inspection.scores.noise_floor`)."""
    residuals, base, field_var, noise_var, grazing = [], [], [], [], []
    for good, reference in zip(goods, references):
        m_ref, s_ref = reference.stats(good.points)
        residuals.append(good.value - m_ref)
        base.append(s_ref**2)
        field_var.append(good.variance)
        noise_var.append(np.full(len(good.points), noise_floor(good.field, noise) ** 2))
        grazing.append(good.grazing)
    with_grazing = all(g is not None for g in grazing)
    return fit_noise_model(np.concatenate(residuals), np.concatenate(base), np.concatenate(field_var),
                           np.concatenate(noise_var), np.concatenate(grazing) if with_grazing else None)


def fit_term_variances_on(goods, references, uncovered, noise=None):
    """Weigh the joint score's two terms by what the calibration scans show
    (:func:`inspection.scores.fit_term_variances`, on the points each scan's score counts,
    :func:`inspection.evidence.kept_points`), and set the variances on every reference they are scored against.
    These scans are the ones the threshold is drawn from: held back, or scored by a fold model or cross-fitted, none
    of them part of the reference it is compared with. ``uncovered``: per scan, (m,) bool or None
    (:func:`uncovered_points`); ``noise``: the settings' noise floor. Returns each scan's two terms (computed once)."""
    terms = [reference_terms(reference, good.points, good.value, good.variance, noise_floor(good.field, noise),
                             good.grazing, good.normals, out, good.field)
             for good, reference, out in zip(goods, references, uncovered)]
    kept = [kept_points(good.stray, len(good.points)) for good in goods]
    variances = fit_term_variances(np.concatenate([t[0][k] for t, k in zip(terms, kept)]),
                                   np.concatenate([t[1][k] for t, k in zip(terms, kept)]))
    for reference in {id(r): r for r in references}.values():
        reference.term_variances = variances
    return terms


def uncovered_points(held, reference, crossed, crossed_references, quantile=COVERAGE_QUANTILE):
    """For each training scan scored against the reference without its own points, the (m,) bool of its points
    farther from that reference's surface than ``quantile`` of the held-back scans' points (those their scores
    count, :func:`inspection.evidence.kept_points`) are from the whole reference's surface.

    Why: left out of the reference, a training scan's surface that no other good scan saw has no good points near it,
    and its good-points term there reads as far as missing or foreign material (with 8 training scans, 6-20 % of a
    scan's points 9-10 reference spacings off: docs/results.md, issue 27), while a new scan meets the reference of
    every training scan. The held-back scans are new scans: how far their points lie from the good scans' surface
    says how far a new good scan's do. Points of a left-out scan beyond that lie in a hole the leaving out opened,
    not one good scans have: there its joint score takes the field's term (which saw the scan) for the good points'
    term. Its field term and every other point count as before (leaving the points out instead also dropped the
    grazing border a new scan has, and calibrated too low).

    A face of a thin wall that only the left-out scan saw, nearer than the reach, needs no mark here: the joint
    score takes the field's term wherever no good scan of the reference it is compared with saw the point's side,
    for every scan (:func:`inspection.scores.reference_terms`).

    Parameters
    ----------
    held : list of ScanEvidence
        The held-back scans.
    reference : LocalReference
        Over every reference scan.
    crossed : list of ScanEvidence
        The training scans scored without their own points.
    crossed_references : list of LocalReference
        The reference each of them is compared with.
    """
    distances = [reference.surface_distance(g.points[kept_points(g.stray, len(g.points))]) for g in held]
    reach = float(np.quantile(np.concatenate(distances), quantile)) if distances else np.inf
    return [ref_j.surface_distance(g.points) > reach for g, ref_j in zip(crossed, crossed_references)]


def calibration_scores(results, settings):
    """The calibration scores (n,) of the good calibration scans' :class:`inspection.scoring.ScanResult` and the
    rays' weighing (an :class:`inspection.combine.Combination`, or None without rays).

    Without rays the scores are the point scores' aggregates. With rays the rays are weighed by these scans' rays
    (:mod:`inspection.ray_calibration`) and the scores are the combined scores, each scan's ray evidence computed
    leave-one-out (:meth:`inspection.combine.Combination.calibration_scores`)."""
    results = list(results)
    if not results:
        raise ValueError("calibration needs at least one good scan, got none")
    points = [r.components["points"] for r in results]
    if not settings.rays:
        return np.asarray(points, dtype=np.float64), None
    from .combine import Combination

    scale = getattr(results[0].field, "lengthscale", None) if results[0].field is not None else None
    combination = Combination.fit(points, [r.rays for r in results], scale, settings.ray_options["aggregate"])
    return combination.calibration_scores(), combination


def site_scans(model, good_scans):
    """The good scans of the inspection's own sensor that set a threshold's level
    (:meth:`inspection.Inspector.fit_level`), as a list; a ValueError when there are none or some are scans the
    model trained on (their scores would be optimistic)."""
    scans = list(good_scans)
    if not scans:
        raise ValueError("fit_level needs at least one good scan of the inspection's own sensor, got none")
    trained = set(str(n) for n in (getattr(model, "train_names", None) or []))
    seen = [scan_name(s, i) for i, s in enumerate(scans) if getattr(s, "name", None) in trained]
    if seen:
        raise ValueError(f"{len(seen)} of the {len(scans)} scans are scans the model trained on (e.g. "
                         f"{seen[0]!r}): their scores would be optimistic; give good scans it never saw")
    return scans


@dataclass
class _Named:
    """Points (m, 3) and normals (m, 3) or None under a scan name (the projected reference scans as surface scans)."""

    name: str
    points: np.ndarray
    normals: np.ndarray = None


def _surface_points(scans, reference_names, seed=0):
    """The points (n, 3) of good scans, their owners (n,): the index in ``reference_names`` of a scan named like one
    of them, else -1 - its own index (never left out), and their normals (n, 3) (None when a scan has none).
    Seeded subsample to ``SURFACE_MAX_POINTS``."""
    points, owners, normals = [], [], []
    for i, scan in enumerate(scans):
        p, n = points_and_normals(scan)
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        name = getattr(scan, "name", None)
        owners.append(np.full(len(p), reference_names.index(name) if name and name in reference_names else -1 - i))
        points.append(p)
        normals.append(None if n is None else np.asarray(n, dtype=np.float64).reshape(-1, 3))
    if not points:
        raise ValueError("surface_scans: no scans given")
    points, owners = np.concatenate(points), np.concatenate(owners)
    normals = None if any(n is None for n in normals) else np.concatenate(normals)
    if len(points) > SURFACE_MAX_POINTS:
        keep = np.sort(np.random.default_rng(seed).choice(len(points), SURFACE_MAX_POINTS, replace=False))
        points, owners, normals = points[keep], owners[keep], None if normals is None else normals[keep]
    return points.astype(np.float32), owners, None if normals is None else normals.astype(np.float32)


def _good_scans(good_scans, model):
    """(scans, whether their training-named scans are the model's training scans, whether every scan of their
    source records a sensor origin) from a collection or a sequence of scans."""
    from datasets import ScanCollection

    if isinstance(good_scans, ScanCollection):
        coll = good_scans
        fingerprint = getattr(model, "fingerprint", "") or ""
        training = bool(fingerprint) and coll.fingerprint() == fingerprint
        # a public layout's collection has rendered template views with origins and test scans without: rays
        # calibrated on the views could not score its test scans, so 'auto' stays off there
        origins = all(m["sensor_origin"] is not None for m in coll.metadata())
        return coll.read_many(coll.select(label="good")), training, origins
    scans = list(good_scans)
    return scans, True, all(getattr(s, "sensor_origin", None) is not None for s in scans)


def _progress(items, verbose, desc):
    """``items``, with a progress bar when ``verbose``."""
    if not verbose:
        return items
    from tqdm import tqdm

    return tqdm(items, desc=desc, unit="scan")
