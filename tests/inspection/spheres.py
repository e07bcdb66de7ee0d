"""The analytic sphere doubles the inspection tests share (one copy): a stochastic field whose mean is a sphere's signed
distance, a 'latent' model whose projection fits a sphere, and one-view scans of a half sphere."""
import math

import numpy as np

from autodecoder.field.protocol import Field


class SphereField(Field):
    """Analytic stochastic field: mean = |x - c| - r (a signed distance), constant variance."""

    def __init__(self, center=(0, 0, 0), radius=1.0, variance=1e-4, noise=0.01):
        self.center, self.radius = np.asarray(center, float), float(radius)
        self.var, self.noise = variance, noise

    def mean(self, x):
        return np.linalg.norm(np.asarray(x) - self.center, axis=1) - self.radius

    def variance(self, x):
        return np.full(len(x), self.var)

    def mean_gradient(self, x):
        d = np.asarray(x) - self.center
        return d / np.linalg.norm(d, axis=1, keepdims=True)


class SaturatingSphereField(SphereField):
    """E f = w tanh((|x - c| - r) / w): a distance near the sphere that saturates at +-w, like a fitted field whose
    GP normal field vanishes a few lengthscales off the points."""

    def __init__(self, width=0.02, **kw):
        super().__init__(**kw)
        self.width = width

    def mean(self, x):
        return self.width * np.tanh(super().mean(x) / self.width)

    def mean_gradient(self, x):
        return (1 - np.tanh(super().mean(x) / self.width) ** 2)[:, None] * super().mean_gradient(x)


class SphereModel:
    """A one-shape 'latent' model: projecting a scan fits a sphere's centre and radius (4 numbers) to it."""

    def project(self, points, normals=None, **options):
        p = np.asarray(points, float)
        A = np.c_[2 * p, np.ones(len(p))]
        sol, *_ = np.linalg.lstsq(A, (p**2).sum(1), rcond=None)
        c = sol[:3]
        r = math.sqrt(sol[3] + c @ c)

        class Projection:
            field = SphereField(c, r)

        return Projection()


class ScaledSphereField(SphereField):
    """The sphere double with a kernel lengthscale (0.1), as the toolkit's fields have: coverage applies to it."""

    lengthscale = 0.1


class ScaledSphereModel(SphereModel):
    """:class:`SphereModel` whose projections are :class:`ScaledSphereField` s."""

    lengthscale = ScaledSphereField.lengthscale

    def project(self, points, normals=None, **options):
        field = super().project(points, normals).field

        class Projection:
            pass

        Projection.field = ScaledSphereField(field.center, field.radius)
        return Projection()


def sphere_scan(n=2000, seed=0, dent=0.0, noise=0.003, center=(0.1, -0.2, 0.05)):
    """Points on the upper half of a unit sphere (one view), optionally with a dent of depth ``dent`` at the pole."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = 1.0 + noise * rng.normal(size=n)
    r -= dent * np.clip(1 - np.arccos(np.clip(d[:, 2], -1, 1)) / 0.35, 0, None)  # cone-shaped dent, 0.35 rad
    return d * r[:, None] + np.asarray(center), d


def sphere_scan_with_dent(n=3000, seed=0, depth=0.0, noise=0.003, arc=0.3):
    """The upper half of a unit sphere (one view) with a paraboloid dent of ``depth`` and radius ``arc`` (radians)
    at its pole; returns points, normals and the points' true signed deviation."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    theta = np.arccos(np.clip(d[:, 2], -1, 1))
    moved = -depth * np.clip(1 - (theta / arc) ** 2, 0, None)
    r = 1.0 + moved + noise * rng.normal(size=n)
    return d * r[:, None], d, moved


class RobustSphereModel(ScaledSphereModel):
    """The sphere double whose projection leaves out the points more than 3 robust deviations off its fit, refitted
    three times, as the toolkit's robust projection leaves out a defect's points: a dent does not pull the sphere
    into itself."""

    def project(self, points, normals=None, **options):
        p = np.asarray(points, float)
        field = super().project(p).field
        for _ in range(3):
            residual = field.mean(p)
            spread = 1.4826 * np.median(np.abs(residual - np.median(residual)))
            field = super().project(p[np.abs(residual - np.median(residual)) <= 3 * spread]).field

        class Projection:
            pass

        Projection.field = ScaledSphereField(field.center, field.radius)
        return Projection()
