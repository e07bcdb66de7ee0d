"""Grid networks: the mean g(x, z) and the covariance feature map phi(x, z) on multi-resolution B-spline grids.

A level is a dense grid of control values over the training box, interpolated by the uniform tricubic B-spline
(C2, so the gradient the Dirichlet loss sees is continuous, and the B-spline matches the paper's kernel). Its
value at x is a weighted sum of the 4 x 4 x 4 control values around x, the weights products of the cubic B-spline
basis along each axis; the spatial gradient is the same sum with one factor replaced by the basis' derivative.
Both come from ONE gather of the 64 control values: the gradient is a second interpolation, not a derivative of the
computation graph, so the Dirichlet loss costs one ordinary backward pass (no double backward), as with the
forward-carried SIREN jets of :mod:`autodecoder.siren`.

* :class:`GridEncoder`: ``levels`` grids from coarse to fine, their interpolated values concatenated into
  features (B, F) with their Jacobian (B, 3, F).
* :class:`JetMLP`: a small decoder of ``[features(x), z]`` that carries the Jacobian forward through its layers.
* :class:`GridMeanNet`: g = the sum of the levels' values (a hierarchical B-spline, no decoder) or a decoder of the
  features and the code.
* :class:`GridCovarianceNet`: c(a, b, z) = phi(a, z) . phi(b, z) / K with phi the features (or a decoder of them),
  so D c(a, b) = J_phi(a)^T J_phi(b) / K as for :class:`autodecoder.field.siren.FeatureCovarianceNet`.

Both nets expose the methods of their SIREN counterparts in :mod:`autodecoder.field.siren`, so the losses, the
step functions of :mod:`autodecoder.field.steps` and :class:`autodecoder.field.stochastic_field.StochasticField` use them unchanged (train
them with :mod:`autodecoder.field.grid_fit`: no weight decay on control values). Coordinates are in the model
(unit-cube) frame; the grids cover the box ``[lo, hi]`` given at construction (stored as buffers, so a state dict
rebuilds the same function); outside the box the field is continued by its value on the box's surface (the
coordinates are clamped, so the gradient there is zero across the clamped axes).

Why levels: a function on a fine grid trained by stochastic gradients gets its low frequencies only slowly
(information travels a few cells per step); coarse levels carry them, as in multigrid. The single-cloud mean does
not need them (it is solved on one level, :func:`autodecoder.field.grid_fit.solve_mean`); the covariance does: its
variance grows smoothly away from the data over the whole box.
"""
import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

GRID_REPRESENTATION = "grid"


def cubic_bspline_weights(t):
    """The four uniform cubic B-spline basis values and derivatives at fractional positions t in [0, 1].

    Parameters
    ----------
    t : (..., ) tensor

    Returns
    -------
    w, dw : (..., 4) tensors
        Weights of the control values at offsets -1, 0, 1, 2 from the cell's first node, and their derivatives
        with respect to t. The weights sum to 1 and the derivatives to 0.
    """
    t2 = t * t
    t3 = t2 * t
    s = 1 - t
    w = torch.stack([s * s * s, 3 * t3 - 6 * t2 + 4, -3 * t3 + 3 * t2 + 3 * t + 1, t3], -1) / 6
    dw = torch.stack([-0.5 * s * s, 1.5 * t2 - 2 * t, -1.5 * t2 + t + 0.5, 0.5 * t2], -1)
    return w, dw


class _Gather(torch.autograd.Function):
    """table[index], table[index + 1], ..., table[index + run - 1] side by side for a flat index: (R, C) -> (n, run C).

    A tricubic tap's 4 control values along the last axis are consecutive rows, so one index fetches all 4 (a
    quarter of the row look-ups of gathering them one by one). Forward: ``index_select`` on an overlapping strided
    view of the table; backward: ``index_add_`` into that view's shape, then each of the ``run`` column blocks added
    back at its row offset (faster on CPU than ``F.embedding``'s backward)."""

    @staticmethod
    def forward(ctx, table, index, run=1):
        rows, channels = table.shape
        ctx.save_for_backward(index)
        ctx.rows, ctx.run = rows, int(run)
        table = table.contiguous()
        windows = table.as_strided((rows - run + 1, run * channels), (channels, 1))
        return windows.index_select(0, index)

    @staticmethod
    def backward(ctx, grad):
        (index,) = ctx.saved_tensors
        run, rows = ctx.run, ctx.rows
        channels = grad.shape[1] // run
        window_grad = torch.zeros(rows - run + 1, run * channels, dtype=grad.dtype, device=grad.device)
        window_grad.index_add_(0, index, grad)
        if run == 1:
            return window_grad, None, None
        table_grad = torch.zeros(rows, channels, dtype=grad.dtype, device=grad.device)
        for k in range(run):
            table_grad[k:k + rows - run + 1] += window_grad[:, k * channels:(k + 1) * channels]
        return table_grad, None, None


class BSplineGrid(nn.Module):
    """One level: ``channels`` tricubic B-spline functions on ``cells`` cells per side of the box [lo, hi].

    Control value (i, j, k) sits at lo + (i - 1, j - 1, k - 1) * cell, so (cells + 3)^3 of them cover the box;
    they are stored flat, ``values`` ((cells + 3)^3, channels) in C order of (i, j, k).

    Parameters
    ----------
    cells : int
        Cells along each side (>= 1).
    channels : int
        Functions interpolated at once.
    lo, hi : (3,) array-likes
        The box (model frame).
    init_std : float
        Standard deviation of the initial control values (0: all zero).
    generator : torch.Generator, optional
    """

    def __init__(self, cells, channels, lo, hi, init_std=0.0, generator=None):
        super().__init__()
        if int(cells) < 1 or int(channels) < 1:
            raise ValueError(f"cells and channels must be >= 1, got cells={cells}, channels={channels}")
        self.cells, self.channels = int(cells), int(channels)
        lo = torch.as_tensor(np.asarray(lo, dtype=np.float64), dtype=torch.float32).reshape(3)
        hi = torch.as_tensor(np.asarray(hi, dtype=np.float64), dtype=torch.float32).reshape(3)
        if not bool((hi > lo).all()):
            raise ValueError(f"the box must have hi > lo on every axis, got lo={lo.tolist()}, hi={hi.tolist()}")
        self.register_buffer("lo", lo)
        self.register_buffer("cell", (hi - lo) / self.cells)
        side = self.cells + 3
        values = torch.zeros(side, side, side, self.channels)
        if init_std > 0:
            values.normal_(0.0, float(init_std), generator=generator)
        self.values = nn.Parameter(values.reshape(side**3, self.channels))

    @torch.no_grad()
    def set_from_nodes(self, nodes, channel=0):
        """Make ``channel`` interpolate ``nodes`` (cells + 1 per side, node i at lo + i * cell) at the nodes.

        The control values are the nodes' cubic B-spline coefficients (``scipy.ndimage.spline_filter``, mirror
        boundary), extended by one mirrored value beyond each side, so the result reproduces ``nodes`` exactly at
        the nodes and interpolates them with C2 continuity in between.

        Parameters
        ----------
        nodes : (cells + 1, cells + 1, cells + 1) array
        channel : int
        """
        from scipy.ndimage import spline_filter

        nodes = np.asarray(nodes, dtype=np.float64)
        if nodes.shape != (self.cells + 1,) * 3:
            raise ValueError(f"nodes must have shape {(self.cells + 1,) * 3}, got {nodes.shape}")
        coef = np.pad(spline_filter(nodes, order=3, mode="mirror"), 1, mode="reflect")
        self.values[:, channel] = torch.from_numpy(coef).reshape(-1).to(self.values.dtype)

    def _taps(self, x):
        """Flat control-value indices (B, 16) of the first of each run of 4 along z (the taps are the 4 rows from
        each), interpolation weights (B, 4, 64): value, d/dx, d/dy, d/dz."""
        u = (x - self.lo.to(x.dtype)) / self.cell.to(x.dtype)  # (B, 3) in cells
        u = u.clamp(0.0, float(self.cells))
        base = u.detach().floor().clamp_(max=self.cells - 1)
        t = u - base  # (B, 3) in [0, 1]; differentiable in x
        base = base.long()
        w, dw = cubic_bspline_weights(t)  # (B, 3, 4)
        dw = dw / self.cell.to(x.dtype)[:, None]
        side = self.cells + 3
        offs = torch.arange(4, device=x.device)
        ix, iy, iz = (base[:, a, None] + offs for a in range(3))  # (B, 4) each
        idx = ((ix[:, :, None] * side + iy[:, None, :]) * side + iz[:, None, :1]).reshape(-1, 16)
        wx, wy, wz = w[:, 0], w[:, 1], w[:, 2]
        dx, dy, dz = dw[:, 0], dw[:, 1], dw[:, 2]

        def outer(a, b, c):
            return (a[:, :, None, None] * b[:, None, :, None] * c[:, None, None, :]).reshape(-1, 64)

        weights = torch.stack([outer(wx, wy, wz), outer(dx, wy, wz), outer(wx, dy, wz), outer(wx, wy, dz)], 1)
        return idx, weights

    def forward(self, x):
        """Values at x (B, 3) -> (B, channels)."""
        return self.value_and_jacobian(x, jacobian=False)[0]

    def value_and_jacobian(self, x, jacobian=True):
        """Values and their spatial Jacobian at x (B, 3) -> (B, C), (B, 3, C) (None without ``jacobian``)."""
        idx, weights = self._taps(x)
        if not jacobian:
            weights = weights[:, :1]
        taps = _Gather.apply(self.values, idx.reshape(-1), 4).reshape(len(x), 64, self.channels)
        out = torch.bmm(weights.to(taps.dtype), taps)  # (B, 1 or 4, C)
        return out[:, 0], (out[:, 1:] if jacobian else None)


def level_cells(finest, levels, base=None):
    """Cells per side of each level, coarse to fine: a geometric sequence from ``base`` to ``finest``.

    Parameters
    ----------
    finest : int
    levels : int
    base : int, optional
        Cells of the coarsest level (default ``finest / 2^(levels - 1)``, at least 2).

    Returns
    -------
    list of int
    """
    finest, levels = int(finest), int(levels)
    if levels < 1 or finest < 1:
        raise ValueError(f"levels and finest must be >= 1, got levels={levels}, finest={finest}")
    if levels == 1:
        return [finest]
    base = max(2, round(finest / 2 ** (levels - 1))) if base is None else int(base)
    ratio = (finest / base) ** (1.0 / (levels - 1))
    return [max(1, round(base * ratio**level)) for level in range(levels - 1)] + [finest]


class GridEncoder(nn.Module):
    """Multi-resolution B-spline features: ``levels`` grids of ``channels`` channels, concatenated coarse to fine.

    Parameters
    ----------
    lo, hi : (3,) array-likes
        The box (model frame).
    finest : int
        Cells per side of the finest level.
    levels : int
    channels : int
        Channels per level (the feature dimension is ``levels * channels``).
    base : int, optional
        Cells per side of the coarsest level (see :func:`level_cells`).
    init_std : float
        Initial control values ~ N(0, (init_std * cell)^2) per level, cell the level's cell size: features whose
        gradients are of the same order at every level.
    seed : int
    """

    def __init__(self, lo, hi, finest=128, levels=4, channels=1, base=None, init_std=0.0, seed=0):
        super().__init__()
        generator = torch.Generator().manual_seed(int(seed))
        cells = level_cells(finest, levels, base)
        extent = float(np.max(np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64)))
        self.levels = nn.ModuleList(BSplineGrid(n, channels, lo, hi, init_std * extent / n, generator)
                                    for n in cells)
        self.out_dim = len(cells) * int(channels)

    def forward(self, x):
        """Features at x (B, 3) -> (B, F)."""
        return torch.cat([level(x) for level in self.levels], -1)

    def value_and_jacobian(self, x):
        """Features and their Jacobian at x (B, 3) -> (B, F), (B, 3, F)."""
        pairs = [level.value_and_jacobian(x) for level in self.levels]
        return torch.cat([p[0] for p in pairs], -1), torch.cat([p[1] for p in pairs], -1)


class JetMLP(nn.Module):
    """A small MLP on ``[features, z]`` that carries the features' spatial Jacobian through its layers.

    Hidden layers are affine maps followed by SiLU (smooth, so the carried Jacobian is continuous); the last layer
    is affine. The code z enters the first layer only; it has no spatial derivative.

    Parameters
    ----------
    in_dim : int
        Feature dimension F.
    out_dim : int
    hidden : int
        Hidden width (0: one affine map).
    depth : int
        Hidden layers (ignored when ``hidden`` is 0).
    latent_dim : int
    """

    def __init__(self, in_dim, out_dim, hidden=64, depth=1, latent_dim=0):
        super().__init__()
        widths = [in_dim] + ([int(hidden)] * int(depth) if hidden > 0 else []) + [out_dim]
        self.latent_dim = int(latent_dim)
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(widths[:-1], widths[1:]))
        self.code_in = nn.Linear(self.latent_dim, widths[1], bias=False) if self.latent_dim > 0 else None

    def _code_term(self, z, batch):
        if self.code_in is None:
            return 0.0
        if z is None:
            raise ValueError(f"this decoder takes a latent code of dimension {self.latent_dim}; got z=None")
        z = z.reshape(1, -1) if z.dim() == 1 else z
        return self.code_in(z.to(self.code_in.weight.dtype)).expand(batch, -1)

    def forward(self, f, z=None, jac=None):
        """Outputs (B, out) and, given the features' Jacobian ``jac`` (B, 3, F), theirs (B, 3, out)."""
        h = self.layers[0](f) + self._code_term(z, len(f))
        j = None if jac is None else jac @ self.layers[0].weight.T
        for layer in self.layers[1:]:
            if j is not None:
                s = torch.sigmoid(h)
                j = j * (s * (1 + h * (1 - s))).unsqueeze(1)  # SiLU'(h) = s (1 + h (1 - s))
            h = F.silu(h)
            h = layer(h)
            if j is not None:
                j = j @ layer.weight.T
        return h, j


class GridMeanNet(nn.Module):
    """g(x, z): the mean on multi-resolution B-spline grids, summed (no decoder) or decoded by a :class:`JetMLP`.

    Parameters
    ----------
    lo, hi : (3,) array-likes
        The box (model frame).
    finest, levels, channels, base : int
        The grids (see :class:`GridEncoder`); without a decoder, ``channels`` must be 1 and g is the sum of the
        levels' B-splines (linear in its parameters: the paper's loss is then a quadratic in them).
    hidden, depth : int
        Decoder width and hidden layers; ``hidden=0`` and no latent code: no decoder.
    latent_dim : int
    init_std : float
        Initial feature scale (see :class:`GridEncoder`; the summed grids start at 0 whatever it is).
    seed : int
    shared_cells : int
        With a decoder: cells per side of one more B-spline level, not decoded, whose value is added to the
        decoder's output, g(x, z) = s(x) + d(features(x), z) (0: none). In a latent model s is the geometry every
        code shares (it can be solved on the union of the training scans, :func:`solve_shared`) and the decoded
        part what the code changes.
    centred : bool
        With a decoder and a latent code: g(x, z) = s(x) + d(features(x), z) - d(features(x), 0), so that the code 0
        gives exactly the shared level and the decoded part is only what the code changes (False: the decoder's
        output as it is, which also holds a code-independent part).
    """

    def __init__(self, lo, hi, finest=128, levels=1, channels=1, base=None, hidden=0, depth=1, latent_dim=0,
                 init_std=0.1, seed=0, shared_cells=0, centred=False):
        super().__init__()
        self.summed = hidden == 0 and latent_dim == 0
        if self.summed and channels != 1:
            raise ValueError(f"a mean without a decoder sums one channel per level, got channels={channels}")
        if int(shared_cells) < 0 or (self.summed and int(shared_cells) > 0):
            raise ValueError(f"shared_cells must be >= 0 and needs a decoder (hidden > 0 or a latent code), got "
                             f"shared_cells={shared_cells}, hidden={hidden}, latent_dim={latent_dim}")
        self.encoder = GridEncoder(lo, hi, finest, levels, channels, base, 0.0 if self.summed else init_std, seed)
        self.decoder = None if self.summed else JetMLP(self.encoder.out_dim, 1, hidden, depth, latent_dim)
        self.shared = BSplineGrid(int(shared_cells), 1, lo, hi) if int(shared_cells) > 0 else None
        if centred and (self.decoder is None or self.decoder.latent_dim == 0):
            raise ValueError("centred needs a decoder with a latent code (latent_dim > 0)")
        self.centred = bool(centred)

    def _decoded(self, f, z, jac=None):
        """d(f, z) (B,) and its spatial gradient (B, 3) (None without ``jac``), minus d(f, 0) when centred."""
        value, grad = self.decoder(f, z, jac)
        if self.centred:
            zero = torch.zeros(self.decoder.latent_dim, dtype=f.dtype, device=f.device)
            v0, g0 = self.decoder(f, zero, jac)
            value = value - v0
            grad = None if grad is None else grad - g0
        return value[:, 0], (None if grad is None else grad[:, :, 0])

    def forward(self, x, z=None):
        """g at x (B, 3) -> (B,)."""
        f = self.encoder(x)
        if self.decoder is None:
            return f.sum(-1)
        value = self._decoded(f, z)[0]
        if self.shared is not None:
            value = value + self.shared(x)[:, 0]
        return value

    def value_and_gradient(self, x, z=None):
        """g and grad_x g at x (B, 3) -> (B,), (B, 3)."""
        f, jac = self.encoder.value_and_jacobian(x)
        if self.decoder is None:
            return f.sum(-1), jac.sum(-1)
        value, grad = self._decoded(f, z, jac)
        if self.shared is not None:
            s, ds = self.shared.value_and_jacobian(x)
            value, grad = value + s[:, 0], grad + ds[:, :, 0]
        return value, grad

    def features_at(self, x):
        """What :meth:`value_and_gradient_from` needs at fixed points x (B, 3): everything that does not depend
        on the code (features, their Jacobian, the shared level's value and gradient), detached.

        Returns
        -------
        dict of tensors: ``f`` (B, F), ``jac`` (B, 3, F), ``s`` (B,), ``ds`` (B, 3) (zeros without a shared level)
        """
        if self.decoder is None:
            raise ValueError("features_at needs a decoded grid mean (a summed one does not depend on a code)")
        with torch.no_grad():
            f, jac = self.encoder.value_and_jacobian(x)
            if self.shared is not None:
                s, ds = self.shared.value_and_jacobian(x)
                s, ds = s[:, 0], ds[:, :, 0]
            else:
                s, ds = torch.zeros(len(x), dtype=f.dtype), torch.zeros(len(x), 3, dtype=f.dtype)
        return {"f": f, "jac": jac, "s": s, "ds": ds}

    def value_and_gradient_from(self, cache, z=None):
        """g and grad_x g from :meth:`features_at`'s cache (rows may be indexed): the decoder alone runs, so a
        code can be fitted to fixed points without interpolating the grids again. Returns (B,), (B, 3)."""
        value, grad = self._decoded(cache["f"], z, cache["jac"])
        return value + cache["s"], grad + cache["ds"]


class GridCovarianceNet(nn.Module):
    """c(a, b, z) = phi(a, z) . phi(b, z) / K with phi multi-resolution B-spline features (optionally decoded).

    Positive semi-definite and symmetric by construction; D c(a, b) = J_phi(a)^T J_phi(b) / K.

    Parameters
    ----------
    lo, hi : (3,) array-likes
        The box (model frame).
    finest, levels, channels, base : int
        The grids (see :class:`GridEncoder`); without a decoder phi is the features, K = ``levels * channels``.
    features : int
        K when there is a decoder.
    hidden, depth : int
        Decoder width and hidden layers; ``hidden=0`` and no latent code: no decoder.
    latent_dim : int
    init_std : float
        Initial feature scale (see :class:`GridEncoder`).
    seed : int
    """

    kind = "feature"

    def __init__(self, lo, hi, finest=16, levels=3, channels=32, base=None, features=64, hidden=0, depth=1,
                 latent_dim=0, init_std=0.1, seed=1):
        super().__init__()
        self.encoder = GridEncoder(lo, hi, finest, levels, channels, base, init_std, seed)
        direct = hidden == 0 and latent_dim == 0
        self.decoder = None if direct else JetMLP(self.encoder.out_dim, features, hidden, depth, latent_dim)
        self.features = self.encoder.out_dim if direct else int(features)
        # the codes' box the decoder reads (set_code_range); non-persistent: state dicts are unchanged
        self.register_buffer("code_lo", None, persistent=False)
        self.register_buffer("code_hi", None, persistent=False)

    @torch.no_grad()
    def set_code_range(self, lo=None, hi=None):
        """Clamp every code this net reads to the box [lo, hi] (per coordinate), or stop clamping (both None).

        A latent model's covariance decoder was trained only on its training codes; a code projected onto a new scan
        can lie far outside them (a grid model's projection walks its mean's code tens of training-code norms away,
        docs/results.md#the-latent-model-on-grids-issue-19), where the decoder extrapolates and the variance at the
        scan's own points grows by an order of magnitude. Clamped, the covariance of such a code is that of the
        nearest code in the training codes' box. Non-persistent buffers: not in the state dict (a checkpoint holds
        the codes, and :class:`autodecoder.latent.model.LatentModel` sets the range from them).

        Parameters
        ----------
        lo, hi : (L,) tensors, optional
            Per-coordinate bounds with lo <= hi, L the decoder's latent dimension.
        """
        if (lo is None) != (hi is None):
            raise ValueError("set_code_range needs both lo and hi, or neither")
        if lo is not None:
            lo = torch.as_tensor(lo, dtype=torch.float32).reshape(-1)
            hi = torch.as_tensor(hi, dtype=torch.float32).reshape(-1)
            latent = 0 if self.decoder is None else self.decoder.latent_dim
            if lo.shape != (latent,) or hi.shape != (latent,) or not bool((lo <= hi).all()):
                raise ValueError(f"code range must be two ({latent},) tensors with lo <= hi, got shapes "
                                 f"{tuple(lo.shape)} and {tuple(hi.shape)}")
        self.code_lo, self.code_hi = lo, hi

    def _code(self, z):
        if z is None or self.code_lo is None:
            return z
        return torch.maximum(torch.minimum(z, self.code_hi.to(z.dtype)), self.code_lo.to(z.dtype))

    def _phi(self, x, z, jacobian):
        z = self._code(z)
        if jacobian:
            f, jac = self.encoder.value_and_jacobian(x)
        else:
            f, jac = self.encoder(x), None
        if self.decoder is not None:
            f, jac = self.decoder(f, z, jac)
        return f, jac

    def features_and_jacobian(self, x, z=None):
        """phi / sqrt(K) and its Jacobian at x (B, 3) -> (B, K), (B, 3, K)."""
        f, jac = self._phi(x, z, True)
        scale = self.features**-0.5
        return f * scale, jac * scale

    def covariance(self, a, b, z=None):
        """c(a_i, b_i) for pairs taken row by row: (B, 3), (B, 3) -> (B,)."""
        return (self._phi(a, z, False)[0] * self._phi(b, z, False)[0]).sum(-1) / self.features

    def variance(self, x, z=None):
        """c(x, x) = |phi(x)|^2 / K: (B, 3) -> (B,)."""
        return self._phi(x, z, False)[0].square().sum(-1) / self.features

    def d_operator(self, a, b, z=None):
        """D c(a_i, b_i) = d2 c / da_k db_l for pairs row by row: (B, 3), (B, 3) -> (B, 3, 3)."""
        _, ja = self.features_and_jacobian(a, z)
        _, jb = self.features_and_jacobian(b, z)
        return ja @ jb.transpose(1, 2)


MEAN_DEFAULTS = {"finest": 128, "levels": 1, "channels": 1, "hidden": 0, "depth": 1}
COV_DEFAULTS = {"finest": 16, "levels": 3, "channels": 32, "hidden": 0, "depth": 1, "features": 64}


def build_grid_networks(config):
    """Grid mean and covariance nets from a configuration dict (``config["representation"] == "grid"``).

    Keys: ``box_lo``, ``box_hi`` (the model-frame box), ``latent_dim``; optional ``grid_mean`` and ``grid_cov``,
    dicts overriding :data:`MEAN_DEFAULTS` / :data:`COV_DEFAULTS` (keys of :class:`GridMeanNet` /
    :class:`GridCovarianceNet`).

    Returns
    -------
    (GridMeanNet, GridCovarianceNet)
    """
    lo, hi, latent = config["box_lo"], config["box_hi"], int(config.get("latent_dim", 0))
    mean_kw = {**MEAN_DEFAULTS, **dict(config.get("grid_mean") or {})}
    cov_kw = {**COV_DEFAULTS, **dict(config.get("grid_cov") or {})}
    return (GridMeanNet(lo, hi, latent_dim=latent, **mean_kw),
            GridCovarianceNet(lo, hi, latent_dim=latent, **cov_kw))
