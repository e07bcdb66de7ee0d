"""The NSSPR losses and what feeds them: the B-spline kernel, the lumped GP posterior and the MIS samplers.

References are independent: hand-computed closed forms, dense numpy linear algebra, explicit loops over pairs, and
Monte-Carlo means over many draws compared to closed-form integrals within a few standard errors.
"""
import numpy as np
import pytest
import torch
from scipy import integrate

from autodecoder.field.gp_targets import GPPosterior
from autodecoder.field.kernel import bspline3, kernel, support_radius
from autodecoder.field.losses import (SCREENING_WEIGHT, covariance_dirichlet_loss_features,
                                covariance_dirichlet_loss_pairs, mean_dirichlet_loss, screening_loss)
from autodecoder.field.siren import FeatureCovarianceNet
from autodecoder.field.sampling import Box, sample_mean_targets, sample_pair_clusters


pytestmark = pytest.mark.usefixtures("one_torch_thread")


# ------------------------------------------------------------------------------------------------------------ losses

def test_covariance_loss_features_equals_explicit_pairs():
    """The Gram-matrix loss == the pair loss over every ordered pair, each D c formed by d_operator one by one."""
    torch.manual_seed(0)
    net = FeatureCovarianceNet(width=16, depth=2, features=7).double()
    s, m = 2, 5
    x = torch.rand(s, m, 3, dtype=torch.float64) * 0.4
    sigma = torch.rand(s, m, m, dtype=torch.float64)
    sigma = 0.5 * (sigma + sigma.transpose(1, 2))
    weights = torch.rand(s, m, m, dtype=torch.float64) + 0.1
    weights[:, torch.arange(m), torch.arange(m)] = 0.0

    jac = torch.stack([net.features_and_jacobian(x[k])[1] for k in range(s)])  # (S, m, 3, K)
    loss = covariance_dirichlet_loss_features(jac, sigma, weights)

    per_scan = []
    for k in range(s):
        d_c, sig, w = [], [], []
        for i in range(m):
            for j in range(m):
                if i == j:
                    continue
                d_c.append(net.d_operator(x[k, i:i + 1], x[k, j:j + 1])[0])
                sig.append(sigma[k, i, j])
                w.append(weights[k, i, j])
        per_scan.append(covariance_dirichlet_loss_pairs(torch.stack(d_c), torch.stack(sig), torch.stack(w)))
    ref = torch.stack(per_scan).mean()
    torch.testing.assert_close(loss, ref, rtol=1e-12, atol=0)


def test_covariance_loss_features_sparse_route_matches_dense_gram():
    """With the pair sampler's weights (one constant weight for pairs beyond the support) and a compact Sigma, the
    loss takes its factored route (w0 ||sum_i J_i J_i^T||^2 plus the few near pairs): value and gradient must equal
    the dense Gram matrix of every pair's D c, in double precision."""
    from autodecoder.field.losses import _covariance_loss_dense

    rng = np.random.default_rng(3)
    box = Box(np.full(3, -0.5), np.full(3, 0.5))
    x, w = sample_pair_clusters(box, 24, 4, 0.05, rng)
    sigma = np.clip(1 - np.abs(x[:, None] - x[None]).max(-1) / 0.1, 0, None)  # zero beyond 0.1, like Sigma
    assert (w == w.max()).mean() > 0.9  # the sampler's weights have the form the factoring exploits
    jac0 = torch.randn(2, len(x), 3, 11, dtype=torch.float64)
    sigma_t = torch.from_numpy(np.stack([sigma, 0.5 * sigma]))
    w_t = torch.from_numpy(np.stack([w, 2 * w]).astype(np.float64))
    grads = []
    for loss_fn in (covariance_dirichlet_loss_features, _covariance_loss_dense):
        jac = jac0.clone().requires_grad_()
        loss = loss_fn(jac, sigma_t, w_t)
        loss.backward()
        grads.append((loss.detach(), jac.grad))
    torch.testing.assert_close(grads[0][0], grads[1][0], rtol=1e-10, atol=0)
    torch.testing.assert_close(grads[0][1], grads[1][1], rtol=1e-9, atol=1e-12)


def test_covariance_loss_features_cluster_blocks_match_dense_gram():
    """With ``cluster_size`` the pairs inside each cluster come from the cluster's own Gram matrix and only the near
    pairs across clusters are gathered: value and gradient equal the dense Gram matrix of every pair's D c (double
    precision), on a batch with near pairs across clusters (clusters that overlap) as well as inside them; a
    cluster size that does not divide the batch takes the pair-by-pair route, the same sum."""
    from autodecoder.field.losses import _covariance_loss_dense

    rng = np.random.default_rng(5)
    box = Box(np.full(3, -0.5), np.full(3, 0.5))
    x, w = sample_pair_clusters(box, 40, 4, 0.08, rng)
    sigma = np.clip(1 - np.abs(x[:, None] - x[None]).max(-1) / 0.16, 0, None)
    cluster = np.arange(len(x)) // 4
    across = (sigma > 0) & (cluster[:, None] != cluster[None, :])
    assert across.sum() > 20  # near pairs across clusters: the gathered part of the blocked route is exercised
    jac0 = torch.randn(2, len(x), 3, 9, dtype=torch.float64)
    sigma_t = torch.from_numpy(np.stack([sigma, 0.5 * sigma]))
    w_t = torch.from_numpy(np.stack([w, 2 * w]).astype(np.float64))

    def value_and_grad(**kwargs):
        jac = jac0.clone().requires_grad_()
        loss = (_covariance_loss_dense(jac, sigma_t, w_t) if kwargs.pop("dense", False) else
                covariance_dirichlet_loss_features(jac, sigma_t, w_t, **kwargs))
        loss.backward()
        return loss.detach(), jac.grad

    ref = value_and_grad(dense=True)
    for kwargs in ({"cluster_size": 4}, {"cluster_size": 7}, {}):  # 7 does not divide 160
        got = value_and_grad(**kwargs)
        torch.testing.assert_close(got[0], ref[0], rtol=1e-10, atol=0)
        torch.testing.assert_close(got[1], ref[1], rtol=1e-9, atol=1e-12)


def test_covariance_loss_pairs_closed_form():
    sigma = torch.tensor([0.5, 2.0], dtype=torch.float64)
    w = torch.tensor([3.0, 0.25], dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64)
    # D c = Sigma I: zero loss; D c = 0: sum_k w_k 3 Sigma_k^2; a single off-diagonal entry e: w e^2
    assert covariance_dirichlet_loss_pairs(sigma[:, None, None] * eye, sigma, w).item() == 0.0
    torch.testing.assert_close(covariance_dirichlet_loss_pairs(torch.zeros(2, 3, 3, dtype=torch.float64), sigma, w),
                               torch.tensor(3 * (3 * 0.25 + 0.25 * 4.0), dtype=torch.float64))
    d = sigma[:, None, None] * eye
    d[1, 0, 2] += 4.0
    torch.testing.assert_close(covariance_dirichlet_loss_pairs(d, sigma, w), torch.tensor(0.25 * 16.0,
                                                                                          dtype=torch.float64))


def test_mean_dirichlet_loss_closed_form():
    # |mu - grad g|^2 = |(1, 2, 2)|^2 = 9 everywhere; two scans of two samples with weights; |B| = 2
    mu = torch.tensor([[1.0, 2.0, 2.0]]).expand(2, 2, 3)
    grad_g = torch.zeros(2, 2, 3)
    omega = torch.tensor([[1.0, 3.0], [0.0, 4.0]])
    # |B| * mean over scans and samples of omega * 9 = 2 * 9 * (1 + 3 + 0 + 4) / 4
    assert mean_dirichlet_loss(grad_g, mu, omega, 2.0).item() == pytest.approx(36.0)
    # omega = 1 (uniform sampling) gives the paper's |B|/s sum |mu - grad g|^2
    g = torch.randn(5, 3)
    m = torch.randn(5, 3)
    assert mean_dirichlet_loss(g, m, torch.ones(5), 3.0).item() == pytest.approx(
        3.0 / 5 * ((m - g) ** 2).sum().item(), rel=1e-6)


def test_screening_loss_weight():
    v = torch.tensor([1.0, 2.0, 3.0])
    assert SCREENING_WEIGHT == 100.0
    assert screening_loss(v).item() == pytest.approx(100.0 * 14.0 / 3.0)
    assert screening_loss(v.reshape(3, 1), weight=2.0).item() == pytest.approx(2.0 * 14.0 / 3.0)


# ------------------------------------------------------------------------------------------------------------ kernel

def b3_reference(t):
    """Piecewise cubic B-spline, written independently with np.piecewise."""
    t = np.abs(np.asarray(t, dtype=float))
    return np.piecewise(t, [t < 1, (t >= 1) & (t < 2), t >= 2],
                        [lambda a: 2 / 3 - a**2 + a**3 / 2, lambda a: (2 - a) ** 3 / 6, 0.0])


def test_bspline3_values():
    t = np.array([0.0, 0.5, -0.5, 1.0, -1.0, 1.5, 2.0, -2.0, 2.5, -7.0, 0.25, 1.75])
    hand = np.array([2 / 3, 23 / 48, 23 / 48, 1 / 6, 1 / 6, 1 / 48, 0, 0, 0, 0, (3 / 64 - 6 / 16 + 4) / 6,
                     0.25**3 / 6])
    np.testing.assert_allclose(bspline3(t), hand, rtol=1e-14, atol=1e-16)
    np.testing.assert_allclose(bspline3(t), b3_reference(t), rtol=1e-14, atol=1e-16)
    np.testing.assert_allclose(bspline3(torch.tensor(t)).numpy(), hand, rtol=1e-14, atol=1e-16)
    assert bspline3(0.0) == pytest.approx(2 / 3)
    dense = np.linspace(-3, 3, 6001)
    vals = bspline3(dense)
    assert np.all(vals[np.abs(dense) >= 2] == 0) and np.all(vals[np.abs(dense) < 2] > 0)


def test_bspline3_integrates_to_one():
    value, err = integrate.quad(lambda t: float(bspline3(t)), -3, 3, points=[-2, -1, 0, 1, 2])
    assert value == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("knot", [1.0, 2.0, -1.0, -2.0])
def test_bspline3_c2_at_knots(knot):
    e = 1e-4
    f = lambda t: float(bspline3(np.float64(t)))  # noqa: E731
    left = [f(knot - k * e) for k in range(4)]  # f(t), f(t-e), f(t-2e), f(t-3e)
    right = [f(knot + k * e) for k in range(4)]
    # values: continuous
    assert abs(left[1] - right[1]) < 5 * e
    # first derivative: one-sided slopes away from the knot agree to O(e)
    d_left = (left[1] - left[2]) / e
    d_right = (right[2] - right[1]) / e
    assert abs(d_left - d_right) < 20 * e
    # second derivative: one-sided second differences agree to O(e); the third derivative jumps, so not O(e^2)
    dd_left = (left[1] - 2 * left[2] + left[3]) / e**2
    dd_right = (right[1] - 2 * right[2] + right[3]) / e**2
    assert abs(dd_left - dd_right) < 50 * e
    expected_dd = 1.0 if abs(knot) == 1 else 0.0  # B3''(1) = 1, B3''(2) = 0
    assert dd_left == pytest.approx(expected_dd, abs=1e-2)


def test_kernel_is_the_dense_triple_product():
    rng = np.random.default_rng(0)
    h, amp = 0.3, 1.7
    diff = rng.uniform(-0.8, 0.8, (200, 3))
    ref = amp * b3_reference(diff[:, 0] / h) * b3_reference(diff[:, 1] / h) * b3_reference(diff[:, 2] / h)
    np.testing.assert_allclose(kernel(diff, h, amp), ref, rtol=1e-13, atol=1e-300)
    np.testing.assert_allclose(kernel(torch.tensor(diff), h, amp).numpy(), ref, rtol=1e-13, atol=1e-300)
    assert kernel(np.zeros(3), h, amp) == pytest.approx(amp * (2 / 3) ** 3)
    assert support_radius(h) == 2 * h
    assert kernel(np.array([2 * h, 0.0, 0.0]), h) == 0.0


# ------------------------------------------------------------------------------------------------- GP posterior

@pytest.fixture(scope="module")
def tiny_cloud():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(30, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    points = 0.3 * n + rng.normal(scale=0.005, size=(30, 3))
    return points, n


def dense_posterior(points, normals, x, h, noise, amp):
    k = lambda a, b: kernel(a[:, None, :] - b[None, :, :], h, amp)  # noqa: E731
    kpp = k(points, points)
    lumped = kpp.sum(1) + noise**2
    k2 = k(x, points)
    k1 = k(x, x)
    mean = k2 @ (normals / lumped[:, None])
    cov = k1 - k2 @ np.diag(1 / lumped) @ k2.T
    exact = k1 - k2 @ np.linalg.solve(kpp + noise**2 * np.eye(len(points)), k2.T)
    return mean, cov, exact, lumped


@pytest.mark.parametrize("noise,amp", [(0.1, 1.0), (0.0, 2.5)])
def test_gp_posterior_against_dense_linear_algebra(tiny_cloud, noise, amp):
    points, normals = tiny_cloud
    h = 0.12
    post = GPPosterior(points, normals, h, normal_noise=noise, amplitude=amp)
    rng = np.random.default_rng(2)
    x = np.concatenate([rng.uniform(-0.45, 0.45, (40, 3)), points[:10] + rng.uniform(-h, h, (10, 3))])
    mean, cov, exact, lumped = dense_posterior(points, normals, x, h, noise, amp)
    assert (cov != 0).sum() > len(x)  # the queries do interact: a non-trivial test

    np.testing.assert_allclose(post.lumped, lumped, rtol=1e-13)
    np.testing.assert_allclose(post.mean(x), mean, rtol=1e-12, atol=1e-14)
    mu, count = post.mean_and_support(x)
    np.testing.assert_allclose(mu, mean, rtol=1e-12, atol=1e-14)
    cheb = np.abs(x[:, None, :] - points[None, :, :]).max(-1)
    np.testing.assert_array_equal(count, (cheb <= 2 * h).sum(1))

    dense = post.covariance_matrix(x).toarray()
    np.testing.assert_allclose(dense, cov, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(dense, dense.T, rtol=0, atol=1e-15)
    i, j = np.meshgrid(np.arange(len(x)), np.arange(len(x)), indexing="ij")
    rowwise = post.covariance(x[i.ravel()], x[j.ravel()]).reshape(len(x), len(x))
    np.testing.assert_allclose(rowwise, cov, rtol=1e-12, atol=1e-14)
    assert post.prior_variance() == pytest.approx(amp * (2 / 3) ** 3)

    if noise > 0:  # K3 = K + sigma_n^2 I is safely invertible
        # lumping only adds uncertainty: diagonal, and in fact the whole difference is PSD
        assert np.all(np.diag(cov) >= np.diag(exact) - 1e-12)
        assert np.linalg.eigvalsh(cov - exact).min() >= -1e-10


def test_gp_covariance_compact_support(tiny_cloud):
    points, normals = tiny_cloud
    h = 0.12
    post = GPPosterior(points, normals, h, normal_noise=0.05)
    rng = np.random.default_rng(3)
    x = rng.uniform(-0.5, 0.5, (120, 3))
    cheb = np.abs(x[:, None, :] - x[None, :, :]).max(-1)
    far = cheb >= 4 * h
    assert far.sum() > 1000 and (~far).sum() > 200
    dense = post.covariance_matrix(x).toarray()
    assert np.all(dense[far] == 0.0)
    i, j = np.nonzero(far)
    assert np.all(post.covariance(x[i], x[j]) == 0.0)
    # exactly at 4h through a cloud point: still exactly zero; just inside: non-zero (the posterior term reaches)
    p = points[0]
    step = np.array([2 * h, 0.0, 0.0])
    assert post.covariance((p - step)[None], (p + step)[None])[0] == 0.0
    inside = post.covariance((p - 0.9 * step)[None], (p + 0.9 * step)[None])[0]
    assert inside != 0.0 and inside < 0  # only the explained term: prior is zero beyond 2h


# ----------------------------------------------------------------------------------------------------- sampling

def mc_check(estimates, truth, n_sigma=4.0, max_rel_sem=0.05):
    """Mean of independent estimates within n_sigma standard errors of truth (and the test has power)."""
    estimates = np.asarray(estimates)
    mean = estimates.mean()
    sem = estimates.std(ddof=1) / np.sqrt(len(estimates))
    assert sem <= max_rel_sem * abs(truth), f"test has no power: sem {sem:.3g} vs truth {truth:.3g}"
    assert abs(mean - truth) <= n_sigma * sem, f"estimate {mean:.6g} +- {sem:.2g}, truth {truth:.6g}"


def test_sample_mean_targets_is_unbiased(tiny_cloud):
    points, normals = tiny_cloud
    h = 0.06
    post = GPPosterior(points, normals, h)
    box = Box.around(points, margin=0.5 * post.radius)  # near-proposal cubes poke out of the box: weight 0 there
    lo, hi = box.lo, box.hi
    p0 = points[np.argmin(np.abs(points - 0.5 * (lo + hi)).max(1))]  # its bump must lie inside the box
    assert np.all(p0 - 2 * h > lo) and np.all(p0 + 2 * h < hi)
    funcs = {
        "one": (lambda x: np.ones(len(x)), 1.0),
        "x0^2": (lambda x: x[:, 0] ** 2, (hi[0] ** 3 - lo[0] ** 3) / (3 * (hi[0] - lo[0]))),
        # a kernel bump at a cloud point: integral h^3, concentrated where the near proposal samples
        "bump": (lambda x: kernel(x - p0, h), h**3 / box.volume),
    }
    rng = np.random.default_rng(4)
    est = {name: [] for name in funcs}
    for _ in range(400):
        x, mu, omega = sample_mean_targets(post, box, 8, 56, rng)
        assert x.shape == (64, 3) and mu.shape == (64, 3) and omega.shape == (64,)
        x = x.astype(np.float64)
        for name, (f, _) in funcs.items():
            est[name].append(np.mean(omega * f(x)))
    for name, (_, truth) in funcs.items():
        mc_check(est[name], truth, max_rel_sem=0.1)


def test_sample_mean_targets_uniform_only_weights_are_one(tiny_cloud):
    points, normals = tiny_cloud
    post = GPPosterior(points, normals, 0.06)
    box = Box.around(points, margin=0.1)
    _, _, omega = sample_mean_targets(post, box, 50, 0, np.random.default_rng(0))
    np.testing.assert_allclose(omega, 1.0)


def test_sample_pair_clusters_is_unbiased():
    box = Box(np.array([0.0, -1.0, 0.5]), np.array([1.0, 0.2, 1.6]))  # anisotropic, off-origin
    h = 0.04
    r = 2 * h
    e = box.extent
    c = box.lo + 0.5 * e
    # int_0^E int_0^E B3((x - y)/h) dx dy = E h - h^2 int |t| B3(t) dt = E h - 7/15 h^2   (2h < E)
    abs_moment = integrate.quad(lambda t: abs(t) * float(bspline3(t)), -2, 2, points=[-1, 0, 1])[0]
    assert abs_moment == pytest.approx(7 / 15, abs=1e-12)
    funcs = {
        "one": (lambda x, y: np.ones(len(x)), box.volume**2),
        "k(x-y)": (lambda x, y: kernel(x - y, h), float(np.prod(e * h - 7 / 15 * h**2))),
        "k(x-c)k(y-c)": (lambda x, y: kernel(x - c, 0.24) * kernel(y - c, 0.24), 0.24**6),
    }
    rng = np.random.default_rng(5)
    est = {name: [] for name in funcs}
    naive = []  # uniform-pair weights |B|^2 / (m (m - 1)), ignoring the clustering: must be visibly biased
    for _ in range(300):
        x, w = sample_pair_clusters(box, 16, 3, r, rng)
        assert x.shape == (48, 3) and w.shape == (48, 48) and np.all(np.diag(w) == 0)
        assert np.all(x >= box.lo) and np.all(x <= box.hi)
        x, w = x.astype(np.float64), w.astype(np.float64)
        i, j = np.nonzero(~np.eye(len(x), dtype=bool))
        for name, (f, _) in funcs.items():
            est[name].append(np.sum(w[i, j] * f(x[i], x[j])))
        naive.append(box.volume**2 / len(i) * np.sum(funcs["k(x-y)"][0](x[i], x[j])))
    for name, (_, truth) in funcs.items():
        # the separable bump is only hit by pairs of different clusters: fewer effective samples, looser power bound
        mc_check(est[name], truth, max_rel_sem=0.15 if name == "k(x-c)k(y-c)" else 0.05)
    sem = np.std(est["k(x-y)"], ddof=1) / np.sqrt(len(naive))
    assert abs(np.mean(naive) - funcs["k(x-y)"][1]) > 10 * sem  # the test detects a wrong weighting
