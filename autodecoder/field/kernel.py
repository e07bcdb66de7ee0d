"""The compactly supported product cubic B-spline kernel ("approximated Gaussian" of Stochastic PSR)."""
import numpy as np
import torch


def bspline3(t):
    """Cubic B-spline B3(t), the 4-fold convolution of a unit box, evaluated elementwise.

    B3(t) = (3|t|^3 - 6t^2 + 4)/6 for |t| < 1, (2-|t|)^3/6 for 1 <= |t| <= 2, 0 beyond. It integrates to 1,
    peaks at B3(0) = 2/3 and has support [-2, 2].

    Parameters
    ----------
    t : array_like or torch.Tensor
        Arguments, any shape.

    Returns
    -------
    array or tensor of the same shape and type as ``t``.
    """
    if isinstance(t, torch.Tensor):
        a = t.abs()
        inner = (3 * a**3 - 6 * a**2 + 4) / 6
        outer = torch.clamp(2 - a, min=0) ** 3 / 6
        return torch.where(a < 1, inner, outer)
    a = np.abs(np.asarray(t, dtype=float))
    inner = (3 * a**3 - 6 * a**2 + 4) / 6
    outer = np.clip(2 - a, 0, None) ** 3 / 6
    return np.where(a < 1, inner, outer)


def kernel(diff, lengthscale, amplitude=1.0):
    """Product B-spline kernel k(x, y) = amplitude * prod_d B3((x_d - y_d) / lengthscale).

    Parameters
    ----------
    diff : (..., 3) array or tensor
        Differences x - y.
    lengthscale : float
        Kernel lengthscale h; the kernel vanishes when any |x_d - y_d| >= 2 h.
    amplitude : float, optional
        Prior scale, so that k(x, x) = amplitude * (2/3)^3.

    Returns
    -------
    (...,) array or tensor
    """
    b = bspline3(diff / lengthscale)
    return amplitude * b.prod(-1) if isinstance(b, torch.Tensor) else amplitude * np.prod(b, axis=-1)


def support_radius(lengthscale):
    """Chebyshev (max-norm) radius beyond which the kernel is exactly zero: 2 * lengthscale."""
    return 2.0 * lengthscale
