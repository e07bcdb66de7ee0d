"""Toy stochastic fields with known answers, shared by the ray and view tests (a helper module: no tests here)."""
import numpy as np
import torch

from autodecoder.field.protocol import Field


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
