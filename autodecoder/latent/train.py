"""Training the latent model over many scans: a code table, the conditioned nets, checkpoints that resume, DDP.

One step takes a batch of S scans and, for each, samples of its GP posterior targets (the targets themselves,
a KD-tree and the lumped diagonal per scan, are built once and cached; the samples come from per-scan pools that
serve ``target_passes`` epochs, see :mod:`autodecoder.latent.pools`); the NSSPR losses are computed for the S
scans in one forward pass with a code per sample (z: (S * n, L)). The covariance net sees the codes detached: the
codes are shaped by the mean (geometry) loss only, and the covariance net learns the uncertainty given the code.

Distributed data parallel (``torchrun --nproc_per_node=N train_latent.py ...``): the training scans are sharded over
the ranks (rank r owns scans r, r + N, ...); each rank holds and optimises only its own scans' codes (outside DDP);
the two nets are wrapped in one :class:`torch.nn.parallel.DistributedDataParallel` module, so their gradients are
averaged over the ranks and the weights stay identical. At checkpoint time the codes, their optimiser moments and the
per-rank random states are gathered and rank 0 writes the file.

:func:`train_latent` trains over scans in memory (or any lazy sequence of them); :func:`train_collection` over a
collection file, holding scans back for calibration by the one rule :func:`split_training_scans` (what
``train_latent.py`` runs).
"""
import contextlib
import math
import os
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from torch import nn

from autodecoder.latent.model import (LATENT_FORMAT, LATENT_VERSION, LatentModel, code_statistics, read_checkpoint,
                                      save_checkpoint)
from autodecoder.field.losses import SCREENING_WEIGHT, covariance_dirichlet_loss_features, mean_dirichlet_loss, screening_loss
from autodecoder.field.networks import build_networks
from autodecoder.field.sampling import Box
from autodecoder.field.schedule import cosine_decay
from autodecoder.latent.pools import ScanTargetPool, stack_inputs
from datasets.atomic import atomic_path
from datasets.frame import Frame
from autodecoder.field.targets import DEFAULT_LENGTHSCALE_FACTOR, MIN_LENGTHSCALE, CloudTargets, point_spacing

# The SIREN's default budget (default_epochs): every code is updated DEFAULT_EPOCHS times (an epoch is one pass over
# the scans, a code moves only when its scan is in a batch), with steps of 256 mean-loss samples a scan. On
# verdicts.py's parts (26 training scans, 1,800 steps) this matched the earlier 2,400 steps of 1,024 samples in object
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

LOG_COLUMNS = ("epoch", "loss", "mean_dirichlet", "mean_screening", "cov_dirichlet", "cov_screening", "code_reg",
               "code_rms", "lr", "seconds")


@dataclass
class LatentOptions:
    """Architecture and optimisation settings of :func:`train_latent` (defaults chosen on the benchmarks; see
    docs/results.md).

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


class _NetPair(nn.Module):
    """Both nets in one module whose forward returns the four NSSPR loss terms (what DDP wraps)."""

    def __init__(self, mean_net, cov_net, screening_weight, box_volume):
        super().__init__()
        self.mean_net, self.cov_net = mean_net, cov_net
        self.screening_weight, self.box_volume = float(screening_weight), float(box_volume)

    def forward(self, x, z_x, mu, omega, screen, z_screen, pair_x, z_pair, sigma, weights):
        s, n = mu.shape[:2]
        _, grad = self.mean_net.value_and_gradient(x, z_x)  # (S n, 3)
        mean_dir = mean_dirichlet_loss(grad.view(s, n, 3), mu, omega, self.box_volume)
        mean_scr = screening_loss(self.mean_net(screen, z_screen), self.screening_weight)
        _, jac = self.cov_net.features_and_jacobian(pair_x, z_pair)  # (S m, 3, K)
        m = sigma.shape[1]
        cov_dir = covariance_dirichlet_loss_features(jac.view(s, m, 3, -1), sigma, weights)
        cov_scr = screening_loss(self.cov_net.variance(screen, z_screen.detach()), self.screening_weight)
        return torch.stack([mean_dir, mean_scr, cov_dir, cov_scr])


def _dist():
    """(rank, world size, initialised?) of torch.distributed."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size(), True
    return 0, 1, False


def _all_gather(obj, world):
    if world == 1:
        return [obj]
    import torch.distributed as dist

    out = [None] * world
    dist.all_gather_object(out, obj)
    return out


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


# torch CPU threads of a training run (train_latent.py --threads, inspection.training.train_model): a step is many
# small tensor operations, which one thread ran faster than two on the 2-core machine (103 s against 139 s for the
# default run on fandisk's 26 scans, docs/results.md#latent-training-in-two-minutes-issue-19); more cores are used by
# torchrun processes, one thread each.
TRAINING_THREADS = 1


@contextlib.contextmanager
def training_threads(threads=None):
    """Run the block with ``threads`` torch CPU threads (None: ``TRAINING_THREADS``; 0: leave torch's setting),
    restored afterwards."""
    threads = TRAINING_THREADS if threads is None else int(threads)
    if threads < 0:
        raise ValueError(f"threads must be >= 0, got {threads}")
    before = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def count_parts(part_ids):
    """The number of part types among training scans' part ids (scans without one, '', count as one type)."""
    return max(1, len({str(p) for p in part_ids}))


def collection_lengthscale(scans, indices, factor=DEFAULT_LENGTHSCALE_FACTOR, max_scans=16):
    """One lengthscale for a collection: ``factor`` x the median point spacing of (up to ``max_scans``) scans."""
    pick = list(indices)[:max_scans] if len(indices) <= max_scans else \
        [indices[i] for i in np.linspace(0, len(indices) - 1, max_scans).round().astype(int)]
    spacing = float(np.median([point_spacing(np.asarray(scans[i].points, dtype=np.float64)) for i in pick]))
    return max(factor * spacing, MIN_LENGTHSCALE)


def train_latent(scans, out=None, options=None, *, names=None, frame=None, fingerprint="", calibration_names=(),
                 resume=None, device="cpu", quiet=False, stop_after=None, **overrides):
    """Train a latent model (autodecoder) over oriented scans, all in one collection frame.

    Parameters
    ----------
    scans : sequence of Scan
        The training scans (``len`` and ``scans[i]``; a lazy view over a collection works: each process reads only
        the scans it owns, plus up to 16 for the lengthscale). Points (N, 3) in the collection frame.
    out : str or Path, optional
        Checkpoint path; the log ``<stem>.log.csv`` and plot ``<stem>.loss.png`` go beside it. None: no files.
    options : LatentOptions, optional
        Overridden field by field by ``**overrides``.
    names : list of str, optional
        Scan names (default: ``scans.names`` or each scan's ``name``).
    frame : datasets.frame.Frame or dict, optional
        The collection's file -> collection frame, stored in the checkpoint (identity by default).
    fingerprint : str
        The training collection's fingerprint (stored; checked on resume).
    calibration_names : list of str
        Good scans held back for calibration (stored only).
    resume : dict, optional
        A checkpoint (see :func:`autodecoder.latent.model.read_checkpoint`) to continue from; its configuration wins
        over ``options`` except ``epochs`` and ``checkpoint_every``.
    device : str or torch.device
    quiet : bool
        No progress bar.
    stop_after : int, optional
        End this run (with a checkpoint) once this many epochs are complete, as if interrupted there.

    Returns
    -------
    LatentModel
        On every rank (codes gathered from all ranks).
    """
    rank, world, distributed = _dist()
    device = torch.device(device)
    names = _scan_names(scans, names)
    n_scans = len(names)
    options = LatentOptions.from_dict({**asdict(options or LatentOptions()), **overrides})
    local = list(range(rank, n_scans, world))  # this rank's scans
    local_scans = _read_local_scans(scans, names, local, world)
    part_ids = _part_ids({i: str(getattr(s, "part_id", "")) for i, s in local_scans.items()}, n_scans, world)
    options, config = _resolve_options(options, resume, fingerprint, names, world, count_parts(part_ids))
    if config is None:
        config = _new_config(options, scans, n_scans, local_scans, world, distributed)

    state = _initial_state(config, options, n_scans, local, rank, device)
    if resume is not None:
        _restore(state, resume, local, rank, device)
    elif config.get("representation", "siren") == "grid":
        state.info["shared_solve"] = _solve_shared_level(state, local_scans, config, options)
    module = state.nets
    if distributed:
        from torch.nn.parallel import DistributedDataParallel

        module = DistributedDataParallel(state.nets, device_ids=[device.index] if device.type == "cuda" else None)
    pools, local_points, state.info["targets_seconds"] = _target_pools(local_scans, local, config, options, device)
    del local_scans
    scope = _RunScope(names=names, local=local, part_ids=part_ids, calibration_names=[str(c) for c in calibration_names],
                      frame=_frame_dict(frame), fingerprint=str(fingerprint), rank=rank, world=world,
                      distributed=distributed, device=device, local_points=local_points)

    end_epoch = options.epochs if stop_after is None else min(options.epochs, int(stop_after))
    checkpoint = _train_epochs(state, module, pools, scope, options, out, end_epoch, show=not quiet and rank == 0)
    if checkpoint is None:  # nothing left to train (resumed a finished run)
        checkpoint = _checkpoint(state, scope)
    return LatentModel(checkpoint, os.fspath(out) if out is not None else "<trained>")


# ---- the steps of train_latent --------------------------------------------------------------------------------------
@dataclass
class TrainingState:
    """What a training run changes, and what its checkpoint saves so that a resumed run continues bit-identically.

    Attributes
    ----------
    config : dict
        The resolved configuration (options, lengthscale, box, world size), stored in the checkpoint.
    nets : _NetPair
        The mean and covariance nets.
    codes : torch.nn.Parameter
        (T_local, L): the codes of this process's scans.
    opt_nets, opt_codes : torch.optim.Adam
    rng : numpy.random.Generator
        This process's sampling generator (batch order, screening points); torch's global generator is the other
        random state a checkpoint saves.
    epoch : int
        Epochs completed.
    history : list of dict
        One log record (``LOG_COLUMNS``) per completed epoch.
    info : dict
        Provenance: ``train_seconds``, ``targets_seconds``.
    """

    config: dict
    nets: nn.Module
    codes: nn.Parameter
    opt_nets: torch.optim.Optimizer
    opt_codes: torch.optim.Optimizer
    rng: np.random.Generator
    epoch: int = 0
    history: list = field(default_factory=list)
    info: dict = field(default_factory=dict)


@dataclass
class _RunScope:
    """What a run is over and never changes: the training scans, this process's share of them and their points
    (for the noise level), and the provenance the checkpoint records."""

    names: list
    local: list
    part_ids: list
    calibration_names: list
    frame: dict
    fingerprint: str
    rank: int
    world: int
    distributed: bool
    device: torch.device
    local_points: list


def _scan_names(scans, names):
    """The training scans' names (``names``, else ``scans.names``, else each scan's ``name``), checked unique."""
    if names is None:
        names = list(getattr(scans, "names", None) or [s.name for s in scans])
    names = [str(n) for n in names]
    if len(names) < 1:
        raise ValueError("no training scans")
    if len(set(names)) != len(names):
        raise ValueError("training scan names must be unique")
    return names


def _read_local_scans(scans, names, local, world):
    """{index: Scan} of this rank's scans (``local``), each checked to have at least 10 points."""
    if not local:
        raise ValueError(f"{world} processes but only {len(names)} training scans: every process needs one")
    local_scans = {i: scans[i] for i in local}
    for i, s in local_scans.items():
        if len(s.points) < 10:
            raise ValueError(f"scan {names[i]!r} has {len(s.points)} points; at least 10 needed")
    return local_scans


def _resolve_options(options, resume, fingerprint, names, world, n_parts=1):
    """(options, config): a fresh run's options with the default epoch count resolved and config None (made by
    :func:`_new_config`), or a resumed run's, whose configuration wins except ``epochs`` and ``checkpoint_every``."""
    config = None
    if resume is not None:
        if resume.get("fingerprint", "") != fingerprint:
            raise ValueError(f"the checkpoint was trained on another collection (fingerprint "
                             f"{resume.get('fingerprint', '')[:12]}... vs {fingerprint[:12]}...)")
        if list(resume["train_names"]) != names:
            raise ValueError("the checkpoint's training scans differ from the scans given")
        config = dict(resume["config"])
        if options.epochs is not None:  # else: the checkpoint's own total
            config["epochs"] = options.epochs
        config["checkpoint_every"] = options.checkpoint_every
        options = LatentOptions.from_dict(config)
        if config.get("world_size", 1) != world:
            raise ValueError(f"the checkpoint was written by {config.get('world_size', 1)} processes; resume it "
                             f"with the same number (got {world})")
    if options.epochs is None:
        options = replace(options, epochs=default_epochs(len(names), options.batch, world, n_parts,
                                                         options.representation))
    return options, config


def _new_config(options, scans, n_scans, local_scans, world, distributed):
    """A fresh run's configuration: the options, the lengthscale and the box around all ranks' scans."""
    h = options.lengthscale or collection_lengthscale(scans, list(range(n_scans)))
    lo = np.min([s.points.min(0) for s in local_scans.values()], 0).astype(np.float64)
    hi = np.max([s.points.max(0) for s in local_scans.values()], 0).astype(np.float64)
    if distributed:
        import torch.distributed as dist

        t = torch.tensor(np.concatenate([-lo, hi]), dtype=torch.float64)
        dist.all_reduce(t, op=dist.ReduceOp.MAX)
        lo, hi = -t[:3].numpy(), t[3:].numpy()
    box = Box.around(np.stack([lo, hi]), margin=max(0.1, 4 * h))
    config = {**asdict(options), "lengthscale": float(h), "covariance": "feature",
              "box_lo": box.lo.tolist(), "box_hi": box.hi.tolist(), "world_size": world}
    if options.representation == "grid":  # the full settings, so that a checkpoint rebuilds its nets exactly
        config["grid_mean"] = {**LATENT_GRID_MEAN, "seed": options.seed, **(options.grid_mean or {})}
        config["grid_cov"] = {**LATENT_GRID_COV, "seed": options.seed + 1, **(options.grid_cov or {})}
    return config


def _box(config):
    return Box(np.asarray(config["box_lo"]), np.asarray(config["box_hi"]))


def _initial_state(config, options, n_scans, local, rank, device):
    """Nets, codes, optimisers and generators of a fresh run, all seeded (a run is reproducible)."""
    torch.manual_seed(options.seed)
    mean_net, cov_net = build_networks(config)
    nets = _NetPair(mean_net, cov_net, options.screening_weight, _box(config).volume).to(device)
    gen = torch.Generator().manual_seed(options.seed + 1)
    all_codes = torch.randn(n_scans, options.latent_dim, generator=gen) * options.code_init_std
    codes = nn.Parameter(all_codes[local].clone().to(device))
    return TrainingState(config=config, nets=nets, codes=codes, opt_nets=_net_optimiser(nets, options),
                         opt_codes=torch.optim.Adam([codes], lr=options.code_lr),
                         rng=np.random.default_rng([options.seed, rank]), info={"train_seconds": 0.0})


def _net_optimiser(nets, options):
    """Adam over the nets in groups with their own peak rates (each group's ``peak_lr``, which the schedule scales):
    the decoders and SIRENs at ``lr``, grid control values at ``grid_lr``, the grid mean's shared level at
    ``shared_lr``."""
    from autodecoder.field.grid_networks import BSplineGrid

    shared_level = getattr(nets.mean_net, "shared", None)
    shared = [] if shared_level is None else [shared_level.values]
    grids = [m.values for m in nets.modules() if isinstance(m, BSplineGrid) and m is not shared_level]
    ids = {id(p) for p in grids + shared}
    others = [p for p in nets.parameters() if id(p) not in ids]
    groups = [{"params": others, "lr": options.lr, "peak_lr": options.lr}]
    for params, lr in ((grids, options.grid_lr), (shared, options.shared_lr)):
        if params:
            groups.append({"params": params, "lr": lr, "peak_lr": lr})
    return torch.optim.Adam(groups, lr=options.lr)


def _solve_shared_level(state, local_scans, config, options):
    """Start the grid mean's shared level at the mean loss's minimiser on the union of this process's training
    scans (``options.shared_points`` of their points, a seeded subset); returns the solver's info (empty when there
    is nothing to solve). Under DDP every rank solves on its own scans and DDP copies rank 0's result."""
    mean_net = state.nets.mean_net
    if getattr(mean_net, "shared", None) is None or options.shared_points == 0:
        return {}
    from autodecoder.field.grid_fit import solve_shared

    t0 = time.perf_counter()
    points = np.concatenate([np.asarray(s.points, np.float64) for s in local_scans.values()])
    normals = np.concatenate([np.asarray(s.normals, np.float64) for s in local_scans.values()])
    if len(points) > options.shared_points:
        pick = np.random.default_rng([options.seed, 7]).choice(len(points), options.shared_points, replace=False)
        points, normals = points[pick], normals[pick]
    union = CloudTargets(points, normals, float(config["lengthscale"]), box=_box(config))
    info = solve_shared(mean_net, union)
    return {**info, "points": len(points), "seconds": time.perf_counter() - t0}


def _restore(state, checkpoint, local, rank, device):
    """Continue from ``checkpoint``: weights, this rank's codes and their optimiser moments, random states, epoch,
    history and provenance."""
    state.nets.mean_net.load_state_dict(checkpoint["mean_state"])
    state.nets.cov_net.load_state_dict(checkpoint["cov_state"])
    r = checkpoint["resume"]
    state.opt_nets.load_state_dict(r["opt_nets"])
    with torch.no_grad():
        state.codes.copy_(checkpoint["codes"][local].to(device))
    code_state = r["opt_codes"]
    state.opt_codes.load_state_dict({"state": {0: {"step": code_state["step"], "exp_avg": code_state["exp_avg"][local],
                                                   "exp_avg_sq": code_state["exp_avg_sq"][local]}},
                                     "param_groups": code_state["param_groups"]})
    state.rng.bit_generator.state = r["numpy_rng"][rank]
    torch.set_rng_state(r["torch_rng"])
    state.epoch = int(checkpoint["epoch"])
    state.history = list(checkpoint.get("info", {}).get("history", []))
    state.info = dict(checkpoint.get("info", {}))
    state.info.setdefault("train_seconds", 0.0)


def _target_pools(local_scans, local, config, options, device):
    """(pools, points, seconds): this rank's scans' target pools by scan index, their points on ``device`` in
    ``local`` order, and the seconds the GP targets took to build."""
    box, h = _box(config), float(config["lengthscale"])
    t0 = time.perf_counter()
    targets = {i: CloudTargets(np.asarray(s.points, np.float64), np.asarray(s.normals, np.float64), h, box=box)
               for i, s in local_scans.items()}
    seconds = time.perf_counter() - t0
    pools = {i: ScanTargetPool(t, i, options.seed, options.mean_samples, options.target_refresh,
                               options.target_passes, options.pair_clusters, options.cluster_size)
             for i, t in targets.items()}
    return pools, [torch.from_numpy(targets[i].points32).to(device) for i in local], seconds


def _train_epochs(state, module, pools, scope, options, out, end_epoch, show):
    """Train from ``state.epoch`` to ``end_epoch``, logging every epoch and writing checkpoints (rank 0, when
    ``out``); returns the last checkpoint dict, None when there was nothing to train."""
    n_scans = len(scope.names)
    batch = min(options.batch, len(scope.local))
    steps_per_epoch = math.ceil(math.ceil(n_scans / scope.world) / batch)
    total_steps = options.epochs * steps_per_epoch
    bar = None
    if show and end_epoch > state.epoch:
        from tqdm.auto import tqdm

        bar = tqdm(total=end_epoch - state.epoch, desc="training", unit="epoch", dynamic_ncols=True)
    checkpoint = None
    state.nets.train()
    for epoch in range(state.epoch, end_epoch):
        record = _train_epoch(state, module, pools, scope, options, epoch, steps_per_epoch, batch, total_steps)
        state.history.append(record)
        state.epoch = epoch + 1
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{record['loss']:.4g}", mean=f"{record['mean_dirichlet']:.3g}",
                            screen=f"{record['mean_screening']:.3g}", cov=f"{record['cov_dirichlet']:.3g}")
        if out is not None and scope.rank == 0:
            _write_log(out, state.history)
        if (options.checkpoint_every and state.epoch % options.checkpoint_every == 0) or state.epoch == end_epoch:
            checkpoint = _checkpoint(state, scope)
            if out is not None and scope.rank == 0:
                save_checkpoint(checkpoint, out)
                _plot_losses(out, state.history)
    if bar is not None:
        bar.close()
    state.nets.eval()
    return checkpoint


def _train_epoch(state, module, pools, scope, options, epoch, steps_per_epoch, batch, total_steps):
    """One pass over this rank's scans (ranks with fewer scans wrap around); returns the epoch's log record."""
    t0 = time.perf_counter()
    order = state.rng.permutation(len(scope.local))
    order = np.resize(order, steps_per_epoch * batch)
    sums = torch.zeros(6, dtype=torch.float64)
    for k in range(steps_per_epoch):
        f = cosine_decay(epoch * steps_per_epoch + k, total_steps, options.final_lr_fraction)
        for g in state.opt_nets.param_groups:
            g["lr"] = g.get("peak_lr", options.lr) * f
        for g in state.opt_codes.param_groups:
            g["lr"] = options.code_lr * f
        sums += _train_step(state, module, pools, scope, options, epoch, order[k * batch:(k + 1) * batch])
    sums /= steps_per_epoch
    if scope.distributed:
        import torch.distributed as dist

        sums = sums.to(scope.device) if scope.device.type == "cuda" else sums
        dist.all_reduce(sums)
        sums = sums.cpu() / scope.world
    seconds = time.perf_counter() - t0
    state.info["train_seconds"] += seconds
    return dict(zip(LOG_COLUMNS, [epoch + 1, *sums.tolist(), float(state.codes.detach().square().mean().sqrt()),
                                  options.lr * f, seconds]))


def _train_step(state, module, pools, scope, options, epoch, pos):
    """One optimisation step on the scans at local positions ``pos`` (S,); returns (loss, the four NSSPR terms,
    the code regulariser) (6,) float64."""
    device = scope.device
    inputs = stack_inputs([pools[scope.local[p]] for p in pos], epoch, options.screen_samples, state.rng, device)
    z = state.codes[torch.as_tensor(pos, device=device)]  # (S, L)
    n, m, q = options.mean_samples, inputs["sigma"].shape[1], inputs["screen"].shape[0] // len(pos)
    terms = module(inputs["x"], z.repeat_interleave(n, 0), inputs["mu"], inputs["omega"], inputs["screen"],
                   z.repeat_interleave(q, 0), inputs["pair_x"], z.detach().repeat_interleave(m, 0),
                   inputs["sigma"], inputs["weights"])
    reg = options.code_reg * z.square().sum(1).mean()
    loss = terms.sum() + reg
    state.opt_nets.zero_grad(set_to_none=True)
    state.opt_codes.zero_grad(set_to_none=True)
    loss.backward()
    state.opt_nets.step()
    state.opt_codes.step()
    return torch.cat([loss.detach().reshape(1), terms.detach(), reg.detach().reshape(1)]).double().cpu()


# ---- training over a collection file: what ``train_latent.py`` runs ---------------------------------------------
class TrainingInputError(ValueError):
    """A problem with what a training run was given (the collection, the checkpoint to write or resume, the device);
    the message names the file. ``train_latent.py`` prints it as one line and exits with status 2."""


def split_training_scans(collection, split="train", calibration_fraction=0.2, seed=0):
    """(training indices, calibration names) of a collection: the one rule for holding scans back.

    The good (or unlabelled) scans of ``split`` are trained on. Calibration scans: the good scans of the
    'validation' split when there are any; otherwise ``calibration_fraction`` of the training scans, drawn with
    ``seed``, held back from training; in a collection of several part types (``part_id``) that fraction of each
    part's scans, drawn as in a collection of that part alone (so each part's held-back and training scans are
    those of its single-part collection, and every part can be calibrated on its own scans). Every way of training (``train_latent.py``, :func:`train_collection`,
    ``inspection.training.train_model``) uses this rule, and the checkpoint records its choice
    (``calibration_names``), which is what inspection calibrates on.

    Parameters
    ----------
    collection : datasets.ScanCollection
        An open collection.
    split : str
    calibration_fraction : float in [0, 1)
    seed : int

    Returns
    -------
    train : list of int
        Collection indices, ascending.
    calibration : list of str
        Collection names.

    Raises
    ------
    TrainingInputError
        No good scans in ``split``, or none left to train on.
    """
    candidates = collection.select(split=split, label=("good", "unknown"))
    if not candidates:
        raise TrainingInputError(f"{collection.path}: no good scans in split {split!r}")
    names = collection.names
    validation = collection.select(split="validation", label="good") if split != "validation" else []
    if validation:
        return candidates, [names[i] for i in validation]
    parts = [m["part_id"] for m in collection.metadata()]
    groups = {}
    for i in candidates:
        groups.setdefault(parts[i], []).append(i)
    train, held = [], []
    for part, members in groups.items():
        n_hold = int(round(calibration_fraction * len(members)))
        if len(members) - n_hold < 1:
            what = f"good scans in split {split!r}" + (f" of part {part!r}" if len(groups) > 1 else "")
            raise TrainingInputError(f"{collection.path}: {len(members)} {what} leave none to train on after holding "
                                     f"back {n_hold} for calibration (lower the calibration fraction)")
        order = np.random.default_rng(seed).permutation(len(members))
        held += [members[i] for i in order[:n_hold]]
        train += [members[i] for i in order[n_hold:]]
    return sorted(train), [names[i] for i in sorted(held)]


class _CollectionScans:
    """A lazy sequence of some scans of an open collection (reads a scan when indexed)."""

    def __init__(self, collection, indices):
        self.collection, self.indices = collection, list(indices)
        all_names = collection.names
        self.names = [all_names[i] for i in self.indices]

    def __len__(self):
        return len(self.indices)

    def __getitem__(self, k):
        return self.collection[self.indices[k]]


def setup_distributed(device="auto"):
    """Initialise torch.distributed from torchrun's environment (``WORLD_SIZE`` > 1; gloo on CPU, nccl on CUDA).

    Returns (torch.device, initialised here?): the caller destroys the process group it initialised.
    ``device``: 'auto' (cuda when available), 'cpu' or 'cuda'.
    """
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise TrainingInputError("device cuda: no CUDA device is available")
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return torch.device(device), False
    import torch.distributed as dist

    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if device == "cuda":
        torch.cuda.set_device(local_rank)
        device = torch.device("cuda", local_rank)
    else:
        device = torch.device("cpu")
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        return device, True
    return device, False


def train_collection(data, out, *, split="train", calibration_fraction=0.2, resume=False, overwrite=False,
                     device="auto", quiet=False, **options):
    """Train a latent model over the good scans of a collection file and write its checkpoint (``train_latent.py``).

    The scans to hold back for calibration are chosen by :func:`split_training_scans`; the checkpoint records them.
    Under torchrun (``WORLD_SIZE`` > 1) each process trains its share (:func:`train_latent`).

    Parameters
    ----------
    data : str or Path
        The scan collection (``datasets`` HDF5 format).
    out : str or Path
        The checkpoint to write; the log and loss plot go beside it (:func:`log_paths`).
    split : str
        The split whose good scans are trained on.
    calibration_fraction : float in [0, 1)
        Held back when the collection has no 'validation' split (see :func:`split_training_scans`).
    resume : bool
        Continue the run whose checkpoint is ``out`` (same data, same number of processes; its own settings are
        kept except ``epochs`` and ``checkpoint_every``); starts afresh when ``out`` does not exist yet.
    overwrite : bool
        Replace an existing ``out`` (otherwise refused unless ``resume``).
    device : {'auto', 'cpu', 'cuda'}
    quiet : bool
    **options
        :class:`LatentOptions` fields (``seed`` also seeds the hold-out).

    Returns
    -------
    LatentModel

    Raises
    ------
    TrainingInputError
        Naming the file: no such or unreadable collection, ``out`` exists, a checkpoint of other data, no scans.
    """
    from datasets.collection import ScanCollection

    data, out = Path(data), Path(out)
    if not data.is_file():
        raise TrainingInputError(f"{data}: no such scan collection")
    try:
        collection = ScanCollection(data)
    except (ValueError, OSError) as exc:
        raise TrainingInputError(f"{data}: not a readable scan collection ({str(exc).splitlines()[0]})") from None
    initialised = False
    try:
        checkpoint = _checkpoint_to_resume(out, collection, data, resume, overwrite)
        if checkpoint is not None:
            index = {n: i for i, n in enumerate(collection.names)}
            train = [index[n] for n in checkpoint["train_names"]]
            calibration = list(checkpoint["calibration_names"])
            options["seed"] = int(checkpoint["config"]["seed"])
        else:
            train, calibration = split_training_scans(collection, split, calibration_fraction,
                                                      options.get("seed", LatentOptions.seed))
        device, initialised = setup_distributed(device)
        try:
            return train_latent(_CollectionScans(collection, train), out, frame=collection.frame,
                                fingerprint=collection.fingerprint(), calibration_names=calibration,
                                resume=checkpoint, device=device, quiet=quiet, **options)
        except TrainingInputError:
            raise
        except ValueError as exc:
            raise TrainingInputError(f"{data}: {exc}") from None
    finally:
        collection.close()
        if initialised:
            import torch.distributed as dist

            dist.destroy_process_group()


def _checkpoint_to_resume(out, collection, data, resume, overwrite):
    """The checkpoint at ``out`` to continue (``resume``), None to start afresh; refuses to replace ``out`` unless
    ``overwrite``, and to resume a checkpoint of other data."""
    if not out.exists():
        return None
    if not resume:
        if overwrite:
            return None
        raise TrainingInputError(f"{out}: already exists (pass --resume to continue it or --overwrite to replace it)")
    try:
        checkpoint = read_checkpoint(out)
    except (ValueError, FileNotFoundError) as exc:
        raise TrainingInputError(str(exc)) from None
    if checkpoint.get("fingerprint", "") != collection.fingerprint():
        raise TrainingInputError(f"{out}: this checkpoint was trained on another collection than {data} "
                                 f"(fingerprints differ); use a new --out or the original data")
    return checkpoint


def _frame_dict(frame):
    """The training frame as the checkpoint stores it (:meth:`datasets.frame.Frame.as_dict`); None is the identity."""
    if frame is None:
        frame = Frame.identity()
    elif isinstance(frame, dict):
        frame = Frame.from_dict(frame)
    return frame.as_dict()


def _part_ids(local_ids, n_scans, world):
    """Every training scan's part id, gathered from the ranks that read them."""
    merged = {}
    for d in _all_gather(local_ids, world):
        merged.update(d)
    return [merged.get(i, "") for i in range(n_scans)]


def _checkpoint(state, scope):
    """The full checkpoint dict of ``state`` (codes, optimiser moments and per-rank random states gathered from
    all ranks; a collective call: every rank makes it)."""
    codes = state.codes
    code_state = state.opt_codes.state_dict()
    st = code_state["state"].get(0)
    latent_dim = codes.shape[1]
    if st is None:
        st = {"step": torch.tensor(0.0), "exp_avg": torch.zeros_like(codes), "exp_avg_sq": torch.zeros_like(codes)}
    # noise: RMS of the mean at this rank's scans' points
    total, count = 0.0, 0
    with torch.no_grad():
        for p, pts in enumerate(scope.local_points):
            total += float(state.nets.mean_net(pts, codes[p]).double().square().sum())
            count += len(pts)
    mine = {"local": scope.local, "codes": codes.detach().cpu(), "exp_avg": st["exp_avg"].detach().cpu(),
            "exp_avg_sq": st["exp_avg_sq"].detach().cpu(), "rng": state.rng.bit_generator.state, "sq": total,
            "n": count}
    gathered = _all_gather(mine, scope.world)
    n = len(scope.names)
    full = {k: torch.zeros(n, latent_dim) for k in ("codes", "exp_avg", "exp_avg_sq")}
    for g in gathered:
        for k in full:
            full[k][g["local"]] = g[k]
    sq, cnt = sum(g["sq"] for g in gathered), sum(g["n"] for g in gathered)
    noise = math.sqrt(sq / cnt) if cnt else 0.0
    mean, std = code_statistics(full["codes"])
    step = st["step"].detach().cpu() if torch.is_tensor(st["step"]) else torch.tensor(float(st["step"]))
    return {
        "format": LATENT_FORMAT,
        "version": LATENT_VERSION,
        "config": dict(state.config),
        "mean_state": {k: v.detach().cpu() for k, v in state.nets.mean_net.state_dict().items()},
        "cov_state": {k: v.detach().cpu() for k, v in state.nets.cov_net.state_dict().items()},
        "codes": full["codes"],
        "code_mean": mean,
        "code_std": std,
        "train_names": list(scope.names),
        "train_part_ids": list(scope.part_ids),
        "calibration_names": list(scope.calibration_names),
        "frame": dict(scope.frame),
        "noise": float(noise),
        "fingerprint": scope.fingerprint,
        "epoch": int(state.epoch),
        "resume": {
            "opt_nets": _to_cpu(state.opt_nets.state_dict()),
            "opt_codes": {"step": step, "exp_avg": full["exp_avg"], "exp_avg_sq": full["exp_avg_sq"],
                          "param_groups": code_state["param_groups"]},
            "numpy_rng": [g["rng"] for g in gathered],
            "torch_rng": torch.get_rng_state(),
        },
        "info": {**state.info, "history": list(state.history)},
    }


def _to_cpu(obj):
    if torch.is_tensor(obj):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_to_cpu(v) for v in obj]
    return obj


def log_paths(out):
    """The CSV log and loss plot that go beside checkpoint ``out``: (model.log.csv, model.loss.png)."""
    out = Path(out)
    stem = out.name[:-len(out.suffix)] if out.suffix else out.name
    return out.with_name(stem + ".log.csv"), out.with_name(stem + ".loss.png")


def _write_log(out, history):
    csv_path, _ = log_paths(out)
    with atomic_path(csv_path) as tmp, open(tmp, "w") as fh:
        fh.write(",".join(LOG_COLUMNS) + "\n")
        for r in history:
            fh.write(",".join(f"{r[c]:.6g}" if isinstance(r[c], float) else str(r[c]) for c in LOG_COLUMNS) + "\n")


def _plot_losses(out, history):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    _, png = log_paths(out)
    epochs = [r["epoch"] for r in history]
    fig, ax = plt.subplots(figsize=(7, 4))
    for key in ("loss", "mean_dirichlet", "mean_screening", "cov_dirichlet", "cov_screening"):
        values = [max(r[key], 1e-12) for r in history]
        ax.plot(epochs, values, label=key)
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss (epoch mean)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(png, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
