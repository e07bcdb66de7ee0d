"""One anomaly score from the point score and the ray score, calibrated on good scans.

The first component (the point score) is the base; every other one (the ray score) adds only what it shows beyond
what good scans show on it. Each component j of a scan's scores s (higher = more anomalous) is taken on its scale
(the point score as it is; a ray score, a sum of surprisals in nats, >= 0 and heavy-tailed on good scans: most score
~0, a few tens of nats, as log(1 + s_j)) and standardized against the good calibration scans,
z_j = (x_j - mean_j) / sd_j; then

    c(s) = s_0 + sd_0 w sum_{j >= 1} max(0, z_j - tau_j),

with the gate tau_j the ``LOG_GATE_QUANTILE`` (0.9) quantile of the calibration scans' z_j plus ``LOG_GATE_MARGIN``
(2) of their standard deviations, and at least ``LOG_GATE_TOP_MARGIN`` (0.75) standard deviations beyond the
largest calibration scan's z_j (up to the ceiling's bound below), and the excess counted ``LOG_GATE_WEIGHT`` (100)
times (the point score itself plus the excess in units of its spread on good scans, kept on the point score's
positive scale, which the log-normal tail of :mod:`inspection.threshold` needs).

Why: the ray score is evidence of one defect type (material missing where the sensor looked through) and noise on
all others: on an unseen part, good and dented scans alike get rays that graze the field's blurred walls. Below the
gate that noise changes nothing, so a scan is ranked by its point score exactly as without the rays. A quantile,
not the largest calibration value, sets the gate, so that one good calibration scan with a heavy ray tail cannot
close it for every scan (the rule before, ``'gated'``, retired: on benchmarks' enclosure the rays then added nothing).
Most good scans' rays score exactly 0 once rays that skim past the good surface are left out
(:mod:`inspection.ray_evidence`), and a quantile of such scores says nothing of the few good scans whose single rays
still reach 75-113 nats (the thin cup): with the gate at the floor they outranked every dent. So the gate is also
at least just beyond the largest calibration scan's ray score; the ceiling's bound below keeps one heavy calibration
scan from closing it (docs/results.md, issue 29; margins from 0.5 to 1 standard deviation gave the same verdicts
on the 33 runs of the verdicts suite, 1.25 and more lowered the enclosure's AUROC). The gate is strict (on
real range scans with pose changes, good test scans' rays went beyond every calibration scan's, and a looser gate
let them outrank dented scans), and beyond it the rays decide: a scan whose rays show what
no good scan's do is ranked above those that pass on their point scores (a hole's rays score hundreds of nats where
good ones score 0-40), which the large weight does while keeping one scale. With ``ceiling`` given (the largest
value a component can take; a ray score's is :data:`autodecoder.scanning.free_space.MAX_SURPRISAL`, 690.8 nats,
where each ray's probability of being free is floored at 1e-300), the gate is at most log(1 + ceiling /
``LOG_GATE_CEILING_FACTOR``) (4: a quarter of the ceiling, 173 nats): calibration scans whose log ray scores spread
widely (many at 0, a few at tens of nats) could otherwise put the gate above the ceiling, where no scan can pass it.
With ``floor`` given (the smallest value of a component that can count: for ray scores
``RAY_GATE_FLOOR``, 40 nats), the gate is at least log(1 + floor): a few calibration scans whose
rays are all near 0 (8 training scans on a solid part: 0-4 nats) would otherwise put the gate at 1-2 nats, where any
good scan's grazing rays pass it (good test scans' ray scores reached 400 to 4,500 in combined score there; across
the benchmarks' trees 10 % of the good test scans go beyond 1.4-38 nats, and missing material through a thin wall
scores 130-690, docs/results.md).
Figures: docs/results.md and docs/results_archive.md#thin-walled-and-open-parts-issue-18.

The combined score is then calibrated like any other (:mod:`inspection.calibration`): the calibration scans' own
combined scores are computed leave-one-out (scan i standardized, and gated, with the statistics of the other n - 1),
so that each is computed the way a new scan's is, from statistics it took no part in; the split-conformal threshold
on them keeps its false-alarm guarantee up to the n - 1 vs n difference.
"""
import numpy as np

MIN_SCANS = 3
RULE = "gated-log"  # the one rule (module docstring); stored with the combination
LOG_GATE_QUANTILE = 0.9  # the gate's quantile of the calibration scans' standardized log scores
LOG_GATE_MARGIN = 2.0  # and its margin, in their standard deviations
LOG_GATE_CEILING_FACTOR = 4.0  # the gate is at most log(1 + ceiling / this) (module docstring)
RAY_GATE_FLOOR = 40.0  # nats: the ray score's gate is at least log(1 + this) (module docstring)
LOG_GATE_WEIGHT = 100.0  # what one standard deviation beyond the gate counts, in the base score's
LOG_GATE_TOP_MARGIN = 0.75  # the gate is at least this many standard deviations beyond the largest calibration value
_REL_FLOOR = 1e-3
_ABS_FLOOR = 1e-9


def _as_matrix(components, names=None):
    """dict name -> (n,) scores, or a list of such dicts per scan -> (names, (n, J) array)."""
    if isinstance(components, dict):
        names = list(components) if names is None else list(names)
        cols = [np.asarray(components[k], dtype=np.float64).reshape(-1) for k in names]
    else:
        rows = list(components)
        names = list(rows[0]) if names is None and rows else list(names or [])
        cols = [np.array([r[k] for r in rows], dtype=np.float64) for k in names]
    if not cols or len({len(c) for c in cols}) != 1:
        raise ValueError(f"components must give the same number of scans for every score, got "
                         f"{ {k: len(c) for k, c in zip(names, cols)} }")
    matrix = np.stack(cols, axis=1)
    if not np.isfinite(matrix).all():
        raise ValueError("component scores must be finite numbers")
    return names, matrix


def standardization(matrix):
    """Per-component (mean, sd) of calibration scores (n, J) -> (J,), (J,); sd floored (never 0)."""
    mean = matrix.mean(0)
    sd = matrix.std(0, ddof=1) if len(matrix) > 1 else np.zeros(matrix.shape[1])
    return mean, np.maximum(sd, _REL_FLOOR * np.abs(mean) + _ABS_FLOOR)


class Combination:
    """The combination of standardized scores fitted on good calibration scans (see the module docstring).

    Parameters
    ----------
    components : dict name -> (n,) array, or a list of n dicts name -> float
        Component scores of the calibration scans (at least ``MIN_SCANS``); those after the first >= 0.
    names : sequence of str, optional
        Component order (default: the dict's); the first is the base score.
    rule : str
        ``RULE``, the only one (the rules before it, ``'gated'`` and ``'max'``, are retired: a ValueError).
    ceiling : float, optional
        The largest value the components after the first can take (a ray score's: 690.8 nats): the gate stays
        below it (module docstring). None: no bound.
    floor : float, optional
        The smallest value of the components after the first that can count (a ray score's: ``RAY_GATE_FLOOR``):
        the gate stays above it (module docstring). None: no bound.
    top_margin : float >= 0 or None
        The gate is at least this many standard deviations beyond the largest calibration value (up to the
        ceiling's bound; module docstring). None: no such bound (a combination stored before it existed).
    """

    def __init__(self, components, names=None, rule=RULE, ceiling=None, floor=None, top_margin=LOG_GATE_TOP_MARGIN):
        if rule != RULE:
            raise ValueError(f"rule must be {RULE!r} (the rules 'gated' and 'max' are retired), got {rule!r}")
        if ceiling is not None and not (np.isfinite(ceiling) and ceiling > 0):
            raise ValueError(f"ceiling must be a positive finite number or None, got {ceiling!r}")
        if floor is not None and not (np.isfinite(floor) and floor >= 0):
            raise ValueError(f"floor must be a finite number >= 0 or None, got {floor!r}")
        if top_margin is not None and not (np.isfinite(top_margin) and top_margin >= 0):
            raise ValueError(f"top_margin must be a finite number >= 0 or None, got {top_margin!r}")
        self.floor = None if floor is None else float(floor)
        self.top_margin = None if top_margin is None else float(top_margin)
        self.rule = rule
        self.ceiling = None if ceiling is None else float(ceiling)
        self.names, self.matrix = _as_matrix(components, names)
        if len(self.matrix) < MIN_SCANS:
            raise ValueError(f"combining scores needs at least {MIN_SCANS} calibration scans, got "
                             f"{len(self.matrix)}")
        if (self.matrix[:, 1:] < 0).any():
            raise ValueError("the combination takes log(1 + s) of the components after the first: they must be "
                             ">= 0 (a ray score in nats)")
        self._scaled = self._scale(self.matrix)
        self.mean, self.sd = standardization(self._scaled)
        self.gate = self._gate(self._scaled, self.mean, self.sd)

    @staticmethod
    def _scale(matrix):
        """The components as standardized: the first as it is, log(1 + s) for the others."""
        return np.c_[matrix[:, :1], np.log1p(np.maximum(matrix[:, 1:], 0.0))]

    def _gate(self, scaled, mean, sd):
        z = (scaled - mean) / sd
        gate = np.quantile(z, LOG_GATE_QUANTILE, axis=0) + LOG_GATE_MARGIN
        bound = None if self.ceiling is None else (np.log1p(self.ceiling / LOG_GATE_CEILING_FACTOR) - mean) / sd
        if self.top_margin is not None:  # beyond what every good calibration scan showed, up to the ceiling's bound
            top = z.max(axis=0) + self.top_margin
            gate[1:] = np.maximum(gate[1:], (top if bound is None else np.minimum(top, bound))[1:])
        if self.floor is not None:  # never below the evidence that can count (module docstring)
            gate[1:] = np.maximum(gate[1:], ((np.log1p(self.floor) - mean) / sd)[1:])
        if bound is not None:  # never above what a scan can reach (module docstring)
            gate[1:] = np.minimum(gate[1:], bound[1:])
        return gate

    def score(self, components):
        """Combined scores of scans: dict name -> (k,) array or list of dicts -> (k,) array."""
        return self._combine(self.standardized(components), self.gate, self.mean, self.sd)

    def standardized(self, components):
        """The standardized components (k, J), in ``names`` order."""
        _, matrix = _as_matrix(components, self.names)
        return (self._scale(matrix) - self.mean) / self.sd

    @staticmethod
    def _combine(z, gate, mean, sd):
        return mean[0] + sd[0] * (z[:, 0] + LOG_GATE_WEIGHT * np.maximum(z[:, 1:] - gate[1:], 0.0).sum(1))

    def calibration_scores(self):
        """Leave-one-out combined scores (n,) of the calibration scans (see the module docstring)."""
        out = np.empty(len(self.matrix))
        for i in range(len(self.matrix)):
            others = np.delete(self._scaled, i, axis=0)
            mean, sd = standardization(others)
            out[i] = self._combine(((self._scaled[i] - mean) / sd)[None], self._gate(others, mean, sd), mean,
                                   sd)[0]
        return out

    def as_dict(self):
        """Plain Python values: the calibration component scores (the statistics follow from them), the rule, the
        ceiling, the floor and the top margin (when set)."""
        out = {name: [float(v) for v in self.matrix[:, j]] for j, name in enumerate(self.names)}
        out["rule"] = self.rule
        if self.ceiling is not None:
            out["ceiling"] = self.ceiling
        if self.floor is not None:
            out["floor"] = self.floor
        if self.top_margin is not None:
            out["top_margin"] = self.top_margin
        return out

    @classmethod
    def from_dict(cls, d):
        """The combination :meth:`as_dict` stored (a record without a rule was made with the retired ``'gated'``:
        a ValueError asking to calibrate again; one without a top margin gates as it was calibrated, without it)."""
        d = dict(d)
        rule, ceiling, floor = d.pop("rule", "gated"), d.pop("ceiling", None), d.pop("floor", None)
        top_margin = d.pop("top_margin", None)
        return cls({k: np.asarray(v, dtype=np.float64) for k, v in d.items()}, rule=rule, ceiling=ceiling,
                   floor=floor, top_margin=top_margin)
