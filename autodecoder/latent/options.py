"""What a latent training run is given: :class:`LatentOptions`, the defaults resolved from the training scans, and
the error for bad inputs.

The epoch budget (:func:`default_epochs`) follows the collection's size, the batch, the processes and the part types
(:func:`count_parts`); the GP lengthscale follows the training scans' point spacing (:func:`collection_lengthscale`).
"""
import math
from dataclasses import dataclass, fields
from typing import Optional

import numpy as np

from autodecoder.field.losses import SCREENING_WEIGHT
from autodecoder.field.targets import DEFAULT_LENGTHSCALE_FACTOR, MIN_LENGTHSCALE, point_spacing

# The SIREN's default budget (default_epochs): every code is updated DEFAULT_EPOCHS times (an epoch is one pass over
# the scans, a code moves only when its scan is in a batch), with steps of 256 mean-loss samples a scan. On
# the inspection benchmark's parts (26 training scans, 1,800 steps) this matched the earlier 2,400 steps of 1,024 samples in object
# AUROC at about a third of the time (under 2 minutes on 2 cores); fewer code updates (300) or narrower or shallower
# nets lost the thin-walled enclosure's missing material at one of three seeds
# (docs/results.md#latent-training-in-two-minutes-issue-19). Large collections get fewer epochs: at most
# MAX_DEFAULT_STEPS steps per part type, and never fewer than MIN_DEFAULT_EPOCHS epochs.
DEFAULT_EPOCHS = 450
MAX_DEFAULT_STEPS = 20_000
MIN_DEFAULT_EPOCHS = 150

# The grid representation's nets in a latent model (``representation="grid"``; keys of
# autodecoder.field.grid_networks.GridMeanNet / GridCovarianceNet, overridden by LatentOptions.grid_mean / grid_cov):
# multi-resolution B-spline features decoded with the code by a small MLP, and for the mean a shared level, solved
# on the union of the training scans, that the decoded part corrects (docs/model.md; figures in docs/results.md).
LATENT_GRID_MEAN = {"finest": 64, "levels": 4, "channels": 4, "hidden": 64, "depth": 1, "shared_cells": 96}
LATENT_GRID_COV = {"finest": 16, "levels": 3, "channels": 16, "hidden": 64, "depth": 1, "features": 64}
REPRESENTATIONS = ("siren", "grid")
# The grid representation's step budget (default_epochs): its mean starts at the union's solved field, and on fandisk
# its loss stopped falling within a few dozen epochs (docs/results.md#the-latent-model-on-grids-issue-19).
GRID_DEFAULT_STEPS = 160
GRID_MIN_DEFAULT_EPOCHS, GRID_MAX_DEFAULT_EPOCHS = 20, 600


@dataclass
class LatentOptions:
    """Architecture and optimisation settings of :func:`autodecoder.latent.train.train_latent` (defaults chosen on
    the benchmarks; see docs/results.md).

    Attributes
    ----------
    latent_dim : int
        Code dimension L.
    width, depth : int
        SIREN hidden width and number of hidden layers of both nets.
    features : int
        Rank K of the feature covariance net.
    omega0 : float
        SIREN first-layer frequency.
    epochs : int, optional
        Passes over the training scans. Default (None): :func:`default_epochs`: ``DEFAULT_EPOCHS`` (fewer for very
        large collections; grid representation: ``GRID_DEFAULT_STEPS`` steps per part type, at least 20 epochs).
    batch : int
        Scans per step (per process under DDP).
    lr, code_lr : float
        Peak Adam learning rates of the nets and of the codes (cosine decay to ``final_lr_fraction`` of them).
    mean_samples, screen_samples : int
        Box samples (mean loss) and cloud points (screening terms) per scan and step.
    pair_clusters, cluster_size : int
        The covariance batch per scan and step: pair_clusters x cluster_size points, all their ordered pairs.
    target_refresh, target_passes : int
        Each scan's mean-loss samples are drawn ``target_refresh`` epochs' worth at a time and each serves
        ``target_passes`` epochs; each covariance batch serves ``target_passes`` epochs (1, 1: fresh targets every
        epoch). Drawing GP targets is a large share of a step; reuse takes that to a few per cent
        (docs/results.md#latent-training-and-projection-cost).
    code_reg : float
        lambda of the code prior lambda * |z|^2 (per scan, averaged over the batch).
    code_init_std : float
        Codes start as N(0, code_init_std^2) (DeepSDF).
    screening_weight : float
        lambda_S.
    lengthscale : float, optional
        GP kernel lengthscale (collection units); default: 2 x the median point spacing of the training scans.
    seed : int
    checkpoint_every : int
        Epochs between checkpoints (0: only at the end).
    representation : {'siren', 'grid'}
        The nets: SIRENs of ``width`` x ``depth`` (the paper's), or B-spline feature grids decoded with the code
        (:data:`LATENT_GRID_MEAN`, :data:`LATENT_GRID_COV`; ``width``, ``depth``, ``features`` and ``omega0`` are
        then unused).
    grid_mean, grid_cov : dict, optional
        Overrides of :data:`LATENT_GRID_MEAN` / :data:`LATENT_GRID_COV` (grid representation only).
    grid_lr : float
        Peak Adam learning rate of the grids' control values (grid representation; the decoders use ``lr``).
    shared_lr : float
        Peak Adam learning rate of the grid mean's shared level: small, since it starts solved and Adam's noise on
        control values few samples visit accumulates (as in :func:`autodecoder.field.grid_fit.fit_grid_cloud`).
    shared_points : int
        Points of the union of the training scans (a seeded random subset) on which the grid mean's shared level
        is solved before training (0: not solved, the level starts at 0 and is trained like the rest).
    """

    latent_dim: int = 32
    width: int = 64
    depth: int = 3
    features: int = 64
    omega0: float = 30.0
    epochs: Optional[int] = None
    batch: int = 8
    lr: float = 1e-3
    code_lr: float = 1e-3
    final_lr_fraction: float = 0.05
    mean_samples: int = 256
    screen_samples: int = 128
    pair_clusters: int = 32
    cluster_size: int = 4
    target_refresh: int = 4
    target_passes: int = 4
    code_reg: float = 1e-4
    code_init_std: float = 0.01
    screening_weight: float = SCREENING_WEIGHT
    lengthscale: Optional[float] = None
    seed: int = 0
    checkpoint_every: int = 0
    representation: str = "siren"
    grid_mean: Optional[dict] = None
    grid_cov: Optional[dict] = None
    grid_lr: float = 1e-2
    shared_lr: float = 1e-5
    shared_points: int = 8000

    def __post_init__(self):
        if self.representation not in REPRESENTATIONS:
            raise ValueError(f"representation must be one of {REPRESENTATIONS}, got {self.representation!r}")
        for name in ("latent_dim", "width", "depth", "features", "batch", "mean_samples",
                     "screen_samples", "pair_clusters", "target_refresh", "target_passes"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.epochs is not None and int(self.epochs) < 1:
            raise ValueError(f"epochs must be >= 1, got {self.epochs}")
        if self.cluster_size < 2:
            raise ValueError(f"cluster_size must be >= 2, got {self.cluster_size}")
        if self.shared_lr < 0:
            raise ValueError(f"shared_lr must be >= 0, got {self.shared_lr}")
        if self.shared_points < 0:
            raise ValueError(f"shared_points must be >= 0, got {self.shared_points}")
        for name in ("lr", "code_lr", "grid_lr"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.code_reg < 0 or self.checkpoint_every < 0:
            raise ValueError("code_reg and checkpoint_every must be >= 0")

    @classmethod
    def from_dict(cls, d):
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


def default_epochs(n_scans, batch, world=1, n_parts=1, representation="siren"):
    """The default number of epochs for ``n_scans`` training scans of ``n_parts`` part types, ``batch`` scans per
    step and process, ``world`` processes.

    SIREN nets: ``DEFAULT_EPOCHS`` (every code gets as many updates, whatever the collection's size, so a collection
    of several part types trains each part's codes as often as a single-part run of the same scans per part, in
    proportionally more steps; one model of two parts trained in one part's step budget ranked each part's defects
    far worse, docs/results.md#one-model-for-several-parts-issue-19), fewer for a collection so large that this
    would exceed ``MAX_DEFAULT_STEPS`` steps per part type, but at least ``MIN_DEFAULT_EPOCHS``.

    The grid representation (``representation="grid"``) starts from the union's solved mean and needs far fewer
    steps: ``GRID_DEFAULT_STEPS`` per part type, between ``GRID_MIN_DEFAULT_EPOCHS`` and
    ``GRID_MAX_DEFAULT_EPOCHS``."""
    if int(n_parts) < 1:
        raise ValueError(f"n_parts must be >= 1, got {n_parts}")
    if representation not in REPRESENTATIONS:
        raise ValueError(f"representation must be one of {REPRESENTATIONS}, got {representation!r}")
    steps_per_epoch = math.ceil(math.ceil(n_scans / world) / max(1, min(batch, math.ceil(n_scans / world))))
    if representation == "grid":
        steps = GRID_DEFAULT_STEPS * int(n_parts)
        return int(min(GRID_MAX_DEFAULT_EPOCHS, max(GRID_MIN_DEFAULT_EPOCHS, math.ceil(steps / steps_per_epoch))))
    affordable = MAX_DEFAULT_STEPS * int(n_parts) // steps_per_epoch
    return int(max(MIN_DEFAULT_EPOCHS, min(DEFAULT_EPOCHS, affordable)))


def count_parts(part_ids):
    """The number of part types among training scans' part ids (scans without one, '', count as one type)."""
    return max(1, len({str(p) for p in part_ids}))


def collection_lengthscale(scans, indices, factor=DEFAULT_LENGTHSCALE_FACTOR, max_scans=16):
    """One lengthscale for a collection: ``factor`` x the median point spacing of (up to ``max_scans``) scans."""
    pick = list(indices)[:max_scans] if len(indices) <= max_scans else \
        [indices[i] for i in np.linspace(0, len(indices) - 1, max_scans).round().astype(int)]
    spacing = float(np.median([point_spacing(np.asarray(scans[i].points, dtype=np.float64)) for i in pick]))
    return max(factor * spacing, MIN_LENGTHSCALE)


class TrainingInputError(ValueError):
    """A problem with what a training run was given (the collection, the checkpoint to write or resume, the device);
    the message names the file. ``train_latent.py`` prints it as one line and exits with status 2."""
