"""One anomaly score from the point score and the rays' evidence: the negative log likelihood of both.

The point score z (an aggregate of standardized residuals, in standard deviations) and the rays' evidence I (nats:
how much less likely the scan's rays are under the good part than good scans' rays are by chance, weighed per ray,
per place and as a whole by what good calibration scans' rays show, :mod:`inspection.ray_calibration`) are two
independent kinds of evidence against the good part. As negative log likelihoods z^2 / 2 and I add, and the
combined score is put back on the point score's scale:

    c = sqrt(z^2 + 2 I)         (z >= 0; for z < 0, c = z + sqrt(2 I)),

the same rule as the anomaly map's per point (:func:`inspection.maps.with_ray_evidence`). A scan whose rays show
nothing beyond chance (I = 0: every good scan whose rays the calibration vouches for) keeps its point score exactly,
so the rays cannot move it; a hole's rays through a wall that good scans always return, hundreds of nats, put the
scan far beyond any good one. No term's outlier sets the threshold by rule: a good calibration scan whose rays were
accused counts as much as the good scans' rays say such an accusation is worth (its own I computed leave-one-out,
from a tail and places fitted without its rays), and a part whose good scans' rays spread wide gets rays that count
little (the calibration line says so).

The combined score is calibrated like any other (:mod:`inspection.calibration`): the threshold is drawn on the
calibration scans' combined scores, each computed from statistics it took no part in.

(The rules before, ``'max'``, ``'gated'`` and ``'gated-log'``, are retired: gated-log standardized a log ray score
on the calibration scans and counted what passed a gate a hundred times, so that one good calibration scan whose
rays were accused set the threshold, and one good test scan's rays outranked most defective scans; docs/results.md.)
"""
import numpy as np

from .ray_calibration import RayCalibration

RULE = "likelihood"  # the one rule (module docstring); stored with the combination
RETIRED_RULES = ("max", "gated", "gated-log")


def combined_score(points, nats):
    """sqrt(z^2 + 2 I) for z >= 0, z + sqrt(2 I) below 0 (the module docstring): arrays or floats, broadcast."""
    points = np.asarray(points, dtype=np.float64)
    nats = np.maximum(np.asarray(nats, dtype=np.float64), 0.0)
    positive = np.maximum(points, 0.0)
    out = np.sqrt(positive ** 2 + 2.0 * nats) + np.minimum(points, 0.0)
    return float(out) if out.ndim == 0 else out


class Combination:
    """The point score and the rays' evidence of scans, as good calibration scans weigh them (module docstring).

    Parameters
    ----------
    points : (n,) array
        The calibration scans' point scores.
    nats : (n,) array
        Their rays' evidence I, each computed leave-one-out (:meth:`RayCalibration.calibration_nats`); kept as
        ``calibration_nats``.
    rays : RayCalibration
        How a new scan's rays are weighed.
    rule : str
        ``RULE``; a retired rule is a ValueError asking to calibrate again.
    """

    def __init__(self, points, nats, rays, rule=RULE):
        if rule in RETIRED_RULES:
            raise ValueError(f"the combination rule {rule!r} is retired (docs/inspection.md): calibrate again")
        if rule != RULE:
            raise ValueError(f"rule must be {RULE!r}, got {rule!r}")
        self.rule = rule
        self.points = np.asarray(points, dtype=np.float64).reshape(-1)
        self.calibration_nats = np.asarray(nats, dtype=np.float64).reshape(-1)
        if len(self.points) != len(self.calibration_nats) or len(self.points) == 0:
            raise ValueError(f"one point score and one ray evidence per calibration scan, got {len(self.points)} and "
                             f"{len(self.calibration_nats)}")
        nats = self.calibration_nats
        if not (np.isfinite(self.points).all() and np.isfinite(nats).all() and (nats >= 0).all()):
            raise ValueError("the calibration scans' point scores must be finite and their ray evidence finite and >= 0")
        if not isinstance(rays, RayCalibration):
            raise TypeError(f"rays must be a RayCalibration, got {type(rays).__name__}")
        self.rays = rays

    @classmethod
    def fit(cls, points, evidences, lengthscale, aggregate):
        """From the calibration scans' point scores (n,) and their :class:`inspection.ray_evidence.RayEvidence`
        (:meth:`RayCalibration.fit`)."""
        rays = RayCalibration.fit(list(evidences), lengthscale, aggregate)
        return cls(points, rays.calibration_nats(), rays)

    def nats(self, evidence):
        """The rays' evidence I of a new scan (its :class:`~inspection.ray_evidence.RayEvidence`), nats."""
        return self.rays.nats(evidence)[1]

    def score(self, points, evidence):
        """The combined score of a new scan: its point score and its ray evidence."""
        return combined_score(points, self.nats(evidence))

    def calibration_scores(self):
        """The calibration scans' combined scores (n,)."""
        return combined_score(self.points, self.calibration_nats)

    def as_dict(self):
        """Plain Python values: the rule, the calibration scans' point scores and ray evidence, the rays' weighing."""
        return {"rule": self.rule, "points": self.points.tolist(), "nats": self.calibration_nats.tolist(),
                "rays": self.rays.as_dict()}

    @classmethod
    def from_dict(cls, d):
        """The combination :meth:`as_dict` stored; one stored under a retired rule (a record without a rule was made
        with ``'gated'``) is a ValueError asking to calibrate again."""
        rule = d.get("rule", "gated")
        if rule in RETIRED_RULES:
            raise ValueError(f"its rays were combined by the retired rule {rule!r} (docs/inspection.md): calibrate "
                             f"again")
        return cls(d["points"], d["nats"], RayCalibration.from_dict(d["rays"]), rule=rule)
