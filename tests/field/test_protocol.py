"""autodecoder.field.protocol: the Field contract, its derived queries against closed forms, and its check."""
import numpy as np
import pytest
import torch
from scipy.stats import norm

from autodecoder.field.protocol import Field, check_field


class Ball(Field):
    """f = |x - c| - r, sd = s (1 + x_0^2): closed forms for every derived query."""

    def __init__(self, c=(0.1, -0.2, 0.3), r=0.5, s=0.01):
        self.c, self.r, self.s = torch.tensor(c, dtype=torch.float64), r, s

    def torch_mean(self, x):
        return (x - self.c.to(x.dtype)).norm(dim=1) - self.r

    def _sd(self, x):
        return self.s * (1 + x[:, 0] ** 2)

    def torch_covariance(self, a, b):
        return self._sd(a) * self._sd(b) * torch.exp(-((a - b) ** 2).sum(1))


def test_subclass_gets_numpy_queries_gradients_and_defaults_from_the_two_torch_methods():
    ball = Ball()
    x = np.random.default_rng(0).uniform(-1, 1, (40, 3))
    d = x - ball.c.numpy()
    dist = np.linalg.norm(d, axis=1)
    sd = ball.s * (1 + x[:, 0] ** 2)
    np.testing.assert_allclose(ball.mean(x), dist - ball.r, rtol=1e-12)
    np.testing.assert_allclose(ball.mean_gradient(x), d / dist[:, None], rtol=1e-10)
    np.testing.assert_allclose(ball.variance(x), sd**2, rtol=1e-12)
    np.testing.assert_allclose(ball.prob_inside(x), norm.cdf(-(dist - ball.r) / sd), rtol=1e-9, atol=1e-15)
    assert ball.noise == 0.0 and ball.bounds is None and ball.lengthscale is None and ball.training_points is None
    assert isinstance(ball, Field) and check_field(ball) is ball


def test_fitted_field_is_a_field_and_says_its_lengthscale_in_world_units():
    from autodecoder import fit_cloud

    rng = np.random.default_rng(0)
    p = rng.normal(size=(300, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    field = fit_cloud(5.0 * p, p, representation="siren",
                      steps=5, quiet=True, width=16, depth=2, features=8, mean_batch=256,
                      screen_batch=128, pair_clusters=8)
    assert isinstance(field, Field) and check_field(field) is field
    assert field.lengthscale == pytest.approx(field.config["lengthscale"] / field.frame.scale)
    assert field.bounds.shape == (2, 3)


def test_check_field_names_what_an_object_lacks():
    class MeanOnly:
        noise = 0.0

        def mean(self, x):
            return np.zeros(len(x))

    with pytest.raises(ValueError, match=r"MeanOnly is not a field .*lacks bounds, lengthscale.*torch_mean"):
        check_field(MeanOnly())
