"""Inspector: a scikit-learn style outlier detector over scans, calibrated on good scans; the one inspection pipeline.

``Inspector(model).fit(good_scans)`` does what ``nsspr-inspect calibrate`` does, and the command line calls it: the
settings are :class:`inspection.config.InspectionConfig`'s (its fields are the estimator's parameters, with the same
defaults), and the calibration procedure is :func:`inspection.calibrating.calibrate` (good scans sorted into their
roles, one calibration per part type of a model of several). The class keeps the estimator's contract: its
parameters, ``fit``, the scores and verdicts, the fitted attributes ending in ``_``; a scan's score is
:mod:`inspection.scoring`'s, the stored record :mod:`inspection.calibration`'s.
"""
from dataclasses import asdict, fields, replace

import numpy as np
from sklearn.base import BaseEstimator
from sklearn.exceptions import NotFittedError

from .calibration import Calibration, FittedState
from .config import DEFAULT_AGGREGATE, DEFAULT_PROJECTION, InspectionConfig
from .evidence import field_for, scan_name, stage
from .scores import WEIGHED_SCORES
from .scoring import ScanResult, score_scan, weigh_rays
from .threshold import fit_threshold
from .regions import RegionMixin
from .verdicts import VerdictMixin

_DEFAULTS = InspectionConfig()  # the parameters' defaults: InspectionConfig's, stated once

__all__ = ["Inspector", "NotFittedError", "ScanResult", "field_for", "DEFAULT_AGGREGATE", "DEFAULT_PROJECTION"]


class Inspector(VerdictMixin, RegionMixin, BaseEstimator):
    """Defect detector over scans: per-point scores under the projected field, one score per scan, and a threshold
    calibrated on good scans (:mod:`inspection.threshold`: split-conformal when there are at least 1 / alpha - 1 of
    them, else a log-normal tail fitted to their scores; either way a false-alarm rate of ``alpha`` on average).

    Parameters
    ----------
    model : latent model, field or callable
        See :func:`inspection.evidence.field_for`. Scans must be in the model's frame. A latent model records its
        training and held-back scans by name, which :meth:`fit` uses to sort the good scans it is given.
    alpha, aggregate, point_score, noise, projection, rays, ray_options, align, coverage
        :class:`inspection.config.InspectionConfig`'s fields, with its defaults; ``'auto'`` settings are decided by
        :meth:`fit` and recorded in ``settings_``, never in the parameters.
    verbose : bool
        Progress bars on the long work (projecting the reference and calibration scans).

    Attributes (after :meth:`fit` or :meth:`from_calibration`)
    --------------------------------------------------------
    settings_ : InspectionConfig
        The settings in force: 'auto' decided, ``ray_options`` complete (None without rays), ``projection`` the
        ``project`` options (None for a fixed field).
    calibration_scores_ : (n,) array
        Anomaly scores of the calibration scans.
    calibration_names_, calibration_roles_ : list of str
        Their names and roles: ``'held-back'``, ``'fold'`` (a training scan scored by a fold model that never saw
        it), ``'cross-fitted'`` (a training scan scored by the main model as if new) or ``'site'`` (:meth:`fit_level`).
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
        How the collection :meth:`fit` read had read its scanner files (None for scans given as a list).
    combination_ : Combination or None
        The standardization of the components on the calibration scans (with rays).
    aligner_ : inspection.align.Aligner or None
        With ``align``: the registration onto good training scans every scan goes through before it is scored.
    alignment_note_ : str
        One line when ``align='auto'`` decided to register the scans ('' otherwise).
    level_rendered_ : bool
        Whether the threshold's level rests on views rendered from clean templates alone (``LEVEL_RENDERED_NOTE``).
    parts_ : dict of str -> Inspector, or None
        A model of several part types: one fitted inspector per part (:meth:`for_scan` picks a scan's); this
        inspector's own calibration attributes then hold every part's scores together and ``threshold_`` is not set.
    """

    def __init__(self, model, alpha=_DEFAULTS.alpha, aggregate=_DEFAULTS.aggregate, point_score=_DEFAULTS.point_score,
                 noise=_DEFAULTS.noise, projection=_DEFAULTS.projection, rays=_DEFAULTS.rays,
                 ray_options=_DEFAULTS.ray_options, align=_DEFAULTS.align, coverage=_DEFAULTS.coverage, verbose=False):
        self.model = model
        self.alpha = alpha
        self.aggregate = aggregate
        self.point_score = point_score
        self.noise = noise
        self.projection = projection
        self.rays = rays
        self.ray_options = ray_options
        self.align = align
        self.coverage = coverage
        self.verbose = verbose

    @property
    def config(self):
        """The parameters as an :class:`~inspection.config.InspectionConfig` (not validated)."""
        return InspectionConfig(**{f.name: getattr(self, f.name) for f in fields(InspectionConfig)})

    @classmethod
    def from_config(cls, model, config=None, verbose=False):
        """An inspector of ``model`` with the settings of ``config`` (None: the defaults)."""
        return cls(model, **asdict(config or InspectionConfig()), verbose=verbose)

    @classmethod
    def from_calibration(cls, model, calibration, alpha=None, verbose=False):
        """A new, fitted inspector from a stored :class:`~inspection.calibration.Calibration` (one per part type
        when the model was trained on several); ``alpha`` (None: the calibration's) sets the threshold."""
        insp = cls.from_config(model, replace(calibration.config(), alpha=calibration.alpha if alpha is None
                                              else alpha), verbose)
        insp.reading_, insp.data_fingerprint_ = calibration.reading, calibration.fingerprint
        parts = calibration.parts()
        if not parts:
            return insp._adopt(calibration.state())
        insp.parts_ = {p: cls.from_calibration(model, record, alpha, verbose) for p, record in parts.items()}
        return insp._gather_parts(calibration.source)

    def fit(self, good_scans, y=None, reference_scans=None, split=None, cross_fit=True):
        """Calibrate on good scans (:func:`inspection.calibrating.calibrate`, whose docstring gives the procedure
        and the parameters): the model's held-back scans among them, and its training scans scored out of sample
        (by fold models, else cross-fitted) with ``cross_fit``, give the calibration scores; the training scans (or
        ``reference_scans``) the per-location reference; ``split`` limits them to one split. ``y`` is ignored.
        Returns self."""
        from .calibrating import calibrate

        fitted = calibrate(self.model, good_scans, self.config, reference_scans, split, cross_fit, self.verbose)
        self.reading_, self.data_fingerprint_ = fitted.reading, fitted.fingerprint
        if fitted.parts is None:
            return self._adopt(fitted.state)
        self.parts_ = {p: type(self)(**self.get_params(deep=False))._adopt(s) for p, s in fitted.parts.items()}
        return self._gather_parts()

    def fit_level(self, good_scans, source=""):
        """Set the threshold's level from real good scans of the inspection's own sensor (4-16, none of them a scan
        the model trained on), keeping the calibration: they alone set the level while every calibration scan keeps
        giving its spread (:func:`inspection.threshold.fit_threshold`, role ``'site'``). The reference, noise model,
        rays' weighing and registration stay as calibrated; a later call's scans replace these. ``source`` says
        where they came from (``calibration_source_``). Returns self."""
        from .calibrating import site_scans

        self._check_is_fitted()
        groups = {}
        for i, s in enumerate(site_scans(self.model, good_scans)):
            groups.setdefault(id(self.for_scan(s)), (self.for_scan(s), []))[1].append((i, s))
        for one, members in groups.values():
            keep = [j for j, r in enumerate(one.calibration_roles_) if r != "site"]  # earlier site scans dropped
            base = (getattr(one, "calibration_source_", "") or "").split("; level from ")[0]
            one.level_rendered_ = False
            one.calibration_source_ = (f"{base}; level from {len(members)} good scan{'s' if len(members) != 1 else ''}"
                                       f" of the inspection's own sensor{f' ({source})' if source else ''}")
            one._set(np.concatenate([one.calibration_scores_[keep], [one.inspect(s, i).score for i, s in members]]),
                     [one.calibration_names_[j] for j in keep] + [scan_name(s, i) for i, s in members],
                     [one.calibration_roles_[j] for j in keep] + ["site"] * len(members))
        return self._gather_parts() if getattr(self, "parts_", None) else self

    def _adopt(self, state: FittedState):
        """This (single-part) inspector fitted with ``state``: its attributes, and the threshold at ``alpha``."""
        self.parts_ = None
        self.settings_, self.reference_, self.combination_ = state.settings, state.reference, state.combination
        self.aligner_, self.alignment_note_, self.level_rendered_ = state.aligner, state.alignment_note, \
            bool(state.level_rendered)
        self.calibration_source_ = state.source
        self.region_maxima_ = state.region_maxima
        self.region_roles_ = list(state.roles if state.region_roles is None else state.region_roles)
        return self._set(state.scores, state.names, state.roles)

    def _set(self, scores, names, roles):
        scores = np.asarray(scores, dtype=np.float64).reshape(-1)
        if len(scores) == 0 or not np.all(np.isfinite(scores)):
            raise ValueError("calibration scores must be a non-empty array of finite numbers")
        if len(roles) != len(scores):
            raise ValueError(f"roles: one per calibration scan ({len(scores)}), got {len(roles)}")
        self.calibration_scores_, self.calibration_names_, self.calibration_roles_ = scores, list(names), list(roles)
        self.n_calibration_ = len(scores)
        self.decision_threshold_ = fit_threshold(scores, self.alpha, self.calibration_roles_)
        self.threshold_ = self.decision_threshold_.value
        self.offset_ = -self.threshold_
        return self

    def _gather_parts(self, source=None):
        """A per-part inspector's own attributes: the parts' settings (shared) and every part's calibration scores
        together (no threshold of its own); ``source`` (None: the parts' sources joined). Returns self."""
        parts = [self.parts_[p] for p in sorted(self.parts_)]
        self.settings_ = parts[0].settings_
        self.calibration_scores_ = np.concatenate([p.calibration_scores_ for p in parts])
        self.calibration_names_ = [n for p in parts for n in p.calibration_names_]
        self.calibration_roles_ = [r for p in parts for r in p.calibration_roles_]
        self.n_calibration_ = len(self.calibration_scores_)
        self.calibration_source_ = "; ".join(p.calibration_source_ for p in parts) if source is None else source
        return self

    def calibration(self, source=None, fingerprint=None):
        """The fitted calibration as a :class:`~inspection.calibration.Calibration` record, ready to store in the
        model (one record per part type for a model of several). ``source`` (None: ``calibration_source_``) and
        ``fingerprint`` (None: ``data_fingerprint_``) describe the calibration scans."""
        self._check_is_fitted()
        source = self.calibration_source_ if source is None else source
        fingerprint = getattr(self, "data_fingerprint_", "") if fingerprint is None else fingerprint
        parts = {p: one.calibration(fingerprint=fingerprint)
                 for p, one in (getattr(self, "parts_", None) or {}).items()}
        state = FittedState(self.settings_, self.calibration_scores_, self.calibration_names_, self.calibration_roles_,
                            source, getattr(self, "reference_", None), getattr(self, "combination_", None),
                            getattr(self, "aligner_", None), "", getattr(self, "level_rendered_", False),
                            getattr(self, "region_maxima_", None), getattr(self, "region_roles_", None))
        return Calibration.from_state(state, self.alpha, source, fingerprint, getattr(self, "reading_", None), parts)

    def summary(self):
        """Per part (a model of several part types; else {}): the threshold, how it was drawn, the number of
        calibration scans and the point score's term variances (summary.json)."""
        return {p: {"threshold": float(i.threshold_), "decision": i.decision_threshold_.as_dict(),
                    "n_calibration": int(i.n_calibration_), "term_variances": i.term_variances()}
                for p, i in sorted((self.parts_ or {}).items())}

    def term_variances(self):
        """[v_d, v_s], the variances on the good calibration scans that weigh the point score's two terms
        (:func:`inspection.scores.fit_term_variances`), or None for a point score without them or a model of
        several part types (each part has its own: :meth:`summary`)."""
        self._check_is_fitted()
        reference = getattr(self, "reference_", None)
        if getattr(self, "parts_", None) or reference is None or self.settings_.point_score not in WEIGHED_SCORES:
            return None
        return [float(v) for v in reference.term_variances]

    def _settings(self):
        """The settings in force: ``settings_`` once fitted, else the parameters with 'auto' decided as without good
        scans (point score ``'residual'``, no rays, no registration), so that an unfitted inspector can score."""
        settings = getattr(self, "settings_", None)
        if settings is None:
            settings = self.config.validated().decided(self.model, False, False)
            settings = replace(settings, align=False) if settings.align == "auto" else settings
        return settings

    def _combination(self):
        combination = getattr(self, "combination_", None)
        if combination is None:
            raise NotFittedError("rays=True: the combined score standardizes the point and ray scores on the "
                                 "calibration scans; call fit(good_scans) or Inspector.from_calibration(...) first "
                                 "(inspect_components works unfitted)")
        return combination

    # ------------------------------------------------------------------------------------------------ scoring
    def inspect(self, scan, index=0, timings=None):
        """Register, project and score one scan (:func:`inspection.scoring.score_scan`) under its part's
        inspector: a :class:`ScanResult`; with rays its score is the combination, which needs calibration.
        ``timings`` (a dict) receives the seconds of each stage (``sample``, ``align``, ``load``, ``projection``,
        ``field``, ``grazing``, ``stray``, ``reference``, ``aggregate``, ``rays``, ``combine``). A scan much denser
        than the training scans is scored on a subset at their density: the result's ``sample``."""
        one = self.for_scan(scan)
        combination = one._combination() if one._settings().rays else None  # before the work: fail fast
        result = one.inspect_components(scan, index, timings)
        if combination is not None:
            with stage(timings, "combine"):
                weigh_rays(result, combination)
        return result

    def inspect_components(self, scan, index=0, timings=None):
        """Like :meth:`inspect`, but ``score`` is the point score's aggregate alone; works unfitted (except for
        the per-location point scores, which need their reference)."""
        one = self.for_scan(scan)
        return score_scan(one.model, scan, index, one._settings(), getattr(one, "reference_", None),
                          getattr(one, "aligner_", None), timings)

    def anomaly_scores(self, scans):
        """Per-scan anomaly scores (n,) (higher = more anomalous), each under its part's inspector. Works unfitted,
        except with rays."""
        return np.array([self.inspect(s, i).score for i, s in enumerate(scans)], dtype=np.float64)

    def anomaly_map(self, scan):
        """The scan's anomaly map (m,): each point's patch residual, with its ray's evidence where the calibration
        scores rays, in standard deviations (higher = more anomalous; :mod:`inspection.maps`), what the PLY maps and
        the report show. The points' own scores are ``inspect_components(scan).point_scores``. Works unfitted. A scan
        much denser than the training scans is scored on a subset at their density (:mod:`inspection.resolution`):
        its map still has a value for every point, each scored point's carried to those nearest it."""
        from .maps import map_values

        one = self.for_scan(scan)
        result = one.inspect_components(scan)
        if one._settings().rays and getattr(one, "combination_", None) is not None:
            weigh_rays(result, one.combination_)
        return result.full(map_values(one._settings(), result.scored(scan), result)[0])

    def ray_map(self, scan):
        """Per-point ray scores (m,) in [0, 1] of one scan (with rays; see :mod:`inspection.ray_evidence`)."""
        one = self.for_scan(scan)
        if not one._settings().rays:
            raise ValueError("ray_map needs an Inspector that scores the rays (rays=True, or 'auto' decided on)")
        result = one.inspect_components(scan)
        return result.full(result.rays.point_map)

    # ------------------------------------------------------------------------------------ sklearn outlier API
    def score_samples(self, scans):
        """Normality scores (n,): the negated anomaly score, so HIGHER = MORE NORMAL (scikit-learn convention)."""
        return -self.anomaly_scores(scans)

    def decision_function(self, scans):
        """``score_samples(scans) - offset_``: negative for defective scans, >= 0 for good ones (each against its
        part's threshold)."""
        scans = list(scans)
        return self._per_scan(self.score_samples(scans), scans, lambda one, s: s - one.offset_)

    def predict(self, scans):
        """+1 for good scans, -1 for defective ones (score > ``threshold_``, i.e. decision_function < 0). A scan the
        command line calls ``'uncertain'`` gets the side of the threshold its score lies on (:meth:`predict_verdict`
        gives the three verdicts)."""
        scans = list(scans)
        return self.predict_from_scores(self.anomaly_scores(scans), scans)

    def predict_verdict(self, scans, uncertain=True, return_reasons=False):
        """The command line's verdict of each scan (in the model's frame, registered first as the calibration
        says): ``'good'``, ``'uncertain'`` (its score lies within the threshold's own uncertainty, or its evidence
        on surface no good scan saw: :meth:`verdicts_from_results`) or ``'defective'``, exactly what ``nsspr-inspect
        score`` writes. ``uncertain=False``: the two classes of :meth:`predict`. Returns the verdicts (n,) of str,
        and with ``return_reasons`` each in words."""
        scans = list(scans)
        verdicts, reasons = self.verdicts_from_results([self.inspect(s, i) for i, s in enumerate(scans)], scans,
                                                       uncertain)
        verdicts = np.array(verdicts, dtype=str)
        return (verdicts, reasons) if return_reasons else verdicts

    def p_values(self, scans):
        """p-values (n,) of scans; small = unlike the good calibration scans."""
        scans = list(scans)
        return self.p_values_from_scores(self.anomaly_scores(scans), scans)
