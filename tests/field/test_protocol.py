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


def test_mean_and_gradient_is_mean_and_mean_gradient():
    """The protocol's joint query is the two separate ones (closed form of the ball), and a stochastic field's one
    pass of its mean net gives the numbers of its separate queries."""
    from autodecoder.field.networks import build_networks
    from autodecoder.field.stochastic_field import StochasticField
    from datasets import Frame

    x = np.random.default_rng(1).uniform(-0.5, 0.5, (300, 3))
    ball = Ball()
    value, grad = ball.mean_and_gradient(x)
    np.testing.assert_array_equal(value, ball.mean(x))
    np.testing.assert_array_equal(grad, ball.mean_gradient(x))
    config = {"width": 16, "depth": 2, "latent_dim": 0, "covariance": "feature", "features": 8, "omega0": 5.0,
              "lengthscale": 0.05, "box_lo": [-0.6] * 3, "box_hi": [0.6] * 3}
    torch.manual_seed(0)
    field = StochasticField(*build_networks(config), Frame(np.array([0.1, 0.0, -0.2]), 2.0), config, noise=0.01)
    value, grad = field.mean_and_gradient(x)
    assert value.shape == (300,) and grad.shape == (300, 3)
    np.testing.assert_allclose(value, field.mean(x), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(grad, field.mean_gradient(x), rtol=1e-5, atol=1e-7)
