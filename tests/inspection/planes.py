"""The tilted-plane doubles the family tests share (one copy): members of a family differ by the slope a of the plane
z = a x (the plane turned about the hinge line x = 0 by atan(a)), whose signed distance is known in closed form, or
of a hinged plate, flat for x < 0 and its arm z = a x beyond the hinge (a bracket bent to several angles: its flat
half is every member's); 'latent' models whose projection fits the slope; noisy scans of a member over [-1, 1]^2."""
import numpy as np
import torch

from autodecoder.field.protocol import Field

LENGTHSCALE = 0.05
NOISE = 0.001


class Tilted(Field):
    """f = (z - a x) / sqrt(1 + a^2): the signed distance to the plane z = a x (outward +z)."""

    def __init__(self, slope):
        self.slope, self.lengthscale = float(slope), LENGTHSCALE

    def torch_mean(self, x):
        return (x[:, 2] - self.slope * x[:, 0]) / np.sqrt(1 + self.slope**2)

    def torch_covariance(self, a, b):
        return torch.full((len(a),), 1e-6, dtype=a.dtype)


HINGE_WIDTH = 0.02  # the hinged plate's bend is rounded over about this width (softplus)


def hinge(x):
    """The hinged plate's height profile over z = slope * hinge(x): softplus of width ``HINGE_WIDTH`` (0 on the flat
    half, x on the arm), and its derivative."""
    t = np.asarray(x, dtype=np.float64) / HINGE_WIDTH
    return HINGE_WIDTH * np.logaddexp(0.0, t), 0.5 * (1 + np.tanh(t / 2))


class Hinged(Field):
    """f = (z - a h(x)) / sqrt(1 + (a h'(x))^2), h the hinge profile (:func:`hinge`): the first-order signed distance
    to the hinged plate z = a h(x) (outward +z), exact on its flat half and on its arm away from the bend."""

    def __init__(self, slope):
        self.slope, self.lengthscale = float(slope), LENGTHSCALE

    def torch_mean(self, x):
        t = x[:, 0] / HINGE_WIDTH
        profile = HINGE_WIDTH * torch.nn.functional.softplus(t)
        return (x[:, 2] - self.slope * profile) / torch.sqrt(1 + (self.slope * torch.sigmoid(t)) ** 2)

    def torch_covariance(self, a, b):
        return torch.full((len(a),), 1e-6, dtype=a.dtype)


class TiltedModel:
    """A family 'latent' model: projecting a scan fits its slope (the median of z / x away from the hinge, so that a
    defect's few points do not move it) and gives that member's :class:`Tilted` field."""

    lengthscale = LENGTHSCALE
    field_type = Tilted

    def project(self, points, normals=None, **options):
        p = np.asarray(points, dtype=np.float64)
        away = p[:, 0] > 0.2 if self.field_type is Hinged else np.abs(p[:, 0]) > 0.2
        field = self.field_type(np.median(p[away, 2] / p[away, 0]))

        class Projection:
            pass

        Projection.field = field
        return Projection()


class HingedModel(TiltedModel):
    """:class:`TiltedModel` of the hinged plates (:class:`Hinged`; its slope fitted on the arm)."""

    field_type = Hinged


def member_scan(slope, seed, n=6000, dent=None, dent_at=(0.7, 0.0), hinged=False):
    """Points (n, 3) of the plane z = slope x (``hinged``: of the hinged plate z = slope h(x)) over [-1, 1]^2 with
    noise, their normals, and (optionally) a dent of depth ``dent`` over the disc of radius 0.15 around ``dent_at``
    (x, y)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1, 1, (n, 2))
    profile, rise = hinge(xy[:, 0]) if hinged else (xy[:, 0], np.ones(n))
    z = slope * profile + rng.normal(0, NOISE, n)
    if dent is not None:
        z -= dent * (np.hypot(xy[:, 0] - dent_at[0], xy[:, 1] - dent_at[1]) < 0.15)
    normals = np.column_stack([-slope * rise, np.zeros(n), np.ones(n)])
    return np.column_stack([xy, z]), normals / np.linalg.norm(normals, axis=1, keepdims=True)
