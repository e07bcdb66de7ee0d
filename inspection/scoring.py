"""One scan's score under an inspection's fitted state: its registration, evidence, point scores, aggregate and rays.

The functions :class:`inspection.Inspector` scores a scan with, and the calibration procedure
(:mod:`inspection.calibrating`) scores the good scans with, so that both score alike. Each takes the model, the
settings in force (an :class:`inspection.config.InspectionConfig` with its 'auto' settings decided) and the fitted
pieces it needs (the per-location reference, the registration, the rays' weighing) as arguments.
"""
from dataclasses import dataclass

import numpy as np
from sklearn.exceptions import NotFittedError

from datasets.validation import points_and_normals

from .aggregates import aggregate as aggregate_scores
from .coverage import MIN_COVERED_POINTS, Coverage, coverage_radius, covered_points
from .evidence import ScanEvidence, gather_evidence, kept_points, stage
from .family_range import FamilyRange, family_range
from .loading import signed_for_scoring
from .reference import REFERENCE_QUANTITY
from .resolution import EvidenceSample, evidence_sample, sampled_scan, training_spacing
from .scores import POINT_SCORES, noise_floor, point_scores, reference_scores


@dataclass
class ScanResult:
    """One scan's inspection: its anomaly score (higher = more anomalous) and per-point scores (m,).

    ``transform`` (4, 4) is the registration that moved the scan before it was scored (``align=True``; None
    otherwise); ``point_scores`` are in the scan's own point order either way. ``components`` holds the per-scan
    scores that make ``score``: ``{"points": ...}`` (the aggregate of the point
    scores), plus ``"rays"`` (the ray score: the aggregate of the rays' surprisals, nats) when rays are used; then
    ``rays`` is the :class:`~inspection.ray_evidence.RayEvidence` (its ``point_map`` is the per-point ray map), and
    once the calibration weighs the rays (:meth:`inspection.Inspector.inspect`, :func:`weigh_rays`)
    ``components["ray_nats"]`` is their evidence I (:mod:`inspection.ray_calibration`), ``ray_point_nats`` (m,) the
    same per point (what the anomaly map adds) and ``score`` the combination (:mod:`inspection.combine`). ``stray``
    (m,) bool marks the scan's stray returns, left out of the score's aggregate
    (:func:`inspection.evidence.kept_points`) and of the anomaly map's patches (None: none looked for).
    ``coverage`` (:class:`inspection.coverage.Coverage`, with a per-location point score and a field with a
    lengthscale) says which points lie on surface the good scans covered: ``score`` and ``components["points"]``
    count those (``components["points_all"]`` every point), the point scores and the maps every point.
    ``evidence``: the :class:`inspection.evidence.ScanEvidence` it was scored from (the defect regions measure it).
    ``sample``: for a scan much denser than the training scans, which of its points were scored at their density
    (:class:`inspection.resolution.EvidenceSample`); then every per-point array here (and ``evidence``) is over
    those points, and ``sample.full`` carries one to every point of the scan. None: every point was scored.
    ``family``: for a model of a family whose members differ, where the scan's member lies against the trained ones
    (:class:`inspection.family_range.FamilyRange`: outside, its verdict is 'uncertain'); None: not judged.
    """

    score: float
    point_scores: np.ndarray
    field: object = None
    components: dict = None
    rays: object = None
    transform: np.ndarray = None
    stray: np.ndarray = None
    ray_point_nats: np.ndarray = None
    coverage: Coverage = None
    evidence: ScanEvidence = None
    sample: EvidenceSample = None
    family: FamilyRange = None

    def scored(self, scan):
        """``scan`` (as given to the inspection) as it was scored: itself, or with ``sample`` its scored points only,
        in the order of every per-point array here."""
        return scan if self.sample is None else sampled_scan(scan, self.sample.kept)

    def full(self, values):
        """Per-point ``values`` over the scored points (``point_scores``, a map) for every point of the scan: as
        they are, or with ``sample`` each point's nearest scored point's (None stays None)."""
        return values if self.sample is None or values is None else self.sample.full(values)


def score_scan(model, scan, index, settings, reference=None, aligner=None, timings=None):
    """A scan registered as the settings say, projected and scored: a :class:`ScanResult` whose ``score`` is the
    point scores' aggregate (the rays, if scored, not yet weighed: :func:`weigh_rays`). A scan much denser than the
    model's training scans is scored on a random subset at their density (:mod:`inspection.resolution`; the
    result's ``sample``).

    Parameters
    ----------
    model : latent model, field or callable
        :func:`inspection.evidence.field_for`.
    scan : Scan, (points, normals) or (m, 3) array
        In the model's frame.
    index : int
        Its position in its batch (names a scan without a name).
    settings : InspectionConfig
        The settings in force ('auto' decided).
    reference : LocalReference or None
        The per-location reference (needed by the point scores with one: a NotFittedError without).
    aligner : inspection.align.Aligner or None
        The registration target (needed with ``settings.align is True``).
    timings : dict, optional
        Receives the seconds of each stage: ``sample``, ``align``, those of
        :func:`inspection.evidence.gather_evidence` and of :func:`score_evidence`.
    """
    if POINT_SCORES[settings.point_score].reference and reference is None:
        raise NotFittedError(f"point_score {settings.point_score!r} needs the per-location reference: call "
                             "fit(good_scans) with the model's training scans among them first")
    with stage(timings, "sample"):
        scan, sample = thinned(model, scan)
    scan, transform = registered(model, scan, settings.align, aligner, timings)
    result = score_evidence(scan_evidence(model, scan, index, settings, reference, timings=timings), reference,
                            settings, timings)
    result.transform, result.sample = transform, sample
    return result


def thinned(model, scan):
    """(``scan`` as it is scored under ``model``, its :class:`inspection.resolution.EvidenceSample` or None): a scan
    much denser than the model's training scans on a random subset at their density (:mod:`inspection.resolution`),
    any other as it is. New scans and the calibration's held-back scans are thinned alike."""
    sample = evidence_sample(points_and_normals(scan)[0], training_spacing(model))
    return (scan if sample is None else sampled_scan(scan, sample.kept)), sample


def registered(model, scan, align, aligner, timings=None):
    """(``scan`` as it is scored, the (4, 4) transform that moved it or None): onto the model's common frame for a
    model with one (:func:`sized`), then onto the good training scans by ``aligner`` when ``align`` is True."""
    transform = None
    if getattr(model, "family", None) is not None:
        with stage(timings, "align"):
            scan = sized(model, scan)
            transform = transform_of(scan)
    if align is True:
        with stage(timings, "align"):
            scan, transform = aligned(aligner, scan)
    return scan, transform


def sized(model, scan):
    """``scan`` registered onto the model's common frame, a family's size or the common pose of parts placed by
    hand (:meth:`autodecoder.latent.model.LatentModel.normalise`; a training scan onto the others); as it is for
    a model without one."""
    family = getattr(model, "family", None)
    return scan if family is None else family.normalise(scan)


def aligned(aligner, scan):
    """``scan`` registered by ``aligner`` (an :class:`inspection.align.Aligner`; None: a NotFittedError). Returns
    (the moved scan, the transform (4, 4))."""
    if aligner is None:
        raise NotFittedError("align=True registers scans onto the good training scans chosen by fit: call fit "
                             "first")
    if isinstance(scan, np.ndarray) or not hasattr(scan, "points"):  # bare points: moved, with their transform
        moved, _, transform = aligner.align(np.asarray(scan, dtype=np.float64).reshape(-1, 3))
        return moved, transform
    moved = aligner.align_scan(scan)
    extra = getattr(moved, "extra", None)
    if isinstance(extra, dict) and "align" in extra:
        return moved, extra["align"]
    return moved, aligner.transform(np.asarray(scan.points, dtype=np.float64))  # a scan-like without extra


def transform_of(scan):
    """The (4, 4) transform a registration recorded in a scan's ``extra['align']``, or None."""
    extra = getattr(scan, "extra", None)
    return extra.get("align") if isinstance(extra, dict) else None


def scan_evidence(model, scan, index, settings, reference=None, exclude_own_code=False, timings=None):
    """:func:`inspection.evidence.gather_evidence` of a scan (already registered) under the settings: the quantity
    the per-location point scores compare when the point score has a reference, the sensor origin required with
    rays. A scan whose reading leaves its normals' signs to the good surface gets them from ``reference``'s good
    scans first (:func:`inspection.loading.signed_for_scoring`: one reading of a file, whether it came from a
    collection or a folder). ``exclude_own_code``: a training scan is projected without its own trained code."""
    scan = signed_for_scoring(scan, reference)
    quantity = REFERENCE_QUANTITY if POINT_SCORES[settings.point_score].reference else None
    return gather_evidence(model, scan, index, quantity=quantity, projection=settings.projection,
                           need_origin=settings.rays, exclude_own_code=exclude_own_code, timings=timings)


def score_evidence(evidence: ScanEvidence, reference, settings, timings=None, uncovered=None, terms=None,
                   surface=None):
    """A :class:`ScanResult` of a scan's evidence against ``reference`` (components: points, rays).

    Parameters
    ----------
    evidence : ScanEvidence
    reference : LocalReference or None
        What the point scores with a reference compare with.
    settings : InspectionConfig
        The settings in force.
    timings : dict, optional
        Receives the seconds of the stages ``reference`` (the point scores), ``aggregate`` and ``rays``.
    uncovered : (m,) bool, optional
        A training scan's points where no other good scan has a surface
        (:func:`inspection.calibrating.uncovered_points`): there the joint score takes the field's term for the good
        points' term.
    terms : ((m,), (m,)), optional
        The joint score's two terms of these points, already computed (the calibration's term variances).
    surface : LocalReference, optional
        The reference whose good scans' surface the rays are tested against (default ``reference``).

    The rays' surface is where good parts have one, whoever scanned it: a training scan scored without its own
    points in the point score's reference (cross-fitted) keeps them in the rays' band and skim normals, as a new
    scan of its view meets them there. Without them, a face of a thin wall that only it saw borrows the other
    face's points and normals, and its rays there were accused (docs/results.md).
    """
    noise = noise_floor(evidence.field, settings.noise)
    with stage(timings, "reference"):
        if POINT_SCORES[settings.point_score].reference:
            values = reference_scores(reference, settings.point_score, evidence.points, evidence.value,
                                      evidence.variance, noise, evidence.grazing, evidence.normals, uncovered, terms,
                                      evidence.field)
        else:
            values = point_scores(evidence.field, evidence.points, kind=settings.point_score, noise=settings.noise)
    with stage(timings, "aggregate"):
        kept = kept_points(evidence.stray, len(values))
        score = aggregate_scores(values[kept], settings.aggregate)
        coverage = family = None
        if POINT_SCORES[settings.point_score].reference:
            coverage = scan_coverage(reference, evidence, settings.coverage, score)
            family = family_range(reference, evidence.field, evidence.points, evidence.normals)
        if coverage is not None and not coverage.counted_all:
            score = aggregate_scores(values[kept & coverage.covered], settings.aggregate)
    result = ScanResult(score, values, evidence.field, components={"points": score}, stray=evidence.stray,
                        coverage=coverage, evidence=evidence, family=family)
    if coverage is not None:
        result.components["points_all"] = coverage.score_all
    if settings.rays:
        from .ray_evidence import ray_evidence

        with stage(timings, "rays"):
            band = reference if surface is None else surface
            result.rays = ray_evidence(evidence.field, evidence.points, evidence.origin,
                                       surface=None if band is None else band.neighbours,
                                       surface_normals=None if band is None else band.oriented_surface(),
                                       grazing=evidence.grazing, **settings.ray_options)
        result.components["rays"] = result.rays.score
    return result


def weigh_rays(result, combination):
    """``result`` with its rays weighed by the calibration's ``combination`` (:mod:`inspection.ray_calibration`):
    its ray evidence I in ``components['ray_nats']``, per point in ``ray_point_nats``, and the combined ``score``."""
    rays = combination.rays
    per_ray = rays.ray_nats(result.rays)
    n = len(result.rays.ray_surprisal)
    result.ray_point_nats = result.rays.per_point(per_ray[:n], per_ray[n:])
    result.components["ray_nats"] = combination.nats(result.rays)
    result.score = combination.score(result.components["points"], result.rays)
    if result.coverage is not None:
        result.coverage.score_all = combination.score(result.components["points_all"], result.rays)
    return result


def scan_coverage(reference, evidence, lengthscales, score_all):
    """The :class:`inspection.coverage.Coverage` of a scan's ``evidence`` against ``reference``'s good surface at
    ``lengthscales`` kernel lengthscales, or None (no reference, no lengthscale, or ``lengthscales`` 0).
    ``score_all``: its score over every (kept) point. ``counted_all`` is set when fewer than
    ``inspection.coverage.MIN_COVERED_POINTS`` (or 1 %) of its kept points are covered: then its score counts every
    point, and its verdict is 'uncertain' whatever the score (:func:`inspection.coverage.coverage_verdict`)."""
    radius = None if reference is None else coverage_radius(evidence.field, lengthscales)
    if radius is None:
        return None
    covered = covered_points(reference, evidence.points, evidence.normals, radius)
    kept = kept_points(evidence.stray, len(covered))
    enough = max(MIN_COVERED_POINTS, int(np.ceil(0.01 * kept.sum())))
    return Coverage(covered, radius, float(score_all), counted_all=bool((kept & covered).sum() < enough))
