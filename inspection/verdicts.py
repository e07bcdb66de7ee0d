"""What a fitted inspector's thresholds say of anomaly scores: p-values, the two and three verdicts, their reasons.

:class:`VerdictMixin` gives :class:`inspection.Inspector` (as scikit-learn's ``OutlierMixin`` gives its detectors)
the judgement of scores already computed, each against the threshold of its scan's part type, so that the command
line scores every scan once and draws its verdict, p-value and reason from that one score.
"""
import numpy as np
from sklearn.exceptions import NotFittedError

SIZE_RATIO = 10.0  # a scan this many times the good scans' size (or 1 / SIZE_RATIO^2 of it) is told why (size_note)
# what every verdict says when the threshold's level was set by views rendered from clean templates alone (the
# template regime): real partial scans of another sensor can score above all of them (issue 47)
LEVEL_RENDERED_NOTE = ("the threshold's level rests on views rendered from the templates only: real scans of another "
                       "sensor may score higher; `nsspr-inspect calibrate --model MODEL --data GOOD_SCANS` with a few "
                       "real good scans of this sensor sets it from them")


class VerdictMixin:
    """Judging anomaly scores (higher = more anomalous) against fitted thresholds.

    The host class's fitted attributes: ``calibration_scores_``, ``parts_`` (part id -> fitted single-part inspector
    for a model of several part types, else None) and, on each single-part inspector, ``threshold_``,
    ``decision_threshold_`` (:class:`inspection.threshold.Threshold`), ``level_rendered_`` and ``reference_``. A model
    of several part types judges each scan against its own part: pass the ``scans``.
    """

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

    def _check_is_fitted(self):
        """A NotFittedError unless calibrated (by ``fit`` or ``from_calibration``)."""
        if not hasattr(self, "calibration_scores_"):
            raise NotFittedError("This Inspector is not calibrated yet: call fit(good_scans) or use "
                                 "Inspector.from_calibration(...) before scoring against a threshold")

    def p_values_from_scores(self, anomaly_scores, scans=None):
        """p-values (n,) of given anomaly scores on the threshold's basis
        (:meth:`inspection.threshold.Threshold.p_values`): ``p <= decision_threshold_.alpha_used`` exactly when the
        score exceeds ``threshold_``. A model of several part types needs the ``scans`` (for their parts)."""
        return self._per_scan(anomaly_scores, scans, lambda one, s: one.decision_threshold_.p_values(s))

    def predict_from_scores(self, anomaly_scores, scans=None):
        """+1 (good) / -1 (defective) for given anomaly scores: -1 exactly when the score exceeds ``threshold_``
        (a model of several part types: the scans' parts' thresholds; pass the ``scans``)."""
        return self._per_scan(anomaly_scores, scans, lambda one, s: np.where(s > one.threshold_, -1, 1))

    def verdicts_from_scores(self, anomaly_scores, scans=None, uncertain=True):
        """``'good'``, ``'defective'`` or ``'uncertain'`` (the score lies within the threshold's own uncertainty,
        :meth:`inspection.threshold.Threshold.uncertain`) for given anomaly scores (several part types: pass the
        ``scans``); ``uncertain=False`` gives the two classes of :meth:`predict`."""
        flags = self.predict_from_scores(anomaly_scores, scans)
        verdicts = np.where(flags == -1, "defective", "good").astype(object)
        if uncertain:
            unsure = self._per_scan(anomaly_scores, scans, lambda one, v: one.decision_threshold_.uncertain(v))
            verdicts[np.asarray(unsure, dtype=bool)] = "uncertain"
        return verdicts.astype(str)

    def reasons_from_scores(self, anomaly_scores, scans=None, uncertain=True):
        """Each verdict of :meth:`verdicts_from_scores` in words (list of str): the score against its threshold,
        its p-value, for ``'uncertain'`` that a rescan says more (:meth:`inspection.threshold.Threshold.reason`),
        and any :meth:`size_note` and ``LEVEL_RENDERED_NOTE``: what report.html shows and ``watch`` journals."""
        scores = np.asarray(anomaly_scores, dtype=np.float64).reshape(-1)
        verdicts = self.verdicts_from_scores(scores, scans, uncertain)
        ones = [self.for_scan(s) for s in scans] if getattr(self, "parts_", None) else [self] * len(scores)
        sizes = [self.size_note(scan) for scan in scans] if scans is not None else [""] * len(scores)
        return [(f"{size}; " if size else "") + one.decision_threshold_.reason(float(s), str(v))
                + (f"; {LEVEL_RENDERED_NOTE}" if getattr(one, "level_rendered_", False) else "")
                for one, s, v, size in zip(ones, scores, verdicts, sizes)]

    def verdicts_from_results(self, results, scans=None, uncertain=True):
        """The verdicts and their reasons (two lists of str) of scans already inspected (their
        :class:`inspection.scoring.ScanResult`): :meth:`verdicts_from_scores` and :meth:`reasons_from_scores` of their
        scores, then what their coverage says (:func:`inspection.coverage.coverage_verdict`: a scan whose evidence
        lies on surface no good scan saw is 'uncertain', never 'good') and, for a family whose members differ, where
        the scan's member lies (:func:`inspection.family_range.family_verdict`: outside the trained family,
        'uncertain', never 'defective'). ``uncertain=False``: the two classes, coverage and the family aside.
        Several part types: pass the ``scans``."""
        from .coverage import coverage_verdict
        from .family_range import family_verdict

        results = list(results)
        scores = [r.score for r in results]
        verdicts = list(self.verdicts_from_scores(scores, scans, uncertain))
        reasons = self.reasons_from_scores(scores, scans, uncertain)
        if not uncertain:
            return verdicts, reasons
        ones = [self.for_scan(s) for s in scans] if getattr(self, "parts_", None) else [self] * len(results)
        judged = [family_verdict(*coverage_verdict(str(v), why, r.coverage, one.threshold_, r.score),
                                 r.family)
                  for v, why, r, one in zip(verdicts, reasons, results, ones)]
        return [v for v, _ in judged], [why for _, why in judged]

    def size_note(self, scan):
        """'' or, for a scan whose size cannot be the part's, one line saying so: its bounding box's diagonal is more
        than ``SIZE_RATIO`` times the good scans' (the per-location reference's points, the whole part) or less than
        1 / ``SIZE_RATIO`` ** 2 of it (a partial scan is smaller than the part, but not that much). A scan written
        in millimetres against a model of metres is about 1000x: no score says why as plainly."""
        reference = getattr(self.for_scan(scan), "reference_", None)
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

    def _per_scan(self, values, scans, fn):
        """``fn(inspector, values)`` with each value under the inspector of its scan's part."""
        self._check_is_fitted()
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        if not getattr(self, "parts_", None):
            return fn(self, values)
        if scans is None or len(scans) != len(values):
            raise ValueError("a model of several part types judges each scan against its own part: pass the scans")
        return np.array([fn(self.for_scan(s), values[i:i + 1])[0] for i, s in enumerate(scans)])
