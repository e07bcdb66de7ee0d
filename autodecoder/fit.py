"""fit_cloud: neural stochastic screened Poisson reconstruction of one oriented point cloud."""
import math
import time
from dataclasses import asdict, dataclass
from typing import Optional

import numpy as np
import torch
from tqdm.auto import tqdm

from .field import StochasticField
from .frame import Normalization
from .losses import (covariance_dirichlet_loss_features, covariance_dirichlet_loss_pairs, mean_dirichlet_loss,
                     screening_loss, SCREENING_WEIGHT)
from .networks import build_networks
from .targets import FIT_LENGTHSCALE_FACTOR, CloudTargets, default_lengthscale
from .validation import check_oriented_cloud


@dataclass
class FitOptions:
    """Optimisation settings of :func:`fit_cloud` (defaults measured on this 2-core CPU, see the README).

    Why many small steps: on fandisk (20k points, Chamfer of the mean surface / diagonal, 256^3 marching cubes,
    ``benchmarks/fit_defaults.py`` and the README) the error falls with the number of Adam steps far more than with
    the batch: 1000 steps of 4096 samples 0.90e-3, 2000 of 512 0.81e-3, 4000 of 512 0.72e-3, and width 64 does as
    well as 128 at equal steps (4000 x 512: 0.74e-3 vs 0.72e-3). A step of width 64 on 256 samples is mostly
    per-operation overhead (~12 ms on 2 cores, ~1/10 of a 4096-sample width-128 step), so 3000 such steps
    (0.80e-3) fit in about a minute where 1000 large ones took 220 s. With the kernel lengthscale at 1.5 point
    spacings (``fit_cloud``'s default) and a covariance step every 8: 3000 steps 0.71e-3, 3500 0.66e-3 in 49-53 s.
    A covariance step costs ~44 ms against ~9 ms for a mean step (profiled on fandisk), so a covariance step every
    16 buys 500 more mean steps in the same time: 4000 steps 0.62e-3 in 49-55 s (seed 1: 0.69e-3 against 0.77e-3
    for 3500 steps with every 8), and the variance's Spearman with gpytoolbox's went 0.770 -> 0.781.

    What limits the accuracy is this training, not the loss: the loss's exact minimiser on a grid
    (``benchmarks/target_limit.py``) is within 1.31x open3d's Chamfer on fandisk, the 4000-step fit 2.25x, and
    15000 steps (183 s) still 1.87x (README, "What limits the mean surface's accuracy").

    Attributes
    ----------
    steps : int
        Adam steps of the mean net.
    covariance_every : int
        One covariance step every this many mean steps (``ceil(steps / covariance_every)`` in all). The mean's
        surface needs many steps; a covariance step costs ~5 mean steps, and more of them do not bring the
        variance closer to the GP's: the Dirichlet term fixes only c's mixed derivatives, so with long training the
        variance drifts down everywhere (fandisk, 3000 mean steps, kernel at 2 spacings: Spearman with
        gpytoolbox's SPSR variance 0.72 / 0.76 / 0.67 / 0.24 for a covariance step every 16 / 8 / 4 / 1 steps; at
        1.5 spacings, 4000 steps every 16: 0.781).
    lr : float
        Peak learning rate (cosine decay to ``lr * final_lr_fraction``).
    weight_decay : float
        Adam weight decay (the paper's 1e-5).
    mean_batch : int
        Box samples per step for the mean loss (half uniform, half near the points).
    screen_batch : int
        Cloud points per step for the screening terms.
    pair_clusters, cluster_size : int
        The covariance batch: pair_clusters x cluster_size points, all their ordered pairs.
    screening_weight : float
        lambda_S.
    covariance_screening_weight : float, optional
        lambda_S of the covariance's screening term c(p, p)^2 alone; default ``screening_weight``, as in the paper.
        (The covariance lives at the scale of Sigma h^2, ~1e-4 in the unit cube, so the paper's 100 c(p, p)^2 is
        small beside its Dirichlet term and pins the variance at the points only loosely.)
    refresh : int
        Minibatches in the mean-sample pool (the pool holds ``mean_batch * refresh`` samples).
    pool_passes : int
        Shuffled passes over the mean-sample pool before it is redrawn. GP targets cost ~20 us a sample on this
        CPU (a 256-sample minibatch ~40 % of a step); a pool served several times keeps that cost to a few per cent
        while every pass is still an unbiased Monte-Carlo estimate of the loss (fandisk: 8 passes instead of 4,
        51 s instead of 59 s, Chamfer/diagonal 0.79e-3 vs 0.80e-3).
    pair_pool, pair_reuse : int
        Covariance batches kept in a pool, and how many steps each serves before it is redrawn (same reason).
    average_decay : float
        The mean net ends as an exponential moving average of its weights over the second half of the run
        (:class:`MeanAverager`); 0 keeps the last iterate. Fandisk, Chamfer of the mean surface: 0.00613 -> 0.00577
        (seed 0) and 0.00692 -> 0.00643 (seed 1) with 0.99; 0.995 gave the same as 0.99.
    outside_weight : float
        lambda_O of an optional boundary term lambda_O mean_{x on the box's surface} (g(x) - w)^2, w the value g
        takes outside a closed surface (:meth:`CloudTargets.outside_value`): Poisson reconstruction's Dirichlet
        condition, "the box's boundary is outside". 0 (default) is the paper's loss. Why: a partial scan is an open
        sheet that the paper's loss does not close, so far from the sheet g decays to the average of its inside and
        outside values, 0, and the far field is the surface's own level, half solid (measured on a one-scan
        fandisk field: the median of g on the box's surface 0.000, against +-0.06 one lengthscale off the sheet).
        The term closes the sheet the way Poisson reconstruction does, which next-best-view needs to cast rays
        through empty space.
    """

    steps: int = 4000
    covariance_every: int = 16
    lr: float = 1e-3
    final_lr_fraction: float = 0.05
    weight_decay: float = 1e-5
    mean_batch: int = 256
    screen_batch: int = 256
    pair_clusters: int = 128
    cluster_size: int = 4
    screening_weight: float = SCREENING_WEIGHT
    covariance_screening_weight: Optional[float] = None
    refresh: int = 32
    pool_passes: int = 8
    pair_pool: int = 8
    pair_reuse: int = 4
    average_decay: float = 0.99
    outside_weight: float = 0.0

    def __post_init__(self):
        # one clear error here instead of an empty loop, a zero-size batch or NaN losses deep in training
        counts = {"steps": 1, "covariance_every": 1, "mean_batch": 1, "screen_batch": 1, "pair_clusters": 1,
                  "cluster_size": 2, "refresh": 1, "pool_passes": 1, "pair_pool": 1, "pair_reuse": 1}
        for name, least in counts.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"FitOptions.{name} must be an integer >= {least}, got {value!r}")
        weights = {"lr": self.lr, "final_lr_fraction": self.final_lr_fraction, "weight_decay": self.weight_decay,
                   "screening_weight": self.screening_weight, "outside_weight": self.outside_weight}
        if self.covariance_screening_weight is not None:
            weights["covariance_screening_weight"] = self.covariance_screening_weight
        for name, value in weights.items():
            if not (isinstance(value, (int, float, np.number)) and np.isfinite(value) and value >= 0):
                raise ValueError(f"FitOptions.{name} must be a finite number >= 0, got {value!r}")
        if self.lr == 0:
            raise ValueError("FitOptions.lr must be > 0")
        if not (isinstance(self.average_decay, (int, float, np.number)) and 0 <= self.average_decay < 1):
            raise ValueError(f"FitOptions.average_decay must be in [0, 1), got {self.average_decay!r}")


def even_pool_size(steps, size, passes):
    """Minibatches per mean-sample pool so that the pools a run draws are all used to the end.

    A run of ``steps`` steps needs ``ceil(steps / (size * passes))`` pools of at most ``size`` minibatches, each
    served ``passes`` times; sizing them equally (instead of drawing a last full pool for a few steps) keeps the GP
    target cost at what the steps use. Drawing one minibatch's targets costs about a quarter of a step.

    Parameters
    ----------
    steps, size, passes : int

    Returns
    -------
    int
        Between 1 and ``size``.
    """
    steps, size, passes = max(1, int(steps)), max(1, int(size)), max(1, int(passes))
    pools = math.ceil(steps / (size * passes))
    return max(1, min(size, math.ceil(steps / (pools * passes))))


def _cosine_lr(step, total, fraction):
    return fraction + (1 - fraction) * 0.5 * (1 + np.cos(np.pi * min(step / max(total, 1), 1.0)))


class MeanPool:
    """Mean-loss samples drawn ``batch * refresh`` at a time, served in shuffled minibatches for ``passes``
    passes, then redrawn.

    Parameters
    ----------
    targets : CloudTargets
    batch : int
        Minibatch size.
    refresh : int
        Minibatches per pool.
    rng : numpy.random.Generator
    passes : int
        Passes over one pool before a new one is drawn.
    """

    def __init__(self, targets, batch, refresh, rng, passes=1):
        self.targets, self.batch, self.refresh, self.rng, self.passes = targets, batch, refresh, rng, passes
        self.served = refresh
        self.pass_count = passes

    def next(self):
        """One minibatch: x (batch, 3), mu (batch, 3), omega (batch,) float32 tensors."""
        if self.served >= self.refresh:
            if self.pass_count >= self.passes:
                x, mu, omega = self.targets.mean_batch(self.batch * self.refresh, self.rng)
                self.x, self.mu, self.omega = map(torch.from_numpy, (x, mu, omega))
                self.pass_count = 0
            self.order = torch.from_numpy(self.rng.permutation(len(self.x)))
            self.pass_count += 1
            self.served = 0
        idx = self.order[self.served * self.batch:(self.served + 1) * self.batch]
        self.served += 1
        return self.x[idx], self.mu[idx], self.omega[idx]


class PairPool:
    """A round-robin pool of ``size`` covariance batches, each redrawn after it has served ``reuse`` steps.

    Parameters
    ----------
    targets : CloudTargets
    n_clusters, cluster_size : int
        Shape of one batch (see :meth:`CloudTargets.pair_batch`).
    rng : numpy.random.Generator
    size, reuse : int
    """

    def __init__(self, targets, n_clusters, cluster_size, rng, size=8, reuse=4):
        self.targets, self.n_clusters, self.cluster_size, self.rng = targets, n_clusters, cluster_size, rng
        self.size, self.reuse = max(1, size), max(1, reuse)
        self.batches = [None] * self.size
        self.uses = [self.reuse] * self.size
        self.count = 0

    def next(self):
        """x (m, 3), sigma (m, m), weights (m, m) float32 tensors."""
        slot = self.count % self.size
        self.count += 1
        if self.uses[slot] >= self.reuse:
            batch = self.targets.pair_batch(self.n_clusters, self.cluster_size, self.rng)
            self.batches[slot] = tuple(map(torch.from_numpy, batch))
            self.uses[slot] = 0
        self.uses[slot] += 1
        return self.batches[slot]


class MeanAverager:
    """Exponential moving average of a net's weights over the second half of a run, copied into the net at the end.

    The last iterate of a stochastic run carries the noise of its last minibatches: on fandisk the mean surface's
    offset from the true surface is smooth over about one kernel lengthscale, the signature of that noise. An
    average of the late iterates removes part of it at the cost of one in-place lerp per step.

    Averaging starts at ``start`` (earlier iterates are far from the final one) with the warm-up decay
    ``min(decay, (1 + k) / (10 + k))`` after k averaged steps, so that a short run (a fine-tune of a few steps)
    is averaged over its own last steps, not pinned to its first.

    Parameters
    ----------
    net : torch.nn.Module
    decay : float
        0 switches averaging off.
    start : int
        First step averaged.
    """

    def __init__(self, net, decay, start):
        self.params, self.decay, self.start = list(net.parameters()), float(decay), int(start)
        self.average = None
        self.count = 0

    def update(self, step):
        if self.decay <= 0 or step < self.start:
            return
        with torch.no_grad():
            if self.average is None:
                self.average = [p.detach().clone() for p in self.params]
            else:
                decay = min(self.decay, (1 + self.count) / (10 + self.count))
                for avg, p in zip(self.average, self.params):
                    avg.lerp_(p, 1 - decay)
        self.count += 1

    def apply(self):
        """Copy the average into the net (no-op when nothing was averaged)."""
        if self.average is None:
            return
        with torch.no_grad():
            for p, avg in zip(self.params, self.average):
                p.copy_(avg)


def mean_step_loss(mean_net, targets, pool, options, rng, code=None):
    """Dirichlet + screening loss of the mean net on one batch; returns (total, dirichlet, screening).

    With ``options.outside_weight`` the boundary term (the box's surface screened to the outside value) is part of
    the returned screening."""
    x, mu, omega = pool.next()
    _, grad = mean_net.value_and_gradient(x, code)
    dirichlet = mean_dirichlet_loss(grad, mu, omega, targets.box.volume)
    screen_pts = torch.from_numpy(targets.screen_batch(options.screen_batch, rng))
    screening = screening_loss(mean_net(screen_pts, code), options.screening_weight)
    if options.outside_weight > 0:
        boundary = torch.from_numpy(targets.boundary_batch(options.screen_batch, rng))
        screening = screening + screening_loss(mean_net(boundary, code) - targets.outside_value(),
                                               options.outside_weight)
    return dirichlet + screening, dirichlet, screening


def covariance_step_loss(cov_net, targets, options, rng, code=None, pairs=None):
    """Dirichlet + screening loss of the covariance net on one batch; returns (total, dirichlet, screening).

    ``pairs`` is a :class:`PairPool` to draw the batch from (default: a fresh batch from ``targets``)."""
    if pairs is None:
        x, sigma, weights = map(torch.from_numpy,
                                targets.pair_batch(options.pair_clusters, options.cluster_size, rng))
    else:
        x, sigma, weights = pairs.next()
    if cov_net.kind == "feature":
        _, jac = cov_net.features_and_jacobian(x, code)
        dirichlet = covariance_dirichlet_loss_features(jac.unsqueeze(0), sigma.unsqueeze(0), weights.unsqueeze(0))
    else:
        i, j, keep_factor = _pair_subset(len(weights), options.cluster_size, rng)
        keep_weight = weights[i, j] * keep_factor
        d_c = cov_net.d_operator(x[i], x[j], code)
        dirichlet = covariance_dirichlet_loss_pairs(d_c, sigma[i, j], keep_weight)
    screen_pts = torch.from_numpy(targets.screen_batch(options.screen_batch, rng))
    weight = options.screening_weight if options.covariance_screening_weight is None \
        else options.covariance_screening_weight
    screening = screening_loss(cov_net.variance(screen_pts, code), weight)
    return dirichlet + screening, dirichlet, screening


def _pair_subset(m, cluster_size, rng):
    """The pairs the paper's pair network is evaluated on (it costs one evaluation per pair, unlike the feature net):
    every within-cluster ordered pair of the m clustered points plus as many cross-cluster pairs drawn uniformly.

    Returns
    -------
    i, j : (P,) int arrays
        Row and column of each kept pair in the (m, m) weight matrix.
    keep_factor : (P,) float32 tensor
        1 for within-cluster pairs, n_cross / n_cross_kept for the sampled cross pairs: multiplying their weights by
        it keeps the loss an unbiased estimate of the sum over all pairs.
    """
    cluster = np.arange(m) // cluster_size
    ii, jj = np.nonzero((cluster[:, None] == cluster[None, :]) & ~np.eye(m, dtype=bool))
    ci, cj = rng.integers(0, m, 4 * len(ii)), rng.integers(0, m, 4 * len(ii))
    cross = cluster[ci] != cluster[cj]
    ci, cj = ci[cross][: len(ii)], cj[cross][: len(ii)]
    keep_factor = np.ones(len(ii) + len(ci), dtype=np.float32)
    keep_factor[len(ii):] = (m * m - m * cluster_size) / max(len(ci), 1)
    return np.concatenate([ii, ci]), np.concatenate([jj, cj]), torch.from_numpy(keep_factor)


def fit_cloud(points, normals, *, seed=0, lengthscale=None, noise=None, width=64, depth=3,
              covariance="feature", features=128, omega0=30.0, options=None, quiet=False, representation="siren",
              **option_overrides):
    """Fit a stochastic implicit surface f ~ N(g, c) to an oriented point cloud (NSSPR).

    The cloud is normalised into the unit cube (the transform is kept in the field), the GP posterior targets are
    built with a KD-tree, and the mean and covariance nets are trained with Adam.

    Parameters
    ----------
    points : (n, 3) array
        Point positions (any units).
    normals : (n, 3) array
        Outward normals (normalised here).
    seed : int
        Seeds every random draw and the network initialisation.
    lengthscale : float, optional
        Kernel lengthscale in the cloud's units (default: 1.5 x the point spacing, ``FIT_LENGTHSCALE_FACTOR`` of
        ``autodecoder.targets``, where it is measured; see also ``default_lengthscale``).
    noise : float, optional
        Default measurement noise (cloud units) of :meth:`StochasticField.nll`; default: the RMS of the fitted
        mean at the cloud's points (how far the surface misses them).
    width, depth : int
        SIREN size of both nets (the paper's is 512 x 5; 64 x 3 measured best for time on 2 cores, see
        :class:`FitOptions`).
    covariance : {'feature', 'pair'}
        Covariance architecture: a feature map phi(a).phi(b) (default, far cheaper) or the paper's symmetrised
        SoftPlus pair network.
    features : int
        Rank of the feature covariance.
    omega0 : float
        SIREN first-layer frequency.
    options : FitOptions, optional
    quiet : bool
        No progress bar.
    representation : {'siren', 'grid'}
        'grid': :func:`autodecoder.grid_fit.fit_grid_cloud` (B-spline grids, the mean solved on its grid; its own
        lengthscale default and options, :class:`autodecoder.grid_fit.GridFitOptions`, given as ``options`` or
        ``option_overrides``; the SIREN arguments do not apply).
    **option_overrides
        Any :class:`FitOptions` field (e.g. ``steps=500``).

    Returns
    -------
    StochasticField
    """
    if representation == "grid":
        from .grid_fit import fit_grid_cloud

        return fit_grid_cloud(points, normals, seed=seed, lengthscale=lengthscale, noise=noise, options=options,
                              **option_overrides)
    if representation != "siren":
        raise ValueError(f"representation must be 'siren' or 'grid', got {representation!r}")
    points, normals = check_oriented_cloud(points, normals)
    options = FitOptions(**{**asdict(options or FitOptions()), **option_overrides})
    t0 = time.perf_counter()
    normalization = Normalization.fit(points)
    model_points = normalization.to_model(points)
    h = (default_lengthscale(model_points, FIT_LENGTHSCALE_FACTOR) if lengthscale is None
         else float(lengthscale) * normalization.scale)
    targets = CloudTargets(model_points, normals, h)
    config = {"width": width, "depth": depth, "latent_dim": 0, "covariance": covariance, "features": features,
              "omega0": omega0, "lengthscale": h, "box_lo": targets.box.lo.tolist(), "box_hi": targets.box.hi.tolist()}

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    mean_net, cov_net = build_networks(config)
    history = train_single(mean_net, cov_net, targets, options, rng, quiet=quiet)

    with torch.no_grad():
        residual = mean_net(torch.from_numpy(targets.points32)).double().numpy() / normalization.scale
    if noise is None:
        noise = float(np.sqrt(np.mean(residual**2)))
    info = {"fit_seconds": time.perf_counter() - t0, "steps": options.steps, "n_points": len(points),
            "final_losses": history[-1] if history else {}, "options": asdict(options),
            "history": history}
    # the field keeps its cloud (world frame) so that field.update() can fine-tune on old + new scans
    return StochasticField(mean_net, cov_net, normalization, config, noise=noise, info=info,
                           training_points=points, training_normals=normals)


def _adam(parameters, options):
    # the fused kernel updates all tensors in one call: ~10 % of a small step's time goes to the per-tensor loop
    return torch.optim.Adam(parameters, lr=options.lr, weight_decay=options.weight_decay, fused=True)


def train_single(mean_net, cov_net, targets, options, rng, quiet=False, steps=None, code=None):
    """Train both nets on one cloud's targets; returns the loss history (a dict per logged step)."""
    steps = options.steps if steps is None else steps
    mean_net.train(), cov_net.train()
    opt_mean = _adam(mean_net.parameters(), options)
    opt_cov = _adam(cov_net.parameters(), options)
    # target pools sized to this run: a short run (a fine-tune) must not draw targets it never uses
    refresh = even_pool_size(steps, options.refresh, options.pool_passes)
    pool = MeanPool(targets, options.mean_batch, refresh, rng, passes=options.pool_passes)
    every = options.covariance_every
    cov_steps = math.ceil(steps / every)
    pair_slots = max(1, min(options.pair_pool, math.ceil(cov_steps / options.pair_reuse)))
    pairs = PairPool(targets, options.pair_clusters, options.cluster_size, rng, pair_slots, options.pair_reuse)
    history = []
    averaging = MeanAverager(mean_net, options.average_decay, start=steps // 2)
    bar = tqdm(range(steps), desc="fitting", disable=quiet, leave=False)
    for step in bar:
        lr = options.lr * _cosine_lr(step, steps, options.final_lr_fraction)
        for opt in (opt_mean, opt_cov):
            for group in opt.param_groups:
                group["lr"] = lr
        total_m, dir_m, scr_m = mean_step_loss(mean_net, targets, pool, options, rng, code)
        opt_mean.zero_grad(set_to_none=True)
        total_m.backward()
        opt_mean.step()
        averaging.update(step)
        if step % every == 0:
            total_c, dir_c, scr_c = covariance_step_loss(cov_net, targets, options, rng, code, pairs)
            opt_cov.zero_grad(set_to_none=True)
            total_c.backward()
            opt_cov.step()
        if step % 10 == 0 or step == steps - 1:
            record = {"step": step, "mean_dirichlet": dir_m.item(), "mean_screening": scr_m.item(),
                      "cov_dirichlet": dir_c.item(), "cov_screening": scr_c.item()}
            history.append(record)
            bar.set_postfix(mean=f"{total_m.item():.3g}", cov=f"{total_c.item():.3g}")
    averaging.apply()
    mean_net.eval(), cov_net.eval()
    return history
