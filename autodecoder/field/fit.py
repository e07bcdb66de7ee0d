"""fit_cloud: neural stochastic screened Poisson reconstruction of one oriented point cloud."""
import math
import time
from dataclasses import asdict, dataclass, fields

import numpy as np
import torch
from tqdm.auto import tqdm

from autodecoder.field.stochastic_field import StochasticField
from autodecoder.field.grid_fit import GridFitOptions, fit_grid_cloud
from autodecoder.field.networks import build_networks
from autodecoder.field.schedule import cosine_decay
from autodecoder.field.steps import (MeanAverager, MeanPool, PairPool, StepOptions, covariance_step_loss,
                                     even_pool_size, mean_step_loss, residual_noise)
from autodecoder.field.targets import FIT_LENGTHSCALE_FACTOR, cloud_frame_and_targets
from datasets.validation import check_oriented_cloud


@dataclass
class FitOptions(StepOptions):
    """Optimisation settings of :func:`fit_cloud` (defaults chosen for time and accuracy on a 2-core CPU).

    Why many small steps: the error of the mean surface falls with the number of Adam steps far more than with the
    batch, and width 64 does as well as 128 at equal steps; a step of width 64 on 256 samples is mostly
    per-operation overhead, so many such steps fit in the time of a few large ones. A covariance step costs several
    mean steps, so one every 16 buys more mean steps in the same time without a worse variance. What limits the
    accuracy is this training, not the loss: the loss's exact minimiser on a grid
    (:func:`autodecoder.field.grid_minimiser.grid_minimiser`) is much closer to open3d's reconstruction than the fit.
    Figures: docs/results.md#single-cloud-fit-defaults-fandisk and #what-limits-the-mean-surface
    (``python -m benchmarks fit --mode grid --variants ...``, ``fit --mode target-limit``).

    Attributes
    ----------
    steps : int
        Adam steps of the mean net.
    covariance_every : int
        One covariance step every this many mean steps (``ceil(steps / covariance_every)`` in all). The mean's
        surface needs many steps; a covariance step costs several mean steps, and more of them do not bring the
        variance closer to the GP's: the Dirichlet term fixes only c's mixed derivatives, so with long training the
        variance drifts down everywhere (docs/results.md#single-cloud-fit-defaults-fandisk).
    lr : float
        Peak learning rate (cosine decay to ``lr * final_lr_fraction``).
    weight_decay : float
        Adam weight decay (the paper's 1e-5).
    final_lr_fraction, mean_batch, screen_batch, pair_clusters, cluster_size, screening_weight,
    covariance_screening_weight, refresh, pool_passes, pair_pool, pair_reuse, average_decay, outside_weight
        See :class:`autodecoder.field.steps.StepOptions`.
    """

    steps: int = 4000
    covariance_every: int = 16
    lr: float = 1e-3
    weight_decay: float = 1e-5

    def _integers(self):
        return {"steps": 1, "covariance_every": 1}

    def _rates(self):
        if self.lr == 0:
            raise ValueError("FitOptions.lr must be > 0")
        return {"lr": self.lr}


# The SIREN settings of fit_cloud and their defaults (representation="siren"); a grid fit refuses them.
SIREN_DEFAULTS = {"width": 64, "depth": 3, "covariance": "feature", "features": 128, "omega0": 30.0}


def fit_cloud(points, normals, *, seed=0, lengthscale=None, noise=None, width=None, depth=None,
              covariance=None, features=None, omega0=None, options=None, quiet=False, representation="grid",
              **option_overrides):
    """Fit a stochastic implicit surface f ~ N(g, c) to an oriented point cloud (NSSPR).

    The cloud is normalised into the unit cube (the transform is kept in the field) and the GP posterior targets are
    built with a KD-tree. The default representation is B-spline grids
    (:func:`autodecoder.field.grid_fit.fit_grid_cloud`: the mean solved exactly on its grid, then briefly fine-tuned,
    the covariance trained with Adam); the paper's SIRENs (``representation="siren"``) are trained with Adam from
    scratch. On fandisk, the Stanford bunny and a thin-walled enclosure the grid's mean surface is 1.7-3x closer to the
    true surface, and its variance follows gpytoolbox's stochastic Poisson reconstruction
    more closely (docs/results.md#the-single-cloud-fits-default-representation-issue-19). The SIREN remains for the
    boundary term ``outside_weight`` (partial scans for view planning), which the grid's solve does not have.

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
        ``autodecoder.field.targets``, where the choice is explained; see also ``default_lengthscale``).
    noise : float, optional
        Default measurement noise (cloud units) of :meth:`StochasticField.nll`; default: the RMS of the fitted
        mean at the cloud's points (how far the surface misses them).
    width, depth : int, optional
        SIREN only: size of both nets (default 64 x 3, the best for time on 2 cores, see :class:`FitOptions`; the
        paper's is 512 x 5).
    covariance : {'feature', 'pair'}, optional
        SIREN only: a feature map phi(a).phi(b) (default, far cheaper) or the paper's symmetrised SoftPlus pair
        network.
    features : int, optional
        SIREN only: rank of the feature covariance (default 128).
    omega0 : float, optional
        SIREN only: first-layer frequency (default 30).
    options : GridFitOptions or FitOptions, optional
        The representation's options (:class:`autodecoder.field.grid_fit.GridFitOptions` for grids,
        :class:`FitOptions` for SIRENs).
    quiet : bool
        No progress bar.
    representation : {'grid', 'siren'}
        'grid' (default): :func:`autodecoder.field.grid_fit.fit_grid_cloud`, with its own lengthscale default (1
        point spacing against the SIREN's 1.5). 'siren': the paper's networks.
    **option_overrides
        Any field of the representation's options (e.g. ``cov_steps=500`` for grids, ``steps=500`` for SIRENs).

    Returns
    -------
    StochasticField
    """
    siren = {"width": width, "depth": depth, "covariance": covariance, "features": features, "omega0": omega0}
    if representation == "grid":
        given = sorted(k for k, v in siren.items() if v is not None)
        if given:
            raise ValueError(f"{', '.join(given)} {'is a SIREN setting' if len(given) == 1 else 'are SIREN settings'}"
                             f": pass representation='siren' (the default representation is 'grid')")
        return _fit_grid(points, normals, seed, lengthscale, noise, options, option_overrides)
    if representation != "siren":
        raise ValueError(f"representation must be 'grid' or 'siren', got {representation!r}")
    width, depth, covariance, features, omega0 = (SIREN_DEFAULTS[k] if v is None else v for k, v in siren.items())
    points, normals = check_oriented_cloud(points, normals)
    if options is not None and not isinstance(options, FitOptions):
        raise TypeError(f"options of a SIREN fit must be FitOptions, got {type(options).__name__}")
    options = FitOptions(**{**asdict(options or FitOptions()), **option_overrides})
    t0 = time.perf_counter()
    frame, targets = cloud_frame_and_targets(points, normals, lengthscale, FIT_LENGTHSCALE_FACTOR)
    h = targets.lengthscale
    config = {"width": width, "depth": depth, "latent_dim": 0, "covariance": covariance, "features": features,
              "omega0": omega0, "lengthscale": h, "box_lo": targets.box.lo.tolist(), "box_hi": targets.box.hi.tolist()}

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    mean_net, cov_net = build_networks(config)
    history = train_single(mean_net, cov_net, targets, options, rng, quiet=quiet)

    if noise is None:
        noise = residual_noise(mean_net, targets, frame)
    info = {"fit_seconds": time.perf_counter() - t0, "steps": options.steps, "n_points": len(points),
            "final_losses": history[-1] if history else {}, "options": asdict(options),
            "history": history}
    # the field keeps its cloud (world frame) so that autodecoder.scanning.update_field can fine-tune on old + new scans
    return StochasticField(mean_net, cov_net, frame, config, noise=noise, info=info,
                           training_points=points, training_normals=normals)


def _adam(parameters, options):
    # the fused kernel updates all tensors in one call: the per-tensor loop is a visible share of a small step's time
    # (docs/results.md#single-cloud-fit-defaults-fandisk)
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
        lr = options.lr * cosine_decay(step, steps, options.final_lr_fraction)
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


def _fit_grid(points, normals, seed, lengthscale, noise, options, option_overrides):
    """fit_cloud's grid branch: options checked against GridFitOptions with an error that says what to do."""
    known = {f.name for f in fields(GridFitOptions)} | {"grid_mean", "grid_cov"}  # fit_grid_cloud's net settings
    unknown = sorted(set(option_overrides) - known)
    if unknown or isinstance(options, FitOptions):
        what = ", ".join(unknown) if unknown else "FitOptions"
        raise ValueError(f"{what}: not an option of the grid fit (GridFitOptions); SIREN options need "
                         f"representation='siren'")
    outside = option_overrides.get("outside_weight", getattr(options, "outside_weight", 0.0))
    if outside:
        raise ValueError("outside_weight: the grid fit's solve has no boundary term; fit partial scans for view "
                         "planning with representation='siren'")
    return fit_grid_cloud(points, normals, seed=seed, lengthscale=lengthscale, noise=noise, options=options,
                          **option_overrides)
