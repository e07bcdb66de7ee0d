"""Inspector: a scikit-learn style outlier detector over scans, calibrated on good scans with conformal p-values."""
import logging
from dataclasses import dataclass

import numpy as np
from sklearn.base import BaseEstimator
from sklearn.exceptions import NotFittedError

from datasets.validation import points_and_normals

from .calibration import Calibration
from .threshold import DEFAULT_ALPHA, check_alpha, fit_threshold
from .scores import (POINT_SCORES, REFERENCE_QUANTITY, LocalReference, aggregate as aggregate_scores, check_aggregate,
                     field_quantity, grazing_factor, point_scores, reference_scores, view_origin_from_normals)

log = logging.getLogger(__name__)

DEFAULT_AGGREGATE = "top1"
DEFAULT_POINT_SCORE = "residual"
# Projection settings for inspection (autodecoder.latent.projection.ProjectionOptions fields): a shorter run from fewer
# starts than the trainer's defaults that reaches the same projection loss at a fraction of the time
# (docs/results.md#latent-training-and-projection-cost).
DEFAULT_PROJECTION = {"steps": 60, "starts": 2, "explore": 20, "max_candidates": 16}
# how the point and ray scores combine (inspection.combine: the ray score on a log scale, gated robustly)
COMBINATION_RULE = "gated-log"
# rays per good scan of the ray reference (denser than a scan's inspection, which tests RAY_DEFAULTS["n_rays"])
REFERENCE_RAYS = 1536


# points of the good scans' own surface kept in a reference (LocalReference.surface), at most: every training scan of
# a 64-view template collection (~180,000 points) or of 32 synthetic scans of 4,000 points fits
SURFACE_MAX_POINTS = 240000


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


@dataclass
class _Named:
    """Points (m, 3) and normals (m, 3) or None under a scan name (the projected reference scans as surface scans)."""

    name: str
    points: np.ndarray
    normals: np.ndarray = None


@dataclass
class _Projected:
    """A scan projected into the model: its name, points (m, 3), field, sensor origin (None when unknown), and for
    reference-based point scores the compared quantity (m,), the field's variance in its units (m,) and the grazing
    factor of the sensor's rays (m,) (None without a sensor origin); ``stray`` (m,) bool marks isolated returns off
    the surface their neighbours define (:func:`datasets.outliers.stray_points`); ``normals`` (m, 3) are the
    scan's (None when it has none)."""

    name: str
    points: np.ndarray
    field: object
    origin: object = None
    value: np.ndarray = None
    variance: np.ndarray = None
    grazing: np.ndarray = None
    stray: np.ndarray = None
    normals: np.ndarray = None


@dataclass
class ScanResult:
    """One scan's inspection: its anomaly score (higher = more anomalous) and per-point scores (m,).

    ``components`` holds the per-scan scores that make ``score``: ``{"points": ...}`` (the aggregate of the point
    scores), plus ``"rays"`` (the ray score) when rays are used; then ``rays`` is the
    :class:`~inspection.ray_evidence.RayEvidence` (its ``point_map`` is the per-point ray map) and ``score`` the
    combination (:mod:`inspection.combine`).
    """

    score: float
    point_scores: np.ndarray
    field: object = None
    components: dict = None
    rays: object = None


def _sensor_origin(scan, i):
    from .ray_evidence import sensor_origin

    return sensor_origin(scan if hasattr(scan, "points") else None, _scan_name(scan, i))


def _known_sensor_origin(scan, i):
    """The scan's sensor origin (3,) when it carries a valid one, else None."""
    if getattr(scan, "sensor_origin", None) is None:
        return None
    return _sensor_origin(scan, i)


def _scan_name(scan, i):
    return getattr(scan, "name", None) or f"scan #{i}"


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


class Inspector(BaseEstimator):
    """Defect detector over scans: per-point scores under the projected field, one score per scan, and a threshold
    calibrated on good scans (:mod:`inspection.threshold`: split-conformal when there are at least 1 / alpha - 1 of
    them, else a log-normal tail fitted to their scores; either way a false-alarm rate of ``alpha`` on average).

    Parameters
    ----------
    model : latent model, field or callable
        See :func:`field_for`. Scans must be in the model's frame.
    alpha : float in (0, 1)
        False-alarm rate: a scan is defective when its p-value is <= alpha (its score > ``threshold_``).
    aggregate : str
        Per-scan aggregate of the point scores (:func:`inspection.scores.aggregate`): ``'top1'`` (default: mean of
        the worst 1 % of the points; chosen on benchmarks/inspect_fandisk.py, where it separated best: defects
        cover a few per cent of a scan's points, so the paper's ``'mean'`` dilutes them), ``'mean'`` (the paper's),
        ``'max'``, ``'median'``, ``'top<P>'``, ``'q<P>'``.
    point_score : {'residual', 'joint', 'distance', 'local', 'nll'}
        Per-point score (:func:`inspection.scores.point_scores`): the standardized residual (default here, as it
        needs nothing more; the command line picks ``'joint'`` when it can reach the training scans), the
        first-order distance to the mean surface standardized against good scans at the same place
        (``'distance'``: :meth:`fit` then needs ``reference_scans``, e.g. the model's training scans), that together
        with the point's offset from the good scans' own surface (``'joint'``, same needs), the same on E f itself
        (``'local'``), or the paper's NLL.
    noise : float, optional
        Noise floor (measurement noise standard deviation, model frame units); default the field's own.
    projection : dict, optional
        Options of ``model.project`` (latent models), e.g. ``DEFAULT_PROJECTION``; None: the model's defaults.
        Scores depend on them, so the calibration stores them and :meth:`set_calibration` restores them.
    rays : bool
        Also score the sensor's rays (:mod:`inspection.ray_evidence`: material the field expects where the
        sensor saw free space, e.g. a hole in a thin wall; with a per-location reference, only where its good
        scans have a surface) and combine that score with the point score (:mod:`inspection.combine`, rule
        ``COMBINATION_RULE``: the point score plus what the ray score shows beyond the good calibration scans).
        Scans need a ``sensor_origin``; the combined score needs calibration (:meth:`fit`) before it can be
        computed.
    ray_options : dict, optional
        Settings of the ray score (keys of ``inspection.ray_evidence.RAY_DEFAULTS``: ``n_rays``, ``n_empty``,
        ``gap``, ``aggregate``, ``seed``, ``clearance``, ``own_depth``, ``band``); stored with the calibration like
        ``projection``.

    Attributes (after :meth:`fit`)
    ------------------------------
    calibration_scores_ : (n,) array
        Anomaly scores of the calibration scans.
    calibration_names_ : list of str
    calibration_roles_ : list of str
        ``'held-back'`` or ``'cross-fitted'`` for each calibration scan (:meth:`fit`).
    threshold_ : float
        Scans with anomaly score > threshold_ are defective.
    decision_threshold_ : inspection.threshold.Threshold
        ``threshold_`` with its basis (exact split-conformal, or the log-normal tail when there are fewer than
        1 / alpha - 1 calibration scans), the false-alarm rate it predicts and that rate's interval.
    offset_ : float
        ``-threshold_``, so that ``decision_function = score_samples - offset_`` is negative exactly for defects.
    n_calibration_ : int
    reference_ : LocalReference or None
        Per-location statistics of good scans (point scores ``'joint'``, ``'distance'`` and ``'local'`` only).
    combination_ : Combination or None
        The standardization of the components on the calibration scans (``rays=True`` only).
    """

    def __init__(self, model, alpha=DEFAULT_ALPHA, aggregate=DEFAULT_AGGREGATE, point_score=DEFAULT_POINT_SCORE, noise=None,
                 projection=None, rays=False, ray_options=None):
        self.model = model
        self.projection = projection
        self.alpha = alpha
        self.aggregate = aggregate
        self.point_score = point_score
        self.noise = noise
        self.rays = rays
        self.ray_options = ray_options

    # ------------------------------------------------------------------------------------------------ checks
    def _check_params(self):
        check_alpha(self.alpha)
        check_aggregate(self.aggregate)
        if self.point_score not in POINT_SCORES:
            raise ValueError(f"point_score must be one of {POINT_SCORES}, got {self.point_score!r}")
        if self.noise is not None and not float(self.noise) >= 0:
            raise ValueError(f"noise must be None or >= 0, got {self.noise!r}")
        if self.rays not in (True, False):
            raise ValueError(f"rays must be True or False, got {self.rays!r}")
        if self.rays:
            from .ray_evidence import check_ray_options

            check_ray_options(self.ray_options)

    def _check_is_fitted(self):
        if not hasattr(self, "calibration_scores_"):
            raise NotFittedError("This Inspector is not calibrated yet: call fit(good_scans) or "
                                 "set_calibration(...) before scoring against a threshold")

    # ------------------------------------------------------------------------------------------------ scoring
    def for_scan(self, scan):
        """The inspector whose threshold applies to ``scan``: this one (see :class:`inspection.parts.PartInspector`
        for a model of several part types)."""
        return self

    def inspect(self, scan):
        """Project one scan and score it. Returns a :class:`ScanResult` (score, per-point scores, field,
        components, ray evidence). With ``rays=True`` the score is the combination, which needs calibration."""
        combination = self._combination() if self.rays else None  # before the work: fail fast
        result = self.inspect_components(scan)
        if combination is not None:
            result.score = float(combination.score([result.components])[0])
        return result

    def inspect_components(self, scan):
        """Like :meth:`inspect`, but ``score`` is the point score's aggregate alone; works unfitted (except for
        the per-location point scores, which need their reference)."""
        self._check_params()
        if self.point_score in REFERENCE_QUANTITY and getattr(self, "reference_", None) is None:
            raise NotFittedError(f"point_score {self.point_score!r} needs the per-location reference: call "
                                 "fit(good_scans, reference_scans=...) or fit_reference(scans) first")
        good = self._project(scan, 0)
        return self._score(good, getattr(self, "reference_", None))

    def _project(self, scan, i, exclude_own_code=False):
        """Project one scan: a :class:`_Projected` with its field and, for reference-based point scores, the
        compared quantity and the field's variance in its units. ``exclude_own_code``: a training scan of a latent
        model is projected without starting from the code it was trained with (cross-fitting)."""
        points, normals = points_and_normals(scan)
        name = _scan_name(scan, i)
        if points.ndim != 2 or points.shape[-1] != 3 or len(points) == 0:
            raise ValueError(f"{name}: a scan needs (m >= 1, 3) points, got shape {points.shape}")
        origin = _sensor_origin(scan, i) if self.rays else _known_sensor_origin(scan, i)  # fail fast
        options = self.projection
        train_names = getattr(self.model, "train_names", None)
        if exclude_own_code and train_names and name in train_names:
            options = {**(options or {}), "exclude": (train_names.index(name),)}
        part = getattr(scan, "part_id", "")
        if part and getattr(self.model, "train_part_ids", None):  # a latent model: start from the part's codes
            options = {**(options or {}), "part_id": part}
        field = field_for(self.model, points, normals, options)
        value = variance = grazing = None
        if self.point_score in REFERENCE_QUANTITY:
            value, variance = field_quantity(field, points, REFERENCE_QUANTITY[self.point_score], with_variance=True)
            if normals is not None:
                # no sensor origin (a public layout's test scan): the view estimated from the normals, for the
                # grazing term alone
                seen_from = origin if origin is not None else view_origin_from_normals(points, normals)
                grazing = grazing_factor(points, normals, seen_from)
        from datasets.outliers import stray_points

        points = np.asarray(points, dtype=np.float64)
        return _Projected(name, points, field, origin, value, variance, grazing, stray_points(points),
                          None if normals is None else np.asarray(normals, dtype=np.float64))

    def _score(self, good, reference, ray_reference=None):
        """A :class:`ScanResult` of a projected scan against ``reference`` and ``ray_reference`` (default: the
        fitted ray reference, if any) (components: points, rays)."""
        if self.point_score in REFERENCE_QUANTITY:
            noise = float(getattr(good.field, "noise", 0.0) if self.noise is None else self.noise)
            values = reference_scores(reference, self.point_score, good.points, good.value, good.variance, noise,
                                      good.grazing, good.normals)
        else:
            values = point_scores(good.field, good.points, kind=self.point_score, noise=self.noise)
        # a stray point (a lone return off the surface) is not a defect unless many points agree: the scan's score
        # aggregates the others; the map keeps every point's score
        kept = values if good.stray is None or good.stray.all() else values[~good.stray]
        score = aggregate_scores(kept, self.aggregate)
        result = ScanResult(score, values, good.field, components={"points": score})
        if self.rays:
            from .ray_evidence import check_ray_options, ray_evidence

            if ray_reference is None:
                ray_reference = getattr(self, "ray_reference_", None)
            result.rays = ray_evidence(good.field, good.points, good.origin, reference=ray_reference,
                                       surface=None if reference is None else reference.tree,
                                       grazing=good.grazing,
                                       **check_ray_options(self.ray_options))
            result.components["rays"] = result.rays.score
        return result

    def _combination(self):
        combination = getattr(self, "combination_", None)
        if combination is None:
            raise NotFittedError("rays=True: the combined score standardizes the point and ray scores on the "
                                 "calibration scans; call fit(good_scans) or set_calibration(...) first "
                                 "(inspect_components works unfitted)")
        return combination

    def anomaly_scores(self, scans):
        """Per-scan anomaly scores (n,) (higher = more anomalous). Works unfitted, except with ``rays=True``."""
        return np.array([self.inspect(s).score for s in scans], dtype=np.float64)

    def anomaly_map(self, scan):
        """Per-point scores (m,) of one scan (higher = more anomalous). Works unfitted."""
        return self.inspect_components(scan).point_scores

    def ray_map(self, scan):
        """Per-point ray scores (m,) in [0, 1] of one scan (``rays=True``; see :mod:`inspection.ray_evidence`).
        Works unfitted."""
        if not self.rays:
            raise ValueError("ray_map needs an Inspector made with rays=True")
        return self.inspect_components(scan).rays.point_map

    # ------------------------------------------------------------------------------------------------ fitting
    def fit_reference(self, scans, max_points=60000, seed=0, surface_scans=None):
        """Build ``reference_`` (for point scores ``'joint'``, ``'distance'`` and ``'local'``) from good scans, each
        projected as a test scan would be (a training scan without starting from its own trained code); the model's
        training scans are the natural choice. They are kept for the cross-fitted calibration of :meth:`fit`.
        ``surface_scans`` (good scans, not projected; e.g. every training scan when ``scans`` is a subset of them):
        the points and normals of the good scans' own surface (:meth:`LocalReference.surface`), up to
        ``SURFACE_MAX_POINTS`` (seeded subsample); a scan named like one of ``scans`` is left out with it when
        cross-fitting. None: ``scans`` themselves. Returns self."""
        if self.point_score not in REFERENCE_QUANTITY:
            raise ValueError(f"point_score {self.point_score!r} uses no per-location reference")
        goods = [self._project(s, i, exclude_own_code=True) for i, s in enumerate(scans)]
        if not goods:
            raise ValueError("fit_reference needs at least one good scan, got none")
        self.reference_ = LocalReference.from_values([(g.points, g.value) for g in goods], max_points=max_points,
                                                     seed=seed, quantity=REFERENCE_QUANTITY[self.point_score])
        names = [g.name for g in goods]
        if surface_scans is None:  # the projected scans themselves, each its own owner
            surface_scans = [_Named(g.name, g.points, g.normals) for g in goods]
        ref = self.reference_
        ref.surface_points, ref.surface_owners, ref.surface_normals = _surface_points(surface_scans, names, seed)
        self._reference_scans = goods
        self.ray_reference_ = None
        if self.rays and all(g.origin is not None for g in goods):
            from .ray_evidence import RayReference, check_ray_options

            options = dict(check_ray_options(self.ray_options), n_rays=REFERENCE_RAYS)
            if options["band"] is not None:
                # the band of good surfaces (these scans' points, ray option band) leaves out what a one-sided
                # field extrapolates through an open part's openings; without it, good rays through them are
                # explained by where good scans' rays enter the field's material (docs/inspection.md)
                return self
            self.ray_reference_ = RayReference.build(((g.points, g.origin, g.field) for g in goods), **options)
        return self

    def fit(self, good_scans, y=None, names=None, reference_scans=None, cross_fit=True, surface_scans=None):
        """Calibrate on good scans: the ones given, which the model did NOT train on (held-back or validation
        scans), and, with a per-location reference, the reference scans themselves, cross-fitted.

        Cross-fitting: each reference scan (usually a training scan) is projected without its own trained code and
        scored against the reference without its own points, as if it were new. Thresholds need many good scores
        (:mod:`inspection.threshold`), and the held-back scans alone are few. The point score's noise model (the
        weights of the field's variance and of the grazing factor, ``reference_.variance_scale`` and
        ``grazing_scale``, :meth:`LocalReference.fit_noise_model`) is fitted on the same scans' residuals first.

        Parameters
        ----------
        good_scans : sequence of Scan (or (m, 3) arrays)
        y : ignored
        names : list of str, optional
            Default: the scans' names.
        reference_scans : sequence of Scan, optional
            Good scans for the per-location reference (point scores ``'joint'``, ``'distance'``, ``'local'``; required
            then, unless ``reference_`` is already set): usually the model's training scans.
        cross_fit : bool
            Also calibrate on the reference scans, cross-fitted (needs the scans the reference was built from
            in this session; with rays, their sensor origins).
        surface_scans : sequence of Scan, optional
            With ``reference_scans``: the good scans whose points make the reference's surface
            (:meth:`fit_reference`).

        Returns
        -------
        self
        """
        self._check_params()
        if reference_scans is not None:
            self.fit_reference(reference_scans, surface_scans=surface_scans)
        elif self.point_score in REFERENCE_QUANTITY and getattr(self, "reference_", None) is None:
            raise ValueError(f"point_score={self.point_score!r} needs reference_scans (good scans, e.g. the training "
                             "scans)")
        held = [self._project(s, i) for i, s in enumerate(good_scans)]  # lazily: good_scans may be a progress bar
        if not held:
            raise ValueError("fit needs at least one good calibration scan, got none")
        names = [g.name for g in held] if names is None else list(names)
        if self.point_score not in REFERENCE_QUANTITY:
            return self.fit_components([self._score(g, None).components for g in held], names)
        crossed = list(getattr(self, "_reference_scans", [])) if cross_fit else []
        if self.rays and any(g.origin is None for g in crossed):
            crossed = []
        references = [self.reference_] * len(held) + [self.reference_.without(j) for j in range(len(crossed))]
        ray_reference = getattr(self, "ray_reference_", None)
        ray_references = [ray_reference] * len(held) + [
            None if ray_reference is None else ray_reference.without(j) for j in range(len(crossed))]
        goods = held + crossed
        kappa, lam = self._fit_noise_model(goods, references)
        components = []
        for good, reference, ray_ref in zip(goods, references, ray_references):
            reference.variance_scale, reference.grazing_scale = kappa, lam
            components.append(self._score(good, reference, ray_ref).components)
        roles = ["held-back"] * len(held) + ["cross-fitted"] * len(crossed)
        return self.fit_components(components, names + [g.name for g in crossed], roles)

    def _fit_noise_model(self, goods, references):
        """:meth:`LocalReference.fit_noise_model` on the residuals of good projected scans against the references
        they are scored with (the grazing term only when every one of them has a sensor origin)."""
        residuals, base, field_var, noise_var, grazing = [], [], [], [], []
        for good, reference in zip(goods, references):
            m_ref, s_ref = reference.stats(good.points)
            noise = float(getattr(good.field, "noise", 0.0) if self.noise is None else self.noise)
            residuals.append(good.value - m_ref)
            base.append(s_ref**2)
            field_var.append(good.variance)
            noise_var.append(np.full(len(good.points), noise**2))
            grazing.append(good.grazing)
        with_grazing = all(g is not None for g in grazing)
        return LocalReference.fit_noise_model(np.concatenate(residuals), np.concatenate(base),
                                              np.concatenate(field_var), np.concatenate(noise_var),
                                              np.concatenate(grazing) if with_grazing else None)

    def fit_components(self, components, names, roles=None):
        """Calibrate from the ``components`` of :meth:`inspect_components` (one dict per good calibration scan);
        ``roles`` says for each whether it was held back or cross-fitted (default: held back).

        Without rays the calibration scores are the point scores' aggregates. With rays the components are
        standardized on these scans (``combination_``) and the calibration scores are their leave-one-out
        combinations (:meth:`inspection.combine.Combination.calibration_scores`). Returns self.
        """
        components = list(components)
        if not components:
            raise ValueError("calibration needs at least one good scan, got none")
        self.calibration_roles_ = ["held-back"] * len(components) if roles is None else list(roles)
        if len(self.calibration_roles_) != len(components):
            raise ValueError(f"roles: one per calibration scan ({len(components)}), got {len(self.calibration_roles_)}")
        if not self.rays:
            self.combination_ = None
            return self._set([c["points"] for c in components], names)
        from autodecoder.scanning.free_space import MAX_SURPRISAL

        from .combine import Combination

        missing = [i for i, c in enumerate(components) if "rays" not in c]
        if missing:
            raise ValueError(f"rays=True: {len(missing)} calibration scan(s) have no ray score (inspect them with "
                             f"this Inspector)")
        self.combination_ = Combination(components, names=("points", "rays"), rule=COMBINATION_RULE,
                                        ceiling=MAX_SURPRISAL)
        return self._set(self.combination_.calibration_scores(), names)

    def _set(self, scores, names):
        scores = np.asarray(scores, dtype=np.float64).reshape(-1)
        if len(scores) == 0 or not np.all(np.isfinite(scores)):
            raise ValueError("calibration scores must be a non-empty array of finite numbers")
        self.calibration_scores_ = scores
        self.calibration_names_ = list(names)
        self.n_calibration_ = len(scores)
        roles = getattr(self, "calibration_roles_", None)
        self.decision_threshold_ = fit_threshold(scores, self.alpha,
                                                 roles if roles is not None and len(roles) == len(scores) else None)
        self.threshold_ = self.decision_threshold_.value
        self.offset_ = -self.threshold_
        return self

    def set_calibration(self, calibration):
        """Use a stored :class:`~inspection.calibration.Calibration` (its aggregate, point score and noise floor
        replace this inspector's; ``alpha`` stays). Returns self. A per-part calibration (a model of several part
        types) is a :class:`inspection.parts.PartInspector`'s, not one inspector's: ValueError."""
        if (calibration.extra or {}).get("parts"):
            raise ValueError("this calibration holds one per part type (the model was trained on several); load it "
                             "with inspection.parts.PartInspector.from_calibration(model, calibration)")
        self.aggregate = calibration.aggregate
        self.point_score = calibration.point_score
        self.noise = calibration.noise
        self.projection = (calibration.extra or {}).get("projection")
        ref = (calibration.extra or {}).get("reference")
        self.reference_ = None if ref is None else LocalReference.from_dict(ref)
        rays = (calibration.extra or {}).get("rays")
        self.rays = rays is not None
        self.ray_options = None if rays is None else dict(rays["options"])
        self.ray_reference_ = None
        if rays is not None:
            from .combine import Combination
            from .ray_evidence import RayReference

            self.combination_ = Combination.from_dict(rays["components"])
            if rays.get("reference") is not None:
                self.ray_reference_ = RayReference.from_dict(rays["reference"])
        else:
            self.combination_ = None
        self._check_params()
        self.calibration_roles_ = list(calibration.roles) or ["held-back"] * len(calibration.scores)
        return self._set(calibration.scores, calibration.names)

    def calibration(self, source="", fingerprint=""):
        """The fitted calibration as a :class:`~inspection.calibration.Calibration`, ready to store in the model."""
        self._check_is_fitted()
        return Calibration(scores=self.calibration_scores_.tolist(), names=list(self.calibration_names_),
                           roles=list(getattr(self, "calibration_roles_", [])),
                           aggregate=self.aggregate, point_score=self.point_score,
                           noise=None if self.noise is None else float(self.noise), alpha=float(self.alpha),
                           source=source, fingerprint=fingerprint,
                           extra={"projection": None if self.projection is None else dict(self.projection),
                                  "reference": None if getattr(self, "reference_", None) is None
                                  else self.reference_.as_dict(),
                                  "rays": self._ray_record()})

    def _ray_record(self):
        """What the calibration stores about rays: None, or the options and the calibration component scores."""
        if not self.rays:
            return None
        from .ray_evidence import check_ray_options

        ray_reference = getattr(self, "ray_reference_", None)
        return {"options": check_ray_options(self.ray_options), "components": self._combination().as_dict(),
                "reference": None if ray_reference is None else ray_reference.as_dict()}

    # ------------------------------------------------------------------------------------ sklearn outlier API
    def p_values_from_scores(self, anomaly_scores):
        """p-values (n,) of given anomaly scores on the threshold's basis (split-conformal or the log-normal
        predictive tail, :meth:`inspection.threshold.Threshold.p_values`); ``p <= decision_threshold_.alpha_used``
        exactly when the score exceeds ``threshold_``."""
        self._check_is_fitted()
        return self.decision_threshold_.p_values(anomaly_scores)

    def p_values(self, scans):
        """p-values (n,) of scans; small = unlike the good calibration scans."""
        return self.p_values_from_scores(self.anomaly_scores(scans))

    def score_samples(self, scans):
        """Normality scores (n,): the negated anomaly score, so HIGHER = MORE NORMAL (scikit-learn convention)."""
        return -self.anomaly_scores(scans)

    def decision_function(self, scans):
        """``score_samples(scans) - offset_``: negative for defective scans, >= 0 for good ones."""
        self._check_is_fitted()
        return self.score_samples(scans) - self.offset_

    def predict_from_scores(self, anomaly_scores):
        """+1 (good) / -1 (defective) for given anomaly scores: -1 exactly when the score exceeds ``threshold_``."""
        self._check_is_fitted()
        s = np.asarray(anomaly_scores, dtype=np.float64)
        return np.where(s > self.threshold_, -1, 1)

    def predict(self, scans):
        """+1 for good scans, -1 for defective ones (score > ``threshold_``, i.e. decision_function < 0)."""
        return self.predict_from_scores(self.anomaly_scores(scans))
