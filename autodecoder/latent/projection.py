"""Test-time projection: fitting a latent code to a new scan with the trained nets frozen (optionally fine-tuning).

The projection loss of a code z on a scan's points p_i with normals n_i (collection frame) is

    lambda_S mean_i g(p_i, z)^2  +  mean_i |grad g(p_i, z) - n_i|^2  +  lambda_z |z|^2,

the screening term plus the mean Dirichlet term restricted to the points (where the GP posterior mean of the normal
field is the unit normal itself, so no KD-tree or box samples are needed). Without normals, the points' PCA normals are
used without an orientation: the second term becomes min(|grad g - n|^2, |grad g + n|^2).

Robust starts: every candidate (the mean code and up to ``max_candidates`` training codes) is scored by this loss on
a small subset of the points; the ``starts`` best are optimised together for a short while and the best one goes on
alone. A model trained on several part types records each training scan's part id; a scan of known part starts from
that part's codes only (and from their mean instead of the mean of all codes), see :func:`part_codes`. Several scans are optimised in one batched forward pass (Adam acts elementwise, so each scan's code follows
exactly the path it would follow alone). With a decoded grid mean (``representation="grid"``) the grids do not
depend on the code: their features at a scan's points are interpolated once per scan
(``mean_net.features_at``) and every step runs only the small decoder. With a SIREN mean a step's loss and code
gradient are computed by hand (:func:`_data_loss_and_code_grad`, the same numbers as autograd's), which halves a
step's time on the few hundred points a step uses.
"""
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Optional

import numpy as np
import torch

from autodecoder.field.fit import FitOptions, train_single
from autodecoder.field.sampling import Box
from autodecoder.field.siren import Siren
from autodecoder.field.schedule import cosine_decay
from autodecoder.field.targets import CloudTargets
from datasets.normals import estimate_normals
from datasets.validation import check_oriented_cloud, check_points, points_and_normals


@dataclass
class ProjectionOptions:
    """Settings of :func:`project` (defaults chosen for inspection on a 2-core CPU; see inspection.estimator's
    DEFAULT_PROJECTION and docs/results.md#latent-training-and-projection-cost).

    Attributes
    ----------
    steps : int
        Adam steps on the code.
    lr : float
        Adam learning rate of the code (cosine decay to 10%).
    sample : int
        Scan points per step (a fresh random subset each step).
    starts : int
        Candidate codes optimised for the first ``explore`` steps.
    explore : int
        Steps after which only the best start continues.
    max_candidates : int
        Training codes scored as candidate starts (evenly spread when there are more).
    score_points : int
        Points on which the candidates are scored.
    code_reg : float, optional
        lambda_z (default: the training's ``code_reg``).
    trim : float in [0, 1)
        Fraction of the points with the largest loss left out of every step's loss (a trimmed mean): the code then
        explains the good majority of a scan and a defect cannot pull it towards itself. 0: plain mean.
    finetune_steps : int
        Steps of fine-tuning copies of both nets on the scan's GP targets after the projection (0: none).
    finetune_lr : float
        Peak learning rate of the fine-tuning.
    exclude : tuple of int
        Training-code indices left out of the candidate starts: a training scan projected as if it were new
        (cross-fitted calibration), without starting from the code it was trained with.
    part_id : str, optional
        The part type of the scan(s): the candidate starts are that part's training codes and their mean
        (:func:`part_codes`). None or '': every training code (also what a model without part ids always does);
        a part id the model was not trained on is a ValueError. :func:`project_many` takes it per scan from the
        scans' ``part_id`` when this is None.
    loss_points : int, optional
        When a single code is left at the end (``steps`` > 0: the best start goes on alone; or ``starts`` 1),
        the reported :attr:`Projection.loss` is computed on a seeded subsample of at most this many of the scan's
        points (the code is the same: the loss only reports it). With several codes left (no steps) the loss picks
        the best on every point. None: every point. The default leaves a scan of up to 4,096 points exact and keeps
        a 30,000-point scan from spending a fifth of its projection on this one number.
    """

    steps: int = 60
    lr: float = 0.05
    sample: int = 256
    starts: int = 4
    explore: int = 15
    max_candidates: int = 64
    score_points: int = 128
    code_reg: Optional[float] = None
    trim: float = 0.0
    finetune_steps: int = 0
    finetune_lr: float = 1e-4
    exclude: tuple = ()
    part_id: Optional[str] = None
    loss_points: Optional[int] = 4096


@dataclass
class Projection:
    """The result of projecting one scan.

    Attributes
    ----------
    code : (L,) float32 tensor
    loss : float
        Projection loss (without the code prior) on all the scan's points (on a seeded subsample of
        ``ProjectionOptions.loss_points`` of them for a larger scan projected down to one code). Computed when first
        read when one code was left (the inspection never reads it: a tenth of a scan's projection saved).
    field : StochasticField
        The field of the code (collection frame); with fine-tuned copies of the nets when ``finetune_steps > 0``.
    start : int
        Which candidate the winning code started from (-1: the mean code, else a training code index).
    seconds : float
        Wall time of this scan's projection (its share when batched).
    """

    code: torch.Tensor
    loss_value: Optional[float]
    field: object
    start: int = -1
    seconds: float = 0.0
    info: dict = field(default_factory=dict)
    loss_of: Optional[Callable] = field(default=None, repr=False)  # computes loss_value when it is None

    @property
    def loss(self):
        if self.loss_value is None:
            self.loss_value, self.loss_of = float(self.loss_of()), None
        return self.loss_value


def _prepare(scan_like, index):
    """(points, normals, oriented) float32 of one scan; a scan without normals gets unoriented estimated ones."""
    points, normals = points_and_normals(scan_like)
    if normals is None:
        points = check_points(points, f"scan {index} points", min_points=10)
        return points.astype(np.float32), estimate_normals(points, orient=False).astype(np.float32), False
    points, normals = check_oriented_cloud(points, normals, min_points=10, name=f"scan {index}")
    return points.astype(np.float32), normals.astype(np.float32), True


def _point_losses(mean_net, x, normals, oriented, z, screening_weight, cache=None):
    """Per-point projection losses: x, normals (G, n, 3), z (G, L), oriented (G,) bool -> (G, n).

    ``cache``: the code-free part of the mean at x (``mean_net.features_at``, each entry (G, n, ...)); the mean is
    then evaluated from it (``mean_net.value_and_gradient_from``) and x is not used."""
    g_, n_, _ = normals.shape
    zz = z[:, None, :].expand(g_, n_, z.shape[1]).reshape(g_ * n_, -1)
    if cache is None:
        g, grad = mean_net.value_and_gradient(x.reshape(-1, 3), zz)
    else:
        g, grad = mean_net.value_and_gradient_from({k: v.reshape(g_ * n_, *v.shape[2:]) for k, v in cache.items()}, zz)
    return _per_point(g.view(g_, n_), grad.view(g_, n_, 3), normals, oriented, screening_weight)[0]


def _per_point(g, grad, normals, oriented, screening_weight):
    """The per-point projection loss lambda_S g^2 + |grad g - n|^2 from g (G, n) and grad g (G, n, 3), with sign-free
    normals (``oriented`` False) compared as whichever of +n and -n is closer. Returns (the losses (G, n), the normal
    each point was compared with (G, n, 3))."""
    plus = (grad - normals).square().sum(-1)
    if bool(oriented.all()):  # the usual case: the sign-free term is not needed (the same numbers, fewer ops)
        return screening_weight * g.square() + plus, normals
    minus = (grad + normals).square().sum(-1)
    flip = ~oriented[:, None] & (minus < plus)
    return (screening_weight * g.square() + torch.where(flip, minus, plus),
            torch.where(flip[..., None], -normals, normals))


def _trimmed_mean(per_point, trim):
    """Mean of the (1 - trim) fraction of each row's smallest values: (G, n) -> (G,).

    With ``trim`` > 0 a defect covering a small part of the scan cannot pull the code towards itself (the projection
    then explains the good majority of the points, which is what makes the defect stand out)."""
    if trim > 0:
        keep = max(1, int(round((1.0 - trim) * per_point.shape[1])))
        per_point = torch.topk(per_point, keep, dim=1, largest=False).values
    return per_point.mean(1)


def _data_loss(mean_net, x, normals, oriented, z, screening_weight, trim=0.0, cache=None):
    """Per-group projection loss: x, normals (G, n, 3), z (G, L), oriented (G,) bool -> (G,) (trimmed mean)."""
    return _trimmed_mean(_point_losses(mean_net, x, normals, oriented, z, screening_weight, cache), trim)


def _manual_path(net, cache):
    """Whether a projection step can use :func:`_data_loss_and_code_grad` (a SIREN mean net evaluated at the points
    themselves): the same loss and gradient as autograd's, at about half a step's time."""
    siren = getattr(net, "net", None)
    return cache is None and isinstance(siren, Siren) and siren.first_z is not None and siren.out_dim == 1


def _data_loss_and_code_grad(mean_net, x, normals, oriented, z, screening_weight, trim=0.0):
    """:func:`_data_loss` and its gradient with respect to the codes, without autograd (SIREN mean nets only:
    :meth:`autodecoder.field.siren.Siren.jet1_with_code_vjp`).

    Parameters
    ----------
    x, normals : (G, n, 3) tensors
    oriented : (G,) bool tensor
    z : (G, L) tensor
    screening_weight, trim : float
        As in :func:`_data_loss`.

    Returns
    -------
    loss : (G,) tensor
    grad : (G, L) tensor
        d sum(loss) / d z.
    """
    siren = mean_net.net
    g_, n_, _ = normals.shape
    with torch.no_grad():
        z_first = (z @ siren.first_z.T)[:, None, :].expand(g_, n_, -1).reshape(g_ * n_, -1)  # (G n, W)
        value, jac, vjp = siren.jet1_with_code_vjp(x.reshape(-1, 3), z_first)
        g, grad = value.view(g_, n_), jac.view(g_, n_, 3)
        per_point, target = _per_point(g, grad, normals, oriented, screening_weight)  # (G, n), (G, n, 3)
        if trim > 0:  # the trimmed mean's weights: 1 / keep on each row's smallest values, 0 elsewhere
            keep = max(1, int(round((1.0 - trim) * n_)))
            kept = torch.topk(per_point, keep, dim=1, largest=False).indices
            weight = torch.zeros_like(per_point).scatter_(1, kept, 1.0 / keep)
            loss = (weight * per_point).sum(1)
        else:
            weight = torch.full_like(per_point, 1.0 / n_)
            loss = per_point.mean(1)
        d_first = vjp((2.0 * screening_weight * weight * g).reshape(-1),
                      (2.0 * weight[..., None] * (grad - target)).reshape(-1, 3))  # (G n, W)
        return loss, d_first.view(g_, n_, -1).sum(1) @ siren.first_z


def _uses_cache(net):
    """Whether the mean net can be evaluated at fixed points from a code-free cache (a decoded grid mean: its
    grids are interpolated once per scan, and each projection step runs only the decoder)."""
    return hasattr(net, "features_at") and getattr(net, "decoder", None) is not None


def _gathered(caches, idx):
    """The caches' rows ``idx`` (one index tensor per scan), stacked: dict of (B, k, ...) tensors (None: no cache)."""
    if caches is None:
        return None
    return {key: torch.stack([c[key][i] for c, i in zip(caches, idx)]) for key in caches[0]}


def _expanded(cache, copies):
    """Each scan's cache repeated for ``copies`` codes: (B, k, ...) -> (B * copies, k, ...) (None stays None)."""
    if cache is None:
        return None
    return {key: v[:, None].expand(v.shape[0], copies, *v.shape[1:]).reshape(-1, *v.shape[1:])
            for key, v in cache.items()}


def project_many(model, scans, *, seed=0, batch=16, workers=None, quiet=True, **options):
    """Project several scans, ``batch`` of them per batched optimisation.

    Parameters
    ----------
    model : LatentModel
    scans : list of Scan, (points, normals) pairs or (n, 3) point arrays
        In the model's collection frame (map scanner-file coordinates with ``model.frame.to_collection``). A scan's
        ``part_id`` (Scan objects), when the ``part_id`` option is not given, restricts its starts to its part's
        training codes (:func:`part_codes`); scans of different parts are projected in separate batches.
    seed : int
        Seeds the point subsets (scan k uses ``seed + k``'s subsets only through the shared generator: the same
        call gives the same codes).
    batch : int
        Scans optimised together.
    workers : int, optional
        Torch intra-op threads for the call (default: leave torch's setting).
    **options
        :class:`ProjectionOptions` fields.

    Returns
    -------
    list of Projection
    """
    opts = ProjectionOptions(**options)
    if opts.steps < 0 or opts.starts < 1 or opts.sample < 1:
        raise ValueError(f"steps must be >= 0, starts and sample >= 1; got {opts.steps}, {opts.starts}, {opts.sample}")
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    if not 0 <= opts.trim < 1:
        raise ValueError(f"trim must be in [0, 1), got {opts.trim}")
    if opts.loss_points is not None and opts.loss_points < 1:
        raise ValueError(f"loss_points must be None or >= 1, got {opts.loss_points}")
    old_threads = torch.get_num_threads()
    if workers is not None:
        torch.set_num_threads(int(workers))
    try:
        prepared = [_prepare(s, i) for i, s in enumerate(scans)]
        parts = [opts.part_id if opts.part_id is not None else getattr(s, "part_id", None) for s in scans]
        groups = {}
        for i, part in enumerate(parts):
            groups.setdefault(part or None, []).append(i)
        for part in groups:  # an unknown part fails before any work
            part_codes(model, part)
        out = [None] * len(prepared)
        for part, members in groups.items():
            group_opts = replace(opts, part_id=part)
            for start in range(0, len(members), batch):
                chunk = members[start:start + batch]
                # seed: as before for one group (the batch's first scan's position)
                done = _project_batch(model, [prepared[i] for i in chunk], group_opts, seed + chunk[0])
                for i, p in zip(chunk, done):
                    out[i] = p
        if opts.finetune_steps > 0:
            out = [_finetune(model, p, prepared[i], opts, seed + i, quiet) for i, p in enumerate(out)]
        return out
    finally:
        torch.set_num_threads(old_threads)


def project(model, points, normals=None, *, seed=0, quiet=True, **options):
    """Fit a latent code to one scan with the nets frozen.

    Parameters
    ----------
    model : LatentModel
    points : (n, 3) array
        The scan's points in the model's collection frame (``model.frame.to_collection`` maps file coordinates).
    normals : (n, 3) array, optional
        Outward unit normals; without them PCA normals are used, sign-free.
    seed : int
    **options
        :class:`ProjectionOptions` fields, e.g. ``steps=200``, ``finetune_steps=300``.

    Returns
    -------
    Projection
    """
    return project_many(model, [(points, normals)], seed=seed, batch=1, quiet=quiet, **options)[0]


def part_codes(model, part_id=None):
    """The training codes a scan of part type ``part_id`` may start from, and their mean.

    Parameters
    ----------
    model : LatentModel
        Its ``train_part_ids`` (one per training code; all '' in a model trained without part ids).
    part_id : str, optional
        None or '': every training code and the model's mean code. A model without part ids ignores ``part_id``
        (all its scans were of one, unnamed, part).

    Returns
    -------
    index : (C,) int array
        Training-code indices, ascending.
    mean : (L,) float32 tensor

    Raises
    ------
    ValueError
        ``part_id`` is not among the model's training part ids (naming them).
    """
    ids = list(getattr(model, "train_part_ids", None) or [""] * len(model.codes))
    known = sorted({p for p in ids if p})
    if not part_id or not known:
        return np.arange(len(model.codes)), model.code_mean
    if part_id not in known:
        raise ValueError(f"part_id {part_id!r}: the model was trained on part(s) {known}, not on this one (project "
                         f"without a part id to start from every training code)")
    index = np.flatnonzero(np.asarray(ids) == part_id)
    return index, model.codes[index].mean(0)


def _candidates(model, max_candidates, exclude=(), part_id=None):
    """Candidate starts: the mean code and up to ``max_candidates`` training codes (evenly spread), none of the
    ``exclude``d ones; of part ``part_id`` only when given (:func:`part_codes`). Returns ((C, L) codes, (C,)
    training-code index, -1 for the mean code)."""
    index, mean = part_codes(model, part_id)
    index = np.setdiff1d(index, np.asarray(exclude, dtype=int))
    if len(index) > max_candidates:
        index = index[np.linspace(0, len(index) - 1, max_candidates).round().astype(int)]
    return torch.cat([mean[None], model.codes[index]]), np.concatenate([[-1], index])


def _project_batch(model, prepared, opts, seed):
    t0 = time.perf_counter()
    net = model.mean_net
    lam_s = float(model.config.get("screening_weight", 100.0))
    lam_z = float(model.config.get("code_reg", 1e-4)) if opts.code_reg is None else float(opts.code_reg)
    rng = np.random.default_rng(seed)
    b = len(prepared)
    pts = [torch.from_numpy(p) for p, _, _ in prepared]
    nrm = [torch.from_numpy(n) for _, n, _ in prepared]
    oriented = torch.tensor([o for _, _, o in prepared])
    sizes = [len(p) for p in pts]
    caches = [net.features_at(p) for p in pts] if _uses_cache(net) else None

    def subset(k):
        idx = [torch.from_numpy(rng.integers(0, n, k)) for n in sizes]
        return (torch.stack([p[i] for p, i in zip(pts, idx)]), torch.stack([q[i] for q, i in zip(nrm, idx)]),
                _gathered(caches, idx))

    cand, cand_index = _candidates(model, opts.max_candidates, opts.exclude, opts.part_id)  # (C, L)
    c, latent = cand.shape
    starts = min(opts.starts, c)
    with torch.no_grad():
        xs, ns, cs = subset(opts.score_points)  # (B, q, 3)
        x = xs[:, None].expand(b, c, *xs.shape[1:]).reshape(b * c, -1, 3)
        n = ns[:, None].expand(b, c, *ns.shape[1:]).reshape(b * c, -1, 3)
        o = oriented[:, None].expand(b, c).reshape(-1)
        z = cand[None].expand(b, c, latent).reshape(b * c, latent)
        score = _data_loss(net, x, n, o, z, lam_s, opts.trim, _expanded(cs, c)).view(b, c)
        best = torch.topk(-score, starts, dim=1).indices  # (B, starts)
    z = torch.nn.Parameter(cand[best].clone())  # (B, starts, L)
    start_index = cand_index[best.numpy()]  # (B, starts)
    adam = _CodeAdam(z)
    explore = min(opts.explore, opts.steps) if starts > 1 else 0
    manual = _manual_path(net, caches)
    for step in range(opts.steps):
        lr = opts.lr * cosine_decay(step, opts.steps, 0.1)
        k = z.shape[1]
        xs, ns, cs = subset(opts.sample)
        x = xs[:, None].expand(b, k, *xs.shape[1:]).reshape(b * k, -1, 3)
        n = ns[:, None].expand(b, k, *ns.shape[1:]).reshape(b * k, -1, 3)
        o = oriented[:, None].expand(b, k).reshape(-1)
        if manual:
            data, grad = _data_loss_and_code_grad(net, x, n, o, z.detach().reshape(b * k, latent), lam_s, opts.trim)
            data = data.view(b, k)
            grad = grad.view(b, k, latent) + 2.0 * lam_z * z.detach()
        else:
            data = _data_loss(net, x, n, o, z.reshape(b * k, latent), lam_s, opts.trim, _expanded(cs, k)).view(b, k)
            loss = data.sum() + lam_z * z.square().sum()
            z.grad = None
            loss.backward()
            grad = z.grad
        adam.step(grad, lr)
        if k > 1 and step + 1 == explore:  # keep each scan's best start, and its Adam moments
            keep = data.detach().argmin(1)  # (B,)
            rows = torch.arange(b)
            z = torch.nn.Parameter(z.detach()[rows, keep][:, None].clone())
            adam = adam.kept(z, rows, keep)
            start_index = start_index[rows.numpy(), keep.numpy()][:, None]
    z = z.detach()
    rows = [None] * b  # the points of each scan's final loss (None: all)
    if z.shape[1] == 1 and opts.loss_points is not None:  # one code: the loss only reports it, a subsample will do
        loss_rng = np.random.default_rng(seed + 1)
        rows = [None if n <= opts.loss_points else torch.from_numpy(np.sort(loss_rng.choice(n, opts.loss_points,
                                                                                            replace=False)))
                for n in sizes]

    def rows_of(a, i):
        return a if rows[i] is None else a[rows[i]]

    def final_losses(i):  # on all points (or the subsample), per start: (k,)
        with torch.no_grad():
            return _full_loss(net, rows_of(pts[i], i), rows_of(nrm[i], i), bool(oriented[i]), z[i], lam_s, opts.trim,
                              cache=None if caches is None else {key: rows_of(v, i) for key, v in caches[i].items()})

    picks = []  # per scan: (the start kept, its loss or None, what computes it)
    for i in range(b):
        if z.shape[1] == 1:  # one code: its loss only reports it, computed if read
            picks.append((0, None, lambda i=i: final_losses(i)[0]))
        else:  # the final loss picks the best start
            losses = final_losses(i)
            keep = int(losses.argmin())
            picks.append((keep, float(losses[keep]), None))
    seconds = (time.perf_counter() - t0) / b
    out = []
    for i, (keep, loss, loss_of) in enumerate(picks):
        code = z[i, keep].clone()
        out.append(Projection(code=code, loss_value=loss, loss_of=loss_of, field=model.field(code),
                              start=int(start_index[i, keep]), seconds=seconds,
                              info={"steps": opts.steps, "oriented": bool(oriented[i])}))
    return out


class _CodeAdam:
    """Adam on the codes z (B, k, L): step for step what ``torch.optim.Adam([z], lr)`` computes on a CPU tensor (its
    single-tensor path: no weight decay, no amsgrad, default betas and eps; the same operations in the same order, so
    the same codes to the bit), without the optimiser's per-step bookkeeping, which cost a tenth of a projection."""

    BETA1, BETA2, EPS = 0.9, 0.999, 1e-8

    def __init__(self, z, steps=0, exp_avg=None, exp_avg_sq=None):
        self.z, self.steps = z, steps
        self.exp_avg = torch.zeros_like(z.detach()) if exp_avg is None else exp_avg
        self.exp_avg_sq = torch.zeros_like(z.detach()) if exp_avg_sq is None else exp_avg_sq

    @torch.no_grad()
    def step(self, grad, lr):
        """One update of z with gradient ``grad`` (z's shape) at learning rate ``lr``."""
        self.steps += 1
        self.exp_avg.lerp_(grad, 1 - self.BETA1)
        self.exp_avg_sq.mul_(self.BETA2).addcmul_(grad, grad, value=1 - self.BETA2)
        step = float(self.steps)
        step_size = lr / (1 - self.BETA1 ** step)
        denom = (self.exp_avg_sq.sqrt() / (1 - self.BETA2 ** step) ** 0.5).add_(self.EPS)
        self.z.addcdiv_(self.exp_avg, denom, value=-step_size)

    def kept(self, z, rows, keep):
        """The optimiser of ``z`` (B, 1, L), each scan's start ``keep`` (B,) of these codes, with its moments."""
        return _CodeAdam(z, self.steps, self.exp_avg[rows, keep][:, None].clone(),
                         self.exp_avg_sq[rows, keep][:, None].clone())


def _full_loss(net, pts, nrm, oriented, z, lam_s, trim=0.0, chunk=8192, cache=None):
    """Projection loss (trimmed mean) of each of k codes z (k, L) on all of a scan's points -> (k,); ``cache``: the
    scan's ``features_at`` (entries (n, ...)), or None."""
    parts = []
    for s in range(0, len(pts), chunk):
        x = pts[s:s + chunk][None].expand(len(z), -1, 3)
        n = nrm[s:s + chunk][None].expand(len(z), -1, 3)
        o = torch.full((len(z),), oriented)
        part = None if cache is None else _expanded({k: v[s:s + chunk][None] for k, v in cache.items()}, len(z))
        parts.append(_point_losses(net, x, n, o, z, lam_s, cache=part).double())
    return _trimmed_mean(torch.cat(parts, 1), trim).float()


def _finetune(model, projection, prepared, opts, seed, quiet):
    """Adapt copies of both nets to the scan's GP targets with the projected code fixed (the paper's fine-tuning)."""
    import copy

    t0 = time.perf_counter()
    points, normals, oriented = prepared
    if not oriented:
        raise ValueError("fine-tuning needs oriented normals (the GP targets are built from them)")
    box = Box(np.asarray(model.config["box_lo"]), np.asarray(model.config["box_hi"]))
    targets = CloudTargets(points.astype(np.float64), normals.astype(np.float64), model.lengthscale, box=box)
    mean_net, cov_net = copy.deepcopy(model.mean_net), copy.deepcopy(model.cov_net)
    for net in (mean_net, cov_net):
        net.requires_grad_(True)
    # a short run on one scan: a covariance step with every mean step and the last iterate kept (the measured
    # inspection figures use this)
    options = FitOptions(steps=opts.finetune_steps, lr=opts.finetune_lr, mean_batch=2048, screen_batch=1024,
                         pair_clusters=64, covariance_every=1, average_decay=0.0)
    code = projection.code.clone()
    train_single(mean_net, cov_net, targets, options, np.random.default_rng(seed), quiet=quiet, code=code)
    for net in (mean_net, cov_net):
        net.requires_grad_(False)
    field = model.field(code, mean_net=mean_net, cov_net=cov_net,
                        info={**projection.info, "finetune_steps": opts.finetune_steps})
    return Projection(code=code, loss_value=projection.loss, field=field, start=projection.start,
                      seconds=projection.seconds + time.perf_counter() - t0,
                      info={**projection.info, "finetune_steps": opts.finetune_steps})
