"""The rays on sensors as users have them (issue 46): rays that pass through the scan's own surface are not tested, a
missing return ends at its rim, and the rays' evidence is weighed per ray, per place and as a whole by what good
calibration scans' rays show, then added to the point score as a likelihood.

Independent computations: the tail against the empirical survival, the chance level against a Monte Carlo of
exponential order statistics and a numerical optimisation of the Chernoff exponent, the combination in closed form,
and a ray caster of a channel (union of boxes) for the sensor geometry.
"""
import math

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from autodecoder.field.protocol import Field
from inspection.combine import Combination, combined_score
from inspection.ray_calibration import (ACCUSED_NATS, PRIOR_ACCUSATIONS, RayCalibration, RayPlaces, RayTail,
                                        chance_nats, top_count)
from inspection.ray_evidence import RayEvidence, ray_evidence


# ---------------------------------------------------------------------------------------------- per ray
def test_tail_trusts_clean_rays_and_recovers_accusations_from_good_scans():
    """Good rays never accused (all below 1 nat) leave each ray's surprisal as it is: the field is trusted. Good
    rays of which 2 % are accused with excesses exponential of scale 30 nats: the tail recovers the share and the
    scale (within 10 %), its survival matches the empirical share of good rays at least that surprising, and a ray
    counts what its rarity among them says, e = -log S(s) < s."""
    rng = np.random.default_rng(0)
    n = 40000
    clean = np.where(rng.random(n) < 0.97, 0.0, rng.uniform(0.0, 0.9, n))
    tail = RayTail.fit(clean)
    s = np.array([0.5, 2.0, 50.0, 690.0])
    np.testing.assert_allclose(tail.nats(s), s)
    assert tail.n_accused == 0 and tail.weight == 1.0
    accused = rng.random(n) < 0.02
    wide = np.where(accused, ACCUSED_NATS + rng.exponential(30.0, n), rng.uniform(0.0, 0.5, n))
    tail = RayTail.fit(wide)
    assert tail.rate == pytest.approx(0.02, rel=0.1) and tail.scale == pytest.approx(30.0, rel=0.1)
    x = np.array([5.0, 30.0, 60.0])
    np.testing.assert_allclose(tail.survival(x), [(wide >= v).mean() for v in x], rtol=0.15)
    np.testing.assert_allclose(tail.nats(x), -np.log(tail.survival(x)))
    assert (tail.nats(x[1:]) < x[1:]).all() and tail.nats(0.7) == 0.7
    assert RayTail.fit([]) is None
    again = RayTail.from_dict(tail.as_dict())
    np.testing.assert_allclose(again.nats(np.linspace(0, 700, 50)), tail.nats(np.linspace(0, 700, 50)))


def test_few_accusations_say_little_of_their_spread():
    """Two good rays accused at 50 nats among 10,000: their mean excess is shrunk toward the calibrated field's 1 nat
    by PRIOR_ACCUSATIONS rays, so a ray far beyond them still counts more than a few nats."""
    s = np.r_[np.zeros(9998), 50.0, 50.0]
    tail = RayTail.fit(s)
    assert tail.scale == pytest.approx((2 * 49.0 + PRIOR_ACCUSATIONS) / (2 + PRIOR_ACCUSATIONS))
    assert tail.nats(690.0) > 20


# ---------------------------------------------------------------------------------------------- per place
def test_places_cap_a_ray_where_good_scans_were_accused():
    """A ray blocked where the rays of k of n calibration scans were accused counts at most -log(k / n); elsewhere
    it counts in full; a calibration scan is not capped by its own places (leave-one-out)."""
    here, there = np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    surprisals = [np.array([50.0, 0.0]), np.array([20.0]), np.array([0.5]), np.array([0.0])]
    blocks = [np.array([here, there]), np.array([here + 0.01]), np.array([there]), np.array([[np.nan] * 3])]
    places = RayPlaces.fit(surprisals, blocks, radius=0.05)
    assert len(places.points) == 2 and sorted(places.owners.tolist()) == [0, 1]  # 0.5 nats: not an accusation
    capped = places.cap(np.array([100.0, 100.0, 0.5]), np.array([here, there, here]))
    np.testing.assert_allclose(capped, [-math.log(2 / 4), 100.0, 0.5])
    np.testing.assert_allclose(places.cap(np.array([100.0]), np.array([here]), exclude=0), [-math.log(1 / 3)])
    assert ACCUSED_NATS < 20
    again = RayPlaces.from_dict(places.as_dict())
    np.testing.assert_allclose(again.cap(np.array([100.0]), np.array([here])), capped[:1])


# ---------------------------------------------------------------------------------------------- as a scan
@pytest.mark.parametrize("m, k", [(512, 6), (100, 1), (40, 40)])
def test_chance_level_bounds_the_monte_carlo_tail_and_is_the_chernoff_exponent(m, k):
    """I(E) = -log of the Chernoff bound on P(mean of the k largest of m Exp(1) >= E): the Monte Carlo tail never
    exceeds exp(-I), it is 0 at and below the mean (1 + H_m - H_k for k < m), and it is the optimum of the exponent
    found by a numerical optimiser."""
    from scipy.optimize import minimize_scalar

    rng = np.random.default_rng(2)
    draws = -np.sort(-rng.exponential(size=(20000, m)), axis=1)[:, :k].mean(1)
    harmonic = lambda n: np.sum(1.0 / np.arange(1, n + 1))  # noqa: E731
    mean = 1 + harmonic(m) - harmonic(k)
    assert draws.mean() == pytest.approx(mean, rel=0.02)
    assert chance_nats(mean - 0.1, m, k) == 0.0 and chance_nats(0.0, m, k) == 0.0
    i = np.arange(1, m + 1)
    w = np.minimum(i, k) / (i * k)
    for value in mean + np.array([0.5, 1.0, 2.0, 3.0]):
        nats = chance_nats(value, m, k)
        assert (draws >= value).mean() <= math.exp(-nats) + 3 * math.sqrt(math.exp(-nats) / len(draws)) + 1e-4
        best = minimize_scalar(lambda t: -(t * value + np.sum(np.log1p(-t * w))), bounds=(0, k * (1 - 1e-9)),
                               method="bounded", options={"xatol": 1e-10})
        assert nats == pytest.approx(-best.fun, rel=1e-5, abs=1e-7)
    assert chance_nats(690.0, m, k) > 100
    assert [top_count(a, 512) for a in ("max", "mean", "top1", "top5")] == [1, 512, 6, 26]
    with pytest.raises(ValueError, match="aggregate"):
        top_count("q99", 10)


def _evidence(surprisals, blocks=None):
    """A RayEvidence with given returned rays' surprisals (its maps unused here)."""
    s = np.asarray(surprisals, dtype=np.float64)
    blocks = np.full((len(s), 3), np.nan) if blocks is None else np.asarray(blocks, dtype=np.float64)
    return RayEvidence(score=0.0, point_map=np.zeros(len(s)), ray_index=np.arange(len(s)), ray_values=1 - np.exp(-s),
                       ray_surprisal=s, ray_block=blocks, through_observed=np.zeros(len(s), bool),
                       nearest=np.arange(len(s)))


def test_combination_is_the_likelihood_of_both_and_calibrates_leave_one_out():
    """c = sqrt(z^2 + 2 I) (z + sqrt(2 I) below 0); a scan whose rays show nothing beyond chance keeps its point
    score; each calibration scan's I is computed with the tail and places fitted on the others' rays alone."""
    assert combined_score(3.0, 0.0) == 3.0 and combined_score(3.0, 8.0) == pytest.approx(5.0)
    np.testing.assert_allclose(combined_score([-1.0, 0.0], [2.0, 2.0]), [1.0, 2.0])
    rng = np.random.default_rng(3)
    rays = [np.where(rng.random(300) < 0.99, 0.0, rng.exponential(2.0, 300)) for _ in range(10)]
    rays[4] = np.r_[np.full(6, 300.0), np.zeros(294)]  # one good calibration scan whose rays were accused
    points = rng.normal(4.0, 0.3, 10)
    comb = Combination.fit(points, [_evidence(s) for s in rays], lengthscale=0.02, aggregate="top1")
    by_hand = RayCalibration(RayTail.fit(np.concatenate(rays[:4] + rays[5:])), None, "top1")._scan_nats(
        rays[4], np.full((300, 3), np.nan), RayTail.fit(np.concatenate(rays[:4] + rays[5:])))[1]
    assert comb.calibration_nats[4] == pytest.approx(by_hand) and by_hand > 0
    np.testing.assert_allclose(comb.calibration_scores(), np.sqrt(points ** 2 + 2 * comb.calibration_nats))
    # its rays, with those of the other good scans, set the tail: a hole's rays count, a good scan's do not
    assert comb.score(4.0, _evidence(np.zeros(300))) == 4.0
    assert comb.score(4.0, _evidence(np.r_[np.full(20, 690.0), np.zeros(280)])) > 6
    again = Combination.from_dict(comb.as_dict())
    hole = _evidence(np.r_[np.full(20, 690.0), np.zeros(280)])
    assert again.score(4.0, hole) == comb.score(4.0, hole)
    for retired in ("gated", "max", "gated-log"):
        with pytest.raises(ValueError, match="retired"):
            Combination.from_dict({**comb.as_dict(), "rule": retired})
    record = comb.as_dict()
    del record["rule"]  # a record of the first rule, 'gated'
    with pytest.raises(ValueError, match="retired"):
        Combination.from_dict(record)
    assert "rays accused" in comb.rays.describe()


def test_ray_weight_goes_to_nearly_nothing_when_good_scans_rays_are_noise():
    """The issue's check: good calibration scans whose rays are noise (a fifth of them anywhere up to the ceiling)
    give the rays a weight near 0, and a new good scan of that noise no evidence at all; a hole's rays, all at the
    ceiling, count nothing beyond what such rays give by chance there, and hundreds of nats against clean good
    scans."""
    rng = np.random.default_rng(4)
    noise = [np.where(rng.random(512) < 0.8, 0.0, rng.uniform(0.0, 690.8, 512)) for _ in range(24)]
    clean = [np.where(rng.random(512) < 0.99, 0.0, rng.exponential(0.5, 512)) for _ in range(24)]
    noisy = Combination.fit(np.full(24, 4.0), [_evidence(s) for s in noise], 0.02, "top1")
    trusted = Combination.fit(np.full(24, 4.0), [_evidence(s) for s in clean], 0.02, "top1")
    assert noisy.rays.tail.weight < 0.01 and trusted.rays.tail.weight == 1.0
    assert "count little" in noisy.rays.describe()
    new_noise = np.where(rng.random(512) < 0.8, 0.0, rng.uniform(0.0, 690.8, 512))
    assert noisy.nats(_evidence(new_noise)) == 0.0 and noisy.score(4.0, _evidence(new_noise)) == 4.0
    hole = _evidence(np.r_[np.full(12, 690.8), np.zeros(500)])
    assert noisy.nats(hole) == 0.0 and trusted.nats(hole) > 100


# ---------------------------------------------------------------------------------------------- sensor geometry
class ChannelField(Field):
    """A U-channel: a floor slab (top face z = -0.5) and two walls 0.04 thick at x = +-0.2 up to z = 0.3, over
    [-0.6, 0.6] in y; its mean is the union's signed distance, and the field extrapolates a lid into the cavity
    (x within 0.14 of 0, 0.22 <= z <= 0.28: material no good scan has a surface near). sd 0.001, lengthscale
    0.02, box [-1, 1]^3."""

    BOXES = np.array([[[-0.6, -0.6, -0.6], [0.6, 0.6, -0.5]],  # floor
                      [[0.18, -0.6, -0.5], [0.22, 0.6, 0.3]],  # right wall
                      [[-0.22, -0.6, -0.5], [-0.18, 0.6, 0.3]]])  # left wall
    LID = np.array([[-0.14, -0.6, 0.22], [0.14, 0.6, 0.28]])

    def __init__(self):
        self.sd, self.ell, self.noise, self.lengthscale = 0.001, 0.05, 0.0, 0.02
        self.bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])

    @staticmethod
    def _box(x, lo, hi):
        lo, hi = torch.as_tensor(lo, dtype=x.dtype), torch.as_tensor(hi, dtype=x.dtype)
        c, h = (lo + hi) / 2, (hi - lo) / 2
        q = (x - c).abs() - h
        return q.clamp_min(0).norm(dim=1) + q.max(dim=1).values.clamp_max(0)

    def torch_mean(self, x):
        d = torch.stack([self._box(x, *b) for b in [*self.BOXES, self.LID]], 1)
        return d.min(1).values

    def torch_covariance(self, a, b):
        return self.sd**2 * torch.exp(-((a - b) ** 2).sum(1) / (2 * self.ell**2))

    def torch_variance(self, x):
        return torch.full((len(x),), self.sd**2, dtype=x.dtype)


WINDOW = (np.array([0.0, -0.1]), 0.15)  # a hole through the right wall: centre (y, z), radius
TARGET = np.array([0.0, 0.0, -0.2])  # where the views look
TRUE_ORIGIN = np.array([1.0, 0.05, 1.5])


def _channel_scan(origin, window=False, n_side=110):
    """A pinhole scan of the channel (the lid is the field's, not the part's) from ``origin``: the first box each
    ray of a grid meets (through the right wall's window when ``window``). Returns the points (m, 3)."""
    forward = (TARGET - origin) / np.linalg.norm(TARGET - origin)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    u = np.linspace(-0.4, 0.4, n_side)
    uu, vv = np.meshgrid(u, u)
    d = forward + uu.reshape(-1, 1) * right + vv.reshape(-1, 1) * up
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    best = np.full(len(d), np.inf)
    for k, (lo, hi) in enumerate(ChannelField.BOXES):
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - origin) / d, (hi - origin) / d
        t_in, t_out = np.minimum(t1, t2).max(1), np.maximum(t1, t2).min(1)
        hit = (t_out >= t_in) & (t_in > 0)
        if k == 1 and window:  # a round hole through the wall along x: a ray entering its mouth meets the hole's
            (cy, cz), r = WINDOW  # side (a cylinder) unless it leaves through the other mouth first
            yz = origin[1:] + t_in[:, None] * d[:, 1:] - (cy, cz)
            mouth = hit & (np.hypot(yz[:, 0], yz[:, 1]) < r)
            a = d[:, 1] ** 2 + d[:, 2] ** 2
            b = 2 * (yz[:, 0] * d[:, 1] + yz[:, 1] * d[:, 2])
            c = yz[:, 0] ** 2 + yz[:, 1] ** 2 - r ** 2
            with np.errstate(invalid="ignore", divide="ignore"):
                side = (-b + np.sqrt(b * b - 4 * a * c)) / (2 * a)  # from the mouth to the hole's side
            blocked = mouth & (side < t_out - t_in)
            t_in = np.where(blocked, t_in + side, t_in)
            hit = hit & (~mouth | blocked)
        best = np.where(hit & (t_in < best), t_in, best)
    keep = np.isfinite(best)
    return origin + best[keep, None] * d[keep]


def _channel_surface(spacing=0.01):
    """Good scans' surface: every face of the channel's boxes (what training views of it show), points (n, 3)."""
    faces = []
    for lo, hi in ChannelField.BOXES:
        for axis in range(3):
            for value in (lo[axis], hi[axis]):
                others = [a for a in range(3) if a != axis]
                g = [np.arange(lo[a], hi[a] + 1e-9, spacing) for a in others]
                grid = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 2)
                face = np.empty((len(grid), 3))
                face[:, axis], face[:, others] = value, grid
                faces.append(face)
    return np.unique(np.round(np.concatenate(faces), 6), axis=0)


def _written(turn_deg):
    """The channel scan's origin as a user writes it: twice the stand-off, the axis turned by ``turn_deg`` degrees
    in its vertical plane (positive: lower, so that rays over the right wall's top cut through it)."""
    from scipy.spatial.transform import Rotation

    axis = TRUE_ORIGIN - TARGET
    across = np.cross(axis, [0.0, 0.0, 1.0])
    turn = Rotation.from_rotvec(np.radians(turn_deg) * across / np.linalg.norm(across)).as_matrix()
    return TARGET + 2.0 * (turn @ axis)


def test_a_cavity_seen_from_an_approximate_origin_is_not_accused():
    """The issue's check: a view into a channel (a cavity the field extrapolates a lid into), its sidecar origin off
    by 2x the stand-off and 5 degrees (3 either way). From the true origin nothing is accused (the band leaves the lid
    out); from a written one lower than the true one the rays to the floor beside the near wall run through that wall
    (whose far face good scans have) and, without the rule, are accused; with it they have passed through the scan's
    own surface and are not tested. No written origin gets an accusation."""
    field, surface = ChannelField(), _channel_surface()
    points = _channel_scan(TRUE_ORIGIN)
    options = dict(surface=surface, n_rays=600, n_empty=128)
    assert ray_evidence(field, points, TRUE_ORIGIN, **options).score < 0.1
    without = ray_evidence(field, points, _written(-5), occlusion=None, empty_to_rim=False, **options)
    assert without.score > 10 and (without.ray_surprisal > 3).sum() >= 5
    for turn in (-5, -3, 3, 5):
        ev = ray_evidence(field, points, _written(turn), **options)
        assert ev.score < 0.1 and (ev.ray_surprisal > 1).sum() == 0
    assert ray_evidence(field, points, _written(-5), **options).through_observed.sum() >= 5


def test_a_hole_in_a_thin_wall_is_accused_from_an_approximate_origin():
    """The issue's check: a round hole through the channel's thin wall, the inside seen through it; the field has
    the wall (good parts do). From the true origin and from written ones 2x the stand-off and 3-5 degrees off either
    way, the rays to the points seen through the hole cross the wall where good parts have it: accused, the scan's
    rays at 100 nats and more where the same scans of the whole channel are at 0."""
    field, surface = ChannelField(), _channel_surface()
    points = _channel_scan(TRUE_ORIGIN, window=True)
    seen_through = cKDTree(_channel_scan(TRUE_ORIGIN)).query(points)[0] > 1e-9
    options = dict(surface=surface, n_rays=600, n_empty=128)
    for origin in (TRUE_ORIGIN, *(_written(turn) for turn in (-5, -3, 3, 5))):
        ev = ray_evidence(field, points, origin, **options)
        assert ev.score > 100 and (ev.point_surprisal[seen_through] > 4.6).sum() > 50


class WasherField(ChannelField):
    """A floor slab (top face z = -0.5) under a plate 0.04 thick at z = 0, with a round hole of radius 0.1 about the
    z axis (a washer) or without (``hole=False``); signed distances, sd 0.001, lengthscale 0.02."""

    def __init__(self, hole=True):
        super().__init__()
        self.hole = hole

    def torch_mean(self, x):
        floor = self._box(x, [-1.0, -1.0, -0.6], [1.0, 1.0, -0.5])
        plate = self._box(x, [-0.6, -0.6, -0.02], [0.6, 0.6, 0.02])
        if self.hole:
            plate = torch.maximum(plate, 0.1 - x[:, :2].norm(dim=1))
        return torch.minimum(floor, plate)


def test_missing_returns_end_at_their_rim():
    """A gap in the image whose rim returns lie on a plate and whose missing wall, were anything missing, would lie
    far behind it (the floor under the plate's hole, returned nowhere: the shadow of an edge that an approximate
    origin uncovers, or a dark patch) is tested only up to the nearest return around it plus own_depth: the floor
    0.5 behind is not accused; without the rule it is. A hole in the plate itself, the field's plate intact, is
    accused either way (its missing wall lies at its rim)."""
    sensor = np.array([0.0, 0.0, 2.0])
    g = np.arange(-0.3, 0.3001, 0.006)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    plate = np.c_[xy, np.full(len(xy), 0.02)]
    scan = plate[np.hypot(xy[:, 0], xy[:, 1]) >= 0.1]  # the plate's returns; none through its hole
    surface = np.r_[scan, np.c_[xy, np.full(len(xy), -0.5)]]  # good scans saw the floor under the hole
    fine = dict(n_rays=16, n_empty=256, step=0.004, max_samples=1024)  # samples finer than the band around a face
    at_rim = ray_evidence(WasherField(), scan, sensor, surface=surface, **fine)
    through = ray_evidence(WasherField(), scan, sensor, surface=surface, empty_to_rim=False, **fine)
    assert len(at_rim.empty_surprisal) > 20
    assert at_rim.empty_surprisal.max() < 0.1 and through.empty_surprisal.min() > 10
    # the part's plate has no hole (good parts are whole): the missing returns through it are missing material
    hole = ray_evidence(WasherField(hole=False), scan, sensor, surface=np.r_[plate, surface], **fine)
    assert len(hole.empty_surprisal) > 20 and np.median(hole.empty_surprisal) > 10
