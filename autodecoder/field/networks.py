"""The mean network g(x, z) and the two covariance networks c(x1, x2, z) of NSSPR.

* :class:`MeanNet`: g(x, z), a SIREN with a scalar output; trained so that grad g matches the posterior mean field.
* :class:`FeatureCovarianceNet` (default): c(a, b, z) = phi(a, z) . phi(b, z) / K with phi a SIREN with K outputs.
  Symmetric and positive semi-definite by construction, and its D operator D c(a, b) = J_phi(a)^T J_phi(b) / K
  needs only each point's first derivatives; one Jacobian serves every pair in the batch.
* :class:`PairCovarianceNet` (the paper's): c(a, b, z) = (s(a, b) + s(b, a)) / 2 with s = SoftPlus(h([a, b], z))
  and h a SIREN on the 6 concatenated coordinates; its D operator comes from the forward-carried mixed jet.

All coordinates are in the model's normalised (unit-cube) frame.
"""
import torch
from torch import nn
from torch.nn import functional as F

from autodecoder.field.grid_networks import build_grid_networks
from autodecoder.field.siren import Siren


class MeanNet(nn.Module):
    """g(x, z): the mean of the stochastic implicit function.

    Parameters
    ----------
    width, depth : int
        SIREN hidden width and number of hidden layers.
    latent_dim : int
        Latent code dimension (0: a single cloud).
    omega0 : float
        First-layer frequency.
    """

    def __init__(self, width=128, depth=3, latent_dim=0, omega0=30.0):
        super().__init__()
        self.net = Siren(3, 1, width, depth, latent_dim=latent_dim, omega0=omega0)

    def forward(self, x, z=None):
        """g at x (B, 3) -> (B,)."""
        return self.net(x, z)[:, 0]

    def value_and_gradient(self, x, z=None):
        """g and grad_x g at x (B, 3) -> (B,), (B, 3)."""
        value, jac = self.net.forward_jet1(x, z)
        return value[:, 0], jac[:, :, 0]


class FeatureCovarianceNet(nn.Module):
    """c(a, b, z) = phi(a, z) . phi(b, z) / K, a positive semi-definite covariance of rank <= K.

    Parameters
    ----------
    width, depth : int
        SIREN hidden width and number of hidden layers.
    features : int
        K, the number of features (the rank of the covariance).
    latent_dim : int
        Latent code dimension (0: a single cloud).
    omega0 : float
        First-layer frequency.
    """

    kind = "feature"

    def __init__(self, width=128, depth=3, features=128, latent_dim=0, omega0=30.0):
        super().__init__()
        self.features = features
        self.net = Siren(3, features, width, depth, latent_dim=latent_dim, omega0=omega0)

    def features_and_jacobian(self, x, z=None):
        """phi / sqrt(K) and its Jacobian at x (B, 3) -> (B, K), (B, 3, K)."""
        value, jac = self.net.forward_jet1(x, z)
        scale = self.features**-0.5
        return value * scale, jac * scale

    def covariance(self, a, b, z=None):
        """c(a_i, b_i) for pairs taken row by row: (B, 3), (B, 3) -> (B,)."""
        scale = 1.0 / self.features
        return (self.net(a, z) * self.net(b, z)).sum(-1) * scale

    def variance(self, x, z=None):
        """c(x, x) = |phi(x)|^2 / K: (B, 3) -> (B,)."""
        return self.net(x, z).square().sum(-1) / self.features

    def d_operator(self, a, b, z=None):
        """D c(a_i, b_i) = d2 c / da_k db_l for pairs row by row: (B, 3), (B, 3) -> (B, 3, 3)."""
        _, ja = self.features_and_jacobian(a, z)
        _, jb = self.features_and_jacobian(b, z)
        return ja @ jb.transpose(1, 2)


class PairCovarianceNet(nn.Module):
    """The paper's covariance network: c(a, b, z) = (SoftPlus(h(a, b, z)) + SoftPlus(h(b, a, z))) / 2.

    Parameters
    ----------
    width, depth : int
        SIREN hidden width and number of hidden layers.
    latent_dim : int
        Latent code dimension (0: a single cloud).
    omega0 : float
        First-layer frequency.
    """

    kind = "pair"

    def __init__(self, width=128, depth=3, latent_dim=0, omega0=30.0):
        super().__init__()
        self.net = Siren(6, 1, width, depth, latent_dim=latent_dim, omega0=omega0)

    @staticmethod
    def _both_orders(a, b, z):
        ab = torch.cat([torch.cat([a, b], 1), torch.cat([b, a], 1)], 0)  # (2B, 6)
        zz = None
        if z is not None:
            zz = torch.cat([z, z], 0) if z.dim() == 2 else z
        return ab, zz

    def covariance(self, a, b, z=None):
        """c(a_i, b_i) for pairs row by row: (B, 3), (B, 3) -> (B,)."""
        ab, zz = self._both_orders(a, b, z)
        s = F.softplus(self.net(ab, zz)[:, 0])
        return 0.5 * (s[: len(a)] + s[len(a):])

    def variance(self, x, z=None):
        """c(x, x) = SoftPlus(h(x, x)): (B, 3) -> (B,)."""
        return F.softplus(self.net(torch.cat([x, x], 1), z)[:, 0])

    def d_operator(self, a, b, z=None):
        """D c(a_i, b_i) = d2 c / da_k db_l, from the forward-carried mixed jet: (B, 3), (B, 3) -> (B, 3, 3).

        For s(u, v) = SoftPlus(h(u, v)): d2 s / du dv^T = sigmoid'(h) grad_u h grad_v h^T + sigmoid(h) H_uv h.
        The symmetrised term s(b, a) contributes the transpose of that block evaluated at (b, a).
        """
        bsz = len(a)
        ab, zz = self._both_orders(a, b, z)
        h, ga, gb, hab = self.net.forward_mixed_jet(ab, zz)
        h, ga, gb, hab = h[:, 0], ga[..., 0], gb[..., 0], hab[..., 0]
        sig = torch.sigmoid(h)
        block = (sig * (1 - sig))[:, None, None] * ga.unsqueeze(2) * gb.unsqueeze(1) + sig[:, None, None] * hab
        return 0.5 * (block[:bsz] + block[bsz:].transpose(1, 2))


def build_networks(config):
    """Mean and covariance nets from a configuration dict.

    Keys: ``width``, ``depth``, ``latent_dim``, ``covariance`` ('feature' or 'pair'), ``features`` (feature net),
    ``omega0``; optional ``cov_width``/``cov_depth`` (default: the mean net's). With ``representation: 'grid'``
    the B-spline grid nets of :func:`autodecoder.field.grid_networks.build_grid_networks` instead.

    Returns
    -------
    (MeanNet, FeatureCovarianceNet or PairCovarianceNet)
    """
    if config.get("representation", "siren") == "grid":
        return build_grid_networks(config)
    width, depth, latent = int(config["width"]), int(config["depth"]), int(config.get("latent_dim", 0))
    omega0 = float(config.get("omega0", 30.0))
    cov_width, cov_depth = int(config.get("cov_width", width)), int(config.get("cov_depth", depth))
    mean_net = MeanNet(width, depth, latent_dim=latent, omega0=omega0)
    kind = config.get("covariance", "feature")
    if kind == "feature":
        cov_net = FeatureCovarianceNet(cov_width, cov_depth, features=int(config.get("features", 128)),
                                       latent_dim=latent, omega0=omega0)
    elif kind == "pair":
        cov_net = PairCovarianceNet(cov_width, cov_depth, latent_dim=latent, omega0=omega0)
    else:
        raise ValueError(f"covariance must be 'feature' or 'pair', got {kind!r}")
    return mean_net, cov_net
