"""Inspector: a scikit-learn style outlier detector over scans, calibrated on good scans; the one inspection pipeline.

``Inspector(model).fit(good_scans)`` does what ``nsspr-inspect calibrate`` does, and the command line calls it: the
settings are :class:`inspection.config.InspectionConfig`'s (its fields are the estimator's parameters, with the same
defaults), the good scans are sorted into calibration, reference and surface scans by
:func:`inspection.selection.select_scans`, and a model of several part types gets one calibration per part.
"""
import logging
from dataclasses import asdict, dataclass, replace

import numpy as np
from sklearn.base import BaseEstimator
from sklearn.exceptions import NotFittedError

from datasets.validation import points_and_normals

from .calibration import Calibration
from .config import DEFAULT_AGGREGATE, DEFAULT_PROJECTION, InspectionConfig
from .evidence import ScanEvidence, field_for, gather_evidence, scan_name, stage
from .loading import reading_of, signed_for_scoring
from .aggregates import aggregate as aggregate_scores
from .reference import REFERENCE_QUANTITY, LocalReference
from .scores import POINT_SCORES, WEIGHED_SCORES, fit_term_variances, point_scores, reference_scores, reference_terms
from .selection import model_parts, select_scans
from .threshold import DEFAULT_ALPHA, fit_threshold

# what every verdict says when the threshold's level was set by views rendered from clean templates alone (the
# template regime): real partial scans of another sensor can score above all of them (issue 47)
SIZE_RATIO = 10.0  # a scan this many times the good scans' size (or 1 / SIZE_RATIO^2 of it) is told why (size_note)
LEVEL_RENDERED_NOTE = ("the threshold's level rests on views rendered from the templates only: real scans of another "
                       "sensor may score higher; `nsspr-inspect calibrate --model MODEL --data GOOD_SCANS` with a few "
                       "real good scans of this sensor sets it from them")

log = logging.getLogger(__name__)

__all__ = ["Inspector", "NotFittedError", "ScanResult", "field_for", "DEFAULT_AGGREGATE", "DEFAULT_PROJECTION"]

# points of the good scans' own surface kept in a reference (LocalReference.surface), at most: every training scan of
# a 64-view template collection (~180,000 points) or of 32 synthetic scans of 4,000 points fits
SURFACE_MAX_POINTS = 240000
# a training scan scored against the reference without its own points takes the field's term for the good points'
# term at its points farther from the other good scans' surface than this quantile of the held-back scans' points
# are from all of them (_uncovered)
COVERAGE_QUANTILE = 0.99


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
class ScanResult:
    """One scan's inspection: its anomaly score (higher = more anomalous) and per-point scores (m,).

    ``transform`` (4, 4) is the registration that moved the scan before it was scored (``align=True``; None
    otherwise); ``point_scores`` are in the scan's own point order either way. ``components`` holds the per-scan
    scores that make ``score``: ``{"points": ...}`` (the aggregate of the point
    scores), plus ``"rays"`` (the ray score: the aggregate of the rays' surprisals, nats) when rays are used; then
    ``rays`` is the :class:`~inspection.ray_evidence.RayEvidence` (its ``point_map`` is the per-point ray map), and
    once the calibration weighs the rays (:meth:`Inspector.inspect`) ``components["ray_nats"]`` is their evidence I
    (:mod:`inspection.ray_calibration`), ``ray_point_nats`` (m,) the same per point (what the anomaly map adds) and
    ``score`` the combination (:mod:`inspection.combine`). ``stray`` (m,) bool marks the scan's stray returns, left
    out of the score's aggregate and of the anomaly map's patches (None: none looked for).
    """

    score: float
    point_scores: np.ndarray
    field: object = None
    components: dict = None
    rays: object = None
    transform: np.ndarray = None
    stray: np.ndarray = None
    ray_point_nats: np.ndarray = None


def _progress(items, verbose, desc):
    if not verbose:
        return items
    from tqdm import tqdm

    return tqdm(items, desc=desc, unit="scan")


class Inspector(BaseEstimator):
    """Defect detector over scans: per-point scores under the projected field, one score per scan, and a threshold
    calibrated on good scans (:mod:`inspection.threshold`: split-conformal when there are at least 1 / alpha - 1 of
    them, else a log-normal tail fitted to their scores; either way a false-alarm rate of ``alpha`` on average).

    The parameters are the fields of :class:`inspection.config.InspectionConfig`, with its defaults (see there);
    ``'auto'`` settings are decided by :meth:`fit` from the good scans and recorded in ``settings_``, never in the
    parameters.

    Parameters
    ----------
    model : latent model, field or callable
        See :func:`inspection.evidence.field_for`. Scans must be in the model's frame. A latent model (or a field
        saved with its collection, :func:`inspection.model_io.load_model`) records its training and held-back scans
        by name, which :meth:`fit` uses to sort the good scans it is given.
    alpha, aggregate, point_score, noise, projection, rays, ray_options, align
        :class:`inspection.config.InspectionConfig`.
    verbose : bool
        Progress bars on the long work (projecting the reference and calibration scans).

    Attributes (after :meth:`fit` or :meth:`from_calibration`)
    --------------------------------------------------------
    settings_ : InspectionConfig
        The settings in force: ``point_score`` and ``rays`` decided, ``ray_options`` complete (or None without
        rays), ``projection`` the ``project`` options (None for a fixed field).
    calibration_scores_ : (n,) array
        Anomaly scores of the calibration scans.
    calibration_names_, calibration_roles_ : list of str
        Their names, and for each ``'held-back'``, ``'fold'`` (a training scan scored by a fold model that never
        saw it) or ``'cross-fitted'`` (a training scan scored by the main model as if new).
    calibration_source_ : str
        Where the calibration scans came from, in words.
    data_fingerprint_ : str
        The fingerprint of the collection :meth:`fit` read ('' for scans given as a list).
    threshold_ : float
        Scans with anomaly score > threshold_ are defective.
    decision_threshold_ : inspection.threshold.Threshold
        ``threshold_`` with its basis, the false-alarm rate it predicts and that rate's interval.
    offset_ : float
        ``-threshold_``, so that ``decision_function = score_samples - offset_`` is negative exactly for defects.
    n_calibration_ : int
    reference_ : LocalReference or None
        Per-location statistics of good scans (point scores with a reference).
    reading_ : dict or None
        How the collection :meth:`fit` read had read its scanner files (:class:`datasets.reading.Reading` as a
        dict; None for scans given as a list): :func:`inspection.loading.load_scans` reads files scored later by it.
    combination_ : Combination or None
        The standardization of the components on the calibration scans (with rays).
    aligner_ : inspection.align.Aligner or None
        With ``align``: the registration onto good training scans that every scan, calibration scans included,
        goes through before it is scored (stored with the calibration).
    alignment_note_ : str
        One line when ``align='auto'`` decided to register the scans ('' otherwise; set by :meth:`fit`).
    parts_ : dict of str -> Inspector, or None
        A model of several part types: one fitted inspector per part (:meth:`for_scan` picks a scan's); this
        inspector's own calibration attributes then hold every part's scores together (for reading, not for a
        threshold) and ``threshold_`` is not set.
    """

    def __init__(self, model, alpha=DEFAULT_ALPHA, aggregate=DEFAULT_AGGREGATE, point_score="auto", noise=None,
                 projection="default", rays="auto", ray_options=None, align="auto", verbose=False):
        self.model = model
        self.alpha = alpha
        self.aggregate = aggregate
        self.point_score = point_score
        self.noise = noise
        self.projection = projection
        self.rays = rays
        self.ray_options = ray_options
        self.align = align
        self.verbose = verbose

    # ------------------------------------------------------------------------------------------ configuration
    @property
    def config(self):
        """The parameters as an :class:`~inspection.config.InspectionConfig` (not validated)."""
        return InspectionConfig(alpha=self.alpha, aggregate=self.aggregate, point_score=self.point_score,
                                noise=self.noise, projection=self.projection, rays=self.rays,
                                ray_options=self.ray_options, align=self.align)

    @classmethod
    def from_config(cls, model, config=None, verbose=False):
        """An inspector of ``model`` with the settings of ``config`` (None: the defaults)."""
        return cls(model, **asdict(config or InspectionConfig()), verbose=verbose)

    @classmethod
    def from_calibration(cls, model, calibration, alpha=None, verbose=False):
        """A new, fitted inspector from a stored :class:`~inspection.calibration.Calibration` (one per part type
        when the model was trained on several); ``alpha`` (None: the calibration's) sets the threshold."""
        config = replace(calibration.config(), alpha=calibration.alpha if alpha is None else alpha)
        insp = cls.from_config(model, config, verbose)
        parts = (calibration.extra or {}).get("parts")
        insp.reading_ = (calibration.extra or {}).get("reading")  # how scanner files are read (inspection.loading)
        if parts:
            insp.parts_ = {p: cls.from_calibration(model, Calibration.from_dict(record), alpha, verbose)
                           for p, record in sorted(parts.items())}
            insp._gather_parts(calibration.source)
            insp.data_fingerprint_ = calibration.fingerprint
            return insp
        insp.parts_ = None
        insp._restore(calibration)
        return insp

    def _resolved(self, config, reference_available, origins_everywhere):
        """``config`` (validated) with its 'auto' settings decided (module docstring of inspection.config)."""
        from .ray_evidence import check_ray_options

        point_score = config.point_score
        if point_score == "auto":
            point_score = "joint" if reference_available else "residual"
        rays = config.rays
        if rays == "auto":
            rays = bool(reference_available and origins_everywhere)
        return replace(config, point_score=point_score, rays=bool(rays),
                       ray_options=check_ray_options(config.ray_options) if rays else None,
                       projection=self._projection_options(config))

    def _projection_options(self, config):
        """The ``project`` options of ``config`` for this model: None for a fixed field; ``'default'`` means
        ``DEFAULT_PROJECTION`` for the toolkit's latent models (:class:`autodecoder.latent.model.LatentModel`) and
        the projector's own defaults for any other model with a ``project`` method."""
        if not hasattr(self.model, "project"):
            return None
        if config.projection == "default":
            from autodecoder.latent.model import LatentModel

            return config.projection_options() if isinstance(self.model, LatentModel) else None
        return config.projection_options() or None

    def _settings(self):
        """The settings in force: ``settings_`` once fitted, else the parameters with 'auto' decided as without
        good scans (point score ``'residual'``, no rays), so that an unfitted inspector can score."""
        settings = getattr(self, "settings_", None)
        if settings is None:
            settings = self._resolved(self.config.validated(), False, False)
            if settings.align == "auto":  # no training scans to decide it from: as without them, unregistered
                settings = replace(settings, align=False)
        return settings

    # ------------------------------------------------------------------------------------------------ scoring
    def for_scan(self, scan):
        """The inspector whose threshold applies to ``scan``: this one, or for a model of several part types the
        fitted inspector of the scan's ``part_id`` (a ValueError naming the parts the model knows otherwise)."""
        parts = getattr(self, "parts_", None)
        if not parts:
            return self
        part = str(getattr(scan, "part_id", "") or "")
        if part not in parts:
            name = getattr(scan, "name", "") or "a scan"
            what = f"part_id {part!r}" if part else "no part_id"
            raise ValueError(f"{name}: {what}, but the model was trained on several part types {sorted(parts)} and "
                             f"judges a scan against good scans of its own part; set the scan's part_id to one of them")
        return parts[part]

    def inspect(self, scan, index=0, timings=None):
        """Project one scan and score it. Returns a :class:`ScanResult` (score, per-point scores, field,
        components, ray evidence). With rays the score is the combination, which needs calibration.

        ``timings`` (a dict, optional) receives the seconds of each stage: those of
        :func:`inspection.evidence.gather_evidence` (``load``, ``projection``, ``field``, ``grazing``, ``stray``)
        and ``reference`` (the point scores against the reference), ``aggregate``, ``rays``, ``combine``."""
        one = self.for_scan(scan)
        if one is not self:
            return one.inspect(scan, index, timings)
        settings = self._settings()
        combination = self._combination() if settings.rays else None  # before the work: fail fast
        result = self.inspect_components(scan, index, timings)
        if combination is not None:
            with stage(timings, "combine"):
                self._weigh_rays(result, combination)
        return result

    @staticmethod
    def _weigh_rays(result, combination):
        """``result`` with its rays weighed by the calibration (:mod:`inspection.ray_calibration`): its ray evidence
        I in ``components['ray_nats']``, per point in ``ray_point_nats``, and the combined ``score``."""
        rays = combination.rays
        per_ray = rays.ray_nats(result.rays)
        n = len(result.rays.ray_surprisal)
        result.ray_point_nats = result.rays.per_point(per_ray[:n], per_ray[n:])
        result.components["ray_nats"] = combination.nats(result.rays)
        result.score = combination.score(result.components["points"], result.rays)
        return result

    def inspect_components(self, scan, index=0, timings=None):
        """Like :meth:`inspect`, but ``score`` is the point score's aggregate alone; works unfitted (except for
        the per-location point scores, which need their reference)."""
        one = self.for_scan(scan)
        if one is not self:
            return one.inspect_components(scan, index, timings)
        settings = self._settings()
        if POINT_SCORES[settings.point_score].reference and getattr(self, "reference_", None) is None:
            raise NotFittedError(f"point_score {settings.point_score!r} needs the per-location reference: call "
                                 "fit(good_scans) with the model's training scans among them first")
        transform = None
        if getattr(self.model, "family", None) is not None:
            with stage(timings, "align"):
                scan = self._sized(scan)
                transform = _transform_of(scan)
        if settings.align is True:
            with stage(timings, "align"):
                scan, transform = self._aligned(scan)
        result = self._score(self._evidence(scan, index, settings, timings=timings),
                             getattr(self, "reference_", None), settings, timings)
        result.transform = transform
        return result

    def _sized(self, scan):
        """``scan`` registered onto the model's common frame, a family's size or the common pose of parts placed by
        hand (:meth:`autodecoder.latent.model.LatentModel.normalise`; a training scan onto the others); as it is for
        a model without one."""
        family = getattr(self.model, "family", None)
        return scan if family is None else family.normalise(scan)

    def _sized_selection(self, selection):
        """Every scan of ``selection`` through :meth:`_sized` (each scan once, the same copy wherever it is used)."""
        if getattr(self.model, "family", None) is None:
            return selection
        moved = {}
        for s in [*selection.calibration, *selection.reference, *selection.surface]:
            if id(s) not in moved:
                moved[id(s)] = self._sized(s)
        return replace(selection, calibration=[moved[id(s)] for s in selection.calibration],
                       reference=[moved[id(s)] for s in selection.reference],
                       surface=[moved[id(s)] for s in selection.surface])

    def _aligned(self, scan):
        """``scan`` registered by ``aligner_``. Returns (the moved scan, the transform (4, 4))."""
        aligner = getattr(self, "aligner_", None)
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

    def _evidence(self, scan, index, settings, exclude_own_code=False, timings=None):
        # one reading of a file (issue 47): a scan whose normal signs its reading leaves to the good surface gets them
        # from the reference's good scans here, whether it came from a collection or a folder
        scan = signed_for_scoring(scan, getattr(self, "reference_", None))
        quantity = REFERENCE_QUANTITY if POINT_SCORES[settings.point_score].reference else None
        return gather_evidence(self.model, scan, index, quantity=quantity, projection=settings.projection,
                               need_origin=settings.rays, exclude_own_code=exclude_own_code, timings=timings)

    def _score(self, evidence: ScanEvidence, reference, settings, timings=None, uncovered=None, terms=None,
               surface=None):
        """A :class:`ScanResult` of a scan's evidence against ``reference`` (components: points, rays);
        ``timings`` as in :meth:`inspect`; ``uncovered`` (m,) bool: a training scan's points where no other good scan
        has a surface (:func:`_uncovered`), where the joint score takes the field's term for the good points' term;
        ``terms``: the joint score's two terms of these points, already computed (:meth:`_fit_term_variances`);
        ``surface``: the reference whose good scans' surface the rays are tested against (default ``reference``).

        The rays' surface is where good parts have one, whoever scanned it: a training scan scored without its own
        points in the point score's reference (cross-fitted) keeps them in the rays' band and skim normals, as a new
        scan of its view meets them there. Without them, a face of a thin wall that only it saw borrows the other
        face's points and normals, and its rays there were accused (on the benchmarks' enclosure and cup every
        accused calibration ray belonged to such a scan, none to a held-back one: docs/results.md)."""
        noise = _noise(evidence, settings)
        with stage(timings, "reference"):
            if POINT_SCORES[settings.point_score].reference:
                values = reference_scores(reference, settings.point_score, evidence.points, evidence.value,
                                          evidence.variance, noise, evidence.grazing, evidence.normals, uncovered,
                                          terms)
            else:
                values = point_scores(evidence.field, evidence.points, kind=settings.point_score,
                                      noise=settings.noise)
        with stage(timings, "aggregate"):
            # a stray point (a lone return off the surface) is not a defect unless many points agree: the scan's
            # score aggregates the others; the map keeps every point's score
            kept = values if evidence.stray is None or evidence.stray.all() else values[~evidence.stray]
            score = aggregate_scores(kept, settings.aggregate)
        result = ScanResult(score, values, evidence.field, components={"points": score}, stray=evidence.stray)
        if settings.rays:
            from .ray_evidence import ray_evidence

            with stage(timings, "rays"):
                band = reference if surface is None else surface
                result.rays = ray_evidence(evidence.field, evidence.points, evidence.origin,
                                           surface=None if band is None else band.tree,
                                           surface_normals=None if band is None else band.oriented_surface(),
                                           grazing=evidence.grazing, **settings.ray_options)
            result.components["rays"] = result.rays.score
        return result

    def _combination(self):
        combination = getattr(self, "combination_", None)
        if combination is None:
            raise NotFittedError("rays=True: the combined score standardizes the point and ray scores on the "
                                 "calibration scans; call fit(good_scans) or Inspector.from_calibration(...) first "
                                 "(inspect_components works unfitted)")
        return combination

    def anomaly_scores(self, scans):
        """Per-scan anomaly scores (n,) (higher = more anomalous), each under its part's inspector. Works unfitted,
        except with rays."""
        return np.array([self.inspect(s, i).score for i, s in enumerate(scans)], dtype=np.float64)

    def anomaly_map(self, scan):
        """The scan's anomaly map (m,): each point's patch residual, with its ray's evidence where the calibration
        scores rays, in standard deviations (higher = more anomalous; :mod:`inspection.maps`), what the PLY maps and
        the report show. The points' own scores are
        ``inspect_components(scan).point_scores``. Works unfitted."""
        from .maps import map_values

        one = self.for_scan(scan)
        result = one.inspect_components(scan)
        if one._settings().rays and getattr(one, "combination_", None) is not None:
            one._weigh_rays(result, one.combination_)
        return map_values(one._settings(), scan, result)[0]

    def ray_map(self, scan):
        """Per-point ray scores (m,) in [0, 1] of one scan (with rays; see :mod:`inspection.ray_evidence`)."""
        one = self.for_scan(scan)
        if not one._settings().rays:
            raise ValueError("ray_map needs an Inspector that scores the rays (rays=True, or 'auto' decided on)")
        return one.inspect_components(scan).rays.point_map

    # ------------------------------------------------------------------------------------------------ fitting
    def fit(self, good_scans, y=None, reference_scans=None, split=None, cross_fit=True):
        """Calibrate on good scans, sorted into their roles by :func:`inspection.selection.select_scans`.

        The calibration scans are the model's held-back scans among ``good_scans`` (else every good scan it did not
        train on); the model's training scans among them (or ``reference_scans``) give the per-location reference
        of the point scores that need one and more calibration scores. A model with fold models
        (:mod:`autodecoder.latent.folds`, ``train_latent.py --calibration-folds K``) scores each training scan with
        the fold model that never saw it, against that fold model's own reference: out-of-sample scores.
        Without fold models the training scans are cross-fitted: each is projected without its own trained code and
        scored against the reference without its own points (the nets saw it: optimistic). The point
        score's noise model (``reference_.variance_scale`` and ``grazing_scale``,
        :meth:`LocalReference.fit_noise_model`) is fitted on the same scans' residuals first. A model of several
        part types is calibrated per part (``parts_``).

        Parameters
        ----------
        good_scans : datasets.ScanCollection or sequence of Scan (or (m, 3) arrays)
            Good scans. A collection: its good scans, and its training scans count as the model's only when it is
            the model's training collection (same fingerprint); a sequence: scans named like the model's training
            scans are taken to be them.
        y : ignored
        reference_scans : sequence of Scan, optional
            Good scans for the per-location reference instead of the training scans among ``good_scans``.
        split : str, optional
            Calibrate on this split's good scans only.
        cross_fit : bool
            Also calibrate on the training scans (by the fold models, else cross-fitted).

        Returns
        -------
        self
        """
        config = self.config.validated()
        scans, training_given, origins_everywhere = _good_scans(good_scans, self.model)
        # a public layout's collection: its good scans are views rendered from clean templates
        provenance = getattr(good_scans, "provenance", None)
        self._rendered_data = isinstance(provenance, dict) and bool(provenance.get("template_views"))
        self.reading_ = reading_of(good_scans)  # how its files were read: files scored later are read the same
        self.data_fingerprint_ = good_scans.fingerprint() if hasattr(good_scans, "fingerprint") else ""
        parts = model_parts(self.model)
        if parts:
            self.parts_ = {}
            for part in parts:
                selection = select_scans(self.model, scans, reference_scans, split, part, training_given)
                if not selection.calibration:
                    raise ValueError(f"no good calibration scans of part {part!r} (the model was trained on parts "
                                     f"{parts} and calibrates each on its own scans)")
                one = type(self)(**self.get_params(deep=False))
                one.parts_, one._rendered_data = None, self._rendered_data
                one._fit_selection(selection, config, origins_everywhere, cross_fit, f" {part}")
                self.parts_[part] = one
            self._gather_parts()
            return self
        self.parts_ = None
        selection = select_scans(self.model, scans, reference_scans, split, None, training_given)
        return self._fit_selection(selection, config, origins_everywhere, cross_fit)

    def _fit_selection(self, selection, config, origins_everywhere, cross_fit, desc=""):
        if not selection.calibration:
            held = list(getattr(self.model, "calibration_names", None) or [])
            hint = (f"the model's held-back scans (e.g. {held[0]!r}) are not among them: pass the training collection "
                    f"itself or include them" if held else "give good scans it did not train on (a validation split)")
            raise ValueError(f"no good scans the model did not train on to calibrate with; {hint}")
        reference = selection.reference
        if config.point_score != "auto" and POINT_SCORES[config.point_score].reference and not reference:
            raise ValueError(f"point_score {config.point_score!r} needs the model's training scans (among the good "
                             f"scans, or as reference_scans) for its per-location reference")
        with_origins = all(getattr(s, "sensor_origin", None) is not None for s in [*selection.calibration, *reference])
        settings = self._resolved(config, bool(reference), with_origins and origins_everywhere)
        if settings.rays:
            missing = [scan_name(s, i) for i, s in enumerate(selection.calibration)
                       if getattr(s, "sensor_origin", None) is None]
            if missing:
                raise ValueError(f"{len(missing)} of {len(selection.calibration)} calibration scans have no sensor "
                                 f"origin (e.g. {missing[0]!r}); the ray score needs where the sensor was (scanner "
                                 f"files: a <stem>.json sidecar {{\"sensor_origin\": [x, y, z]}}); calibrate "
                                 f"without rays")
        selection = self._sized_selection(selection)
        settings, selection = self._fit_alignment(settings, selection)
        reference = selection.reference
        self.settings_ = settings
        self.reference_ = None
        self.level_rendered_ = bool(getattr(self, "_rendered_data", False)) or all(
            isinstance(getattr(s, "extra", None), dict) and bool(s.extra.get("template")) for s in selection.calibration)
        crossed = []
        if POINT_SCORES[settings.point_score].reference:
            crossed = self._fit_reference(_progress(reference, self.verbose, f"reference{desc}"), selection.surface,
                                          settings)
        held = [self._evidence(self._aligned(s)[0] if settings.align is True else s, i, settings) for i, s in
                enumerate(_progress(selection.calibration, self.verbose, f"calibrate{desc}"))]
        names = [g.name for g in held]
        needs_reference = POINT_SCORES[settings.point_score].reference
        folded = self._fold_evidence(selection, settings, desc) if cross_fit else None
        if folded is not None:  # the fold models' out-of-sample scores replace the cross-fitted ones
            crossed, crossed_references, role = folded[0], folded[1], "fold"
        else:  # training scans cross-fitted: scored by the main model against the reference without their points
            crossed = crossed if cross_fit and needs_reference else []
            crossed_references = [self.reference_.without(j) for j in range(len(crossed))]
            role = "cross-fitted"
        if settings.rays and any(g.origin is None for g in crossed):
            crossed, crossed_references = [], []
        goods = held + crossed
        references = [self.reference_] * len(held) + crossed_references
        if needs_reference:
            kappa, lam = self._fit_noise_model(goods, references, settings)
            for reference_j in references:
                reference_j.variance_scale, reference_j.grazing_scale = kappa, lam
        uncovered = [None] * len(held)
        if needs_reference and crossed:
            uncovered += _uncovered(held, self.reference_, crossed, crossed_references)
        terms = [None] * len(goods)
        if settings.point_score in WEIGHED_SCORES:
            terms = self._fit_term_variances(goods, references, uncovered, settings)
        results = [self._score(good, reference_j, settings, uncovered=out, terms=t, surface=self.reference_)
                   for good, reference_j, out, t in zip(goods, references, uncovered, terms)]
        roles = ["held-back"] * len(held) + [role] * len(crossed)
        how = selection.how
        if crossed:
            how += (f" and {len(crossed)} training scans scored by fold models that never saw them" if role == "fold"
                    else f" and {len(crossed)} training scans cross-fitted")
        self.calibration_source_ = how
        return self._calibrate_from(results, names + [g.name for g in crossed], roles)

    def _fit_term_variances(self, goods, references, uncovered, settings):
        """Weigh the joint score's two terms by what the calibration scans show (:func:`fit_term_variances`, on
        every point of theirs but the stray returns, which no scan's score counts), and set the variances on every
        reference they are scored against. These scans are the ones the threshold is drawn from: held back, or scored
        by a fold model or cross-fitted, none of them part of the reference it is compared with. Returns each scan's
        two terms (computed once)."""
        terms = [reference_terms(reference, good.points, good.value, good.variance, _noise(good, settings),
                                 good.grazing, good.normals, out)
                 for good, reference, out in zip(goods, references, uncovered)]
        kept = [slice(None) if good.stray is None or good.stray.all() else ~good.stray for good in goods]
        variances = fit_term_variances(np.concatenate([t[0][k] for t, k in zip(terms, kept)]),
                                       np.concatenate([t[1][k] for t, k in zip(terms, kept)]))
        for reference in {id(r): r for r in references}.values():
            reference.term_variances = variances
        return terms

    def _fit_alignment(self, settings, selection):
        """Decide ``align='auto'`` (the training scans' pose spread, :func:`inspection.align.pose_spread`) and, when
        scans are registered, move the training scans into one common pose (each registered onto the others,
        :func:`inspection.align.register_group`): the target of every later registration (``aligner_``) and the
        scans the per-location reference is built from. Sets ``aligner_`` and ``alignment_note_``; returns the
        settings with ``align`` decided and the selection with its reference and surface scans registered."""
        self.alignment_note_, self.aligner_ = "", None
        reference = selection.reference
        if settings.align == "auto":
            from datasets.registration import registration_ticks

            from .align import AUTO_RATIO, pose_spread

            with registration_ticks("pose: placed by hand?", self.verbose and bool(reference)) as tick:
                spread = pose_spread(reference, tick=tick) if reference else 1.0
            settings = replace(settings, align=bool(spread > AUTO_RATIO))
            if settings.align is True:
                self.alignment_note_ = (f"the training scans' poses spread (registered onto the others, their "
                                        f"residuals fall by a median {100 * (1 - 1 / spread):.0f} %): every scan is "
                                        f"registered first (calibrate --no-align turns it off)")
        if settings.align is not True:
            return settings, selection
        if not reference:
            raise ValueError("align=True registers every scan onto the model's good training scans: include them "
                             "among the good scans (calibrate on the model's training collection)")
        from datasets.registration import registration_ticks

        from .align import Aligner, register_group

        surface = selection.surface or reference
        with registration_ticks("common pose", self.verbose) as tick:
            moved = dict(zip(map(id, surface), register_group(surface, tick=tick)))
        selection = replace(selection, reference=[moved.get(id(s), s) for s in reference],
                            surface=[moved[id(s)] for s in surface])
        self.aligner_ = Aligner.from_scans(selection.surface)
        return settings, selection

    def _fold_evidence(self, selection, settings, desc=""):
        """The training scans' evidence under the model's fold models (:mod:`autodecoder.latent.folds`): each
        reference scan projected by the fold model that never trained on it, and compared with that fold model's
        per-location reference over every other reference scan (all of them projected by the fold model, as the
        model's own reference is by the model, the scored scan's points left out). Nothing in such a score has seen
        the scan: it is scored as a new scan is, by a model trained on fewer scans, against a reference of one scan
        fewer. (A fold model's reference over its own training scans alone rests on fewer scans and scored good
        scans higher than the main model scores new ones: docs/results.md, issue 27.)

        Returns (evidence list, reference per evidence), or None when the model has no fold models or none of the
        scans they score is among the reference scans."""
        folds = list(getattr(self.model, "calibration_folds", None) or [])
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
            sub = type(self)(**{**self.get_params(deep=False), "model": fold.model, "verbose": False})
            sub.settings_, sub.aligner_ = settings, getattr(self, "aligner_", None)
            if needs_reference:
                evidence = sub._fit_reference(_progress(selection.reference, self.verbose, f"fold {j + 1}{desc}"),
                                              selection.surface, settings)
                references += [sub.reference_.without(i) for i in scored]
            if not needs_reference:  # (with align, the reference scans come registered onto each other)
                evidence = {i: sub._evidence(selection.reference[i], i, settings) for i in scored}
            goods += [evidence[i] for i in scored]
            if not needs_reference:
                references += [None] * len(scored)
        return (goods, references) if goods else None

    def _fit_reference(self, scans, surface_scans, settings, max_points=60000, seed=0):
        """Build ``reference_`` from good scans, each projected as a test scan would be (a training scan without
        starting from its own trained code), with the points and normals of ``surface_scans`` (None: the scans
        themselves) as the good scans' own surface (:meth:`LocalReference.surface`). Returns the scans' evidence
        (for cross-fitting)."""
        goods = [self._evidence(s, i, settings, exclude_own_code=True) for i, s in enumerate(scans)]
        if not goods:
            raise ValueError("the per-location reference needs at least one good scan, got none")
        self.reference_ = LocalReference.from_values([(g.points, g.value) for g in goods], max_points=max_points,
                                                     seed=seed, quantity=REFERENCE_QUANTITY)
        names = [g.name for g in goods]
        if not surface_scans:  # the projected scans themselves, each its own owner
            surface_scans = [_Named(g.name, g.points, g.normals) for g in goods]
        ref = self.reference_
        ref.surface_points, ref.surface_owners, ref.surface_normals = _surface_points(surface_scans, names, seed)
        return goods

    def _fit_noise_model(self, goods, references, settings):
        """:meth:`LocalReference.fit_noise_model` on the residuals of good scans' evidence against the references
        they are scored with (the grazing term only when every one of them has a grazing factor)."""
        residuals, base, field_var, noise_var, grazing = [], [], [], [], []
        for good, reference in zip(goods, references):
            m_ref, s_ref = reference.stats(good.points)
            noise = _noise(good, settings)
            residuals.append(good.value - m_ref)
            base.append(s_ref**2)
            field_var.append(good.variance)
            noise_var.append(np.full(len(good.points), noise**2))
            grazing.append(good.grazing)
        with_grazing = all(g is not None for g in grazing)
        return LocalReference.fit_noise_model(np.concatenate(residuals), np.concatenate(base),
                                              np.concatenate(field_var), np.concatenate(noise_var),
                                              np.concatenate(grazing) if with_grazing else None)

    def fit_level(self, good_scans, source=""):
        """Set the threshold's level from real good scans of the inspection's own sensor, keeping the calibration.

        The template regime's (and any) model calibrates on scans its own data holds: views rendered from clean
        templates, or scans of the training sensor. Good scans of the inspection's own sensor, a first shift's
        worth (4-16), can score higher or lower than those as a whole; given here, they alone set the threshold's
        level while every calibration scan keeps giving its spread (:func:`inspection.threshold.fit_threshold`,
        role ``'site'``): split-conformal on them once there are enough. The per-location reference, the noise
        model, the ray weighing and the registration stay as calibrated. Called again, the new scans replace the
        previous call's.

        Parameters
        ----------
        good_scans : sequence of Scan
            Good scans (in the model's frame; :func:`inspection.loading.load_scans` reads scanner files), none of
            them a scan the model trained on.
        source : str
            Where they came from, for the calibration's record (``calibration_source_``).

        Returns
        -------
        self
        """
        self._check_is_fitted()
        scans = list(good_scans)
        if not scans:
            raise ValueError("fit_level needs at least one good scan of the inspection's own sensor, got none")
        trained = set(str(n) for n in (getattr(self.model, "train_names", None) or []))
        seen = [scan_name(s, i) for i, s in enumerate(scans) if getattr(s, "name", None) in trained]
        if seen:
            raise ValueError(f"{len(seen)} of the {len(scans)} scans are scans the model trained on (e.g. "
                             f"{seen[0]!r}): their scores would be optimistic; give good scans it never saw")
        groups = {}
        for i, s in enumerate(scans):
            groups.setdefault(id(self.for_scan(s)), (self.for_scan(s), []))[1].append((i, s))
        for one, members in groups.values():
            one._set_site_level([one.inspect(s, i).score for i, s in members],
                                [scan_name(s, i) for i, s in members], source)
        if getattr(self, "parts_", None):
            self._gather_parts()
        return self

    def _set_site_level(self, scores, names, source):
        """This (single-part) inspector's threshold with ``scores`` as its 'site' scores (any earlier ones dropped)."""
        keep = [j for j, r in enumerate(self.calibration_roles_) if r != "site"]
        self.level_rendered_ = False
        base = getattr(self, "calibration_source_", "") or ""
        base = base.split("; level from ")[0]
        self.calibration_source_ = (f"{base}; level from {len(scores)} good scan{'s' if len(scores) != 1 else ''} of "
                                    f"the inspection's own sensor{f' ({source})' if source else ''}")
        self._set(np.concatenate([self.calibration_scores_[keep], np.asarray(scores, dtype=np.float64)]),
                  [self.calibration_names_[j] for j in keep] + list(names),
                  [self.calibration_roles_[j] for j in keep] + ["site"] * len(scores))

    def _calibrate_from(self, results, names, roles=None):
        """Calibrate from the :class:`ScanResult` of each good calibration scan (:meth:`inspect_components`'s);
        ``roles`` says for each whether it was held back, scored by a fold model or cross-fitted (default: held
        back).

        Without rays the calibration scores are the point scores' aggregates. With rays the rays are weighed by these
        scans' rays (``combination_``: :mod:`inspection.ray_calibration`) and the calibration scores are the
        combined scores, each scan's ray evidence computed leave-one-out
        (:meth:`inspection.combine.Combination.calibration_scores`). Returns self.
        """
        results = list(results)
        if not results:
            raise ValueError("calibration needs at least one good scan, got none")
        roles = ["held-back"] * len(results) if roles is None else list(roles)
        points = [r.components["points"] for r in results]
        if not self.settings_.rays:
            self.combination_ = None
            return self._set(points, names, roles)
        from .combine import Combination

        scale = getattr(results[0].field, "lengthscale", None) if results[0].field is not None else None
        self.combination_ = Combination.fit(points, [r.rays for r in results], scale,
                                            self.settings_.ray_options["aggregate"])
        return self._set(self.combination_.calibration_scores(), names, roles)

    def _set(self, scores, names, roles):
        scores = np.asarray(scores, dtype=np.float64).reshape(-1)
        if len(scores) == 0 or not np.all(np.isfinite(scores)):
            raise ValueError("calibration scores must be a non-empty array of finite numbers")
        if len(roles) != len(scores):
            raise ValueError(f"roles: one per calibration scan ({len(scores)}), got {len(roles)}")
        self.calibration_scores_ = scores
        self.calibration_names_ = list(names)
        self.calibration_roles_ = list(roles)
        self.n_calibration_ = len(scores)
        self.decision_threshold_ = fit_threshold(scores, self.alpha, self.calibration_roles_)
        self.threshold_ = self.decision_threshold_.value
        self.offset_ = -self.threshold_
        return self

    def _gather_parts(self, source=None):
        """A per-part inspector's own attributes: the parts' settings (shared) and every part's calibration
        scores together (no threshold of its own); ``source`` (None: the parts' sources joined) says where they
        came from."""
        parts = [self.parts_[p] for p in sorted(self.parts_)]
        self.settings_ = parts[0].settings_
        self.calibration_scores_ = np.concatenate([p.calibration_scores_ for p in parts])
        self.calibration_names_ = [n for p in parts for n in p.calibration_names_]
        self.calibration_roles_ = [r for p in parts for r in p.calibration_roles_]
        self.n_calibration_ = len(self.calibration_scores_)
        self.calibration_source_ = "; ".join(p.calibration_source_ for p in parts) if source is None else source

    def _restore(self, calibration):
        """This inspector's fitted state from a single-part calibration record."""
        extra = calibration.extra or {}
        self.settings_ = calibration.config()
        ref = extra.get("reference")
        self.reference_ = None if ref is None else LocalReference.from_dict(ref)
        self.aligner_ = None
        if self.settings_.align == "auto":  # a record from before alignment was a setting: never registered
            self.settings_ = replace(self.settings_, align=False)
        self.alignment_note_ = ""
        if self.settings_.align is True:
            if extra.get("align") is None:
                raise ValueError("its settings say align=True but it stores no alignment target")
            from .align import Aligner

            self.aligner_ = Aligner.from_dict(extra["align"])
        rays = extra.get("rays")
        self.combination_ = None
        if rays is not None:  # (a record whose rays were combined by a retired rule: a ValueError to calibrate again)
            from .combine import Combination

            self.combination_ = Combination.from_dict(rays["components"])
        self.calibration_source_ = calibration.source
        self.data_fingerprint_ = calibration.fingerprint
        self.level_rendered_ = bool(extra.get("level_rendered", False))
        self._set(calibration.scores, calibration.names,
                  list(calibration.roles) or ["held-back"] * len(calibration.scores))

    def calibration(self, source=None, fingerprint=None):
        """The fitted calibration as a :class:`~inspection.calibration.Calibration`, ready to store in the model
        (one record per part type under ``extra['parts']`` for a model of several). ``source`` (None: where the
        calibration scans came from) describes them; ``fingerprint`` (None: the collection :meth:`fit` read, '' for
        scans given as a list) identifies their data."""
        self._check_is_fitted()
        source = self.calibration_source_ if source is None else source
        fingerprint = getattr(self, "data_fingerprint_", "") if fingerprint is None else fingerprint
        settings = self.settings_
        common = dict(scores=self.calibration_scores_.tolist(), names=list(self.calibration_names_),
                      roles=list(self.calibration_roles_), aggregate=settings.aggregate,
                      point_score=settings.point_score, noise=settings.noise, alpha=float(self.alpha), source=source,
                      fingerprint=fingerprint)
        if getattr(self, "parts_", None):
            records = {p: one.calibration(fingerprint=fingerprint).as_dict() for p, one in sorted(self.parts_.items())}
            return Calibration(**common, extra={"config": settings.as_dict(), "parts": records,
                                                "reading": getattr(self, "reading_", None)})
        aligner = getattr(self, "aligner_", None)
        return Calibration(**common, extra={"config": settings.as_dict(), "reading": getattr(self, "reading_", None),
                                            "level_rendered": bool(getattr(self, "level_rendered_", False)),
                                            "reference": None if self.reference_ is None else self.reference_.as_dict(),
                                            "rays": self._ray_record(),
                                            "align": None if aligner is None else aligner.as_dict()})

    def _ray_record(self):
        """What the calibration stores about rays: None, or the calibration component scores (the options are in
        the settings)."""
        if not self.settings_.rays:
            return None
        return {"components": self._combination().as_dict()}

    def summary(self):
        """Per part (a model of several part types; else {}): the threshold, how it was drawn, the number of
        calibration scans and the point score's term variances (summary.json)."""
        return {p: {"threshold": float(i.threshold_), "decision": i.decision_threshold_.as_dict(),
                    "n_calibration": int(i.n_calibration_), "term_variances": i.term_variances()}
                for p, i in sorted((self.parts_ or {}).items())}

    def term_variances(self):
        """[v_d, v_s], the variances on the good calibration scans that weigh the point score's two terms (the
        field's, the good points'; :func:`inspection.scores.fit_term_variances`), or None for a point score without
        them or a model of several part types (each part has its own: :meth:`summary`)."""
        self._check_is_fitted()
        reference = getattr(self, "reference_", None)
        if getattr(self, "parts_", None) or reference is None or self.settings_.point_score not in WEIGHED_SCORES:
            return None
        return [float(v) for v in reference.term_variances]

    def _check_is_fitted(self):
        if not hasattr(self, "calibration_scores_"):
            raise NotFittedError("This Inspector is not calibrated yet: call fit(good_scans) or use "
                                 "Inspector.from_calibration(...) before scoring against a threshold")

    # ------------------------------------------------------------------------------------ sklearn outlier API
    def p_values_from_scores(self, anomaly_scores, scans=None):
        """p-values (n,) of given anomaly scores on the threshold's basis (split-conformal or the log-normal
        predictive tail, :meth:`inspection.threshold.Threshold.p_values`); ``p <= decision_threshold_.alpha_used``
        exactly when the score exceeds ``threshold_``. A model of several part types needs the ``scans`` (for
        their parts)."""
        return self._per_scan(anomaly_scores, scans, lambda one, s: one.decision_threshold_.p_values(s))

    def p_values(self, scans):
        """p-values (n,) of scans; small = unlike the good calibration scans."""
        scans = list(scans)
        return self.p_values_from_scores(self.anomaly_scores(scans), scans)

    def score_samples(self, scans):
        """Normality scores (n,): the negated anomaly score, so HIGHER = MORE NORMAL (scikit-learn convention)."""
        return -self.anomaly_scores(scans)

    def decision_function(self, scans):
        """``score_samples(scans) - offset_``: negative for defective scans, >= 0 for good ones (each against its
        part's threshold)."""
        scans = list(scans)
        return self._per_scan(self.score_samples(scans), scans, lambda one, s: s - one.offset_)

    def predict_from_scores(self, anomaly_scores, scans=None):
        """+1 (good) / -1 (defective) for given anomaly scores: -1 exactly when the score exceeds ``threshold_``
        (a model of several part types: the scans' parts' thresholds; pass the ``scans``)."""
        return self._per_scan(anomaly_scores, scans, lambda one, s: np.where(s > one.threshold_, -1, 1))

    def verdicts_from_scores(self, anomaly_scores, scans=None, uncertain=True):
        """``'good'``, ``'defective'`` or ``'uncertain'`` for given anomaly scores (a model of several part types:
        pass the ``scans``). ``'uncertain'``: the score lies within the threshold's own uncertainty
        (:meth:`inspection.threshold.Threshold.uncertain`), so a rescan says more than the verdict would;
        ``uncertain=False`` gives the two classes of :meth:`predict`."""
        flags = self.predict_from_scores(anomaly_scores, scans)
        verdicts = np.where(flags == -1, "defective", "good").astype(object)
        if uncertain:
            unsure = self._per_scan(anomaly_scores, scans, lambda one, v: one.decision_threshold_.uncertain(v))
            verdicts[np.asarray(unsure, dtype=bool)] = "uncertain"
        return verdicts.astype(str)

    def reasons_from_scores(self, anomaly_scores, scans=None, uncertain=True):
        """Each verdict of :meth:`verdicts_from_scores` in words (list of str): the score against its threshold,
        its p-value and, for ``'uncertain'``, that a rescan says more (:meth:`inspection.threshold.Threshold.reason`):
        what ``nsspr-inspect score``'s report.html shows beside each verdict and ``watch`` journals as ``why``."""
        scores = np.asarray(anomaly_scores, dtype=np.float64).reshape(-1)
        verdicts = self.verdicts_from_scores(scores, scans, uncertain)
        ones = [self.for_scan(s) for s in scans] if getattr(self, "parts_", None) else [self] * len(scores)
        sizes = [self.size_note(scan) for scan in scans] if scans is not None else [""] * len(scores)
        return [(f"{size}; " if size else "") + one.decision_threshold_.reason(float(s), str(v))
                + (f"; {LEVEL_RENDERED_NOTE}" if getattr(one, "level_rendered_", False) else "")
                for one, s, v, size in zip(ones, scores, verdicts, sizes)]

    def size_note(self, scan):
        """'' or, for a scan whose size cannot be the part's, one line saying so: its bounding box's diagonal is more
        than ``SIZE_RATIO`` times the good scans' (the per-location reference's points, the whole part) or less than
        1 / ``SIZE_RATIO`` ** 2 of it (a partial scan is smaller than the part, but not that much). A scan written
        in millimetres against a model of metres is about 1000x: no score says why as plainly."""
        one = self.for_scan(scan)
        reference = getattr(one, "reference_", None)
        points = getattr(scan, "points", scan)
        if reference is None or points is None or len(points) < 2:
            return ""
        good = float(np.linalg.norm(np.ptp(reference.points, axis=0)))
        size = float(np.linalg.norm(np.ptp(np.asarray(points, dtype=np.float64).reshape(-1, 3), axis=0)))
        if not (good > 0 and np.isfinite(size)):
            return ""
        ratio = size / good
        if 1 / SIZE_RATIO ** 2 <= ratio <= SIZE_RATIO:
            return ""
        what = f"about {ratio:.3g}x" if ratio > 1 else f"about 1/{1 / ratio:.3g}"
        return (f"its size is {what} the good scans' (its bounding box's diagonal against theirs, in the model's "
                f"frame): other units (millimetres against metres?) or not this part")

    def predict_verdict(self, scans, uncertain=True, return_reasons=False):
        """The command line's verdict of each scan: ``'good'``, ``'uncertain'`` (its score lies within the
        threshold's own uncertainty: rescan it) or ``'defective'``, exactly what ``nsspr-inspect score`` writes for
        the same scans and calibration (each scan registered first as the calibration says, as ``score`` does).

        Parameters
        ----------
        scans : sequence of Scan
            In the model's frame (:func:`inspection.loading.load_scans` reads scanner files as ``score`` does).
        uncertain : bool
            False: the two classes of :meth:`predict` ('good' / 'defective'), as ``score --two-class``.
        return_reasons : bool
            Also return each verdict in words (:meth:`reasons_from_scores`), from the same scores.

        Returns
        -------
        verdicts : (n,) array of str
        reasons : list of str
            With ``return_reasons``.
        """
        scans = list(scans)
        scores = self.anomaly_scores(scans)
        verdicts = self.verdicts_from_scores(scores, scans, uncertain)
        if return_reasons:
            return verdicts, self.reasons_from_scores(scores, scans, uncertain)
        return verdicts

    def predict(self, scans):
        """+1 for good scans, -1 for defective ones (score > ``threshold_``, i.e. decision_function < 0): the
        two-class view of scikit-learn's outlier detectors. A scan the command line calls ``'uncertain'`` (its score
        within the threshold's own uncertainty) gets -1 or +1 here by the side of the threshold its score lies on;
        :meth:`predict_verdict` gives the command line's three verdicts."""
        scans = list(scans)
        return self.predict_from_scores(self.anomaly_scores(scans), scans)

    def _per_scan(self, values, scans, fn):
        """``fn(inspector, values)`` with each value under the inspector of its scan's part."""
        self._check_is_fitted()
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        if not getattr(self, "parts_", None):
            return fn(self, values)
        if scans is None or len(scans) != len(values):
            raise ValueError("a model of several part types judges each scan against its own part: pass the scans")
        return np.array([fn(self.for_scan(s), values[i:i + 1])[0] for i, s in enumerate(scans)])


def _noise(evidence, settings):
    """The measurement noise a scan's point scores use: the settings' (a length), else its projected field's own."""
    return float(getattr(evidence.field, "noise", 0.0) if settings.noise is None else settings.noise)


def _uncovered(held, reference, crossed, crossed_references, quantile=COVERAGE_QUANTILE):
    """For each training scan scored against the reference without its own points, the (m,) bool of its points
    farther from that reference's surface than ``quantile`` of the held-back scans' points are from the whole
    reference's surface.

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
    for every scan (:func:`inspection.scores.reference_terms`)."""
    distances = [reference.surface_distance(g.points[~g.stray] if g.stray is not None and not g.stray.all()
                                            else g.points) for g in held]
    reach = float(np.quantile(np.concatenate(distances), quantile)) if distances else np.inf
    return [ref_j.surface_distance(g.points) > reach for g, ref_j in zip(crossed, crossed_references)]


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


def _transform_of(scan):
    """The (4, 4) transform a registration recorded in a scan's ``extra['align']``, or None."""
    extra = getattr(scan, "extra", None)
    return extra.get("align") if isinstance(extra, dict) else None
