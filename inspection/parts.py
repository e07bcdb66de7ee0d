"""Per-part inspection: one calibrated Inspector per part type of a latent model trained on several part types.

A latent model records the part id of every training scan (``train_part_ids``). When it holds two or more part types,
a scan is judged against good scans of its own part only: its projection starts from its part's training codes
(:func:`autodecoder.latent.projection.part_codes`), and the per-location reference, the calibration scores and the
threshold are the part's own. The good scans of one part say nothing about the noise floor of another (a bracket's
edges are not a casing's), and a threshold pooled over parts would trade one part's false alarms for the other's
misses. A scan's part is its ``part_id``; a scan without one, or of a part the model was not trained on, cannot be
judged this way and is a ValueError naming the parts the model knows.
"""
import numpy as np


def model_parts(model):
    """The part ids a latent model was trained on, sorted, when there are two or more; else [] (one inspector)."""
    parts = sorted({str(p) for p in (getattr(model, "train_part_ids", None) or []) if p})
    return parts if len(parts) >= 2 else []


class PartInspector:
    """Inspectors by part id, one per part type of the model, behind the interface the command line scores with.

    Parameters
    ----------
    inspectors : dict of str -> inspection.Inspector
        Calibrated (or to be calibrated) inspectors, one per part id, over the same model with the same settings.

    Notes
    -----
    ``inspect(scan)`` gives the scan's score under its part's inspector, so scores are comparable within a part
    (per-part ROC curves), not across parts; :meth:`for_scan` gives the inspector whose threshold and p-values
    apply.
    """

    def __init__(self, inspectors):
        self.inspectors = dict(inspectors)
        if len(self.inspectors) < 1:
            raise ValueError("PartInspector needs at least one part's inspector")

    @property
    def parts(self):
        return sorted(self.inspectors)

    def for_scan(self, scan):
        """The inspector of ``scan``'s part (its ``part_id``)."""
        part = str(getattr(scan, "part_id", "") or "")
        if part not in self.inspectors:
            name = getattr(scan, "name", "") or "a scan"
            what = f"part_id {part!r}" if part else "no part_id"
            raise ValueError(f"{name}: {what}, but the model was trained on several part types {self.parts} and "
                             f"judges a scan against good scans of its own part; set the scan's part_id to one of them")
        return self.inspectors[part]

    def inspect(self, scan):
        return self.for_scan(scan).inspect(scan)

    def anomaly_scores(self, scans):
        """Per-scan anomaly scores (n,), each under its part's inspector."""
        return np.array([self.inspect(s).score for s in scans], dtype=np.float64)

    def predict(self, scans):
        """+1 good / -1 defective, each scan against its part's threshold."""
        return np.array([self.for_scan(s).predict_from_scores([self.inspect(s).score])[0] for s in scans])

    # settings shared by the parts' inspectors (the same for all of them)
    def __getattr__(self, name):
        if name in ("alpha", "aggregate", "point_score", "noise", "projection", "rays", "ray_options", "model"):
            return getattr(next(iter(self.__dict__["inspectors"].values())), name)
        raise AttributeError(name)

    @property
    def n_calibration_(self):
        return sum(i.n_calibration_ for i in self.inspectors.values())

    @property
    def calibration_scores_(self):
        return np.concatenate([self.inspectors[p].calibration_scores_ for p in self.parts])

    def calibration(self, source="", fingerprint=""):
        """One :class:`~inspection.calibration.Calibration` holding every part's (``extra['parts']``); its own
        scores and names are all parts' together (for reading, not for a threshold)."""
        from .calibration import Calibration

        records = {p: self.inspectors[p].calibration(source=f"{source}, part {p}", fingerprint=fingerprint)
                   for p in self.parts}
        first = records[self.parts[0]]
        return Calibration(scores=[s for p in self.parts for s in records[p].scores],
                           names=[n for p in self.parts for n in records[p].names],
                           roles=[r for p in self.parts for r in records[p].roles],
                           aggregate=first.aggregate, point_score=first.point_score, noise=first.noise,
                           alpha=first.alpha, source=source, fingerprint=fingerprint,
                           extra={**first.extra, "reference": None, "parts": {p: r.as_dict() for p, r in records.items()}})

    @classmethod
    def from_calibration(cls, model, calibration, alpha=None):
        """The PartInspector of a stored per-part calibration (``calibration.extra['parts']``)."""
        from .calibration import Calibration
        from .estimator import Inspector

        out = {}
        for part, record in calibration.extra["parts"].items():
            c = Calibration.from_dict(record)
            out[part] = Inspector(model, alpha=c.alpha if alpha is None else alpha).set_calibration(c)
        return cls(out)

    def summary(self):
        """Per part: the threshold, how it was drawn, and the number of calibration scans (summary.json)."""
        return {p: {"threshold": float(i.threshold_), "decision": i.decision_threshold_.as_dict(),
                    "n_calibration": int(i.n_calibration_)} for p, i in sorted(self.inspectors.items())}
