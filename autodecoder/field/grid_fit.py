"""fit_grid_cloud: neural stochastic screened Poisson reconstruction of one oriented cloud on B-spline grids.

The targets, losses and field are those of :func:`autodecoder.field.fit.fit_cloud`; the networks are the grid networks
of :mod:`autodecoder.field.grid_networks`. The mean loss is a quadratic in the grid mean's control values, so the mean is
started at the loss's exact minimiser on a grid (:func:`autodecoder.field.grid_minimiser.grid_minimiser`, conjugate
gradients), interpolated by the finest level's cubic B-spline; optional Adam steps then fine-tune it on the
paper's Monte-Carlo loss. The covariance's feature grids are trained by Adam on the paper's covariance loss.
"""
import math
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch

from autodecoder.field.stochastic_field import StochasticField
from autodecoder.field.steps import (MeanAverager, MeanPool, PairPool, StepOptions, covariance_step_loss,
                                     even_pool_size, mean_step_loss, residual_noise)
from autodecoder.field.grid_minimiser import grid_minimiser
from autodecoder.field.grid_networks import GRID_REPRESENTATION, BSplineGrid, build_grid_networks
from autodecoder.field.schedule import cosine_decay
from autodecoder.field.targets import cloud_frame_and_targets
from datasets.validation import check_oriented_cloud

# Kernel lengthscale / point spacing of the grid fit. The grid mean follows the sharper posterior mean of a
# smaller kernel, which the SIREN's 4000 steps could not (fit_cloud uses 1.5); see docs/results.md.
GRID_LENGTHSCALE_FACTOR = 1.0


@dataclass
class GridFitOptions(StepOptions):
    """Settings of :func:`fit_grid_cloud` (field names shared with :class:`autodecoder.field.fit.FitOptions` mean the
    same; the step helpers of :mod:`autodecoder.field.steps` read them).

    Attributes
    ----------
    solve : bool
        Start the mean at the loss's grid minimiser (else at 0).
    solve_tol : float
        Relative residual of the conjugate gradients.
    mean_steps : int
        Adam steps of the mean on the paper's Monte-Carlo loss after the solve (0: none). A few hundred small
        steps bring the surface slightly closer; many more, or larger ones, take it further away again, as the
        stochastic gradients' noise on control values that samples rarely visit accumulates (docs/results.md).
    mean_lr : float
        Their peak learning rate.
    cov_steps : int
        Adam steps of the covariance.
    cov_lr : float
        Their peak learning rate.
    final_lr_fraction : float
        Cosine decay of both learning rates to this fraction.
    weight_decay : float
        Adam weight decay of decoder weights (never of grid control values, see :func:`_optimisers`).
    mean_batch, screen_batch, pair_clusters, cluster_size, screening_weight, covariance_screening_weight, refresh,
    pool_passes, pair_pool, pair_reuse, average_decay, outside_weight
        See :class:`autodecoder.field.steps.StepOptions`.
    """

    solve: bool = True
    solve_tol: float = 1e-6
    mean_steps: int = 300
    mean_lr: float = 1e-5
    cov_steps: int = 250
    cov_lr: float = 1e-3

    def _integers(self):
        return {"mean_steps": 0, "cov_steps": 0}

    def _rates(self):
        return {"mean_lr": self.mean_lr, "cov_lr": self.cov_lr, "solve_tol": self.solve_tol}


def _optimisers(net, lr, weight_decay):
    """Adam over the grid control values (no weight decay) and over the rest (decoder weights).

    No weight decay on control values: Adam normalises every gradient, so the decay's gradient on a control value
    that no sample touched would become a full-size step toward 0 at every step, erasing the fine levels between
    visits.
    """
    grids = [m.values for m in net.modules() if isinstance(m, BSplineGrid)]
    ids = {id(p) for p in grids}
    others = [p for p in net.parameters() if id(p) not in ids]
    groups = [{"params": grids, "weight_decay": 0.0}]
    if others:
        groups.append({"params": others, "weight_decay": weight_decay})
    return torch.optim.Adam(groups, lr=lr, fused=True)


def _run_adam(net, steps, peak_lr, options, loss_fn, averager=None):
    """``steps`` Adam steps of ``loss_fn()`` (returns total, dirichlet, screening); returns the logged losses."""
    if steps == 0 or peak_lr == 0:
        return []
    net.train()
    opt = _optimisers(net, peak_lr, options.weight_decay)
    history = []
    for step in range(steps):
        for group in opt.param_groups:
            group["lr"] = peak_lr * cosine_decay(step, steps, options.final_lr_fraction)
        total, dirichlet, screening = loss_fn()
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()
        if averager is not None:
            averager.update(step)
        if step % 10 == 0 or step == steps - 1:
            history.append({"step": step, "dirichlet": dirichlet.item(), "screening": screening.item()})
    if averager is not None:
        averager.apply()
    net.eval()
    return history


def train_grid(mean_net, cov_net, targets, options, rng, code=None):
    """The mean's fine-tuning steps, then the covariance's, on one cloud's targets.

    Parameters
    ----------
    mean_net : GridMeanNet
    cov_net : GridCovarianceNet
    targets : CloudTargets
    options : GridFitOptions
    rng : numpy.random.Generator
    code : tensor, optional

    Returns
    -------
    dict
        ``mean`` and ``cov``: lists of logged losses.
    """
    refresh = even_pool_size(max(options.mean_steps, 1), options.refresh, options.pool_passes)
    pool = MeanPool(targets, options.mean_batch, refresh, rng, passes=options.pool_passes)
    averager = MeanAverager(mean_net, options.average_decay, start=options.mean_steps // 2)
    mean_history = _run_adam(mean_net, options.mean_steps, options.mean_lr, options,
                             lambda: mean_step_loss(mean_net, targets, pool, options, rng, code), averager)
    slots = max(1, min(options.pair_pool, math.ceil(options.cov_steps / options.pair_reuse)))
    pairs = PairPool(targets, options.pair_clusters, options.cluster_size, rng, slots, options.pair_reuse)
    cov_history = _run_adam(cov_net, options.cov_steps, options.cov_lr, options,
                            lambda: covariance_step_loss(cov_net, targets, options, rng, code, pairs))
    mean_net.eval(), cov_net.eval()
    return {"mean": mean_history, "cov": cov_history}


def solve_mean(mean_net, targets, tol=1e-6):
    """Set the grid mean to the mean loss's minimiser on its finest level's nodes; returns the solver's info.

    The minimiser is computed on the (cells + 1)^3 nodes of the finest level (:func:`grid_minimiser`), and that
    level's B-spline is made to interpolate it (:meth:`BSplineGrid.set_from_nodes`); the other levels are zeroed.
    Only for a mean without decoder (``mean_net.decoder is None``) over a cubic box.
    """
    if mean_net.decoder is not None:
        raise ValueError("solve_mean needs a summed grid mean (no decoder): a decoded mean is not linear in the grids")
    with torch.no_grad():
        for level in mean_net.encoder.levels:
            level.values.zero_()
    return _solve_level(mean_net.encoder.levels[-1], targets, tol)


def solve_shared(mean_net, targets, tol=1e-6):
    """Set a decoded grid mean's shared level s(x) (``GridMeanNet(shared_cells > 0)``) to the mean loss's minimiser
    for ``targets`` on its nodes; returns the solver's info.

    In a latent model ``targets`` are those of the union of the training scans: s is then the field every code
    shares, and the decoder starts as a small correction of it.
    """
    if getattr(mean_net, "shared", None) is None:
        raise ValueError("solve_shared needs a grid mean with a shared level (shared_cells > 0)")
    return _solve_level(mean_net.shared, targets, tol)


def _solve_level(level, targets, tol):
    """Make the B-spline ``level`` interpolate the minimiser of ``targets``' mean loss on its nodes."""
    extent = targets.box.hi - targets.box.lo
    if not np.allclose(extent, extent[0], rtol=1e-6):
        raise ValueError(f"the grid solve needs a cubic box, got extents {extent.tolist()}")
    nodes, lo, _, info = grid_minimiser(targets, level.cells + 1, tol=tol)
    if not np.allclose(lo, level.lo.double().numpy(), atol=1e-6):
        raise ValueError("the grid mean's box is not the targets' box")
    level.set_from_nodes(nodes)
    return info


def fit_grid_cloud(points, normals, *, seed=0, lengthscale=None, noise=None, grid_mean=None, grid_cov=None,
                   options=None, **option_overrides):
    """Fit a stochastic implicit surface f ~ N(g, c) to an oriented point cloud with grid networks.

    Parameters
    ----------
    points, normals : (n, 3) arrays
        The oriented cloud (any units; normals outward, normalised here).
    seed : int
        Seeds every random draw and the initial grids.
    lengthscale : float, optional
        Kernel lengthscale in the cloud's units (default: ``GRID_LENGTHSCALE_FACTOR`` point spacings).
    noise : float, optional
        Default measurement noise of :meth:`StochasticField.nll` (default: the RMS of the mean at the points).
    grid_mean, grid_cov : dict, optional
        Overrides of :data:`autodecoder.field.grid_networks.MEAN_DEFAULTS` / ``COV_DEFAULTS``.
    options : GridFitOptions, optional
    **option_overrides
        Any :class:`GridFitOptions` field.

    Returns
    -------
    StochasticField
        Its ``config["representation"]`` is ``"grid"``; ``info`` holds the fit time and the solver's figures.
    """
    points, normals = check_oriented_cloud(points, normals)
    if options is not None and not isinstance(options, GridFitOptions):
        raise TypeError(f"options of a grid fit must be GridFitOptions, got {type(options).__name__}")
    options = GridFitOptions(**{**asdict(options or GridFitOptions()), **option_overrides})
    t0 = time.perf_counter()
    frame, targets = cloud_frame_and_targets(points, normals, lengthscale, GRID_LENGTHSCALE_FACTOR)
    h = targets.lengthscale
    config = {"representation": GRID_REPRESENTATION, "latent_dim": 0, "covariance": "feature",
              "grid_mean": dict(grid_mean or {}), "grid_cov": dict(grid_cov or {}), "lengthscale": h,
              "box_lo": targets.box.lo.tolist(), "box_hi": targets.box.hi.tolist()}
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    mean_net, cov_net = build_grid_networks({**config, "grid_mean": {"seed": seed, **config["grid_mean"]},
                                             "grid_cov": {"seed": seed + 1, **config["grid_cov"]}})
    t1 = time.perf_counter()
    solve_info = solve_mean(mean_net, targets, options.solve_tol) if options.solve else {}
    t2 = time.perf_counter()
    history = train_grid(mean_net, cov_net, targets, options, rng)
    if noise is None:
        noise = residual_noise(mean_net, targets, frame)
    info = {"fit_seconds": time.perf_counter() - t0, "solve_seconds": t2 - t1,
            "train_seconds": time.perf_counter() - t2, "solve": solve_info, "n_points": len(points),
            "steps": options.mean_steps + options.cov_steps, "options": asdict(options), "history": history}
    return StochasticField(mean_net, cov_net, frame, config, noise=noise, info=info,
                           training_points=points, training_normals=normals)
