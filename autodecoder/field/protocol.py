"""What the rest of the toolkit asks of "a field": the :class:`Field` protocol.

Ray casting, free-space evidence, view planning and the inspection scores work with any stochastic implicit surface
f ~ N(g, c), not only with a fitted :class:`autodecoder.field.stochastic_field.StochasticField`: analytic fields with
closed-form answers test them, and a user may bring a field of their own. This protocol is that contract, in one
place, instead of each caller probing for attributes.

A class satisfies it by defining :meth:`Field.torch_mean` and :meth:`Field.torch_covariance`; subclassing
:class:`Field` explicitly then provides everything else (the numpy queries from the torch ones, gradients by
autograd, and the optional attributes' "unknown" values), which a concrete field overrides where it knows better.
"""
import math
from typing import Optional, Protocol, runtime_checkable

import numpy as np
import torch

_MIN_VARIANCE = 1e-20  # keeps P(f <= 0) defined where a field claims zero variance


@runtime_checkable
class Field(Protocol):
    """A stochastic implicit surface f ~ N(g, c) in world coordinates (f < 0 inside, f > 0 outside).

    Attributes
    ----------
    noise : float
        Measurement noise (world units) the field's own likelihoods add to its variance; 0 when unknown.
    bounds : (2, 3) array or None
        Min and max corners of the box where the field is defined (rays are tested inside it); None: unbounded.
    lengthscale : float or None
        The kernel lengthscale the field was fitted with, world units (the scale of detail it can carry; free-space
        tests and view planning derive their clearances from it); None when the field does not say.
    training_points : (n, 3) array or tensor or None
        The cloud the field was fitted to (world frame), when it kept it.
    """

    noise: float = 0.0
    bounds: Optional[np.ndarray] = None
    lengthscale: Optional[float] = None
    training_points = None

    # ---------------------------------------------------------------------------------- required (torch)
    def torch_mean(self, x: torch.Tensor) -> torch.Tensor:
        """E f at points x (B, 3) -> (B,), differentiable."""
        ...

    def torch_covariance(self, x1: torch.Tensor, x2: torch.Tensor) -> torch.Tensor:
        """Cov(f(x1_i), f(x2_i)) for pairs row by row: (B, 3), (B, 3) -> (B,), differentiable."""
        ...

    # ---------------------------------------------------------------------------------- derived (torch)
    def torch_variance(self, x: torch.Tensor) -> torch.Tensor:
        """Var f at points x (B, 3) -> (B,): the covariance of each point with itself."""
        return self.torch_covariance(x, x)

    def torch_mean_and_gradient(self, x: torch.Tensor):
        """(E f (B,), grad E f (B, 3)) at points x (B, 3), by autograd."""
        with torch.enable_grad():
            x = x.detach().requires_grad_(True)
            value = self.torch_mean(x)
            (grad,) = torch.autograd.grad(value.sum(), x)
        return value.detach(), grad

    # ---------------------------------------------------------------------------------- derived (numpy)
    def mean(self, x) -> np.ndarray:
        """E f at world points x (m, 3) -> (m,) float64."""
        with torch.no_grad():
            return self.torch_mean(torch.as_tensor(np.asarray(x, dtype=np.float64))).double().numpy()

    def mean_gradient(self, x) -> np.ndarray:
        """grad E f at world points x (m, 3) -> (m, 3) float64."""
        return self.torch_mean_and_gradient(torch.as_tensor(np.asarray(x, dtype=np.float64)))[1].double().numpy()

    def mean_and_gradient(self, x):
        """(E f (m,), grad E f (m, 3)) at world points x (m, 3), float64: :meth:`mean` and :meth:`mean_gradient`
        (a field whose nets carry the value and its gradient forward together overrides this with one pass)."""
        return self.mean(x), self.mean_gradient(x)

    def variance(self, x) -> np.ndarray:
        """Var f at world points x (m, 3) -> (m,) float64."""
        with torch.no_grad():
            return self.torch_variance(torch.as_tensor(np.asarray(x, dtype=np.float64))).double().numpy()

    def prob_inside(self, x) -> np.ndarray:
        """P(f(x) <= 0) at world points x (m, 3) -> (m,) float64 in [0, 1]."""
        mean, var = self.mean(x), np.maximum(self.variance(x), _MIN_VARIANCE)
        return 0.5 * np.vectorize(math.erfc)(mean / np.sqrt(2 * var))


_MEMBERS = ("noise", "bounds", "lengthscale", "training_points", "torch_mean", "torch_covariance", "torch_variance",
            "torch_mean_and_gradient", "mean", "mean_gradient", "mean_and_gradient", "variance", "prob_inside")


def check_field(field, what="field"):
    """``field`` itself if it provides every member of :class:`Field`, else one ValueError naming what it lacks.

    An object that does not subclass :class:`Field` must provide them all itself; subclassing supplies all but
    ``torch_mean`` and ``torch_covariance``.
    """
    missing = [name for name in _MEMBERS if not hasattr(field, name)]
    if missing:
        raise ValueError(f"{what}: {type(field).__name__} is not a field (autodecoder.field.protocol.Field): it lacks "
                         f"{', '.join(missing)}; subclass Field and define torch_mean and torch_covariance")
    return field
