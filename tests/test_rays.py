"""Orthant probabilities along rays: against scipy's MVN CDF, Monte Carlo first hits, the paper's didactic
segment, and gradients against finite differences."""
import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from autodecoder.field.protocol import Field
from autodecoder.scanning.rays import cast_rays, first_hit, monte_carlo_survival, orthant_probability, orthant_survival


def random_cases(K, n, kind, seed):
    """n (mean, cov) pairs: 'random' A A^T + 0.1 I, or 'ray' a squared-exponential kernel along a segment."""
    rng = np.random.default_rng(seed)
    means, covs = [], []
    for _ in range(n):
        if kind == "random":
            A = rng.normal(size=(K, K))
            C = A @ A.T + 0.1 * np.eye(K)
        else:
            t = np.linspace(0, 1, K)
            C = np.exp(-(t[:, None] - t[None]) ** 2 / (2 * rng.uniform(0.1, 2.0) ** 2)) + 1e-6 * np.eye(K)
        d = np.sqrt(np.diag(C))
        C = C / np.outer(d, d) * rng.uniform(0.5, 2) ** 2
        means.append(rng.normal(0.5, 1.0, size=K) * np.sqrt(np.diag(C)))
        covs.append(C)
    return np.array(means), np.array(covs)


def scipy_orthant(mean, cov):
    # P(f > 0) for f ~ N(m, C) equals P(X < m) for X ~ N(0, C)
    return np.array([multivariate_normal(np.zeros(len(m)), C, abseps=1e-4, releps=1e-4).cdf(m)
                     for m, C in zip(mean, cov)])


# Tolerances: ~2x the largest error measured over 100 cases per K (see the table in autodecoder/scanning/rays.py);
# scipy's own error (abseps 1e-4, for speed) is far below them.
@pytest.mark.parametrize("kind,tol", [("random", 5e-3), ("ray", 2.5e-2)])
def test_genz_matches_scipy_mvn_cdf(kind, tol):
    for K in (2, 3, 5, 8):
        mean, cov = random_cases(K, 5, kind, seed=K)
        ref = scipy_orthant(mean, cov)
        got = orthant_probability(torch.tensor(mean), torch.tensor(cov), method="genz").numpy()
        err = np.abs(got - ref)
        assert err.max() < tol, f"K={K} {kind}: max error {err.max():.2e} at case {err.argmax()}"


def test_bivariate_conditioning_is_exact_for_two_samples_and_close_beyond():
    mean, cov = random_cases(2, 10, "random", seed=0)
    got = orthant_probability(torch.tensor(mean), torch.tensor(cov), method="bivariate").numpy()
    assert np.abs(got - scipy_orthant(mean, cov)).max() < 1e-6
    mean, cov = random_cases(6, 10, "random", seed=1)
    got = orthant_probability(torch.tensor(mean), torch.tensor(cov), method="bivariate").numpy()
    assert np.abs(got - scipy_orthant(mean, cov)).max() < 5e-2


def test_survival_matches_monte_carlo_first_hits_along_a_ray():
    K = 16
    t = np.linspace(0.0, 2.0, K)
    # a surface near t = 1 (mean crosses zero there), correlated noise with lengthscale 0.3
    mean = (1.0 - t)[None]
    cov = (0.3**2 * np.exp(-(t[:, None] - t[None]) ** 2 / (2 * 0.3**2)) + 1e-8 * np.eye(K))[None]
    ref = monte_carlo_survival(mean, cov, n_samples=200_000, seed=1)
    s = orthant_survival(torch.tensor(mean), torch.tensor(cov), method="genz", n_samples=2048)
    assert np.abs(s.numpy() - ref).max() < 1e-2
    hit = first_hit(s, torch.tensor(t))
    # Monte Carlo first-hit distances (capped at t_K + step)
    rng = np.random.default_rng(2)
    f = mean[0] + rng.standard_normal((200_000, K)) @ np.linalg.cholesky(cov[0]).T
    neg = f <= 0
    first = np.where(neg.any(1), neg.argmax(1), K)
    t_ext = np.append(t, t[-1] + (t[-1] - t[-2]))
    assert abs(hit["expected_t_capped"].item() - t_ext[first].mean()) < 1e-2
    hits = first < K
    assert abs(hit["expected_t"].item() - t[first[hits]].mean()) < 1e-2
    assert abs(hit["p_no_hit"].item() - (~hits).mean()) < 5e-3
    assert torch.allclose(hit["p_bins"].sum(1) + hit["p_no_hit"], torch.ones(1, dtype=torch.float64))


def test_perfectly_correlated_segment_the_paper_didactic_case():
    """Mean slightly positive along a segment, correlation ~1: f is one number repeated; the ray hits with
    probability P(f < 0) ~ 0.46 however many samples. The marginal product predicts an almost sure hit."""
    K, mu, sd = 32, 0.1, 1.0
    mean = torch.full((1, K), mu, dtype=torch.float64)
    cov = torch.full((1, K, K), sd**2 * 0.9999, dtype=torch.float64) + 1e-4 * torch.eye(K, dtype=torch.float64)
    exact = 0.5 * (1 + torch.erf(torch.tensor(mu / np.sqrt(2)))).item()  # P(f > 0)
    for method in ("genz", "bivariate"):
        s = orthant_survival(mean, cov, method=method)
        assert abs(s[0, -1].item() - exact) < 0.02, method
    indep = orthant_survival(mean, cov, method="independent")
    assert indep[0, -1].item() < 1e-8  # "hits along the segment"
    assert abs(indep[0, 0].item() - exact) < 1e-3


def test_singular_and_slightly_indefinite_covariances_are_repaired():
    """Exactly rank one (f one number repeated, float32) and a float32 round-off below zero: the factorization is
    repaired with a small jitter and S_K stays P(f > 0); non-finite input is refused."""
    K, mu = 24, 0.1
    exact = 0.5 * (1 + torch.erf(torch.tensor(mu / np.sqrt(2)))).item()
    mean = torch.full((2, K), mu, dtype=torch.float32)
    ones = torch.ones(K, K, dtype=torch.float32)
    cov = torch.stack([ones, ones - 1e-6 * torch.eye(K)])  # the second has a negative eigenvalue
    s = orthant_survival(mean, cov)
    assert torch.all(torch.isfinite(s))
    assert np.allclose(s[:, -1].numpy(), exact, atol=0.02), s[:, -1]
    with pytest.raises(ValueError, match="not finite"):
        orthant_survival(mean, cov * float("nan"))


class Sphere(Field):
    """Toy field: f = |x| - 1, std 0.1 (1 + x_0) / 2 + 0.02, squared-exponential correlation (lengthscale 0.3)."""

    def __init__(self, dtype=torch.float64):
        self.dtype = dtype
        self.bounds = np.array([[-1.2] * 3, [1.2] * 3])

    def torch_mean(self, x):
        return x.norm(dim=1) - 1.0

    def _sd(self, x):
        return 0.1 * torch.sigmoid(4 * x[:, 0]) + 0.02

    def torch_variance(self, x):
        return self._sd(x) ** 2

    def torch_covariance(self, a, b):
        return self._sd(a) * self._sd(b) * torch.exp(-((a - b) ** 2).sum(1) / (2 * 0.3**2))


def test_cast_rays_hits_the_sphere_where_the_mean_does():
    origins = torch.tensor([[0.0, 0.0, 3.0], [0.0, 3.0, 0.0], [0.0, 3.0, 3.0]], dtype=torch.float64)
    dirs = torch.tensor([[0.0, 0.0, -1.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    cast = cast_rays(Sphere(), origins, dirs, 1.0, 5.0, n_samples=41)
    assert torch.allclose(cast.p_hit[:2], torch.ones(2, dtype=torch.float64), atol=1e-3)
    assert cast.p_hit[2] < 1e-3  # passes beside the sphere
    # the hit is the first sample inside: within one step (0.1) after t = 2
    assert ((cast.expected_t[:2] - 2.0) > -0.02).all() and ((cast.expected_t[:2] - 2.0) < 0.12).all()
    assert torch.allclose(cast.expected_point[0], origins[0] + cast.expected_t[0] * dirs[0])


@pytest.mark.parametrize("method", ["genz", "bivariate", "me"])
def test_survival_gradients_match_finite_differences(method):
    mean, cov = random_cases(4, 2, "random", seed=3)
    m = torch.tensor(mean, requires_grad=True)
    A = torch.tensor(np.linalg.cholesky(cov), requires_grad=True)

    def fn(m_, A_):
        return orthant_survival(m_, A_ @ A_.transpose(1, 2), method=method, jitter=0.0 if method != "genz" else 1e-7,
                                n_samples=64)

    assert torch.autograd.gradcheck(fn, (m, A), eps=1e-6, atol=1e-5, rtol=1e-3)


def test_ray_gradients_match_finite_differences():
    origins = torch.tensor([[0.2, 0.1, 3.0]], dtype=torch.float64, requires_grad=True)
    dirs = torch.tensor([[0.0, 0.05, -1.0]], dtype=torch.float64, requires_grad=True)

    def fn(o, d):
        c = cast_rays(Sphere(), o, d, 1.0, 4.0, n_samples=8, qmc_samples=64)
        return c.expected_t_capped, c.expected_point

    assert torch.autograd.gradcheck(fn, (origins, dirs), eps=1e-6, atol=1e-5, rtol=1e-3)


def test_indefinite_covariance_is_clipped_not_fatal():
    cov = torch.tensor([[[1.0, 0.9, 0.0], [0.9, 1.0, 0.9], [0.0, 0.9, 1.0]]], dtype=torch.float64)  # eigenvalue < 0
    s = orthant_survival(torch.full((1, 3), 0.5, dtype=torch.float64), cov)
    assert torch.isfinite(s).all() and (s[0, 1:] <= s[0, :-1] + 1e-12).all()
