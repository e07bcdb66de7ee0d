"""The pieces of one optimisation step shared by every single-cloud fit (SIREN and grid): target pools sized to
the run, the late-iterate weight average, and the mean and covariance losses of a step."""
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
from torch.optim.swa_utils import AveragedModel

from autodecoder.field.losses import (SCREENING_WEIGHT, covariance_dirichlet_loss_features,
                                      covariance_dirichlet_loss_pairs, mean_dirichlet_loss, screening_loss)


@dataclass
class StepOptions:
    """The sampling, averaging and loss settings every single-cloud fit shares (:class:`autodecoder.field.fit.FitOptions`,
    :class:`autodecoder.field.grid_fit.GridFitOptions`); each subclass adds its own steps and rates.

    Attributes
    ----------
    final_lr_fraction : float
        Cosine decay of the learning rates to this fraction of their peak (:func:`autodecoder.field.schedule.cosine_decay`).
    weight_decay : float
        Adam weight decay (each fit sets its own default).
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
        Shuffled passes over the mean-sample pool before it is redrawn. GP targets are a large share of a small
        step's cost; a pool served several times keeps that cost to a few per cent while every pass is still an
        unbiased Monte-Carlo estimate of the loss (docs/results.md#single-cloud-fit-defaults-fandisk).
    pair_pool, pair_reuse : int
        Covariance batches kept in a pool, and how many steps each serves before it is redrawn (same reason).
    average_decay : float
        The mean net ends as an exponential moving average of its weights over the second half of the run
        (:class:`MeanAverager`); 0 keeps the last iterate. 0.99 lowered fandisk's surface error on every seed
        tried; 0.995 did no better (docs/results.md#single-cloud-fit-defaults-fandisk).
    outside_weight : float
        lambda_O of an optional boundary term lambda_O mean_{x on the box's surface} (g(x) - w)^2, w the value g
        takes outside a closed surface (:meth:`CloudTargets.outside_value`): Poisson reconstruction's Dirichlet
        condition, "the box's boundary is outside". 0 (default) is the paper's loss. Why: a partial scan is an open
        sheet that the paper's loss does not close, so far from the sheet g decays to the average of its inside and
        outside values, 0, and the far field is the surface's own level, half solid (on a one-scan fandisk field
        the median of g on the box's surface is 0: docs/results.md#scanning-partial-scan-fields-and-next-best-view).
        The term closes the sheet the way Poisson reconstruction does, which next-best-view needs to cast rays
        through empty space.
    """

    final_lr_fraction: float = 0.05
    weight_decay: float = 0.0
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

    def _integers(self):
        """{name: least value} of the subclass's own integer settings."""
        return {}

    def _rates(self):
        """{name: value} of the subclass's own non-negative numbers (and any further check of them)."""
        return {}

    def __post_init__(self):
        # one clear error here instead of an empty loop, a zero-size batch or NaN losses deep in training
        kind = type(self).__name__
        counts = {**self._integers(), "mean_batch": 1, "screen_batch": 1, "pair_clusters": 1, "cluster_size": 2,
                  "refresh": 1, "pool_passes": 1, "pair_pool": 1, "pair_reuse": 1}
        for name, least in counts.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"{kind}.{name} must be an integer >= {least}, got {value!r}")
        weights = {**self._rates(), "final_lr_fraction": self.final_lr_fraction, "weight_decay": self.weight_decay,
                   "screening_weight": self.screening_weight, "outside_weight": self.outside_weight}
        if self.covariance_screening_weight is not None:
            weights["covariance_screening_weight"] = self.covariance_screening_weight
        for name, value in weights.items():
            if not (isinstance(value, (int, float, np.number)) and np.isfinite(value) and value >= 0):
                raise ValueError(f"{kind}.{name} must be a finite number >= 0, got {value!r}")
        if not (isinstance(self.average_decay, (int, float, np.number)) and 0 <= self.average_decay < 1):
            raise ValueError(f"{kind}.average_decay must be in [0, 1), got {self.average_decay!r}")


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
    average of the late iterates removes part of it at the cost of one in-place lerp per step
    (``torch.optim.swa_utils.AveragedModel`` with this schedule as its ``avg_fn``).

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
        self.net, self.decay, self.start = net, float(decay), int(start)
        self._averaged = None  # torch.optim.swa_utils.AveragedModel, made at the first averaged step

    def _ema(self, average, current, n_averaged):
        # n_averaged: steps averaged before this one (>= 1); the warm-up decay of the class docstring
        decay = min(self.decay, (1 + float(n_averaged)) / (10 + float(n_averaged)))
        return average.lerp_(current, 1 - decay)

    def update(self, step):
        if self.decay <= 0 or step < self.start:
            return
        if self._averaged is None:  # copies the net: the first averaged step is the average
            self._averaged = AveragedModel(self.net, avg_fn=self._ema, use_buffers=False)
        self._averaged.update_parameters(self.net)

    @property
    def average(self):
        """The averaged parameters (list of tensors, the net's order), or None before the first averaged step."""
        return None if self._averaged is None else list(self._averaged.module.parameters())

    def apply(self):
        """Copy the average into the net (no-op when nothing was averaged)."""
        if self._averaged is None:
            return
        with torch.no_grad():
            for p, avg in zip(self.net.parameters(), self._averaged.module.parameters()):
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


def residual_noise(mean_net, targets, frame, code=None):
    """RMS of the fitted mean at the cloud's own points, world units: how far the surface misses them (a fit's
    default measurement noise)."""
    with torch.no_grad():
        residual = mean_net(torch.from_numpy(targets.points32), code).double().numpy() / frame.scale
    return float(np.sqrt(np.mean(residual**2)))
