"""The rays' evidence weighed by what good scans' rays show: per ray, per place and as a whole, in nats.

A ray's surprisal s = -log P(free) (:mod:`inspection.ray_evidence`) is its negative log likelihood under the scan's
projected field. Were the field's ray probabilities calibrated, a good scan's rays would be that surprising no more
often than e^-s: P(S >= s) <= e^-s. Good scans show how far that holds on a part and a sensor: where the sidecar
origins are approximate, the field extrapolates, or the sensor drops returns, their rays are accused far more often.
Three steps turn the surprisals into evidence that good scans vouch for (:class:`RayCalibration`, fitted on the
calibration scans' rays: held back, cross-fitted or scored by fold models, as the threshold's scans):

1. **Per ray, as a whole** (:class:`RayTail`): e = min(s, -log S(s)), S the survival of the good calibration
   rays' surprisals, pooled: beyond ``ACCUSED_NATS`` (1 nat: an accusation) an exponential tail through the share
   of good rays accused (the peaks-over-threshold model, its scale beta their mean excess), below it each ray's own
   surprisal. e is a ray's surprisal among good scans' rays, never more than the field's own. Where good rays are
   never accused the field is trusted as it is (e = s); where they are accused often and far (approximate origins,
   dropouts), a ray counts what its rarity among them says, at most -log(rate) + (690.8 - 1) / beta: the rays'
   weight, which good scans set and the calibration line reports.
2. **Per place** (:class:`RayPlaces`): a ray accuses only where good scans' rays were not accused. Where the
   rays of k of the n calibration scans were accused (surprisal above ``ACCUSED_NATS``) within ``PLACE_RADIUS``
   kernel lengthscales of the place a ray is blocked at (its most likely blocked sample), the ray's evidence is at
   most -log(k / n): how rare such an accusation there is among good scans. Views that repeat (a fixture, a line)
   make their false accusations at the same places.
3. **As a scan** (:func:`chance_nats`): the scan's ray statistic E is the rays' aggregate (``top1``: the mean of
   the worst 1 %) of e over its M rays; its evidence is I(E) = -log of the Chernoff bound on the probability that M
   calibrated rays reach E by chance (E's mean is 1 + H_M - H_k for the mean of the worst k: 5.4 nats for 512 rays;
   below it I = 0). A good scan's rays, calibrated by steps 1 and 2, give I = 0 or nearly; a hole's dozens of
   rays at hundreds of nats give hundreds.

:mod:`inspection.combine` adds I to the point score as a likelihood: sqrt(z^2 + 2 I). The calibration scans' own I
is computed leave-one-out (their tail and places fitted without their own rays), as a new scan's is.
"""
import math

import numpy as np

ACCUSED_NATS = 1.0  # a ray with more surprisal than this is accused (P(blocked) > 0.63), where it is blocked
PRIOR_ACCUSATIONS = 2  # the accusations' mean excess is shrunk toward the calibrated field's 1 nat by this many
PLACE_RADIUS = 2.0  # kernel lengthscales: how near a place must lie to be the same place (the kernel's support)
LOW_WEIGHT = 0.25  # below this weight per nat the calibration line says that the rays count little
THROUGH_NOTE = 0.02  # the line says how many good rays passed through their own scan's surface above this share


class RayTail:
    """How often good calibration rays were accused, and how strongly: the survival S(s) of their surprisals beyond
    ``ACCUSED_NATS`` and each ray's evidence e(s) = min(s, -log S(s)) (module docstring, step 1).

    Beyond u = ``ACCUSED_NATS`` (a ray the field calls blocked with P > 0.63: an accusation) S(s) = r exp(-(s -
    u) / beta): r the share of good rays accused ((k + 1) / (N + 1) of N rays, k accused), beta their mean excess
    over u (the peaks-over-threshold model: excesses over a high threshold are exponential), shrunk toward the
    calibrated field's 1 nat by ``PRIOR_ACCUSATIONS`` rays (a handful of accusations say little of their spread).
    Below u every ray counts its own surprisal.

    Parameters
    ----------
    rate : float
        r, in (0, 1].
    scale : float
        beta, nats (> 0).
    n_rays, n_accused : int
        N and k.
    """

    def __init__(self, rate, scale, n_rays, n_accused):
        self.rate, self.scale = float(rate), float(scale)
        self.n_rays, self.n_accused = int(n_rays), int(n_accused)
        if not (self.scale > 0 and 0 < self.rate <= 1 and self.n_rays >= 0 and 0 <= self.n_accused <= self.n_rays):
            raise ValueError(f"RayTail: not a fitted tail (rate {rate}, scale {scale}, {n_accused} of {n_rays} rays)")

    @classmethod
    def fit(cls, surprisals):
        """From the good calibration rays' surprisals (any shape, nats >= 0); None when there are none."""
        s = np.maximum(np.asarray(surprisals, dtype=np.float64).reshape(-1), 0.0)
        if len(s) == 0:
            return None
        excess = s[s > ACCUSED_NATS] - ACCUSED_NATS
        scale = (excess.sum() + PRIOR_ACCUSATIONS * 1.0) / (len(excess) + PRIOR_ACCUSATIONS)
        return cls((len(excess) + 1) / (len(s) + 1), scale, len(s), len(excess))

    @property
    def weight(self):
        """The most one ray can count, as a share of what the field alone gives it: e(690.8) / 690.8 (a ray through
        material the field is sure of; 1: the good scans' rays vouch for the field's own surprisal)."""
        from autodecoder.scanning.free_space import MAX_SURPRISAL

        return float(self.nats(MAX_SURPRISAL) / MAX_SURPRISAL)

    def survival(self, s):
        """S(s) for s > ``ACCUSED_NATS``: the share of good rays at least this surprising (nats -> share)."""
        return self.rate * np.exp(-(np.asarray(s, dtype=np.float64) - ACCUSED_NATS) / self.scale)

    def nats(self, s):
        """e(s) = min(s, -log S(s)) beyond ``ACCUSED_NATS``, s below it: each ray's surprisal among good rays, never
        above its own (nats)."""
        s = np.maximum(np.asarray(s, dtype=np.float64), 0.0)
        among_good = -np.log(self.rate) + (s - ACCUSED_NATS) / self.scale
        return np.where(s > ACCUSED_NATS, np.minimum(s, among_good), s)

    def as_dict(self):
        return {"rate": self.rate, "scale": self.scale, "n_rays": self.n_rays, "n_accused": self.n_accused}

    @classmethod
    def from_dict(cls, d):
        return cls(d["rate"], d["scale"], d["n_rays"], d["n_accused"])


class RayPlaces:
    """Where good calibration scans' rays were accused (module docstring, step 2).

    Parameters
    ----------
    points : (P, 3) array
        The places (the most likely blocked sample of each accused ray), the model's frame.
    owners : (P,) int array
        The calibration scan (0 .. n_scans - 1) each place belongs to.
    n_scans : int
        n, the calibration scans.
    radius : float
        How near a place must lie to be the same (world units).
    """

    def __init__(self, points, owners, n_scans, radius):
        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self.owners = np.asarray(owners, dtype=np.int64).reshape(-1)
        self.n_scans, self.radius = int(n_scans), float(radius)
        if len(self.owners) != len(self.points) or not self.radius > 0 or self.n_scans < 1:
            raise ValueError(f"RayPlaces: {len(self.points)} places, {len(self.owners)} owners, {n_scans} scans, "
                             f"radius {radius}")
        self._trees = {}

    @classmethod
    def fit(cls, surprisals, blocks, radius):
        """From each calibration scan's rays: ``surprisals`` (list of (R_i,) arrays, nats) and ``blocks`` (list of
        (R_i, 3), NaN where untested)."""
        points, owners = [], []
        for i, (s, b) in enumerate(zip(surprisals, blocks)):
            b = np.asarray(b, dtype=np.float64).reshape(-1, 3)
            hot = (np.asarray(s, dtype=np.float64).reshape(-1) > ACCUSED_NATS) & np.isfinite(b).all(axis=1)
            points.append(b[hot])
            owners.append(np.full(int(hot.sum()), i))
        return cls(np.concatenate(points) if points else np.zeros((0, 3)),
                   np.concatenate(owners) if owners else np.zeros(0, int), len(surprisals), radius)

    def _tree(self, exclude):
        from scipy.spatial import cKDTree

        if exclude not in self._trees:
            keep = self.owners != exclude
            self._trees[exclude] = (cKDTree(self.points[keep]), self.owners[keep])
        return self._trees[exclude]

    def cap(self, nats, blocks, exclude=None):
        """``nats`` (R,) of a scan's rays, each at most -log(k / n) where the rays of k calibration scans (not
        ``exclude``) were accused near its block point ``blocks`` (R, 3); a copy."""
        nats = np.array(nats, dtype=np.float64).reshape(-1)
        blocks = np.asarray(blocks, dtype=np.float64).reshape(-1, 3)
        n = self.n_scans - (exclude is not None)
        rows = np.flatnonzero((nats > ACCUSED_NATS) & np.isfinite(blocks).all(axis=1))
        if n < 1 or len(rows) == 0 or not (self.owners != exclude).any():
            return nats
        tree, owners = self._tree(exclude)
        for row, near in zip(rows, tree.query_ball_point(blocks[rows], self.radius)):
            k = len(set(owners[near].tolist()))
            if k:
                nats[row] = min(nats[row], -math.log(k / n))
        return nats

    def as_dict(self):
        return {"points": self.points.tolist(), "owners": self.owners.tolist(), "n_scans": self.n_scans,
                "radius": self.radius}

    @classmethod
    def from_dict(cls, d):
        return cls(d["points"], d["owners"], d["n_scans"], d["radius"])


def top_count(aggregate, m):
    """How many of m values the ray aggregate averages: ``'max'`` 1, ``'mean'`` m, ``'top<P>'`` ceil(P % m) (at
    least 1); other aggregates have no chance model here (a ValueError)."""
    if aggregate == "max":
        return 1
    if aggregate == "mean":
        return m
    if isinstance(aggregate, str) and aggregate.startswith("top"):
        return max(1, int(math.ceil(float(aggregate[3:]) / 100 * m)))
    raise ValueError(f"the rays' aggregate must be 'max', 'mean' or 'top<P>' (the mean of the worst P %), whose "
                     f"chance level is known; got {aggregate!r}")


def chance_nats(value, m, k):
    """I(E): -log of the Chernoff bound on P(the mean of the k largest of m independent Exp(1) surprisals >= E).

    By Renyi's representation the j-th largest of m Exp(1) is sum_{i >= j} Z_i / i (Z_i independent Exp(1)), so the
    mean of the k largest is T = sum_i w_i Z_i with w_i = min(i, k) / (i k), and log E exp(theta T) = -sum_i
    log(1 - theta w_i) for theta < k; I(E) = sup_theta [theta E + sum_i log(1 - theta w_i)], 0 for E at or below
    E[T] = sum_i w_i. Exact in the exponent; the bound holds for any m calibrated rays that are independent.

    Parameters
    ----------
    value : float
        E (nats).
    m, k : int
        Rays, and how many of the largest the aggregate averages (1 <= k <= m).

    Returns
    -------
    float >= 0 (nats)
    """
    m, k = int(m), int(k)
    if m < 1 or not 1 <= k <= m:
        raise ValueError(f"chance_nats: need 1 <= k <= m, got k={k}, m={m}")
    i = np.arange(1, m + 1, dtype=np.float64)
    w = np.minimum(i, k) / (i * k)
    value = float(value)
    if not value > w.sum():
        return 0.0
    lo, hi = 0.0, 1.0 / w.max()
    for _ in range(200):  # the derivative E - sum w / (1 - theta w) falls from E - E[T] > 0 to -inf at theta = k
        mid = 0.5 * (lo + hi)
        if value > np.sum(w / (1.0 - mid * w)):
            lo = mid
        else:
            hi = mid
    return float(max(0.0, lo * value + np.sum(np.log1p(-lo * w))))


class RayCalibration:
    """The rays' evidence as good calibration scans weigh it (module docstring).

    Parameters
    ----------
    tail : RayTail or None
        None: the calibration scans tested no ray (each ray counts its own surprisal).
    places : RayPlaces or None
    aggregate : str
        The rays' per-scan aggregate (:func:`top_count`).
    through_share : float
        The share of the calibration scans' returned rays that passed through their own scan's surface (not
        tested: their sensor origins are approximate; :mod:`autodecoder.scanning.free_space`), for the note.
    """

    def __init__(self, tail, places, aggregate, through_share=0.0):
        top_count(aggregate, 1)  # validates
        self.tail, self.places, self.aggregate = tail, places, aggregate
        self.through_share = float(through_share)

    @classmethod
    def fit(cls, evidences, lengthscale, aggregate):
        """From the calibration scans' :class:`inspection.ray_evidence.RayEvidence` (in calibration order);
        ``lengthscale`` (the field's kernel lengthscale, world units) sizes the places."""
        surprisals = [_surprisals(e) for e in evidences]
        blocks = [_blocks(e) for e in evidences]
        tail = RayTail.fit(np.concatenate(surprisals)) if surprisals else None
        places = RayPlaces.fit(surprisals, blocks, PLACE_RADIUS * lengthscale) if lengthscale else None
        through = np.concatenate([_through(e) for e in evidences]) if evidences else np.zeros(0)
        one = cls(tail, places, aggregate, float(through.mean()) if len(through) else 0.0)
        one._fitted_on = (surprisals, blocks)
        return one

    def calibration_nats(self):
        """Each calibration scan's evidence I (n,), leave-one-out: its tail and places fitted without its own rays
        (only right after :meth:`fit`, which keeps the rays)."""
        fitted = getattr(self, "_fitted_on", None)
        if fitted is None:
            raise ValueError("calibration_nats needs the rays RayCalibration.fit was given")
        surprisals, blocks = fitted
        out = np.empty(len(surprisals))
        for i, (s, b) in enumerate(zip(surprisals, blocks)):
            others = [o for j, o in enumerate(surprisals) if j != i]
            tail = RayTail.fit(np.concatenate(others)) if others else None
            out[i] = self._scan_nats(s, b, tail, exclude=i)[1]
        return out

    def nats(self, evidence):
        """(E, I) of a new scan's :class:`inspection.ray_evidence.RayEvidence`: its ray statistic and its evidence
        in nats (module docstring, step 3)."""
        return self._scan_nats(_surprisals(evidence), _blocks(evidence), self.tail)

    def ray_nats(self, evidence):
        """Each tested ray's evidence e, in the order of ``evidence.ray_surprisal`` then ``empty_surprisal``."""
        return self._ray_nats(_surprisals(evidence), _blocks(evidence), self.tail)

    def _ray_nats(self, s, blocks, tail, exclude=None):
        e = np.maximum(np.asarray(s, dtype=np.float64), 0.0) if tail is None else tail.nats(s)
        return e if self.places is None else self.places.cap(e, blocks, exclude)

    def _scan_nats(self, s, blocks, tail, exclude=None):
        e = self._ray_nats(s, blocks, tail, exclude)
        if len(e) == 0:
            return 0.0, 0.0
        from .aggregates import aggregate

        value = aggregate(e, self.aggregate)
        return value, chance_nats(value, len(e), top_count(self.aggregate, len(e)))

    def describe(self):
        """The calibration's line on the rays: their weight, where good scans' rays were accused, and how many
        passed through their own scan's surface."""
        from autodecoder.scanning.free_space import MAX_SURPRISAL

        parts = []
        if self.tail is None:
            return "the rays: the calibration scans tested none (each ray counts its own surprisal)"
        w = self.tail.weight
        parts.append(f"{self.tail.n_accused} of their {self.tail.n_rays} rays accused, so that a ray through "
                     f"material the field is sure of counts {w * MAX_SURPRISAL:.3g} of its {MAX_SURPRISAL:.0f} nats")
        if self.places is not None and len(self.places.points):
            parts.append(f"accused at {len(self.places.points)} places by {len(set(self.places.owners.tolist()))} "
                         f"of the {self.places.n_scans} good scans, where rays count what those scans show")
        if self.through_share > THROUGH_NOTE:
            parts.append(f"{100 * self.through_share:.0f} % of their rays passed through their own scan's surface "
                         f"and were not tested (the sensor origins are approximate)")
        line = "the rays weighed by the good scans': " + "; ".join(parts)
        if w < LOW_WEIGHT:
            line += "; their rays spread wide, so the rays count little"
        return line

    def as_dict(self):
        return {"tail": None if self.tail is None else self.tail.as_dict(),
                "places": None if self.places is None else self.places.as_dict(), "aggregate": self.aggregate,
                "through_share": self.through_share}

    @classmethod
    def from_dict(cls, d):
        return cls(None if d.get("tail") is None else RayTail.from_dict(d["tail"]),
                   None if d.get("places") is None else RayPlaces.from_dict(d["places"]), d["aggregate"],
                   d.get("through_share", 0.0))


def _surprisals(evidence):
    """A scan's rays' surprisals (R,): the returned rays', then the missing returns'."""
    return np.concatenate([np.asarray(evidence.ray_surprisal, dtype=np.float64).reshape(-1),
                           np.asarray(evidence.empty_surprisal, dtype=np.float64).reshape(-1)])


def _blocks(evidence):
    """Where those rays are most likely blocked (R, 3) (NaN where untested)."""
    ray = np.asarray(evidence.ray_block, dtype=np.float64).reshape(-1, 3)
    empty = np.asarray(evidence.empty_block, dtype=np.float64).reshape(-1, 3)
    if len(ray) != len(evidence.ray_surprisal):  # evidence without block points: no places
        ray = np.full((len(evidence.ray_surprisal), 3), np.nan)
    if len(empty) != len(evidence.empty_surprisal):
        empty = np.full((len(evidence.empty_surprisal), 3), np.nan)
    return np.concatenate([ray, empty])


def _through(evidence):
    """Per tested returned ray: whether it passed through its scan's own surface (all False when not recorded)."""
    through = getattr(evidence, "through_observed", None)
    return np.zeros(len(evidence.ray_surprisal), bool) if through is None else np.asarray(through, bool)
