"""fit_cloud and StochasticField on a sphere: surface, P(inside), variance, save/load, bad input.

One small fit is shared by the module (a few seconds); the assertions are properties of a sphere that any correct
stochastic Poisson reconstruction must have, not numbers copied from a run.
"""
import numpy as np
import pytest
import torch

from autodecoder import StochasticField, fit_cloud

CENTER = np.array([1.0, -2.0, 0.5])
RADIUS = 3.0  # deliberately not the unit sphere at the origin: the field must undo its normalisation


def sphere_cloud(n, seed=0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return CENTER + RADIUS * d, d


@pytest.fixture(scope="module")
def sphere_field():
    points, normals = sphere_cloud(1500)
    # a short run: a covariance step every 8 mean steps (fit_cloud's 16 is sized for its 4000 steps)
    return fit_cloud(points, normals, representation="siren",
                     seed=0, quiet=True, width=64, depth=2, features=32, steps=250,
                     mean_batch=1024, screen_batch=512, pair_clusters=48, covariance_every=8)


def test_mean_surface_lies_on_the_sphere(sphere_field):
    mesh = sphere_field.mesh(resolution=48)
    radii = np.linalg.norm(mesh.vertices - CENTER, axis=1)
    assert np.abs(radii - RADIUS).max() < 0.04 * RADIUS
    assert abs(radii.mean() - RADIUS) < 0.01 * RADIUS
    # outward orientation: the faces' normals point away from the centre
    outward = np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles_center - CENTER)
    assert (outward > 0).mean() > 0.99


def test_training_lowers_every_loss(sphere_field):
    history = sphere_field.info["history"]
    first, last = history[0], history[-1]
    for key in ("mean_dirichlet", "cov_dirichlet"):
        assert last[key] < 0.5 * first[key], key
    # the screening terms start near zero (small initial outputs) and must stay small, not necessarily fall
    assert last["mean_screening"] < 0.05 * first["mean_dirichlet"]


def test_sign_convention_and_prob_inside(sphere_field):
    inside, far = CENTER[None], CENTER[None] + [[0, 0, 1.6 * RADIUS]]
    assert sphere_field.mean(inside)[0] < 0 < sphere_field.mean(far)[0]
    assert sphere_field.prob_inside(inside)[0] > 0.99
    assert sphere_field.prob_inside(far)[0] < 0.01
    p = sphere_field.prob_inside(CENTER + RADIUS * np.eye(3))
    assert np.all((p > 0.05) & (p < 0.95)), "on the surface the field should be uncertain about its sign"


def test_variance_smallest_on_points_and_grows_away(sphere_field):
    points, _ = sphere_cloud(200, seed=1)
    direction = (points - CENTER) / RADIUS
    on = sphere_field.variance(points)
    near = sphere_field.variance(CENTER + (RADIUS * 1.1) * direction)
    far = sphere_field.variance(CENTER + (RADIUS * 1.45) * direction)
    assert np.all(on > 0)
    assert np.median(on) < np.median(near) < np.median(far)


def test_covariance_is_symmetric_and_variance_on_diagonal(sphere_field):
    rng = np.random.default_rng(2)
    a, b = CENTER + rng.uniform(-4, 4, (50, 3)), CENTER + rng.uniform(-4, 4, (50, 3))
    np.testing.assert_allclose(sphere_field.covariance(a, b), sphere_field.covariance(b, a), rtol=1e-5, atol=1e-12)
    np.testing.assert_allclose(sphere_field.covariance(a, a), sphere_field.variance(a), rtol=1e-5, atol=1e-12)


def test_nll_matches_gaussian_formula_and_prefers_surface_points(sphere_field):
    points, _ = sphere_cloud(100, seed=3)
    noise = 0.01
    nll = sphere_field.nll(points, noise=noise)
    mean, var = sphere_field.mean(points), sphere_field.variance(points) + noise**2
    np.testing.assert_allclose(nll, 0.5 * mean**2 / var + 0.5 * np.log(2 * np.pi * var), rtol=1e-10)
    off = CENTER + (points - CENTER) * 1.05
    assert np.median(sphere_field.nll(off, noise=noise)) > np.median(nll) + 1.0
    with pytest.raises(ValueError, match="noise"):
        sphere_field.nll(points, noise=-1)


def test_save_load_round_trip_gives_identical_outputs(sphere_field, tmp_path):
    path = tmp_path / "field.pt"
    sphere_field.save(path)
    loaded = StochasticField.load(path)
    x = CENTER + np.random.default_rng(4).uniform(-4, 4, (300, 3))
    for query in ("mean", "variance", "prob_inside"):
        np.testing.assert_array_equal(getattr(loaded, query)(x), getattr(sphere_field, query)(x))
    assert loaded.noise == sphere_field.noise
    assert list(tmp_path.iterdir()) == [path], "the atomic save must leave no temporary file behind"


def test_load_rejects_foreign_and_corrupt_files(tmp_path):
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(ValueError, match="foreign.pt.*not a stochastic field"):
        StochasticField.load(foreign)
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"this is not a torch file")
    with pytest.raises(ValueError, match="corrupt.pt"):
        StochasticField.load(corrupt)
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        StochasticField.load(tmp_path / "missing.pt")


def test_same_seed_same_field():
    points, normals = sphere_cloud(300)
    kwargs = dict(representation="siren", seed=5, quiet=True, width=16, depth=1, features=8, steps=5, mean_batch=128,
                  screen_batch=64, pair_clusters=8)
    a, b = fit_cloud(points, normals, **kwargs), fit_cloud(points, normals, **kwargs)
    x = CENTER + np.random.default_rng(6).uniform(-4, 4, (50, 3))
    np.testing.assert_array_equal(a.mean(x), b.mean(x))
    np.testing.assert_array_equal(a.variance(x), b.variance(x))


def test_default_lengthscale_is_one_and_a_half_point_spacings_whatever_the_units():
    """fit_cloud's kernel lengthscale follows the cloud's own spacing, in the cloud's units: checked against the
    analytic spacing of n points spread over a sphere of radius r, sqrt(4 pi r^2 / n), at two scales."""
    points, normals = sphere_cloud(2000)
    kwargs = dict(seed=0, quiet=True, width=8, depth=1, features=4, steps=1, mean_batch=16, screen_batch=16,
                  pair_clusters=2)
    for scale in (1.0, 40.0):
        field = fit_cloud(CENTER + scale * (points - CENTER), normals, representation="siren", **kwargs)
        h_world = field.config["lengthscale"] / field.frame.scale
        expected = 1.5 * np.sqrt(4 * np.pi * (scale * RADIUS) ** 2 / len(points))
        assert abs(h_world / expected - 1) < 0.15


@pytest.mark.parametrize("points, normals, message", [
    (np.zeros((0, 3)), np.zeros((0, 3)), "0 points"),
    (np.full((50, 3), np.nan), np.ones((50, 3)), "NaN"),
    (np.ones((50, 2)), np.ones((50, 2)), r"\(n, 3\)"),
    (np.random.default_rng(0).normal(size=(50, 3)), None, "normals are missing"),
    (np.random.default_rng(0).normal(size=(50, 3)), np.ones((40, 3)), "same shape"),
    (np.random.default_rng(0).normal(size=(50, 3)), np.zeros((50, 3)), "zero length"),
    (np.ones((50, 3)), np.ones((50, 3)), "span no volume"),
])
def test_bad_input_gives_one_clear_error(points, normals, message):
    with pytest.raises(ValueError, match=message):
        fit_cloud(points, normals, representation="siren", quiet=True, steps=1)


def test_pair_subset_estimates_the_sum_over_all_ordered_pairs():
    from autodecoder.field.steps import _pair_subset

    m, cluster_size = 24, 4
    rng = np.random.default_rng(7)
    values = rng.random((m, m))
    exact = values.sum() - np.trace(values)
    estimates = []
    for _ in range(3000):
        i, j, factor = _pair_subset(m, cluster_size, rng)
        assert np.all(i != j)
        estimates.append(float((values[i, j] * factor.numpy()).sum()))
    standard_error = np.std(estimates) / np.sqrt(len(estimates))
    assert abs(np.mean(estimates) - exact) < 4 * standard_error


def test_paper_pair_covariance_fits_and_stays_symmetric():
    points, normals = sphere_cloud(300)
    field = fit_cloud(points, normals, representation="siren",
                      seed=0, quiet=True, covariance="pair", width=16, depth=1, steps=20,
                      mean_batch=128, screen_batch=64, pair_clusters=8)
    rng = np.random.default_rng(8)
    a, b = CENTER + rng.uniform(-4, 4, (30, 3)), CENTER + rng.uniform(-4, 4, (30, 3))
    np.testing.assert_allclose(field.covariance(a, b), field.covariance(b, a), rtol=1e-5, atol=1e-12)
    assert np.all(field.variance(a) > 0) and np.all(np.isfinite(field.mean(a)))


def test_queries_reject_malformed_points(sphere_field):
    with pytest.raises(ValueError, match=r"query points must be an \(n, 3\) array"):
        sphere_field.mean(np.zeros(3))
    with pytest.raises(ValueError, match="NaN"):
        sphere_field.variance(np.full((2, 3), np.nan))
    assert sphere_field.mean(np.zeros((0, 3))).shape == (0,)


def test_mean_gradient_matches_finite_differences(sphere_field):
    """grad E f in world units (the cloud is not in the unit cube: the frame's scale must cancel)."""
    x = np.random.default_rng(3).uniform(-0.3, 0.3, (20, 3)) + sphere_field.frame.center
    eps = 1e-3
    fd = np.stack([(sphere_field.mean(x + eps * e) - sphere_field.mean(x - eps * e)) / (2 * eps)
                   for e in np.eye(3)], 1)
    np.testing.assert_allclose(sphere_field.mean_gradient(x), fd, rtol=2e-2, atol=2e-3 * np.abs(fd).max())


@pytest.mark.parametrize("steps", [1, 7, 100, 129, 150, 1000])
def test_even_pool_size_uses_every_pool_to_the_end(steps):
    """The mean-sample pools of a run are all served to the end: as few pools as the size cap allows, none with more
    minibatches than the run still needs (counted by serving a MeanPool for `steps` steps)."""
    from autodecoder.field.steps import MeanPool, even_pool_size

    size, passes = 32, 4
    refresh = even_pool_size(steps, size, passes)
    assert 1 <= refresh <= size

    class CountingTargets:
        drawn = 0

        def mean_batch(self, n, rng):
            CountingTargets.drawn += n
            return (np.zeros((n, 3), np.float32),) * 2 + (np.ones(n, np.float32),)

    pool = MeanPool(CountingTargets(), 2, refresh, np.random.default_rng(0), passes=passes)
    for _ in range(steps):
        pool.next()
    pools = -(-steps // (size * passes))
    assert CountingTargets.drawn == 2 * refresh * pools  # no more pools than the cap forces
    assert refresh * passes * pools - steps < pools * passes  # and no pool holds a minibatch nobody uses


def test_covariance_screening_weight_pins_the_variance_at_the_points(sphere_field):
    """A larger lambda_S on c(p, p)^2 alone (the mean's screening unchanged) lowers the variance at the cloud
    relative to the variance off it, against the shared fit with the paper's weight."""
    points, normals = sphere_cloud(1500)
    strong = fit_cloud(points, normals, representation="siren",
                       seed=0, quiet=True, width=64, depth=2, features=32, steps=250,
                       mean_batch=1024, screen_batch=512, pair_clusters=48, covariance_screening_weight=1e6)
    assert strong.info["options"]["covariance_screening_weight"] == 1e6
    off = CENTER + 1.6 * (points - CENTER)  # 0.6 radii outside

    def contrast(field):
        return np.median(field.variance(points)) / np.median(field.variance(off))

    assert contrast(strong) < 0.5 * contrast(sphere_field)
    # the mean's screening is the paper's in both: the mean surface stays on the sphere
    assert np.abs(strong.mean(points)).mean() < 0.05 * RADIUS


@pytest.mark.parametrize("steps, every", [(10, 1), (10, 3), (7, 7), (5, 20)])
def test_covariance_every_spreads_covariance_steps_through_the_run(steps, every, adam_steps):
    """covariance_every=k: the mean net takes every step, the covariance net ceil(steps / k), the first at step 0
    (counted on the optimisers' own steps)."""
    points, normals = sphere_cloud(300)
    fit_cloud(points, normals, representation="siren",
              quiet=True, width=16, depth=1, features=8, steps=steps, mean_batch=64,
              screen_batch=64, pair_clusters=8, covariance_every=every)
    mean_opt = adam_steps[0]  # the mean net steps first in every iteration
    assert adam_steps.count(mean_opt) == steps
    assert len(adam_steps) - steps == -(-steps // every)


@pytest.mark.parametrize("override, message", [
    ({"steps": 0}, "steps must be an integer >= 1"),
    ({"covariance_every": 0}, "covariance_every must be an integer >= 1"),
    ({"mean_batch": 2.5}, "mean_batch must be an integer"),
    ({"cluster_size": 1}, "cluster_size must be an integer >= 2"),
    ({"lr": 0.0}, "lr must be > 0"),
    ({"screening_weight": float("nan")}, "screening_weight must be a finite number"),
    ({"covariance_screening_weight": -1.0}, "covariance_screening_weight must be a finite number >= 0"),
    ({"average_decay": 1.0}, "average_decay must be in"),
    ({"outside_weight": -1.0}, "outside_weight must be a finite number >= 0"),
])
def test_bad_fit_options_give_one_clear_error(override, message):
    points, normals = sphere_cloud(200)
    with pytest.raises(ValueError, match=message):
        fit_cloud(points, normals, representation="siren", quiet=True, **override)


def test_mean_averager_matches_a_hand_computed_moving_average():
    """MeanAverager against the closed form: from step `start`, a0 = w_start, a_k = d_k a_{k-1} + (1 - d_k) w,
    d_k = min(decay, (1 + k) / (10 + k)) when k steps have been averaged already; earlier steps ignored."""
    from autodecoder.field.steps import MeanAverager

    net = torch.nn.Linear(2, 1, bias=False)
    weights = [torch.tensor([[float(i), -2.0 * i]]) for i in range(12)]
    averager = MeanAverager(net, decay=0.5, start=4)
    for step, w in enumerate(weights):
        with torch.no_grad():
            net.weight.copy_(w)
        averager.update(step)
    expected = weights[4].clone()
    for k, w in enumerate(weights[5:], start=1):
        d = min(0.5, (1 + k) / (10 + k))
        expected = d * expected + (1 - d) * w
    assert not torch.allclose(net.weight, expected)  # the net still holds its last iterate
    averager.apply()
    torch.testing.assert_close(net.weight, expected, rtol=1e-6, atol=1e-6)


def test_average_decay_zero_keeps_the_last_iterate():
    from autodecoder.field.steps import MeanAverager

    net = torch.nn.Linear(2, 1)
    before = [p.clone() for p in net.parameters()]
    averager = MeanAverager(net, decay=0.0, start=0)
    for step in range(3):
        averager.update(step)
    averager.apply()
    for p, q in zip(net.parameters(), before):
        assert torch.equal(p, q)


def test_fit_ends_on_the_averaged_mean_net(monkeypatch):
    """With averaging on, fit_cloud's mean net is MeanAverager's average (same seed, same run, decay 0 vs 0.9 give
    different nets; the averaged one equals the average recorded during the run)."""
    from autodecoder.field import fit as fit_module

    recorded = {}
    original_apply = fit_module.MeanAverager.apply

    def spy(self):
        recorded["average"] = None if self.average is None else [a.clone() for a in self.average]
        original_apply(self)

    monkeypatch.setattr(fit_module.MeanAverager, "apply", spy)
    points, normals = sphere_cloud(200)
    kw = dict(quiet=True, width=16, depth=1, features=8, steps=12, mean_batch=64, screen_batch=64, pair_clusters=8)
    plain = fit_cloud(points, normals, representation="siren", average_decay=0.0, **kw)
    assert recorded["average"] is None
    averaged = fit_cloud(points, normals, representation="siren", average_decay=0.9, **kw)
    for p, a in zip(averaged.mean_net.parameters(), recorded["average"]):
        torch.testing.assert_close(p, a)
    assert not np.allclose(plain.mean(points[:20]), averaged.mean(points[:20]))


def test_outside_value_is_the_far_field_of_a_closed_surface(sphere_field):
    """CloudTargets.outside_value: the jump integral agrees with adaptive quadrature of the posterior mean, and it is
    the value the paper's loss gives g outside a closed surface (box boundary) and -value inside (centre)."""
    from scipy.integrate import quad

    from autodecoder.field.targets import CloudTargets

    points, normals = sphere_cloud(1500)
    model_points = sphere_field.frame.to_collection(points)
    targets = CloudTargets(model_points, normals, sphere_field.config["lengthscale"])
    w = targets.outside_value()
    post = targets.posterior
    p, n = post.points[0], post.normals[0]
    jump, _ = quad(lambda t: float(post.mean((p + t * n)[None])[0] @ n), -2 * post.radius, 2 * post.radius,
                   limit=200)
    # one line against the median over 256: the sphere's lines differ only by the sampling around them
    assert abs(0.5 * jump - w) < 0.15 * w
    rng = np.random.default_rng(0)
    with torch.no_grad():
        outside = sphere_field.mean_net(torch.from_numpy(targets.boundary_batch(400, rng))).numpy()
        centre = sphere_field.mean_net(torch.from_numpy(model_points.mean(0, keepdims=True).astype(np.float32)))
    assert abs(np.median(outside) - w) < 0.25 * w
    assert abs(float(centre) + w) < 0.25 * w


def test_boundary_batch_lies_on_the_box_faces_in_proportion_to_their_area():
    from autodecoder.field.sampling import Box
    from autodecoder.field.targets import CloudTargets

    points, normals = sphere_cloud(300)
    box = Box(np.array([-1.0, -1.0, -1.0]), np.array([3.0, 1.0, 0.0]))  # extents 4, 2, 1
    targets = CloudTargets(points / 10, normals, 0.05, box=box)
    x = targets.boundary_batch(20000, np.random.default_rng(0))
    on_face = np.isclose(x, box.lo) | np.isclose(x, box.hi)
    assert on_face.any(1).all()
    assert (x >= box.lo - 1e-6).all() and (x <= box.hi + 1e-6).all()
    # face pairs normal to x, y, z have areas 2, 4, 8 (x2 faces): shares 1/7, 2/7, 4/7
    shares = on_face.argmax(1)
    np.testing.assert_allclose(np.bincount(shares, minlength=3) / len(x), [1 / 7, 2 / 7, 4 / 7], atol=0.015)


def test_outside_term_closes_an_open_sheet():
    """A hemisphere (an open sheet, one scan's worth): with the paper's loss g on the box's boundary falls well
    short of the outside value w of a closed surface (measured: median 0.5 w, half the boundary below w / 2);
    with outside_weight the boundary is outside (g ~ w, measured: all of it within 0.8 w .. 1.05 w)."""
    from autodecoder.field.targets import CloudTargets

    points, normals = sphere_cloud(1500)
    keep = normals[:, 2] > 0
    points, normals = points[keep], normals[keep]
    kw = dict(seed=0, quiet=True, width=32, depth=2, features=16, steps=250, mean_batch=512, screen_batch=256,
              pair_clusters=16)
    boundary = {}
    for weight in (0.0, 100.0):
        field = fit_cloud(points, normals, representation="siren", outside_weight=weight, **kw)
        targets = CloudTargets(field.frame.to_collection(points), normals, field.config["lengthscale"])
        with torch.no_grad():
            boundary[weight] = field.mean_net(torch.from_numpy(
                targets.boundary_batch(1000, np.random.default_rng(1)))).numpy()
    w = targets.outside_value()
    assert (boundary[0.0] < 0.5 * w).mean() > 0.3
    assert (boundary[100.0] < 0.5 * w).mean() < 0.01
    assert abs(np.median(boundary[100.0]) - w) < 0.15 * w


def test_cosine_decay_closed_form():
    """The one learning-rate schedule: 1 at the start, the floor at the end and after, (1 + floor) / 2 half-way,
    never increasing."""
    from autodecoder.field.schedule import cosine_decay

    assert cosine_decay(0, 100, 0.1) == pytest.approx(1.0)
    assert cosine_decay(50, 100, 0.1) == pytest.approx(0.55)
    assert cosine_decay(100, 100, 0.1) == pytest.approx(0.1)
    assert cosine_decay(250, 100, 0.1) == pytest.approx(0.1)
    assert cosine_decay(0, 0, 0.3) == pytest.approx(1.0)
    values = [cosine_decay(s, 37, 0.05) for s in range(40)]
    assert all(a >= b for a, b in zip(values, values[1:]))


def test_mean_averager_is_the_warmed_up_exponential_average_of_the_late_iterates():
    """MeanAverager against the recursion written out by hand: nothing before ``start``, the first averaged iterate
    copied, then a <- d_k a + (1 - d_k) p with d_k = min(decay, (1 + k) / (10 + k)) after k averaged steps."""
    from autodecoder.field.steps import MeanAverager

    net = torch.nn.Linear(2, 1)
    averager = MeanAverager(net, decay=0.5, start=3)
    values = np.random.default_rng(0).normal(size=(12, 3))
    expected, k = None, 0
    for step, v in enumerate(values):
        with torch.no_grad():
            net.weight.copy_(torch.tensor(v[:2]).reshape(1, 2))
            net.bias.copy_(torch.tensor(v[2:]))
        averager.update(step)
        if step >= 3:
            if expected is None:
                expected = v.copy()
            else:
                d = min(0.5, (1 + k) / (10 + k))
                expected = d * expected + (1 - d) * v
            k += 1
    averager.apply()
    np.testing.assert_allclose(np.concatenate([net.weight.detach().numpy().ravel(), net.bias.detach().numpy()]),
                               expected, rtol=1e-6)
