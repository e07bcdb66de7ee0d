"""The training loop of the latent model: a run's state, its start (nets, codes, optimisers, target pools, the grid's
shared level) and its epochs and steps.

One step takes a batch of S scans and, for each, samples of its GP posterior targets (the targets themselves,
a KD-tree and the lumped diagonal per scan, are built once and cached; the samples come from per-scan pools that
serve ``target_passes`` epochs, see :mod:`autodecoder.latent.pools`; the next step's are drawn in a worker thread
while a step runs); the NSSPR losses are computed for the S scans in one forward pass per net with a code per sample
(z: (S * n, L)). The covariance net sees the codes detached: the codes are shaped by the mean (geometry) loss only,
and the covariance net learns the uncertainty given the code; its graph shares nothing with the mean net's, and on a
CPU it runs in a second thread beside it (:func:`_train_step`), the same to the bit as one backward pass.
"""
import math
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch
from torch import nn

from autodecoder.field.losses import covariance_dirichlet_loss_features, mean_dirichlet_loss, screening_loss
from autodecoder.field.networks import build_networks
from autodecoder.field.sampling import Box
from autodecoder.field.schedule import cosine_decay
from autodecoder.field.targets import CloudTargets
from autodecoder.latent.checkpoint import frame_dict, gather_checkpoint, restore_state
from autodecoder.latent.distributed import all_gather, rank_and_world
from autodecoder.latent.history import LOG_COLUMNS, plot_losses, write_log
from autodecoder.latent.model import save_checkpoint
from autodecoder.latent.options import (LATENT_GRID_COV, LATENT_GRID_MEAN, LatentOptions, collection_lengthscale,
                                        count_parts, default_epochs)
from autodecoder.latent.pools import ScanTargetPool, stack_inputs


class _NetPair(nn.Module):
    """Both nets in one module whose forward returns the four NSSPR loss terms (what DDP wraps)."""

    def __init__(self, mean_net, cov_net, screening_weight, box_volume, cluster_size=None):
        super().__init__()
        self.mean_net, self.cov_net = mean_net, cov_net
        self.screening_weight, self.box_volume = float(screening_weight), float(box_volume)
        # the covariance batches' clusters (the pairs inside them from each cluster's Gram matrix, losses.py)
        self.cluster_size = cluster_size

    def forward(self, x, z_x, mu, omega, screen, z_screen, pair_x, z_pair, sigma, weights):
        return torch.cat([self.mean_terms(x, z_x, mu, omega, screen, z_screen),
                          self.covariance_terms(screen, z_screen, pair_x, z_pair, sigma, weights)])

    def mean_terms(self, x, z_x, mu, omega, screen, z_screen):
        """The mean net's two terms (2,): its graph reaches the mean net and the codes only."""
        s, n = mu.shape[:2]
        _, grad = self.mean_net.value_and_gradient(x, z_x)  # (S n, 3)
        mean_dir = mean_dirichlet_loss(grad.view(s, n, 3), mu, omega, self.box_volume)
        mean_scr = screening_loss(self.mean_net(screen, z_screen), self.screening_weight)
        return torch.stack([mean_dir, mean_scr])

    def covariance_terms(self, screen, z_screen, pair_x, z_pair, sigma, weights):
        """The covariance net's two terms (2,): it sees the codes detached, so its graph reaches the covariance net
        only (what lets :func:`_train_step` run the two graphs side by side)."""
        s, m = sigma.shape[:2]
        _, jac = self.cov_net.features_and_jacobian(pair_x, z_pair)  # (S m, 3, K)
        cov_dir = covariance_dirichlet_loss_features(jac.view(s, m, 3, -1), sigma, weights, self.cluster_size)
        cov_scr = screening_loss(self.cov_net.variance(screen, z_screen.detach()), self.screening_weight)
        return torch.stack([cov_dir, cov_scr])


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
        Provenance: ``train_seconds`` (the epochs), ``targets_seconds`` (the scans' GP targets), ``read_seconds``
        (reading the scans, registering them onto a common frame when the run has one) and, from
        :func:`autodecoder.latent.train.train_collection`, ``decision_seconds`` (the family and pose decisions).
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
class RunScope:
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
    family: object = None  # the FamilyFrame's dict when the scans were brought to one size (family.py)


def scan_names(scans, names):
    """The training scans' names (``names``, else ``scans.names``, else each scan's ``name``), checked unique."""
    if names is None:
        names = list(getattr(scans, "names", None) or [s.name for s in scans])
    names = [str(n) for n in names]
    if len(names) < 1:
        raise ValueError("no training scans")
    if len(set(names)) != len(names):
        raise ValueError("training scan names must be unique")
    return names


def start_run(scans, names, options, *, resume=None, frame=None, fingerprint="", calibration_names=(), device="cpu",
              family=None, progress=False):
    """Everything a run trains with, on this process: its state (fresh and seeded, or restored from ``resume``),
    the nets as this process steps them, the target pools of its scans and the run's scope.

    Parameters
    ----------
    scans : sequence of Scan
        The training scans (only this process's share is read, plus up to 16 for the lengthscale).
    names : list of str
        Their names (:func:`scan_names`).
    options : LatentOptions
        ``epochs`` None: :func:`autodecoder.latent.options.default_epochs`.
    resume : dict, optional
        A checkpoint to continue; its configuration wins over ``options`` except ``epochs`` and
        ``checkpoint_every``.
    frame, fingerprint, calibration_names, family
        Provenance the checkpoint records (see :func:`autodecoder.latent.train.train_latent`).
    device : str or torch.device
    progress : bool
        Progress bars (rank 0) over reading the scans (registering each onto a common frame, when the run has one)
        and building their GP targets: seconds each for scans of tens of thousands of points.

    Returns
    -------
    state : TrainingState
    module : torch.nn.Module
        The nets, wrapped in DistributedDataParallel under torch.distributed.
    pools : dict of int to ScanTargetPool
        This process's scans' targets, by scan index.
    scope : RunScope
    options : LatentOptions
        The run's resolved options (epoch count resolved; a resumed run's own).
    """
    rank, world, distributed = rank_and_world()
    device = torch.device(device)
    n_scans = len(names)
    local = list(range(rank, n_scans, world))  # this rank's scans
    progress = bool(progress) and rank == 0
    t_read = time.perf_counter()
    local_scans = _read_local_scans(scans, names, local, world, progress)
    read_seconds = time.perf_counter() - t_read
    part_ids = _part_ids({i: str(getattr(s, "part_id", "")) for i, s in local_scans.items()}, n_scans, world)
    options, config = _resolve_options(options, resume, fingerprint, names, world, count_parts(part_ids))
    if config is None:
        config = _new_config(options, scans, n_scans, local_scans, world, distributed)

    state = _initial_state(config, options, n_scans, local, rank, device)
    state.info["read_seconds"] = read_seconds
    if resume is not None:
        restore_state(state, resume, local, rank, device)
    elif config.get("representation", "siren") == "grid":
        state.info["shared_solve"] = _solve_shared_level(state, local_scans, config, options)
    module = state.nets
    if distributed:
        from torch.nn.parallel import DistributedDataParallel

        module = DistributedDataParallel(state.nets, device_ids=[device.index] if device.type == "cuda" else None)
    pools, local_points, state.info["targets_seconds"] = _target_pools(local_scans, local, config, options, device,
                                                                       progress)
    del local_scans
    scope = RunScope(names=names, local=local, part_ids=part_ids, calibration_names=[str(c) for c in calibration_names],
                      frame=frame_dict(frame), fingerprint=str(fingerprint), rank=rank, world=world,
                      distributed=distributed, device=device, local_points=local_points,
                      family=None if family is None else dict(family))
    return state, module, pools, scope, options


def _bar(items, progress, desc, total=None):
    """``items`` under a progress bar when ``progress`` (tqdm.auto, as the epochs' bar); ``items`` None: the bar
    alone (of ``total`` scans; None without ``progress``), updated by its owner."""
    if not progress:
        return items
    from tqdm.auto import tqdm

    return tqdm(items, desc=desc, total=total, unit="scan", dynamic_ncols=True)


def _read_local_scans(scans, names, local, world, progress=False):
    """{index: Scan} of this rank's scans (``local``), each checked to have at least 10 points. Read side by side
    (:mod:`datasets.parallel`): a scan read from a common frame (:class:`autodecoder.latent.family.NormalisedScans`)
    is registered onto it."""
    from datasets.parallel import parallel_map

    if not local:
        raise ValueError(f"{world} processes but only {len(names)} training scans: every process needs one")
    bar = _bar(None, progress, "reading scans", total=len(local))
    local_scans = dict(zip(local, parallel_map(scans.__getitem__, local, tick=None if bar is None else bar.update)))
    if bar is not None:
        bar.close()
    for i, s in local_scans.items():
        if len(s.points) < 10:
            raise ValueError(f"scan {names[i]!r} has {len(s.points)} points; at least 10 needed")
    return local_scans


def _part_ids(local_ids, n_scans, world):
    """Every training scan's part id, gathered from the ranks that read them."""
    merged = {}
    for d in all_gather(local_ids, world):
        merged.update(d)
    return [merged.get(i, "") for i in range(n_scans)]


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
    nets = _NetPair(mean_net, cov_net, options.screening_weight, _box(config).volume, options.cluster_size).to(device)
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


def _target_pools(local_scans, local, config, options, device, progress=False):
    """(pools, points, seconds): this rank's scans' target pools by scan index, their points on ``device`` in
    ``local`` order, and the seconds the GP targets took to build."""
    box, h = _box(config), float(config["lengthscale"])
    t0 = time.perf_counter()
    targets = {i: CloudTargets(np.asarray(s.points, np.float64), np.asarray(s.normals, np.float64), h, box=box)
               for i, s in _bar(list(local_scans.items()), progress, "GP targets")}
    seconds = time.perf_counter() - t0
    pools = {i: ScanTargetPool(t, i, options.seed, options.mean_samples, options.target_refresh,
                               options.target_passes, options.pair_clusters, options.cluster_size)
             for i, t in targets.items()}
    return pools, [torch.from_numpy(targets[i].points32).to(device) for i in local], seconds


def train_epochs(state, module, pools, scope, options, out, end_epoch, show):
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
            write_log(out, state.history)
        if (options.checkpoint_every and state.epoch % options.checkpoint_every == 0) or state.epoch == end_epoch:
            checkpoint = gather_checkpoint(state, scope)
            if out is not None and scope.rank == 0:
                save_checkpoint(checkpoint, out)
                plot_losses(out, state.history, settings=state.config)
    if bar is not None:
        bar.close()
    state.nets.eval()
    return checkpoint


def _train_epoch(state, module, pools, scope, options, epoch, steps_per_epoch, batch, total_steps):
    """One pass over this rank's scans (ranks with fewer scans wrap around); returns the epoch's log record.

    Each step's targets (:func:`autodecoder.latent.pools.stack_inputs`) are drawn by one worker thread while the
    step before is computed: they do not depend on the nets, their draws follow each other in the same order from
    ``state.rng`` as when drawn in the step itself, so the run is the same to the bit; and the worker's numpy and
    KD-tree work runs on a core the single-threaded step leaves idle (docs/results_archive.md, "Speed"). Nothing is
    drawn beyond the epoch, so a checkpoint's ``rng`` is where a resumed run continues."""
    from concurrent.futures import ThreadPoolExecutor
    from contextlib import nullcontext

    from datasets.parallel import usable_cores

    t0 = time.perf_counter()
    order = state.rng.permutation(len(scope.local))
    order = np.resize(order, steps_per_epoch * batch)
    positions = [order[k * batch:(k + 1) * batch] for k in range(steps_per_epoch)]

    def draw(pos):
        return stack_inputs([pools[scope.local[p]] for p in pos], epoch, options.screen_samples, state.rng,
                            scope.device)

    sums = torch.zeros(6, dtype=torch.float64)
    # the covariance net's graph beside the mean net's: on a CPU of several cores, where one process is not spread
    # over processes (DDP's hooks need the wrapped module's own forward)
    split = module is state.nets and scope.device.type == "cpu" and usable_cores() > 1
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="targets") as worker, \
            (ThreadPoolExecutor(max_workers=1, thread_name_prefix="covariance") if split else nullcontext()) as beside:
        drawn = worker.submit(draw, positions[0])
        for k in range(steps_per_epoch):
            inputs = drawn.result()
            if k + 1 < steps_per_epoch:
                drawn = worker.submit(draw, positions[k + 1])
            f = cosine_decay(epoch * steps_per_epoch + k, total_steps, options.final_lr_fraction)
            for g in state.opt_nets.param_groups:
                g["lr"] = g.get("peak_lr", options.lr) * f
            for g in state.opt_codes.param_groups:
                g["lr"] = options.code_lr * f
            sums += _train_step(state, module, inputs, options, positions[k], beside)
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


def _train_step(state, module, inputs, options, pos, beside=None):
    """One optimisation step on the scans at local positions ``pos`` (S,) with their targets ``inputs``
    (:func:`autodecoder.latent.pools.stack_inputs`); returns (loss, the four NSSPR terms, the code regulariser) (6,)
    float64.

    ``beside`` (an executor of one thread, or None): the covariance net's terms and their gradients are computed in
    it while this thread computes the mean net's. The two graphs share nothing (the covariance net sees the codes
    detached, :meth:`_NetPair.covariance_terms`), so every parameter gets the gradient the one backward pass of their
    sum gives, to the bit, and the two run on two cores."""
    device = state.codes.device
    z = state.codes[torch.as_tensor(pos, device=device)]  # (S, L)
    n, m, q = options.mean_samples, inputs["sigma"].shape[1], inputs["screen"].shape[0] // len(pos)
    mean_inputs = (inputs["x"], z.repeat_interleave(n, 0), inputs["mu"], inputs["omega"], inputs["screen"],
                   z.repeat_interleave(q, 0))
    cov_inputs = (inputs["pair_x"], z.detach().repeat_interleave(m, 0), inputs["sigma"], inputs["weights"])
    reg = options.code_reg * z.square().sum(1).mean()
    state.opt_nets.zero_grad(set_to_none=True)
    state.opt_codes.zero_grad(set_to_none=True)
    if beside is None:
        terms = module(*mean_inputs, *cov_inputs)
        loss = terms.sum() + reg
        loss.backward()
    else:
        def covariance():
            cov_terms = state.nets.covariance_terms(mean_inputs[4], mean_inputs[5], *cov_inputs)
            cov_terms.sum().backward()
            return cov_terms.detach()

        running = beside.submit(covariance)
        mean_terms = state.nets.mean_terms(*mean_inputs)
        (mean_terms.sum() + reg).backward()
        terms = torch.cat([mean_terms.detach(), running.result()])
        loss = terms.sum() + reg.detach()
    state.opt_nets.step()
    state.opt_codes.step()
    return torch.cat([loss.detach().reshape(1), terms.detach(), reg.detach().reshape(1)]).double().cpu()
