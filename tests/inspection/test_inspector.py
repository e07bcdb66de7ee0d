"""inspection: per-point scores, aggregates, conformal p-values and thresholds, the Inspector estimator contract."""
import math
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from inspection import Inspector, NotFittedError, aggregate, conformal_threshold, point_scores
from inspection.calibration import Calibration
from tests.inspection.spheres import SaturatingSphereField, SphereField, SphereModel, sphere_scan


# ---------------------------------------------------------------------------------------------- scores
def test_point_scores_match_formulae():
    f = SphereField(variance=4e-4, noise=0.03)
    x = np.array([[1.1, 0, 0], [0, 0.95, 0], [0, 0, 1.0]])
    total = 4e-4 + 0.03**2
    m = np.array([0.1, -0.05, 0.0])
    np.testing.assert_allclose(point_scores(f, x, "residual"), np.abs(m) / math.sqrt(total))
    np.testing.assert_allclose(point_scores(f, x, "nll"), 0.5 * (m**2 / total + np.log(2 * math.pi * total)))
    # an explicit noise floor replaces the field's
    np.testing.assert_allclose(point_scores(f, x, "residual", noise=0.0), np.abs(m) / 0.02)


def test_point_scores_validate():
    f = SphereField()
    with pytest.raises(ValueError, match="point_score"):
        point_scores(f, np.zeros((2, 3)), "bogus")
    with pytest.raises(ValueError, match="no points"):
        point_scores(f, np.zeros((0, 3)))
    with pytest.raises(ValueError, match="noise"):
        point_scores(f, np.zeros((2, 3)), noise=-1)


def test_aggregates():
    v = np.arange(1, 101, dtype=float)  # 1..100
    assert aggregate(v, "mean") == 50.5
    assert aggregate(v, "max") == 100
    assert aggregate(v, "top5") == np.mean([96, 97, 98, 99, 100])
    assert aggregate(v, "top1") == 100
    assert aggregate(v, "q50") == 50.5
    assert aggregate([3.0], "top5") == 3.0  # at least one point
    for bad in ("top0", "top150", "worst", "q", 5):
        with pytest.raises(ValueError, match="aggregate"):
            aggregate(v, bad)


def test_alpha_validated():
    with pytest.raises(ValueError, match="alpha must be in"):
        conformal_threshold([1.0], 0)
    with pytest.raises(ValueError, match="alpha must be in"):
        Inspector(SphereModel(), alpha=1.5).fit([sphere_scan()[0]])


# ---------------------------------------------------------------------------------------------- estimator
@pytest.fixture(scope="module")
def fitted():
    good = [sphere_scan(seed=s)[0] for s in range(10, 49)]  # 39 good calibration scans
    return Inspector(SphereModel(), alpha=0.05).fit(good)


def test_flags_deformed_passes_good(fitted):
    good = [sphere_scan(seed=s)[0] for s in (102, 103, 104)]  # good scans: each passes with probability ~1 - alpha
    dented = [sphere_scan(seed=s, dent=0.08)[0] for s in (200, 201)]
    pred = fitted.predict(good + dented)
    assert pred.tolist() == [1, 1, 1, -1, -1]
    amap = fitted.anomaly_map(dented[0])
    top = np.argsort(amap)[-20:]
    # the worst points are at the dent (near the pole)
    pts = dented[0] - np.array([0.1, -0.2, 0.05])
    assert np.all(pts[top, 2] / np.linalg.norm(pts[top], axis=1) > math.cos(0.35))


def test_estimator_contract(fitted):
    scans = [sphere_scan(seed=s)[0] for s in (300, 301)] + [sphere_scan(seed=302, dent=0.05)[0]]
    assert fitted.offset_ == -fitted.threshold_
    assert len(fitted.calibration_scores_) == fitted.n_calibration_ == 39
    ss, df = fitted.score_samples(scans), fitted.decision_function(scans)
    np.testing.assert_array_equal(df, ss - fitted.offset_)
    np.testing.assert_array_equal(ss, -fitted.anomaly_scores(scans))
    pv, pred = fitted.p_values(scans), fitted.predict(scans)
    np.testing.assert_array_equal(pred == -1, pv <= fitted.alpha)
    np.testing.assert_array_equal(pred == -1, df < 0)
    assert set(pred.tolist()) <= {-1, 1}


def test_not_fitted_and_params_untouched():
    insp = Inspector(SphereModel(), alpha=0.05, aggregate="mean")
    assert insp.get_params()["alpha"] == 0.05  # scikit-learn BaseEstimator: get_params / set_params / clone
    assert insp.aggregate == "mean" and not hasattr(insp, "threshold_")
    with pytest.raises(NotFittedError, match="not calibrated"):
        insp.predict([sphere_scan()[0]])
    with pytest.raises(NotFittedError):
        insp.decision_function([sphere_scan()[0]])
    assert insp.anomaly_scores([sphere_scan()[0]]).shape == (1,)  # scoring itself needs no calibration


def test_fit_rejects_empty_and_empty_scans():
    with pytest.raises(ValueError, match="no good scans"):
        Inspector(SphereModel()).fit([])
    with pytest.raises(ValueError, match="points"):
        Inspector(SphereModel()).fit([np.zeros((0, 3))])


def test_calibration_roundtrip(fitted):
    cal = fitted.calibration(source="unit test")
    again = Calibration.from_dict(cal.as_dict())
    other = Inspector.from_calibration(SphereModel(), again, alpha=0.05)
    assert other.threshold_ == fitted.threshold_ and other.settings_ == fitted.settings_
    np.testing.assert_array_equal(other.calibration_scores_, fitted.calibration_scores_)


def test_fixed_field_and_callable_models():
    pts, _ = sphere_scan(seed=3, center=(0, 0, 0))
    field = SphereField()
    a = Inspector(field).anomaly_scores([pts])
    b = Inspector(lambda p, n: field).anomaly_scores([pts])
    np.testing.assert_array_equal(a, b)


def test_sklearn_clone_keeps_params_drops_fit(fitted):
    from sklearn.base import clone

    c = clone(fitted)
    assert c.get_params()["alpha"] == fitted.alpha and not hasattr(c, "threshold_")


def test_distance_point_score_undoes_saturation():
    from inspection.reference import GRADIENT_FLOOR, LocalReference, field_quantity

    f = SaturatingSphereField(width=0.02, noise=0.0)
    depth = np.array([0.0, 0.004, 0.03, 0.06, 0.12])
    x = np.c_[np.zeros((5, 2)), 1 + depth]
    # closed form: E f / max(|grad E f|, floor) with E f = w tanh(t / w), |grad| = 1 - tanh^2(t / w)
    th = np.tanh(depth / 0.02)
    expected = 0.02 * th / np.maximum(1 - th**2, GRADIENT_FLOOR)
    np.testing.assert_allclose(field_quantity(f, x, "distance"), expected, rtol=1e-12)
    assert field_quantity(f, x[:2], "distance")[1] == pytest.approx(0.004, rel=0.05)  # ~ the distance near the surface
    # good scans put E f = 0 at the pole (sd 0.001): E f saturates past ~1.5 w; the distance follows the depth
    # until |grad E f| reaches the floor and then stays at |E f| / floor, 1 / floor = 5 x the plateau
    rng = np.random.default_rng(0)
    pts = np.c_[rng.normal(0, 0.01, (64, 2)), np.ones(64)]
    vals = np.where(np.arange(64) % 2 == 0, -0.001, 0.001)
    # E f itself against the good scans' E f = 0 (the retired point score 'local', up to its constant denominator)
    local = np.abs(f.mean(x))
    dist = point_scores(f, x, "distance", reference=LocalReference(pts, vals, k=64, quantity="distance"))
    assert local[4] < 1.01 * local[3]  # saturated: a pit twice as deep scores the same
    assert np.all(np.diff(dist) > 0)
    # relative to a point near the surface, a deep point is lifted by ~1 / floor
    assert (dist[4] / dist[1]) > 0.7 / GRADIENT_FLOOR * (local[4] / local[1])
    with pytest.raises(ValueError, match="retired"):
        LocalReference(pts, vals, k=64, quantity="mean")

    class MeanOnly:
        noise = 0.0

        def mean(self, x):
            return np.zeros(len(x))

    with pytest.raises(ValueError, match="mean_gradient"):
        field_quantity(MeanOnly(), x, "distance")


def test_reference_inspector_needs_reference():
    insp = Inspector(SphereModel(), point_score="distance")
    with pytest.raises(NotFittedError, match="reference"):
        insp.anomaly_scores([sphere_scan()[0]])
    with pytest.raises(ValueError, match="reference_scans"):
        insp.fit([sphere_scan()[0]])
    good = [sphere_scan(seed=s)[0] for s in range(5)]
    insp.fit([sphere_scan(seed=s)[0] for s in range(5, 15)], reference_scans=good)
    assert insp.reference_.points.shape == (10000, 3)
    # the distance score builds its reference on distances, and the calibration remembers which
    assert insp.reference_.quantity == "distance" and insp.point_score == "distance"
    restored = Inspector.from_calibration(SphereModel(), insp.calibration())
    assert restored.settings_.point_score == "distance" and restored.reference_.quantity == "distance"
    np.testing.assert_array_equal(restored.anomaly_scores(good[:2]), insp.anomaly_scores(good[:2]))


def test_aligner_recovers_a_small_rotation():
    from scipy.spatial.transform import Rotation

    from inspection.align import Aligner

    rng = np.random.default_rng(0)
    # an asymmetric part: a box-ish cloud with a bump, so the pose is well defined
    p = rng.uniform(-1, 1, (6000, 3)) * [1.0, 0.6, 0.3]
    p[:, 2] = np.where(rng.random(6000) < 0.5, 0.3, -0.3)
    p[:, 2] += 0.3 * np.exp(-((p[:, 0] - 0.5) ** 2 + p[:, 1] ** 2) / 0.05)
    R = Rotation.from_euler("xyz", [3, -2, 4], degrees=True).as_matrix()
    moved = (p[:3000] - 0.02) @ R.T
    aligned, _, T = Aligner(p, seed=0).align(moved)
    assert np.abs(aligned - p[:3000]).max() < 0.01


# ---------------------------------------------------------------------------------------------- calibrated variance
def test_noise_model_matches_the_closed_form_and_a_grid_search():
    from inspection.reference import fit_noise_model as fit
    rng = np.random.default_rng(0)
    # constant b, u, e and no grazing: the ML kappa of r ~ N(0, b + kappa u + e) is (mean r^2 - b - e) / u
    b, u, e, kappa = 0.5, 2.0, 0.1, 1.7
    r = rng.normal(0, math.sqrt(b + kappa * u + e), 200000)
    k, lam = fit(r, np.full_like(r, b), np.full_like(r, u), e)
    assert k == pytest.approx((np.mean(r**2) - b - e) / u, rel=1e-3) and lam == 0.0
    # heterogeneous b, u, g: the optimum of the likelihood on a fine 2-D grid
    b, u, g = rng.uniform(0.1, 1, 20000), rng.uniform(0, 3, 20000), rng.exponential(2.0, 20000)
    r = rng.normal(0, np.sqrt(b + 0.6 * u + 0.2 * (1 + 1.5 * g)))
    ks, ls = np.geomspace(0.2, 2, 121), np.geomspace(0.5, 5, 121)
    nll = np.empty((len(ks), len(ls)))
    for i, k in enumerate(ks):  # row by row: the whole grid at once would take gigabytes
        total = (b + k * u + 0.2)[None, :] + 0.2 * ls[:, None] * g[None, :]
        nll[i] = np.mean(r**2 / total + np.log(total), axis=1)
    i, j = np.unravel_index(np.argmin(nll), nll.shape)
    k, lam = fit(r, b, u, 0.2, g)
    assert k == pytest.approx(ks[i], rel=0.03) and lam == pytest.approx(ls[j], rel=0.03)
    # residuals the reference alone explains: neither the field's variance nor the grazing gets weight
    r = rng.normal(0, np.sqrt(b) * 0.5)
    assert fit(r, b, u, 0.01, g) == (0.0, 0.0)


def test_grazing_factor_is_one_over_cos_squared_minus_one():
    from autodecoder.scanning.sensor import GRAZING_COS2_FLOOR, grazing_factor

    origin = np.array([0.0, 0.0, 3.0])
    x = np.array([[0, 0, 1.0], [math.sin(0.5), 0, math.cos(0.5)], [1.0, 0, 0]])
    # the ray from the origin to each point against the sphere's normal (the point itself)
    rays = x - origin
    cos = np.sum(rays / np.linalg.norm(rays, axis=1, keepdims=True) * x, axis=1)
    expected = 1 / np.maximum(cos**2, GRAZING_COS2_FLOOR) - 1
    np.testing.assert_allclose(grazing_factor(x, -2 * x, origin), expected, rtol=1e-12)  # any length, either sign
    assert grazing_factor(x, x, origin)[0] == pytest.approx(0.0, abs=1e-12)


def test_reference_standardizes_with_the_weighted_field_variance_and_leaves_scans_out():
    from inspection.reference import LocalReference

    pts = np.r_[np.zeros((20, 3)), np.ones((20, 3))]
    vals = np.r_[np.full(20, 0.5), np.full(20, 2.0)]
    ref = LocalReference.from_values([(pts[:20], vals[:20]), (pts[20:], vals[20:])], k=4, quantity="distance")
    ref.variance_scale, ref.grazing_scale = 2.0, 3.0
    x = np.zeros((1, 3))
    # all 4 neighbours of the origin come from scan 0: m_ref = 0.5, s_ref = 0
    assert ref.standardized(x, np.array([1.5]), np.array([0.125]), 0.5)[0] == pytest.approx(
        1.0 / math.sqrt(2.0 * 0.125 + 0.25))
    assert ref.standardized(x, np.array([1.5]), np.array([0.125]), 0.5, np.array([2.0]))[0] == pytest.approx(
        1.0 / math.sqrt(2.0 * 0.125 + 0.25 * (1 + 3.0 * 2.0)))
    alone = ref.without(0)
    assert len(alone.points) == 20 and np.all(alone.values == 2.0) and (alone.variance_scale, alone.grazing_scale) \
        == (2.0, 3.0)
    assert alone.stats(x)[0][0] == pytest.approx(2.0)
    with pytest.raises(ValueError, match="owners"):
        LocalReference(pts, vals, k=4).without(0)


def test_fit_cross_fits_the_reference_scans():
    """Calibration scores = held-back scans against the full reference + each reference scan against the reference
    without its own points; the field-variance weight is fitted first and stored."""
    from inspection.reference import field_quantity

    good = [sphere_scan(seed=s, n=600)[0] for s in range(8)]
    held = [sphere_scan(seed=s, n=600)[0] for s in range(20, 24)]
    insp = Inspector(SphereModel(), point_score="distance", alpha=0.2).fit(held, reference_scans=good)
    assert insp.calibration_roles_ == ["held-back"] * 4 + ["cross-fitted"] * 8
    assert insp.n_calibration_ == 12 and insp.reference_.variance_scale >= 0
    model, noise = SphereModel(), 0.01
    for j, scan in enumerate(good):
        field = model.project(scan).field
        value, variance = field_quantity(field, scan, "distance", with_variance=True)
        alone = insp.reference_.without(j)
        expected = aggregate(alone.standardized(scan, value, variance, noise), "top1")  # no origin: no grazing
        assert insp.calibration_scores_[4 + j] == pytest.approx(expected, rel=1e-9)
    expected_held = insp.anomaly_scores(held)
    np.testing.assert_allclose(insp.calibration_scores_[:4], expected_held, rtol=1e-9)
    stored = insp.calibration()
    assert stored.roles == insp.calibration_roles_
    assert stored.extra["reference"]["variance_scale"] == insp.reference_.variance_scale
    assert stored.extra["reference"]["grazing_scale"] == insp.reference_.grazing_scale == 0.0  # no sensor origins
    without = Inspector(SphereModel(), point_score="distance").fit(held, reference_scans=good, cross_fit=False)
    assert without.calibration_roles_ == ["held-back"] * 4


def test_a_handful_of_stray_points_does_not_flag_a_good_scan():
    """Real scanners return a few isolated points off the part; the scan score aggregates the points that lie on
    a surface, so a stray point is not a defect unless many points agree (a dent of many points still is)."""
    good = [sphere_scan(seed=s, n=1500)[0] for s in range(10)]
    held = [sphere_scan(seed=s, n=1500)[0] for s in range(20, 26)]
    insp = Inspector(SphereModel(), point_score="distance", alpha=0.05).fit(held, reference_scans=good)
    clean = sphere_scan(seed=40, n=1500)[0]
    rng = np.random.default_rng(1)
    picked = clean[rng.choice(len(clean), 5, replace=False)]
    strays = picked * 1.15  # 5 lone returns 0.15 off the unit sphere (the noise is 0.003)
    scan = np.r_[clean, strays]
    result = insp.inspect(scan)
    assert result.point_scores[-5:].min() > 10 * insp.threshold_  # the map still shows them
    assert insp.predict([scan])[0] == 1 and result.score == pytest.approx(insp.inspect(clean).score, rel=0.05)
    # the same 5 points' worth of evidence as a surface (a dent of many points) is flagged
    assert insp.predict([sphere_scan(seed=40, n=1500, dent=0.06)[0]])[0] == -1


def _cap_scan(seed, n=2000, noise=0.002, name="cap"):
    """A unit sphere's cap as a sensor 3 units away sees it (a random view within 60 degrees of +z), the noise
    growing where the ray grazes the surface (sd noise / |cos|, as a real range sensor's), with the sensor origin
    recorded: a datasets.Scan."""
    from datasets import Scan

    rng = np.random.default_rng(seed)
    tilt, turn = np.arccos(rng.uniform(0.5, 1.0)), rng.uniform(0, 2 * np.pi)
    o = 3.0 * np.array([np.sin(tilt) * np.cos(turn), np.sin(tilt) * np.sin(turn), np.cos(tilt)])
    d = rng.normal(size=(8 * n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ray = d - o
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    cos = -np.sum(ray * d, axis=1)
    d, cos = d[cos > 0.05][:n], cos[cos > 0.05][:n]  # the visible cap, out to grazing incidence
    points = d * (1 + rng.normal(size=len(d)) * noise / cos)[:, None]
    return Scan(name, points.astype(np.float32), d.astype(np.float32), sensor_origin=o)


def test_a_good_scan_whose_border_grazes_the_surface_is_not_flagged_for_it():
    """Good scans from many views whose noise grows at grazing incidence (where one view grazes a place, others saw
    it head-on, so the per-location reference alone does not know): the grazing term, fitted on good scans, keeps
    new good scans within the calibration scans' range; a constant noise floor lets their grazing border set their
    score."""
    good = [_cap_scan(s, name=f"train/{s}") for s in range(16)]
    held = [_cap_scan(s, name=f"held/{s}") for s in range(20, 26)]
    # the point score alone ('auto' rays would score these scans' rays too: they have sensor origins)
    insp = Inspector(SphereModel(), point_score="distance", alpha=0.05, rays=False).fit(held, reference_scans=good)
    assert insp.reference_.grazing_scale > 0
    fitted_scale = insp.reference_.grazing_scale
    for seed in (40, 41, 42):
        scan = _cap_scan(seed, name="test")
        score = insp.inspect(scan).score
        assert insp.predict([scan])[0] == 1 and score <= insp.calibration_scores_.max()
        insp.reference_.grazing_scale = 0.0  # a constant noise floor
        assert insp.inspect(scan).score > 1.3 * score
        insp.reference_.grazing_scale = fitted_scale


def test_a_scan_without_sensor_origin_grazes_from_the_view_its_normals_face():
    """Public layouts' test scans record no sensor: the grazing term then uses a viewpoint estimated from the
    scan's outward normals (their mean faces the sensor), not none at all."""

    from autodecoder.scanning.sensor import view_origin_from_normals

    scan = _cap_scan(40, name="test")
    true = np.asarray(scan.sensor_origin, float) - scan.points.mean(0)
    est = view_origin_from_normals(scan.points, scan.normals) - scan.points.mean(0)
    angle = np.degrees(np.arccos(true @ est / np.linalg.norm(true) / np.linalg.norm(est)))
    assert angle < 10
    span = np.linalg.norm(np.ptp(scan.points, axis=0))
    assert np.linalg.norm(est) == pytest.approx(2.0 * span, rel=1e-6)

    good = [_cap_scan(s, name=f"train/{s}") for s in range(16)]
    held = [_cap_scan(s, name=f"held/{s}") for s in range(20, 26)]
    # the point score alone ('auto' rays would score these scans' rays too: they have sensor origins)
    insp = Inspector(SphereModel(), point_score="distance", alpha=0.05, rays=False).fit(held, reference_scans=good)
    blind = replace(scan, sensor_origin=None)
    stand_in = replace(scan, sensor_origin=view_origin_from_normals(scan.points, scan.normals))
    np.testing.assert_allclose(insp.inspect_components(blind).point_scores,
                               insp.inspect_components(stand_in).point_scores, rtol=1e-6)
    known, score = insp.inspect(scan).score, insp.inspect(blind).score
    insp.reference_.grazing_scale = 0.0  # what a scan without sensor scored before: no grazing term
    before = insp.inspect(blind).score
    # the stand-in view recovers part of what the true one explains (the silhouette's grazing angles are sensitive
    # to the view's direction and distance, so not all of it)
    assert known < score < before - 0.1


def test_joint_point_score_calibrates_restores_and_ranks_a_dent():
    """'joint' builds its reference on distances like 'distance', stores itself in the calibration, and a scan with a
    dent scores above good ones."""
    from inspection.scores import joint_score

    good = [sphere_scan(seed=s, n=800)[0] for s in range(6)]
    held = [sphere_scan(seed=s, n=800)[0] for s in range(20, 24)]
    insp = Inspector(SphereModel(), point_score="joint", alpha=0.2).fit(held, reference_scans=good)
    assert insp.reference_.quantity == "distance" and insp.calibration_roles_.count("cross-fitted") == 6
    restored = Inspector.from_calibration(SphereModel(), insp.calibration())
    assert restored.settings_.point_score == "joint"
    np.testing.assert_array_equal(restored.anomaly_scores(held[:2]), insp.anomaly_scores(held[:2]))
    distance = Inspector.from_calibration(SphereModel(), insp.calibration())
    distance.settings_ = replace(distance.settings_, point_score="distance")
    scan = held[0]
    assert restored.reference_.term_variances == insp.reference_.term_variances
    np.testing.assert_allclose(insp.inspect_components(scan).point_scores, joint_score(
        distance.inspect_components(scan).point_scores, insp.reference_.surface_scores(scan, 0.01),
        variances=insp.reference_.term_variances), rtol=1e-12)
    dented = sphere_scan(seed=40, n=800, dent=0.05)[0]
    assert insp.anomaly_scores([dented])[0] > insp.calibration_scores_.max()


def test_joint_weighs_its_terms_by_their_spread_on_the_calibration_scans():
    """The joint score's term variances are median(z^2) / median(chi2_1) of each term over the calibration scans'
    points (their stray returns left out), recomputed here from the two terms scored apart; a calibration stored
    before they were fitted (no term_variances) scores with equal weights, as it was calibrated."""
    good = [sphere_scan(seed=s, n=800)[0] for s in range(6)]
    held = [sphere_scan(seed=s, n=800)[0] for s in range(20, 24)]
    insp = Inspector(SphereModel(), point_score="joint", alpha=0.2).fit(held, reference_scans=good, cross_fit=False)
    distance = Inspector.from_calibration(SphereModel(), insp.calibration())
    distance.settings_ = replace(distance.settings_, point_score="distance")
    z_d, z_s = [], []
    for scan in held:
        components = insp.inspect_components(scan)
        kept = ~components.stray if components.stray is not None else slice(None)
        z_d.append(distance.inspect_components(scan).point_scores[kept])
        z_s.append(insp.reference_.surface_scores(scan, 0.01)[kept])
    chi2_median = stats.chi2(1).median()
    expected = (np.median(np.concatenate(z_d) ** 2) / chi2_median, np.median(np.concatenate(z_s) ** 2) / chi2_median)
    np.testing.assert_allclose(insp.reference_.term_variances, expected, rtol=1e-9)
    assert not np.allclose(expected, 1.0, rtol=0.05)  # the sphere's terms are not N(0, 1): the weights do something
    stored = insp.calibration()
    for damaged in ([1.0], "x", [1.0, float("nan")], None):  # a damaged record: one clear error
        stored.extra["reference"]["term_variances"] = damaged
        with pytest.raises(ValueError, match="term_variances must be two positive finite numbers"):
            Inspector.from_calibration(SphereModel(), stored)
    record = stored.as_dict()  # a version-1 record stored before the term variances were fitted: equal weights
    record["version"] = 1
    del record["extra"]["reference"]["term_variances"]
    old = Inspector.from_calibration(SphereModel(), Calibration.from_dict(record))
    assert old.reference_.term_variances == (1.0, 1.0)
    np.testing.assert_allclose(old.inspect_components(held[0]).point_scores ** 2,
                               (distance.inspect_components(held[0]).point_scores ** 2
                                + insp.reference_.surface_scores(held[0], 0.01) ** 2) / 2, rtol=1e-10)


def test_agreement_point_score_is_the_geometric_mean_and_needs_both_terms():
    """'agreement' = sqrt(distance * surface) on the same scan and reference (closed form against the two terms
    scored apart); a point that only one term calls off (8 deviations under one, 0.5 under the other) scores 2, a
    point 2 deviations off under both scores 2 too, while 'joint' puts the first at 5.7."""
    from inspection.scores import agreement_score, joint_score

    good = [sphere_scan(seed=s, n=800)[0] for s in range(6)]
    held = [sphere_scan(seed=s, n=800)[0] for s in range(20, 24)]
    insp = Inspector(SphereModel(), point_score="agreement", alpha=0.2).fit(held, reference_scans=good)
    assert Inspector.from_calibration(SphereModel(), insp.calibration()).settings_.point_score == "agreement"
    maps = {}
    for kind in ("agreement", "distance", "surface"):
        one = Inspector.from_calibration(SphereModel(), insp.calibration())
        one.settings_ = replace(one.settings_, point_score=kind)
        maps[kind] = one.inspect_components(held[0]).point_scores
    v_d, v_s = insp.reference_.term_variances
    np.testing.assert_allclose(maps["agreement"] ** 2, maps["distance"] * maps["surface"] / math.sqrt(v_d * v_s),
                               rtol=1e-10)
    np.testing.assert_allclose(agreement_score([8.0, 2.0], [0.5, 2.0]), [2.0, 2.0])
    np.testing.assert_allclose(joint_score([8.0], [0.5]), [math.sqrt(32.125)])
    with pytest.raises(ValueError, match="one surface score per distance score"):
        agreement_score([1.0, 2.0], [1.0])
    dented = sphere_scan(seed=40, n=800, dent=0.1)[0]  # off under both terms: it still ranks above the good scans
    assert insp.inspect_components(dented).score > max(insp.calibration_scores_)


def test_surface_point_score_is_joints_model_free_term_and_ignores_the_field():
    """'surface' is z_s alone: joint^2 = (distance^2 + surface^2) / 2 on the same scan and reference, and a field
    that errs everywhere leaves it as it was (no field in it), while 'distance' follows the field."""
    good = [sphere_scan(seed=s, n=800)[0] for s in range(6)]
    held = [sphere_scan(seed=s, n=800)[0] for s in range(20, 24)]
    insp = Inspector(SphereModel(), point_score="joint", alpha=0.2).fit(held, reference_scans=good)
    maps = {}
    for kind in ("joint", "distance", "surface"):
        one = Inspector.from_calibration(SphereModel(), insp.calibration())
        one.settings_ = replace(one.settings_, point_score=kind)
        maps[kind] = one.inspect_components(held[0]).point_scores
    v_d, v_s = insp.reference_.term_variances
    np.testing.assert_allclose(maps["joint"] ** 2, (maps["distance"] ** 2 / v_d + maps["surface"] ** 2 / v_s) / 2,
                               rtol=1e-10)
    np.testing.assert_allclose(maps["surface"], insp.reference_.surface_scores(held[0], 0.01), rtol=1e-12)
    class ShrunkSphereModel(SphereModel):  # the fitted sphere, then 0.1 smaller: a field off the part everywhere
        def project(self, points, normals=None, **options):
            fitted = super().project(points, normals, **options).field

            class Projection:
                field = SphereField(fitted.center, fitted.radius - 0.1)

            return Projection()

    wrong = Inspector.from_calibration(ShrunkSphereModel(), insp.calibration())
    for kind in ("surface", "distance"):
        wrong.settings_ = replace(wrong.settings_, point_score=kind)
        moved = wrong.inspect_components(held[0]).point_scores
        if kind == "surface":
            np.testing.assert_allclose(moved, maps["surface"], rtol=1e-12)
        else:
            assert np.median(moved) > 3 * np.median(maps["distance"])


def test_the_reference_takes_its_surface_from_every_training_scan(monkeypatch):
    """The training scans among the good scans: all of them make the reference's surface, an evenly spread subset
    is projected for its values, and owners are matched by name so that cross-fitting leaves a scan's surface
    points out with its values."""
    from datasets.scan import Scan
    from inspection import selection

    def scan(seed, name, split="train"):
        pts, nrm = sphere_scan(seed=seed, n=400)
        return Scan(name=name, points=pts, normals=nrm, split=split, label="good")

    every = [scan(s, f"train/{s}") for s in range(6)]
    held = [scan(s, f"validation/{s}", "validation") for s in range(10, 14)]
    model = SphereModel()
    model.train_names = [s.name for s in every]
    monkeypatch.setattr(selection, "MAX_REFERENCE_SCANS", 3)
    insp = Inspector(model).fit(every + held)
    ref = insp.reference_
    assert insp.settings_.point_score == "joint" and not insp.settings_.rays  # 'auto' with a reference, no origins
    assert insp.calibration_names_[:4] == [s.name for s in held]
    assert len(ref.points) == 1200 and len(ref.surface_points) == 2400
    # every[0], every[2] and every[5] were projected (owners 0, 1, 2); the others only give surface points
    np.testing.assert_array_equal(np.unique(ref.surface_owners), [-5, -4, -2, 0, 1, 2])
    np.testing.assert_array_equal(ref.surface_points[ref.surface_owners == 1], every[2].points.astype(np.float32))
    assert len(ref.without(1).surface_points) == 2000


def test_fitting_on_training_scans_alone_says_which_scans_are_missing():
    """The obvious call with the training scans only: no scan the model did not train on; the error names a
    held-back scan to add (calibrating on in-sample scans alone would understate the false-alarm rate)."""
    from datasets.scan import Scan

    model = SphereModel()
    model.train_names = [f"train/{i}" for i in range(3)]
    model.calibration_names = ["validation/0"]
    scans = [Scan(name=n, points=sphere_scan(seed=i, n=200)[0], normals=sphere_scan(seed=i, n=200)[1])
             for i, n in enumerate(model.train_names)]
    with pytest.raises(ValueError, match="held-back scans \\(e.g. 'validation/0'\\) are not among them"):
        Inspector(model).fit(scans)


def test_inspect_reports_its_stages_seconds_and_the_same_score(fitted):
    """``timings`` receives each stage's seconds (the latency benchmark's breakdown) and changes nothing."""
    scan = sphere_scan(seed=60)[0]
    timings = {}
    timed = fitted.inspect(scan, timings=timings)
    plain = fitted.inspect(scan)
    assert timed.score == plain.score
    np.testing.assert_array_equal(timed.point_scores, plain.point_scores)
    assert {"load", "projection", "stray", "reference", "aggregate"} <= set(timings)
    assert all(v >= 0 for v in timings.values())
    again = dict(timings)
    fitted.inspect(scan, timings=timings)  # a second scan adds to the same entries
    assert all(timings[k] >= again[k] for k in again)
