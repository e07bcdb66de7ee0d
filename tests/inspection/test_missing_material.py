"""Missing material from the sensor's rays: free-space probabilities on toy fields with known answers, image holes,
the max-of-standardized combination, the Inspector with rays, and the command line round trip."""
import csv
import json
import math

import numpy as np
import pytest
import torch

from autodecoder.scanning.free_space import blocked_probability, box_interval, missing_return_probability
from autodecoder.scanning.rays import monte_carlo_survival
from inspection import Inspector, NotFittedError
from inspection.calibration import Calibration
from inspection.ray_evidence import check_ray_options, image_holes, ray_evidence
from autodecoder.field.protocol import Field

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SENSOR = np.array([0.0, 0.0, 2.0])


# ---------------------------------------------------------------------------------------------- a toy field
class WallField(Field):
    """A thin horizontal wall |z| <= thickness / 2 over a solid floor z <= floor, optionally with a round hole
    through the wall (radius ``hole`` about the z axis), or ending at x = ``edge``. Mean: min of the two solids' signed distances (exact
    distances away from the hole's rim); covariance: sd^2 exp(-|a - b|^2 / (2 ell^2)); box [-1, 1]^3."""

    def __init__(self, thickness=0.04, hole=0.0, floor=-0.5, sd=0.005, ell=0.05, offset=0.0, edge=None):
        self.thickness, self.hole, self.floor, self.edge = thickness, hole, floor, edge
        self.sd, self.ell, self.offset = sd, ell, offset
        self.noise = 0.0
        self.lengthscale = 0.02
        self.bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])

    def torch_mean(self, x):
        wall = x[:, 2].abs() - self.thickness / 2
        if self.hole > 0:
            wall = torch.maximum(wall, self.hole - x[:, :2].norm(dim=1))
        if self.edge is not None:  # the wall ends at x = edge
            wall = torch.maximum(wall, x[:, 0] - self.edge)
        return torch.minimum(wall, x[:, 2] - self.floor) + self.offset

    def torch_covariance(self, a, b):
        return self.sd**2 * torch.exp(-((a - b) ** 2).sum(1) / (2 * self.ell**2))

    def torch_variance(self, x):
        return torch.full((len(x),), self.sd**2, dtype=x.dtype)

    # numpy queries, for the point scores
    def mean(self, x):
        return self.torch_mean(torch.as_tensor(np.asarray(x), dtype=torch.float64)).numpy()

    def variance(self, x):
        return np.full(len(x), self.sd**2)


def wall_scan(hole=0.0, n=4000, seed=0, noise=0.0):
    """A depth scan of the WallField's part from SENSOR: the rays of a pinhole grid, each stopped at the part's first
    surface (the wall's top face, or the floor through the hole). Returns (points (m, 3), labels (m,) 1 through the
    hole)."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(n / 0.9)))
    u = (np.arange(side) + 0.5) / side * 2 - 1
    uu, vv = np.meshgrid(u * 0.3, u * 0.3)  # directions spanning [-0.3, 0.3]^2 on the plane 1 below the sensor
    d = np.c_[uu.ravel(), vv.ravel(), -np.ones(uu.size)]
    d = d[rng.random(len(d)) < 0.9]  # the scanner keeps a random ~90 % of its pixels
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t_wall = (SENSOR[2] - 0.02) / -d[:, 2]
    at_wall = SENSOR + t_wall[:, None] * d
    through = np.linalg.norm(at_wall[:, :2], axis=1) < hole
    t_floor = (SENSOR[2] + 0.5) / -d[:, 2]
    t = np.where(through, t_floor, t_wall) + noise * rng.normal(size=len(d))
    return SENSOR + t[:, None] * d, through.astype(np.uint8)


# ---------------------------------------------------------------------------------------------- free space
def test_box_interval():
    t_in, t_out = box_interval(np.array([0.0, 0.0, 3.0]), np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]),
                               np.array([[-1.0, -1, -1], [1, 1, 1]]))
    np.testing.assert_allclose(t_in, [2.0, 0.0])
    np.testing.assert_allclose(t_out, [4.0, 0.0])  # the second ray misses the box


def test_point_behind_a_wall_is_blocked_and_one_on_it_is_not():
    field = WallField()
    behind = np.array([[0.0, 0.0, -0.5], [0.1, -0.05, -0.5]])  # on the floor, straight below the wall
    front = np.array([[0.0, 0.0, 0.02], [0.2, 0.1, 0.02]])  # on the wall's top face
    check = blocked_probability(field, SENSOR, np.r_[behind, front])
    # the wall is 4 sd inside over several samples: blocked beyond doubt. Above the wall the samples up to the
    # last clearly outside one (E f >= 2 sd) count, so a point on the surface keeps a floor of ~Phi(-2) = 0.023
    assert (check.p_blocked[:2] > 0.999).all() and (check.p_blocked[2:] < 0.05).all()
    # log P(free) without cancellation: below the one-sample bound log Phi(-4) = -10.4, where 1 - p_blocked is 0
    assert (check.log_free[:2] < -10.4).all() and np.isfinite(check.log_free).all()
    np.testing.assert_allclose(np.exp(check.log_free), 1 - check.p_blocked, atol=1e-12)
    assert abs(check.t_block[0] - 2.0) < 0.03  # the blocking material is the wall (z ~ 0, 2 below the sensor)
    # the same point seen through a hole in the wall: the field of that part has no material on its ray
    assert blocked_probability(WallField(hole=0.1), SENSOR, behind[:1]).p_blocked[0] < 0.05


def test_a_point_inside_its_own_expected_surface_is_not_blocked():
    """The material just before a point is the point's own surface, however far the mean surface is off: a field
    whose surfaces sit 5 sd (0.025) above the points leaves their rays free (the point score sees that)."""
    field = WallField(offset=-0.025)
    pts = np.array([[0.0, 0.0, 0.02], [0.3, 0.2, 0.02]])
    assert (blocked_probability(field, SENSOR, pts).p_blocked < 0.05).all()


def test_material_next_to_an_observed_surface_is_left_out():
    """A field that blurs the end of a wall 0.03 beyond where the scan saw its end face (x = 0): a ray passing 0.01
    past the observed edge crosses the blurred material; with the scan's points given, samples within the
    clearance (the lengthscale, 0.02) of them are left out and the ray is free. Far from the edge the wall counts."""
    field = WallField(edge=0.03)
    y, z = np.meshgrid(np.linspace(-0.1, 0.1, 21), np.linspace(-0.02, 0.02, 5))
    end_face = np.c_[np.zeros(y.size), y.ravel(), z.ravel()]  # the returns on the wall's end face
    target = np.array([[0.01 * 2.5 / 2.0, 0.0, -0.5],  # passes z = 0 at x = 0.01: inside the blur
                       [-0.2, 0.0, -0.5]])  # through the middle of the wall (no return there, say a hole)
    blind = blocked_probability(field, SENSOR, target)
    seen = blocked_probability(field, SENSOR, target, observed=end_face)
    assert (blind.p_blocked > 0.99).all()
    assert seen.p_blocked[0] < 0.05 and seen.p_blocked[1] > 0.99
    # without the clearance (and without leaving out rays that pass that close to the scan's own points) it is
    assert blocked_probability(field, SENSOR, target, observed=end_face, clearance=0.0,
                               occlusion_radius=None).p_blocked[0] > 0.99


def test_blocked_probability_matches_monte_carlo_on_its_samples():
    """An uncertain wall (mean -0.2 sd inside at its middle, strongly correlated along the ray): the correlated
    probability over the tested samples against sampling the Gaussian on the same samples; the product of the
    marginals (independent samples) would be far off."""
    field = WallField(thickness=0.04, sd=0.01, ell=0.05, offset=0.018)
    point = np.array([[0.0, 0.0, -0.5]])
    step = 0.01
    check = blocked_probability(field, SENSOR, point, step=step, n_select=8, qmc_samples=4096)
    # the same dense grid (documented: linspace from the box entry to the point, without the point) up to t_end
    n = int(min(128, max(3, np.ceil((check.t_obs[0] - check.t_near[0]) / step) + 1)))
    t = np.linspace(check.t_near[0], check.t_obs[0], n)[:-1]
    t = t[t <= check.t_end[0] + 1e-9]
    x = torch.as_tensor(SENSOR + t[:, None] * np.array([0.0, 0.0, -1.0]))
    mean = field.torch_mean(x).numpy()
    cov = field.torch_covariance(x[:, None].expand(-1, len(x), -1).reshape(-1, 3),
                                 x[None].expand(len(x), -1, -1).reshape(-1, 3)).numpy().reshape(len(x), len(x))
    reference = 1 - monte_carlo_survival(mean[None], cov[None], n_samples=200_000, seed=1)[0, -1]
    q = 0.5 * np.array([math.erfc(m / (math.sqrt(2) * 0.01)) for m in mean])
    assert check.p_blocked[0] == pytest.approx(reference, abs=0.02)
    assert check.max_marginal[0] == pytest.approx(q.max(), abs=1e-6)
    assert 1 - np.prod(1 - q) > reference + 0.1  # independence would overstate it


def test_missing_returns_through_a_wall_and_through_a_hole():
    """Rays that returned nothing: they should have hit the intact wall (P ~ 1), not where the hole is."""
    intact, holed = WallField(floor=-5.0), WallField(hole=0.1, floor=-5.0)  # no floor in the box
    d = np.array([[0.0, 0.0, -1.0], [0.02, 0.0, -1.0]])
    # 2 units through the box at steps of half the lengthscale (0.01): 201 samples, so raise the cap
    assert (missing_return_probability(intact, SENSOR, d, max_samples=256).p_blocked > 0.999).all()
    assert (missing_return_probability(holed, SENSOR, d, max_samples=256).p_blocked < 0.05).all()


def test_free_space_bad_input():
    field = WallField()
    with pytest.raises(ValueError, match="origin"):
        blocked_probability(field, [0.0, 1.0], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="coincide"):
        blocked_probability(field, SENSOR, SENSOR[None])
    with pytest.raises(ValueError, match=r"points must be an \(n, 3\)"):
        blocked_probability(field, SENSOR, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="step"):
        blocked_probability(field, SENSOR, np.zeros((2, 3)), step=0.0)
    with pytest.raises(ValueError, match="zero length"):
        missing_return_probability(field, SENSOR, np.zeros((1, 3)))


# ---------------------------------------------------------------------------------------------- scan level
def test_image_holes_finds_an_enclosed_gap_only():
    points, through = wall_scan(hole=0.1)
    blind = points[through == 0]  # a hole with nothing behind it: its returns are missing
    dirs, uv, _, pitch = image_holes(blind, SENSOR)
    assert len(dirs) > 10
    at_wall = SENSOR + dirs * ((SENSOR[2] - 0.02) / -dirs[:, 2])[:, None]
    assert np.linalg.norm(at_wall[:, :2], axis=1).max() < 0.1  # all inside the hole
    assert len(image_holes(points, SENSOR)[0]) == 0  # every pixel returned: no hole
    # a gap at the edge of the image is background around the part, not a hole
    edge = points[points[:, 0] < 0.3]
    assert len(image_holes(edge, SENSOR)[0]) == 0


def test_hole_in_a_thin_wall_scores_higher_than_no_hole():
    field = WallField()  # the model of good parts: an intact wall
    good, _ = wall_scan(seed=1)
    holed, through = wall_scan(hole=0.1, seed=2)
    ev_good = ray_evidence(field, good, SENSOR, n_rays=256)
    ev_holed = ray_evidence(field, holed, SENSOR, n_rays=256)
    assert ev_good.score < 0.05 and ev_holed.score > 10  # nats: P(free) > 0.95 against < 5e-5
    # the map: high where the points were seen through the hole, low elsewhere
    assert ev_holed.point_map[through == 1].min() > 0.99
    assert np.median(ev_holed.point_map[through == 0]) < 0.05
    # a hole with nothing behind it: no returns there, the missing-return rays see it; the rim lights up
    blind = through == 0
    ev_blind = ray_evidence(field, holed[blind], SENSOR, n_rays=256)
    assert ev_blind.score > 0.99 and len(ev_blind.empty_values) > 0
    rim = np.abs(np.linalg.norm(holed[blind][:, :2], axis=1) - 0.1) < 0.02
    assert ev_blind.point_map[rim].mean() > 0.5 and np.median(ev_blind.point_map[~rim]) < 0.05
    # seeded: the same result twice
    again = ray_evidence(field, holed, SENSOR, n_rays=256)
    np.testing.assert_array_equal(again.point_map, ev_holed.point_map)
    # the per-point surprisal: the nearest tested ray's -log P(free) (brute force), and at a hole's rim at least the
    # missing returns' there
    for ev, pts in ((ev_holed, holed), (ev_blind, holed[blind])):
        nearest = np.argmin(np.linalg.norm(pts[:, None, :] - pts[ev.ray_index][None], axis=2), axis=1)
        own = ev.ray_surprisal[nearest]
        assert np.all(ev.point_surprisal >= own - 1e-12)
        np.testing.assert_allclose(ev.point_surprisal[ev.point_map == ev.ray_values[nearest]],
                                   own[ev.point_map == ev.ray_values[nearest]], rtol=1e-12)
    assert ev_holed.point_surprisal[through == 1].min() > 4.6  # P(blocked) > 0.99
    assert ev_blind.point_surprisal[rim].mean() > ev_blind.point_surprisal[~rim].mean() + 1


def test_ray_options_validated():
    assert check_ray_options(None)["n_rays"] == 384
    with pytest.raises(ValueError, match="unknown ray option"):
        check_ray_options({"rays": 3})
    with pytest.raises(ValueError, match="n_rays"):
        check_ray_options({"n_rays": 0})
    with pytest.raises(ValueError, match="gap"):
        check_ray_options({"gap": 0.5})
    with pytest.raises(ValueError, match="aggregate"):
        check_ray_options({"aggregate": "worst"})
    for bad in (1.0, -0.1):
        with pytest.raises(ValueError, match="skim_cos"):
            check_ray_options({"skim_cos": bad})
    for bad in ("q99", "median"):  # no chance level of those (inspection.ray_calibration.top_count)
        with pytest.raises(ValueError, match="ray option aggregate"):
            check_ray_options({"aggregate": bad})
    with pytest.raises(ValueError, match="occlusion"):
        check_ray_options({"occlusion": 0.0})
    with pytest.raises(ValueError, match="empty_to_rim"):
        check_ray_options({"empty_to_rim": "yes"})
    assert check_ray_options({"occlusion": None})["occlusion"] is None


# ---------------------------------------------------------------------------------------------- Inspector
class WallModel:
    """Projection of any scan: the intact wall (the latent space of good parts holds no holes)."""

    def project(self, points, normals=None):
        class Projection:
            field = WallField()

        return Projection()


def _scans(kind, seeds):
    from datasets import Scan

    out = []
    for s in seeds:
        pts, through = wall_scan(hole=0.1 if kind == "hole" else 0.0, seed=s, noise=0.002)
        out.append(Scan(name=f"test/{kind}/{s:03d}", points=pts, normals=np.tile([0.0, 0, 1], (len(pts), 1)),
                        split="test", label="good" if kind == "good" else "defective",
                        defect="" if kind == "good" else "missing", point_labels=through, sensor_origin=SENSOR))
    return out


def test_inspector_with_rays_flags_the_hole_and_round_trips():
    good = _scans("good", range(6))
    insp = Inspector(WallModel(), alpha=0.2, rays=True, ray_options={"n_rays": 256}).fit(good)
    assert insp.combination_.rule == "likelihood" and len(insp.calibration_scores_) == 6
    assert (insp.combination_.calibration_nats == 0).all()  # the good scans' rays: nothing beyond chance
    tests = _scans("good", [50, 51]) + _scans("hole", [60, 61])
    res = [insp.inspect(s) for s in tests]
    assert [r.components["rays"] > 0.5 for r in res] == [False, False, True, True]
    assert [r.components["ray_nats"] > 10 for r in res] == [False, False, True, True]
    assert insp.predict(tests[2:]).tolist() == [-1, -1]
    # rays with nothing beyond chance change nothing: a good scan is judged by its point score alone, at the threshold
    # the point score alone would have; a hole's by both, sqrt(z^2 + 2 I)
    assert [r.score for r in res[:2]] == [r.components["points"] for r in res[:2]]
    for r in res[2:]:
        assert r.score == pytest.approx(math.sqrt(r.components["points"] ** 2 + 2 * r.components["ray_nats"]))
    # the point score alone cannot tell: the points seen through the hole lie on a good surface
    plain = Inspector(WallModel(), alpha=0.2).fit(good)
    assert plain.predict(tests[2:]).tolist() == [1, 1]
    assert insp.ray_map(tests[2]).shape == (len(tests[2].points),)
    # the anomaly map adds each point's ray surprisal to its patch's likelihood: sqrt(r^2 + 2 s); the points seen
    # through the hole, on a good floor, stand out in it and not in the patch residual alone
    from sklearn.metrics import roc_auc_score

    from inspection.maps import patch_residuals, with_ray_evidence

    comps = insp.inspect(tests[2])
    patch = patch_residuals(tests[2].points, comps.point_scores, excluded=comps.stray)
    amap = insp.anomaly_map(tests[2])
    # the map's ray evidence is the rays' as the calibration weighs them (here clean good rays: their own surprisal)
    np.testing.assert_allclose(amap ** 2 - patch ** 2, 2 * comps.ray_point_nats, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(comps.ray_point_nats, comps.rays.point_surprisal, rtol=1e-9)
    through = tests[2].point_labels == 1
    assert roc_auc_score(through, amap) > 0.95 and roc_auc_score(through, patch) < 0.8
    good_comps = insp.inspect_components(tests[0])  # no ray evidence on a good scan: the patch residual itself
    np.testing.assert_allclose(insp.anomaly_map(tests[0]),
                               with_ray_evidence(patch_residuals(tests[0].points, good_comps.point_scores,
                                                                 excluded=good_comps.stray),
                                                 good_comps.rays.point_surprisal), rtol=1e-12)
    assert good_comps.rays.point_surprisal.max() < 0.1
    with pytest.raises(ValueError, match="3 ray surprisals for 4 map values"):
        with_ray_evidence(np.ones(4), np.zeros(3))
    np.testing.assert_array_equal(with_ray_evidence(np.arange(3.0), None), np.arange(3.0))
    # stored and restored: the same scores without the calibration scans
    cal = Calibration.from_dict(insp.calibration(source="unit test").as_dict())
    assert cal.config().ray_options["n_rays"] == 256
    again = Inspector.from_calibration(WallModel(), cal, alpha=0.2)
    assert again.settings_.rays and again.settings_.ray_options["n_rays"] == 256
    np.testing.assert_allclose(again.anomaly_scores(tests), insp.anomaly_scores(tests))
    assert again.threshold_ == insp.threshold_
    assert again.settings_.ray_options["skim_cos"] == check_ray_options(None)["skim_cos"] > 0
    # a calibration whose rays were combined by a retired rule (gated-log, before) cannot score: calibrate again
    record = cal.as_dict()
    record["extra"]["rays"]["components"] = {"points": [1.0, 2.0, 3.0], "rays": [0.0, 0.0, 1.0],
                                             "rule": "gated-log", "ceiling": 690.8}
    with pytest.raises(ValueError, match="retired rule 'gated-log'.*calibrate again"):
        Inspector.from_calibration(WallModel(), Calibration.from_dict(record), alpha=0.2)


def test_inspector_rays_errors():
    good = _scans("good", range(3))
    with pytest.raises(NotFittedError, match="rays=True"):
        Inspector(WallModel(), rays=True).anomaly_scores(good[:1])
    no_origin = good[0]
    no_origin.sensor_origin = None
    with pytest.raises(ValueError, match="test/good/000: no sensor origin"):
        Inspector(WallModel(), rays=True).inspect_components(no_origin)
    with pytest.raises(ValueError, match="no sensor origin"):
        Inspector(WallModel(), rays=True).inspect_components(good[1].points)  # a bare array has none
    with pytest.raises(ValueError, match="unknown ray option"):
        Inspector(WallModel(), rays=True, ray_options={"bogus": 1}).fit(good)
    with pytest.raises(ValueError, match="rays must be"):
        Inspector(WallModel(), rays="yes").fit(good)


# ---------------------------------------------------------------------------------------------- command line
def test_cli_calibrate_and_score_with_rays(tmp_path, capsys):
    """A field model file (a tiny untrained network: the plumbing, not the detection), scans with sensor origins:
    calibrate --rays stores the ray record, score writes the two components and the ray maps; scans without an
    origin are refused in one line."""
    from autodecoder.field.stochastic_field import StochasticField
    from datasets.frame import Frame
    from autodecoder.field.networks import build_networks
    from datasets import Frame, ScanCollection, read_cloud
    from inspection.__main__ import main
    from inspection.calibration import read_calibration
    from inspection.model_io import save_reference_field
    from inspection.report import RAY_CSV_COLUMNS

    def scans(kind, split, seeds, origin=True):
        out = _scans(kind, seeds)
        for s in out:
            s.name = f"{split}/{kind}/{s.name[-3:]}"
            s.split = split
            s.points = s.points[::6] * 0.2  # ~250 points inside the model's box
            s.normals, s.point_labels = s.normals[::6], None if split == "train" else s.point_labels[::6]
            s.sensor_origin = SENSOR * 0.2 if origin else None
        return out

    frame = Frame(np.zeros(3), 1.0)
    data = tmp_path / "tree.h5"
    ScanCollection.create(data, scans("good", "train", range(6)) + scans("good", "test", [10, 11])
                          + scans("hole", "test", [20]), frame=frame)
    with ScanCollection(data) as c:
        fp, names = c.fingerprint(), c.names
    config = {"width": 16, "depth": 1, "latent_dim": 0, "covariance": "feature", "features": 8, "omega0": 5.0,
              "lengthscale": 0.05, "box_lo": [-0.6] * 3, "box_hi": [0.6] * 3}
    torch.manual_seed(0)
    field = StochasticField(*build_networks(config), Frame.identity(), config, noise=0.01)
    model = tmp_path / "model.pt"
    save_reference_field(field, model, frame=frame, fingerprint=fp, train_names=names[:2],
                         heldback_names=names[2:6])
    assert main(["calibrate", "--model", str(model), "--data", str(data), "--alpha", "0.3", "--rays",
                 "--ray-options", "n_rays=64,n_empty=16,aggregate=top5", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "+ ray score" in printed and "the rays weighed by the good scans'" in printed
    cal = read_calibration(model)
    # 4 held-back scans and the 2 training scans, cross-fitted
    assert cal.config().ray_options["aggregate"] == "top5" and len(cal.extra["rays"]["components"]["nats"]) == 6
    out = tmp_path / "res"
    assert main(["score", "--model", str(model), "--data", str(data), "--out", str(out), "--maps", "all",
                 "--quiet"]) == 0
    rows = list(csv.DictReader(open(out / "scores.csv")))
    assert tuple(rows[0]) == RAY_CSV_COLUMNS and len(rows) == 3
    assert all(float(r["score_rays"]) >= 0 and float(r["ray_nats"]) >= 0 for r in rows)  # nats
    assert all(0 <= float(r["rays_through"]) <= 1 for r in rows)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["rays"]["options"]["n_rays"] == 64 and "ray_point_auroc" in summary["metrics"]
    assert summary["rays"]["weighing"].startswith("the rays weighed by the good scans'")
    pts, _ = read_cloud(out / "maps" / "rays" / "test__hole__020.ply")
    with ScanCollection(data) as c:
        assert len(pts) == len(c[c.index_of("test/hole/020")].points)
    assert (out / "maps" / "rays" / "legend.png").is_file()
    # a scan without a sensor origin among others: verdict 'error' with its reason, the others scored, exit 1
    bare = tmp_path / "bare.h5"
    ScanCollection.create(bare, scans("good", "test", [30], origin=False) + scans("good", "test", [31]), frame=frame)
    rc = main(["score", "--model", str(model), "--data", str(bare), "--out", str(tmp_path / "r2"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1 and "1 scan(s) could not be scored" in err
    with open(tmp_path / "r2" / "scores.csv", newline="") as f:
        verdicts = {r["name"]: (r["verdict"], r["reason"]) for r in csv.DictReader(f)}
    assert verdicts["test/good/030"][0] == "error" and "test/good/030: no sensor origin" in verdicts["test/good/030"][1]
    assert verdicts["test/good/031"][0] in ("good", "defective", "uncertain") and verdicts["test/good/031"][1] == ""
    # --ray-options without the rays (--no-rays: on by default when the scans have sensor origins)
    rc = main(["calibrate", "--model", str(model), "--data", str(data), "--ray-options", "n_rays=5", "--no-rays",
               "--quiet"])
    assert rc == 2 and "--ray-options needs --rays" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------- issue 18
class OneSidedField(Field):
    """The one-sided field of a sheet's top face z = top seen from above: "material" everywhere below it, the
    cavity under the sheet and the part's real openings included (mean z - top, sd ``sd``); box [-1, 1]^3."""

    def __init__(self, top=0.02, sd=0.005, ell=0.05):
        self.top, self.sd, self.ell = top, sd, ell
        self.noise = 0.0
        self.lengthscale = 0.02
        self.bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])

    def torch_mean(self, x):
        return x[:, 2] - self.top

    def torch_covariance(self, a, b):
        return self.sd**2 * torch.exp(-((a - b) ** 2).sum(1) / (2 * self.ell**2))

    def torch_variance(self, x):
        return torch.full((len(x),), self.sd**2, dtype=x.dtype)


def _sheet_points(opening, spacing=0.01, top=0.02):
    """Good scans' points of a sheet's top face over [-0.6, 0.6]^2 without the disc ``opening`` (centre, radius),
    and of the floor z = -0.5 under it."""
    g = np.arange(-0.6, 0.6 + 1e-9, spacing)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    (cx, cy), r = opening
    sheet = xy[np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) >= r]
    return np.r_[np.c_[sheet, np.full(len(sheet), top)], np.c_[xy, np.full(len(xy), -0.5)]]


def test_surface_band_against_brute_force():
    from autodecoder.scanning.free_space import SurfaceBand

    rng = np.random.default_rng(3)
    pts, x = rng.uniform(-1, 1, (300, 3)), rng.uniform(-1, 1, (500, 3))
    band = SurfaceBand(pts, 0.15)
    brute = np.sqrt(((x[:, None] - pts[None]) ** 2).sum(-1)).min(1) <= 0.15
    np.testing.assert_array_equal(band.contains(x), brute)
    from scipy.spatial import cKDTree

    from datasets.neighbours import NearestNeighbours

    index = NearestNeighbours(pts)  # an index the caller already holds (the point score's reference): used as it is
    shared = SurfaceBand(index, 0.15)
    assert shared._index is index
    for band in (shared, SurfaceBand(cKDTree(pts), 0.15)):
        np.testing.assert_array_equal(band.contains(x), brute)
        np.testing.assert_array_equal(band.points, pts)
    with pytest.raises(ValueError, match="radius"):
        SurfaceBand(pts, 0.0)


def test_band_leaves_out_a_one_sided_fields_cavity_but_not_a_hole_in_the_sheet():
    """Rays through a real opening cross the one-sided field's extrapolated material where good parts have no
    surface: with the band they are free. Rays through a hole where good parts have the sheet cross it inside the
    band: blocked, by at most what the band's deepest sample says (closed form: mean -radius, sd 0.005)."""
    from autodecoder.scanning.free_space import SurfaceBand

    field = OneSidedField()
    good_surface = _sheet_points(((-0.3, 0.0), 0.15))  # the part's real opening at (-0.3, 0)
    band = SurfaceBand(good_surface, field.lengthscale)  # the face at z = 0.02: the band is 0 <= z <= 0.04
    sensor = np.array([0.0, 0.0, 2.0])
    # points on the floor seen through the real opening, and through a hole at (0.3, 0) (the sheet of good parts)
    through_opening = np.c_[-0.3 + 0.03 * np.arange(-2, 3), np.zeros(5), np.full(5, -0.5)]
    through_hole = through_opening * [-1, 1, 1]
    observed = np.r_[through_opening, through_hole]
    for with_band, expect_open, expect_hole in ((False, 1.0, 1.0), (True, 0.0, 1.0)):
        check = blocked_probability(field, sensor, observed, observed=observed, own_depth=0.06,
                                    band=band if with_band else None)
        np.testing.assert_allclose(check.p_blocked[:5], expect_open, atol=1e-6)
        assert (check.p_blocked[5:] > 0.9).all() == (expect_hole == 1.0)
    # closed form: inside the band no sample is deeper than 0.02 below the top face: P(f <= 0) <= Phi(0.02 / 0.005);
    # the samples are < 0.012 apart along the rays (box length 1.5 / 127), so one lies in 0 <= z < 0.012: >= Phi(1.6)
    phi = [0.5 * math.erfc(-v / math.sqrt(2)) for v in (4.0, 1.6)]
    assert (check.max_marginal[5:] <= phi[0] + 1e-9).all() and (check.max_marginal[5:] >= phi[1]).all()
    # ray_evidence with the good scans' points as its surface: the same, through the scan's own options
    ev_open = ray_evidence(field, through_opening, sensor, n_empty=0, surface=good_surface, band=1.0)
    ev_hole = ray_evidence(field, through_hole, sensor, n_empty=0, surface=good_surface, band=1.0)
    ev_open_no_band = ray_evidence(field, through_opening, sensor, n_empty=0, own_depth=0.06)  # no good surface
    assert ev_open.score < 1e-6 < 1.0 < ev_hole.score and ev_open_no_band.score > 1.0



def test_the_field_is_read_only_where_a_ray_can_test_it():
    """The rays read the field at the samples the band and the scan's own surface leave testable and within
    own_depth of each point (where the tested segment's end is decided), nowhere else: every point whose marginal
    is asked for is in the band or that close to an observed point, and the answers are those of the same check
    with a field that answers nonsense everywhere else (which no unread sample can change)."""
    from scipy.spatial import cKDTree

    from autodecoder.scanning.free_space import SurfaceBand

    field = OneSidedField()
    good_surface = _sheet_points(((-0.3, 0.0), 0.15))
    band = SurfaceBand(good_surface, field.lengthscale)
    observed = np.c_[0.3 * np.cos(np.linspace(0, 6, 40)), 0.3 * np.sin(np.linspace(0, 6, 40)), np.full(40, -0.5)]
    own_depth, near_observed = 0.06, cKDTree(observed)

    class Recording(OneSidedField):
        """The same field, recording where its marginal variance is read (the rays' dense pass); off the band and
        the points' depth it answers nonsense (a variance of 1e6)."""

        read = []

        def torch_variance(self, x):
            self.read.append(x.numpy().copy())
            p = x.numpy().astype(np.float64)
            there = band.contains(p) | (near_observed.query(p)[0] <= own_depth + 1e-6)
            return torch.where(torch.as_tensor(there), super().torch_variance(x), torch.full_like(x[:, 0], 1e6))

    recording = Recording()
    check = blocked_probability(field, SENSOR, observed, observed=observed, own_depth=own_depth, band=band)
    again = blocked_probability(recording, SENSOR, observed, observed=observed, own_depth=own_depth, band=band)
    read = np.concatenate(Recording.read).astype(np.float64)
    assert len(read) and (band.contains(read) | (near_observed.query(read)[0] <= own_depth + 1e-5)).all()
    for key in ("p_blocked", "max_marginal", "t_end", "t_block"):
        np.testing.assert_array_equal(getattr(again, key), getattr(check, key))
    # the test still tests: rays through the sheet where good parts have it are blocked, those through its opening
    # (centre (-0.3, 0), radius 0.15) free; a ray to p crosses the sheet's face at p_xy (2 - 0.02) / (2 + 0.5)
    crossing = np.hypot(observed[:, 0] * 1.98 / 2.5 + 0.3, observed[:, 1] * 1.98 / 2.5)
    assert (check.p_blocked[crossing > 0.17] > 0.9).all() and (check.p_blocked[crossing < 0.13] < 0.1).all()
    assert (crossing > 0.17).sum() > 20 and (crossing < 0.13).sum() > 2

class SphereField(Field):
    """A solid ball of radius ``radius`` about the origin: mean |x| - radius, sd ``sd`` everywhere (a blurred rim);
    box [-1, 1]^3."""

    def __init__(self, radius=0.3, sd=0.004, ell=0.05):
        self.radius, self.sd, self.ell = radius, sd, ell
        self.noise = 0.0
        self.lengthscale = 0.02
        self.bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])

    def torch_mean(self, x):
        return x.norm(dim=1) - self.radius

    def torch_covariance(self, a, b):
        return self.sd**2 * torch.exp(-((a - b) ** 2).sum(1) / (2 * self.ell**2))

    def torch_variance(self, x):
        return torch.full((len(x),), self.sd**2, dtype=x.dtype)


def _sphere_surface(radius=0.3, n=20000):
    """Good scans' points on the ball's surface (Fibonacci lattice) and their unit outward normals."""
    k = np.arange(n) + 0.5
    z, phi = 1 - 2 * k / n, math.pi * (1 + 5**0.5) * k
    unit = np.c_[np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z]
    return radius * unit, unit


def test_surface_band_skims_against_brute_force():
    """:meth:`SurfaceBand.skims` against the nearest point found by brute force: outside its tangent plane and a
    ray at |cos| < min_cos with its normal; nothing without normals or at min_cos 0."""
    from autodecoder.scanning.free_space import SurfaceBand
    from datasets.neighbours import NearestNeighbours

    rng = np.random.default_rng(5)
    pts, normals = _sphere_surface(n=2000)
    x = rng.uniform(-0.4, 0.4, (800, 3))
    d = rng.normal(size=(800, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    band = SurfaceBand(pts, 0.1, normals=(NearestNeighbours(pts), normals), min_cos=0.3)
    nearest = np.sqrt(((x[:, None] - pts[None]) ** 2).sum(-1)).argmin(1)
    n = normals[nearest]
    brute = (((x - pts[nearest]) * n).sum(1) > 0) & (np.abs((d * n).sum(1)) < 0.3)
    np.testing.assert_array_equal(band.skims(x, d), brute)
    assert 0 < brute.sum() < len(x)
    np.testing.assert_array_equal(band.tested(x, d), band.contains(x) & ~brute)
    for plain in (SurfaceBand(pts, 0.1), SurfaceBand(pts, 0.1, normals=(NearestNeighbours(pts), normals))):
        assert not plain.skims(x, d).any()
    with pytest.raises(ValueError, match="min_cos"):
        SurfaceBand(pts, 0.1, normals=(NearestNeighbours(pts), normals), min_cos=1.0)
    with pytest.raises(ValueError, match="one finite, non-zero normal per indexed point"):
        SurfaceBand(pts, 0.1, normals=(NearestNeighbours(pts), normals[:-1]), min_cos=0.2)


def test_a_ray_skimming_past_a_good_surface_is_not_accused_but_one_through_its_material_is():
    """A ray that passes the ball 0.001 outside its rim runs along the good surface through the field's blurred rim:
    without the good surface's normals it is blocked with at least the closest sample's marginal (closed form,
    Phi(-0.00104 / sd): a sample lies within half a step of the tangent point); with them the samples it skims past are not tested,
    and only those where it has left the tangent plane by |cos| >= 0.2 are, no nearer than 0.0072 to the rim
    (closed form: d(s) = sqrt(0.301^2 + s^2) - 0.3 at cos = s / sqrt(0.301^2 + s^2) = 0.2), so the ray is blocked
    with little more than the sum of those samples' marginals. A ray to a point behind the ball through its middle (material a good
    part has) stays blocked."""
    from autodecoder.scanning.free_space import SurfaceBand
    from datasets.neighbours import NearestNeighbours

    field = SphereField()
    pts, normals = _sphere_surface()
    sensor = np.array([-2.0, 0.0, 0.0])
    # the ray from the sensor to (0.9, y, 0) passes the centre at 2 y / sqrt(2.9^2 + y^2) = 0.301: 0.001 outside
    skimming = np.array([[0.9, 2.9 * 0.301 / math.sqrt(4.0 - 0.301**2), 0.0]])
    behind = np.array([[0.9, 0.0, 0.0]])  # through the ball's middle (a point seen where the ball should hide it)
    targets = np.r_[skimming, behind]
    phi = lambda v: 0.5 * math.erfc(v / math.sqrt(2))  # noqa: E731  P(N(0, 1) > v)
    plain = blocked_probability(field, sensor, targets, observed=targets, band=SurfaceBand(pts, 0.02))
    oriented = blocked_probability(field, sensor, targets, observed=targets,
                                   band=SurfaceBand(pts, 0.02, normals=(NearestNeighbours(pts), normals),
                                                    min_cos=0.2))
    # samples every <= 0.01 (half the lengthscale): one within 0.005 of the tangent point, 0.00104 outside the rim
    assert plain.max_marginal[0] >= phi(0.00104 / field.sd)
    # the lattice's normals are off by up to ~0.0125 rad (its spacing 0.0075 over the radius): |cos| 0.1875 lies
    # 0.0064 outside the rim
    assert oriented.max_marginal[0] <= phi(0.0064 / field.sd) + 1e-9
    assert oriented.p_blocked[0] < 0.15 < 0.35 < plain.p_blocked[0]
    assert oriented.p_blocked[1] > 0.999 and plain.p_blocked[1] > 0.999
    # ray_evidence with the good surface's normals (its own options: band 1 lengthscale, skim_cos)
    oriented_surface = (NearestNeighbours(pts), normals)
    scores = [ray_evidence(field, skimming, sensor, n_empty=0, surface=pts, band=1.0, own_depth=0.06,
                           surface_normals=oriented_surface, skim_cos=skim).score for skim in (0.0, 0.2)]
    assert scores[1] < -math.log(1 - 0.15) < -math.log(1 - 0.35) < scores[0]


def test_grazing_rays_are_not_tested():
    """Rays to points whose |cos| of incidence is below min_cos are left out (grazing = 1 / cos^2 - 1)."""
    field = WallField()
    points, _ = wall_scan(n=300)
    cos = np.linspace(0.01, 1.0, len(points))
    grazing = 1.0 / cos**2 - 1.0
    ev = ray_evidence(field, points, SENSOR, n_rays=len(points), n_empty=0, grazing=grazing, min_cos=0.2)
    np.testing.assert_array_equal(ev.ray_index, np.flatnonzero(cos >= 0.2))
    sub = ray_evidence(field, points, SENSOR, n_rays=50, n_empty=0, grazing=grazing, min_cos=0.2)
    assert len(sub.ray_index) == 50 and (cos[sub.ray_index] >= 0.2).all()
    assert len(ray_evidence(field, points, SENSOR, n_rays=len(points), n_empty=0, grazing=grazing,
                            min_cos=0.0).ray_index) == len(points)
    with pytest.raises(ValueError, match="min_cos"):
        check_ray_options({"min_cos": 1.0})
