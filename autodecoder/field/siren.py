"""SIREN MLPs that carry their spatial derivatives forward through the layers (no double backward).

A SIREN (Sitzmann et al. 2020) maps u -> sin(w0 (W u + b)) layer after layer. Because every layer is an affine map
followed by an elementwise sine, the derivatives of the activations with respect to the input coordinates can be
carried forward alongside the values ("jets"): an affine map acts on every derivative channel the same way (the
bias only on the value), and the sine's chain rule is elementwise. All derivative channels of a layer go through one
matrix multiply, laid out as (batch, channels, width), which is what a CPU does fastest. Training then
backpropagates through this forward computation once, instead of differentiating a backward pass again.

Two jets are provided:

* order 1 (value + 3 first derivatives): the gradient of the mean net g(x, z), and the Jacobian of the covariance
  feature map phi(x, z);
* the mixed jet of a pair network h(a, b, z) (value, d/da, d/db, d2/da_k db_l: 16 channels), for the paper's
  pairwise covariance net c(a, b), whose D operator is the 3 x 3 block of mixed second derivatives.

Shapes follow PyTorch3D's habit of inline comments: B batch, W width, L latent dimension, K output features.

The networks of NSSPR built of them (all coordinates in the model's normalised, unit-cube frame):

* :class:`MeanNet`: g(x, z), a SIREN with a scalar output; trained so that grad g matches the posterior mean field.
* :class:`FeatureCovarianceNet` (default): c(a, b, z) = phi(a, z) . phi(b, z) / K with phi a SIREN with K outputs.
  Symmetric and positive semi-definite by construction, and its D operator D c(a, b) = J_phi(a)^T J_phi(b) / K
  needs only each point's first derivatives; one Jacobian serves every pair in the batch.
* :class:`PairCovarianceNet` (the paper's): c(a, b, z) = (s(a, b) + s(b, a)) / 2 with s = SoftPlus(h([a, b], z))
  and h a SIREN on the 6 concatenated coordinates; its D operator comes from the forward-carried mixed jet.

:func:`build_siren_networks` builds a pair of them from a configuration
(:func:`autodecoder.field.networks.build_networks` chooses between these and the grid's).
"""
import math

import torch
from torch import nn
from torch.nn import functional as F


class Siren(nn.Module):
    """A SIREN MLP f(x, z) with spatial input x (B, in_dim) and an optional latent code z (B, L).

    Parameters
    ----------
    in_dim : int
        Number of spatial input coordinates that are differentiated (3 for g(x), 6 for h(a, b)).
    out_dim : int
        Number of outputs.
    width : int
        Hidden width.
    depth : int
        Number of hidden (sine) layers, >= 1.
    latent_dim : int, optional
        Dimension of the latent code concatenated to the input (0: none).
    omega0 : float, optional
        Frequency of the first layer (SIREN's w0); hidden layers use ``omega``.
    omega : float, optional
        Frequency of the hidden layers.
    """

    def __init__(self, in_dim, out_dim, width, depth, latent_dim=0, omega0=30.0, omega=30.0):
        super().__init__()
        if depth < 1 or width < 1:
            raise ValueError(f"depth and width must be >= 1, got depth={depth}, width={width}")
        self.in_dim, self.out_dim, self.width, self.depth = in_dim, out_dim, width, depth
        self.latent_dim = latent_dim
        self.omega0, self.omega = float(omega0), float(omega)
        self.first_x = nn.Parameter(torch.empty(width, in_dim))
        self.first_z = nn.Parameter(torch.empty(width, latent_dim)) if latent_dim > 0 else None
        self.first_b = nn.Parameter(torch.empty(width))
        self.hidden = nn.ModuleList(nn.Linear(width, width) for _ in range(depth - 1))
        self.last = nn.Linear(width, out_dim)
        self.reset_parameters()

    @torch.no_grad()
    def reset_parameters(self):
        # SIREN initialisation: first layer U(-1/fan_in, 1/fan_in) so that w0 sets its frequencies; the spatial and
        # latent parts get their own fan-in so that a long code does not dilute the spatial frequencies.
        self.first_x.uniform_(-1 / self.in_dim, 1 / self.in_dim)
        if self.first_z is not None:
            self.first_z.uniform_(-1 / self.latent_dim, 1 / self.latent_dim)
        self.first_b.uniform_(-1 / self.in_dim, 1 / self.in_dim)
        for lin in list(self.hidden) + [self.last]:
            bound = math.sqrt(6 / lin.in_features) / self.omega
            lin.weight.uniform_(-bound, bound)
            lin.bias.uniform_(-bound, bound)

    def _first_preactivation(self, x, z):
        pre = x @ self.first_x.T + self.first_b  # (B, W)
        if self.first_z is not None:
            if z is None:
                raise ValueError(f"this network expects a latent code of dimension {self.latent_dim}")
            pre = pre + z @ self.first_z.T  # z (B, L) or (L,) broadcasts
        return pre

    def forward(self, x, z=None):
        """Values only: x (B, in_dim), z (B, L) or (L,) -> (B, out_dim)."""
        y = torch.sin(self.omega0 * self._first_preactivation(x, z))
        for lin in self.hidden:
            y = torch.sin(self.omega * lin(y))
        return self.last(y)

    def forward_jet1(self, x, z=None):
        """Values and first derivatives with respect to x, carried forward.

        Parameters
        ----------
        x : (B, in_dim) tensor
        z : (B, L) or (L,) tensor, optional

        Returns
        -------
        value : (B, out_dim) tensor
        jacobian : (B, in_dim, out_dim) tensor
            ``jacobian[b, k, o]`` = d value[b, o] / d x[b, k].
        """
        pre = self.omega0 * self._first_preactivation(x, z)  # (B, W)
        y = torch.sin(pre)
        # d pre / dx_k = w0 * first_x[:, k], the same for every sample
        # contiguous: the broadcast product comes out with strides (W in, 1, in), which torch's matmul does not fold
        # into one matrix product but runs as B tiny batched ones, six times slower
        jac = ((self.omega0 * torch.cos(pre)).unsqueeze(1) * self.first_x.T.unsqueeze(0)).contiguous()  # (B, in, W)
        for lin in self.hidden:
            # the value and the derivative channels in two matrix products, not one over their concatenation: the
            # slices of a concatenated product cost a zero-filled copy each in the backward pass (about a fifth of a
            # latent training step's forward and backward, docs/results.md#latent-training-and-projection-cost)
            pre = self.omega * torch.addmm(lin.bias, y, lin.weight.T)  # (B, W)
            d_pre = jac @ (self.omega * lin.weight.T)  # (B, in, W)
            y = torch.sin(pre)
            jac = torch.cos(pre).unsqueeze(1) * d_pre
        value = self.last(y)
        return value, jac @ self.last.weight.T

    @torch.no_grad()
    def jet1_with_code_vjp(self, x, z_first):
        """:meth:`forward_jet1` of a scalar-output net without autograd, and a function that back-propagates to the
        code: the cheap path of fitting a code with the weights frozen (test-time projection), where a step is a
        few hundred points and autograd's bookkeeping costs more than the arithmetic.

        Parameters
        ----------
        x : (B, in_dim) tensor
        z_first : (B, W) tensor
            The code's contribution to the first pre-activation, ``z @ first_z.T`` per row (a code shared by many
            rows is multiplied once by the caller).

        Returns
        -------
        value : (B,) tensor
        jacobian : (B, in_dim) tensor
        vjp : callable (d_value (B,), d_jacobian (B, in_dim)) -> (B, W)
            The gradient of sum(d_value * value + d_jacobian * jacobian) with respect to ``z_first``; the code's
            gradient is that times ``first_z`` (summed over the rows of each code).
        """
        if self.out_dim != 1:
            raise ValueError(f"jet1_with_code_vjp needs a scalar output, this net has {self.out_dim}")
        w0x = self.omega0 * self.first_x.T  # (in, W)
        pre = self.omega0 * (torch.addmm(self.first_b, x, self.first_x.T) + z_first)  # (B, W)
        y, c = torch.sin(pre), torch.cos(pre)
        d_pre = w0x.unsqueeze(0).expand(len(x), -1, -1)  # (B, in, W)
        saved = []  # per layer: (its input's jet d_pre, y, c) and the weight that follows
        for lin in self.hidden:
            jac = (c.unsqueeze(1) * d_pre).contiguous()  # see forward_jet1
            saved.append((d_pre, y, c))
            pre = self.omega * torch.addmm(lin.bias, y, lin.weight.T)
            d_pre = jac @ (self.omega * lin.weight.T)
            y, c = torch.sin(pre), torch.cos(pre)
        jac = c.unsqueeze(1) * d_pre
        saved.append((d_pre, y, c))
        wl = self.last.weight[0]  # (W,)
        value = y @ wl + self.last.bias[0]
        jacobian = jac @ wl

        def vjp(d_value, d_jacobian):
            with torch.no_grad():
                d_y = d_value[:, None] * wl  # (B, W)
                d_jac = d_jacobian[:, :, None] * wl  # (B, in, W)
                layers = list(self.hidden)
                for i in range(len(saved) - 1, -1, -1):
                    d_pre_in, y_i, c_i = saved[i]
                    # jac_i = c_i * d_pre_in, y_i = sin(pre_i): back to pre_i and to the jet d_pre_in
                    d_c = (d_jac * d_pre_in).sum(1)  # (B, W)
                    d_pre_value = d_y * c_i - d_c * y_i
                    if i == 0:
                        return self.omega0 * d_pre_value
                    d_jet = c_i.unsqueeze(1) * d_jac  # (B, in, W)
                    weight = self.omega * layers[i - 1].weight  # pre_i = omega (y_{i-1} W^T + b)
                    d_y = d_pre_value @ weight
                    d_jac = d_jet @ weight

        return value, jacobian, vjp

    def forward_mixed_jet(self, x, z=None):
        """Value, first and mixed second derivatives of a pair network h(a, b), with x = [a, b] (B, 6).

        Returns
        -------
        value : (B, out_dim)
        grad_a, grad_b : (B, 3, out_dim)
        mixed : (B, 3, 3, out_dim)
            ``mixed[b, k, l, o]`` = d2 value[b, o] / d a_k d b_l.
        """
        if self.in_dim != 6:
            raise ValueError(f"the mixed jet needs a pair network with 6 spatial inputs, this one has {self.in_dim}")
        bsz = x.shape[0]
        pre = self.omega0 * self._first_preactivation(x, z)  # (B, W)
        w0x = self.omega0 * self.first_x.T  # (6, W): d pre / d(a, b)
        y, c = torch.sin(pre), torch.cos(pre)
        ga = c.unsqueeze(1) * w0x[:3].unsqueeze(0)  # (B, 3, W)
        gb = c.unsqueeze(1) * w0x[3:].unsqueeze(0)  # (B, 3, W)
        # the first pre-activation is affine in (a, b), so only the sine's curvature contributes here
        mixed = -(y.unsqueeze(1).unsqueeze(1) * w0x[:3, None, :] * w0x[None, 3:, :])  # (B, 3, 3, W)
        for lin in self.hidden:
            stacked = torch.cat([y.unsqueeze(1), ga, gb, mixed.reshape(bsz, 9, -1)], dim=1) @ lin.weight.T
            pre_v = self.omega * (stacked[:, 0] + lin.bias)  # (B, W)
            pa, pb = self.omega * stacked[:, 1:4], self.omega * stacked[:, 4:7]  # (B, 3, W)
            pab = self.omega * stacked[:, 7:].reshape(bsz, 3, 3, -1)
            y, c = torch.sin(pre_v), torch.cos(pre_v)
            ga, gb = c.unsqueeze(1) * pa, c.unsqueeze(1) * pb
            mixed = c[:, None, None, :] * pab - y[:, None, None, :] * pa.unsqueeze(2) * pb.unsqueeze(1)
        wl = self.last.weight.T  # (W, out)
        return self.last(y), ga @ wl, gb @ wl, mixed @ wl


class MeanNet(nn.Module):
    """g(x, z): the mean of the stochastic implicit function.

    Parameters
    ----------
    width, depth, latent_dim, omega0
        Those of the :class:`Siren` it holds: hidden width, hidden layers, latent code dimension (0: a single
        cloud), first-layer frequency.
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
    features : int
        K, the number of features (the rank of the covariance): the :class:`Siren`'s outputs.
    width, depth, latent_dim, omega0
        Those of the :class:`Siren` it holds, as in :class:`MeanNet`.
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
    width, depth, latent_dim, omega0
        Those of the :class:`Siren` h it holds, as in :class:`MeanNet`; h takes the 6 coordinates of a pair.
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


def build_siren_networks(config):
    """The SIREN mean and covariance nets of a configuration dict (:func:`autodecoder.field.networks.build_networks`'s
    keys: ``width``, ``depth``, ``latent_dim``, ``covariance`` ('feature' or 'pair'), ``features``, ``omega0``,
    optional ``cov_width``/``cov_depth``).

    Returns
    -------
    (MeanNet, FeatureCovarianceNet or PairCovarianceNet)
    """
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
