"""Next-best-view: score depth-camera placements by the field's variance where their rays are expected to hit.

Score of a camera at position p looking along d: over a bundle of n x n rays of a pinhole camera with field of view
``fov_deg``, cast with :func:`autodecoder.scanning.rays.cast_rays` (correlated first hits),

    score(p, d) = sum_rays P(hit) Var f(x_hat) / n^2,     x_hat = p + E[T | hit] d_ray,

i.e. the variance at the expected hit point, with rays that are expected to miss the part weighted down by their
hit probability (a ray into empty space would otherwise report the prior variance far from the data). World frame,
variance in world units squared.

When the already-measured points are known (a fitted field carries them in ``training_points``), each ray is also
weighted by how new its expected hit point is,

    novelty(x_hat) = 1 - exp(-d(x_hat)^2 / (2 s^2)),     d = distance to the nearest measured point,

with s one kernel support (2 lengthscales, the unit the integration box's margin is counted in). Why: the learned
covariance of a field fitted to one scan keeps a large floor on the surface it has seen (on fandisk the variance
there is barely below the variance on the unseen side, with the spreads overlapping), so the variance alone ranks
a camera that re-measures the seen side barely below one that looks at the unseen side. (The floor is the
covariance net's: its loss fixes only the mixed derivatives of c, and the screening term that pins c(p, p) to 0
is small at the covariance's scale; ``FitOptions.covariance_screening_weight`` strengthens it.) A new scan
of surface already measured within a kernel support adds nothing the fit can use; the factor says so explicitly,
and leaves the variance to rank the cameras that do look at new surface.

Fit the fields of partial scans with ``fit_cloud(..., representation='siren', outside_weight=100,
lengthscale=2 * point_spacing(points))``
(:class:`autodecoder.field.fit.FitOptions`, :func:`autodecoder.field.targets.point_spacing`): with ``fit_cloud``'s
default kernel of 1.5 point spacings next-best-view chose worse views. The boundary term: the paper's loss leaves an
open sheet unclosed, so far from one scan the mean sits at the surface's own level, every ray "hits" empty space at
once, and the score ranks cameras by the variance of that empty space; with the term the score ranks cameras by
the surface they would add.

What limits the ranking is the score, not the learned variance: the learned variance agrees with gpytoolbox's
stochastic Poisson variance of the same scan, and with that exact variance in its place the score ranks cameras
about as well, while P(hit) x novelty with no variance at all ranks them better; the score's best cameras lie at a
right angle to the first view, while the most new surface lies opposite it. Figures (``python -m benchmarks scanning --mode next-view``,
``--mode view-score``): docs/results.md#scanning-partial-scan-fields-and-next-best-view.

The optimiser (:func:`next_best_views`) maximises the score by Adam from many starts on a sphere around the part
(the global multi-start the paper recommends; optionally the starts are the best of a larger set of random
cameras scored once), projecting the stand-off distance into a range and the optical axis into a cone around the
part's centre after every step. "The part" is the field's integration box (its centre and the radius of its corner
sphere): a field fitted to one scan has a box around that scan, which may be off-centre of the physical part.
"""
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from autodecoder.scanning.rays import cast_rays
from autodecoder.field.sampling import Box

# next_best_views warns when more of the box's boundary than this is likely inside (see far_field_inside_fraction)
HALF_SOLID_FRACTION = 0.1


@dataclass
class ViewCandidate:
    """A ranked camera placement (world frame).

    Attributes
    ----------
    position : (3,) float array
    direction : (3,) float array, unit
    score : float
        :func:`camera_score` (world units squared), evaluated without penalties.
    look_at : (3,) float array
        The point on the optical axis closest to the part's centre (for scanners that take a target).
    """

    position: np.ndarray
    direction: np.ndarray
    score: float
    look_at: np.ndarray

    def as_dict(self):
        return {"position": [float(v) for v in self.position], "direction": [float(v) for v in self.direction],
                "look_at": [float(v) for v in self.look_at], "score": float(self.score)}


def part_sphere(field):
    """Centre (3,) and radius of the sphere through the corners of the field's box (world frame)."""
    lo, hi = np.asarray(field.bounds, dtype=np.float64)
    return (lo + hi) / 2, float(np.linalg.norm(hi - lo) / 2)


def camera_rays(positions, directions, fov_deg=30.0, n_side=3):
    """Ray bundle of pinhole cameras, differentiable in positions and directions.

    Parameters
    ----------
    positions, directions : (C, 3) tensors
        Camera centres and optical axes (normalised here).
    fov_deg : float
        Full field of view (square image).
    n_side : int
        Rays per image side (n_side^2 rays per camera, pixel centres).

    Returns
    -------
    origins (C, R, 3), ray directions (C, R, 3) unit, R = n_side^2.
    """
    d = directions / directions.norm(dim=1, keepdim=True).clamp_min(1e-30)
    up0 = torch.tensor([0.0, 0.0, 1.0], dtype=d.dtype).expand_as(d)
    alt = torch.tensor([1.0, 0.0, 0.0], dtype=d.dtype).expand_as(d)
    up0 = torch.where((d[:, 2].abs() > 0.99)[:, None], alt, up0)
    right = torch.linalg.cross(d, up0)
    right = right / right.norm(dim=1, keepdim=True)
    up = torch.linalg.cross(right, d)
    half = float(np.tan(np.radians(fov_deg) / 2))
    g = ((torch.arange(n_side, dtype=d.dtype) + 0.5) / n_side * 2 - 1) * half
    u, v = torch.meshgrid(g, g, indexing="ij")
    u, v = u.reshape(-1), v.reshape(-1)  # (R,)
    rays = d[:, None] + u[None, :, None] * right[:, None] + v[None, :, None] * up[:, None]
    rays = rays / rays.norm(dim=2, keepdim=True)
    return positions[:, None].expand_as(rays), rays


HIT_SUMMARIES = ("expected-point", "distribution")


def camera_score(field, positions, directions, center, radius, fov_deg=30.0, n_side=3, n_samples=24,
                 method="genz", qmc_samples=128, seed=0, observed=None, observed_scale=None,
                 hit_summary="expected-point"):
    """Variance where each camera's rays are expected to hit (see the module docstring).

    Parameters
    ----------
    field : StochasticField or a toy with ``torch_mean``/``torch_variance``/``torch_covariance`` (world frame)
    positions, directions : (C, 3) tensors
    center : (3,) array, radius : float
        Bounding sphere of the part: each ray is sampled where it can meet the sphere, from
        max(|p - c| - radius, 0) to |p - c| + radius (the range is not differentiated).
    fov_deg, n_side : see :func:`camera_rays`.
    n_samples : int
        Samples per ray (K).
    method, qmc_samples, seed : see :func:`autodecoder.scanning.rays.cast_rays`.
    observed : (m, 3) tensor or array, optional
        Points already measured (world frame). When given, each ray's term is multiplied by the novelty of its
        expected hit point (see the module docstring); None scores the variance alone.
    observed_scale : float, optional
        s of the novelty factor (world units); required with ``observed``.
    hit_summary : {'expected-point', 'distribution'}
        'expected-point' (the paper's): P(hit) Var f(x_hat) novelty(x_hat) at the expected hit point x_hat.
        'distribution': the expectation over the first-hit distribution instead,
        sum_k P(first hit in bin k) Var f(x_k) novelty(x_k) at the ray's samples x_k (the variances are the
        diagonal of the ray's covariance, already computed). Where a ray may hit either of two surfaces (at a
        silhouette, or past a thin part) the expected hit point lies in the empty space between them, where the
        variance is that of no surface at all; the distribution scores the surfaces the ray can actually meet.

    Returns
    -------
    (C,) tensor, world units squared.
    """
    if hit_summary not in HIT_SUMMARIES:
        raise ValueError(f"hit_summary must be one of {HIT_SUMMARIES}, got {hit_summary!r}")
    C = len(positions)
    origins, rays = camera_rays(positions, directions, fov_deg, n_side)
    R = rays.shape[1]
    c = torch.as_tensor(center, dtype=positions.dtype)
    dist = (positions - c).norm(dim=1).detach()
    t_near = (dist - radius).clamp_min(0.0)[:, None].expand(C, R).reshape(-1)
    t_far = (dist + radius)[:, None].expand(C, R).reshape(-1)
    cast = cast_rays(field, origins.reshape(-1, 3), rays.reshape(-1, 3), t_near, t_far, n_samples=n_samples,
                     method=method, qmc_samples=qmc_samples, seed=seed)
    if hit_summary == "expected-point":
        x = cast.expected_point.to(positions.dtype)  # (B, 3)
        weight = cast.p_hit.to(positions.dtype)[:, None]  # (B, 1)
        var = field.torch_variance(x).to(positions.dtype)[:, None]
        x = x[:, None]
    else:
        rays_unit = rays.reshape(-1, 3) / rays.reshape(-1, 3).norm(dim=1, keepdim=True).clamp_min(1e-30)
        x = origins.reshape(-1, 3)[:, None] + cast.t.to(positions.dtype)[..., None] * rays_unit[:, None]  # (B, K, 3)
        weight = cast.p_bins.to(positions.dtype)  # (B, K)
        var = torch.diagonal(cast.cov, dim1=1, dim2=2).to(positions.dtype)
    score = weight * var
    if observed is not None:
        if observed_scale is None or not observed_scale > 0:
            raise ValueError(f"observed_scale must be > 0 with observed points, got {observed_scale}")
        score = score * _novelty(x.reshape(-1, 3), observed, observed_scale).reshape(score.shape)
    return score.sum(1).reshape(C, R).mean(1)


def _novelty(x, observed, scale):
    """1 - exp(-d^2 / (2 s^2)), d the distance of each of x (m, 3) to the nearest observed point -> (m,)."""
    seen = torch.as_tensor(observed, dtype=x.dtype)
    # nearest measured point, in chunks so that a large cloud does not make one (points x measured) matrix
    d = torch.cat([torch.cdist(x, chunk).min(1, keepdim=True).values for chunk in seen.split(8192)], 1)
    d = d.min(1).values
    return 1 - torch.exp(-(d**2) / (2 * float(scale) ** 2))


def far_field_inside_fraction(field, n=512, threshold=0.25, seed=0):
    """Fraction of the field's box boundary where P(f <= 0) > ``threshold``.

    The box's boundary should be outside the part. A field fitted to a partial scan with the paper's loss
    (``FitOptions.outside_weight=0``) leaves the scanned sheet open, so far from it the mean sits at the surface's
    own level and about half of the boundary is likely "inside" (the median of the mean there is 0); rays through
    such a field hit empty space. A closed cloud, or one fitted with the boundary term, gives ~0.

    Parameters
    ----------
    field : StochasticField (``bounds`` and ``prob_inside``)
    n : int
        Boundary samples.
    threshold : float
    seed : int

    Returns
    -------
    float in [0, 1]
    """
    lo, hi = np.asarray(field.bounds, dtype=np.float64)
    x = Box(lo, hi).surface(n, np.random.default_rng(seed))
    return float(np.mean(field.prob_inside(x) > threshold))


def _project_to_cone(a, to_center, tolerance):
    """Unit directions a (C, 3) rotated, where needed, into the cone of axes that pass within ``tolerance``
    (distance / radius, ``to_center`` in radii) of the centre: half-angle asin(min(1, tolerance / |to_center|))."""
    a = a / a.norm(dim=1, keepdim=True).clamp_min(1e-30)
    dist = to_center.norm(dim=1, keepdim=True).clamp_min(1e-12)
    u = to_center / dist
    cos_max = torch.cos(torch.asin((tolerance / dist).clamp(max=1.0)))
    cos_a = (a * u).sum(1, keepdim=True)
    w = a - cos_a * u
    w = w / w.norm(dim=1, keepdim=True).clamp_min(1e-30)
    sin_max = (1 - cos_max**2).clamp_min(0.0).sqrt()
    return torch.where(cos_a >= cos_max, a, cos_max * u + sin_max * w)


def _sphere_starts(n, rng):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def next_best_views(field, n_views=5, starts=16, steps=60, standoff=(1.5, 2.5), fov_deg=30.0, n_side=3,
                    n_samples=24, lr=0.05, aim_weight=1.0, aim_tolerance=0.2, min_separation_deg=15.0,
                    method="genz", qmc_samples=128, seed=0, observed="auto", observed_scale=None, candidates=None,
                    hit_summary="expected-point"):
    """Rank camera placements by :func:`camera_score` after multi-start gradient ascent.

    Parameters
    ----------
    field : StochasticField (or a toy with the same torch methods)
    n_views : int
        Views returned (at most ``starts``).
    starts : int
        Starting cameras of the gradient ascent: random cameras uniform on the sphere of mid stand-off radius,
        aimed at the centre (or the best-scoring ``starts`` of ``candidates`` such cameras).
    steps : int
        Adam steps.
    standoff : (2,) floats
        Allowed distance from the part's centre, in multiples of its bounding-sphere radius (projected after every
        step).
    fov_deg, n_side, n_samples : see :func:`camera_score`.
    lr : float
        Adam learning rate; positions move in units of the bounding-sphere radius, directions are unit vectors.
    aim_weight, aim_tolerance : float
        The optical axis must pass within aim_tolerance x radius of the part's centre: enforced by projecting the
        direction into that cone after every step, with a smooth penalty
        aim_weight * max(0, dist(centre, axis) / radius - aim_tolerance)^2 on the normalised score during it.
    min_separation_deg : float
        Returned views are at least this far apart in angle around the centre (greedy by score).
    method, qmc_samples : see :func:`autodecoder.scanning.rays.cast_rays`.
    seed : int
    observed : (m, 3) array, 'auto' or None
        Points already measured, for the novelty factor of :func:`camera_score`. 'auto' (default): the field's
        ``training_points`` when it carries them (else no factor); None: the variance alone.
    observed_scale : float, optional
        s of the novelty factor, world units; default one kernel support, 2 x the field's kernel lengthscale
        (``field.lengthscale``, world units).
    candidates : int, optional
        Random cameras scored (one pass, no gradient, a fraction of an ascent step each) to choose the starts
        from; default ``starts`` (plain random starts). A local ascent moves a camera a few tens of degrees at
        most, so on a toy field the screened starts find the high-variance side without any ascent step. On
        fandisk's one-scan fields it did not help: cameras on quite different sides score nearly alike, the
        maximiser is sometimes a near repeat of the first view, and a wider search then picks worse views; the
        score, not the search, is the weak part (docs/results.md#scanning-partial-scan-fields-and-next-best-view).
    hit_summary : {'expected-point', 'distribution'}
        See :func:`camera_score`. The paper's 'expected-point' stays the default: on fandisk the distribution
        chose worse views and ranked cameras no better
        (docs/results.md#scanning-partial-scan-fields-and-next-best-view).

    Returns
    -------
    list of ViewCandidate, best first.
    """
    candidates, lo_r, hi_r = _check_view_options(n_views, starts, candidates, standoff)
    observed, observed_scale = _observed_points(field, observed, observed_scale)
    _warn_if_half_solid(field)
    rng = np.random.default_rng(seed)
    center, radius = part_sphere(field)
    c = torch.as_tensor(center, dtype=torch.float32)

    def score_of(q_, a_):
        return camera_score(field, c + q_ * radius, a_, center, radius, fov_deg, n_side, n_samples, method,
                            qmc_samples, seed, observed, observed_scale, hit_summary)

    dirs0 = _sphere_starts(candidates, rng)
    if candidates > starts:
        dirs0 = _best_starts(score_of, dirs0, starts, (lo_r + hi_r) / 2)
    q, a = _ascend(score_of, dirs0, steps, lr, (lo_r, hi_r), aim_weight, aim_tolerance)
    with torch.no_grad():
        final = score_of(q, a).double().numpy()
    positions = center + q.detach().double().numpy() * radius
    directions = a.detach().double().numpy()
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    out = []
    for i in _separated_best(final, positions - center, n_views, min_separation_deg):
        p, d = positions[i], directions[i]
        look_at = p + np.dot(center - p, d) * d
        out.append(ViewCandidate(position=p, direction=d, score=float(final[i]), look_at=look_at))
    return out


def _check_view_options(n_views, starts, candidates, standoff):
    """(candidates, min stand-off, max stand-off) of :func:`next_best_views`, checked."""
    if starts < 1 or n_views < 1:
        raise ValueError(f"starts and n_views must be >= 1, got {starts} and {n_views}")
    candidates = starts if candidates is None else int(candidates)
    if candidates < starts:
        raise ValueError(f"candidates must be >= starts ({starts}), got {candidates}")
    lo_r, hi_r = float(standoff[0]), float(standoff[1])
    if not 0 < lo_r <= hi_r:
        raise ValueError(f"standoff must be (min, max) with 0 < min <= max, got {standoff}")
    return candidates, lo_r, hi_r


def _observed_points(field, observed, observed_scale):
    """(observed (m, 3) float32 tensor or None, novelty scale s) of :func:`next_best_views`: 'auto' takes the field's
    training points; the scale defaults to one kernel support in world units."""
    if isinstance(observed, str):
        if observed != "auto":
            raise ValueError(f"observed must be points, 'auto' or None, got {observed!r}")
        observed = field.training_points
    if observed is None:
        return None, observed_scale
    observed = torch.as_tensor(np.asarray(observed, dtype=np.float32))
    if observed.ndim != 2 or observed.shape[1] != 3 or len(observed) == 0:
        raise ValueError(f"observed must be (m, 3) points with m >= 1, got shape {tuple(observed.shape)}")
    if not torch.isfinite(observed).all():
        raise ValueError("observed points contain NaN or infinite coordinates")
    if observed_scale is None:
        if field.lengthscale is None:
            raise ValueError("observed_scale is needed for a field without a kernel lengthscale")
        observed_scale = 2.0 * field.lengthscale
    return observed, observed_scale


def _warn_if_half_solid(field):
    """Warn (at the caller of :func:`next_best_views`) when much of the field's box boundary is likely inside."""
    if field.bounds is not None:
        inside = far_field_inside_fraction(field)
        if inside > HALF_SOLID_FRACTION:
            warnings.warn(f"{inside:.0%} of the field's box boundary is likely inside the part (P(f <= 0) > 0.25): "
                          "the far field sits at the surface's own level, as for a partial scan fitted with the "
                          "paper's loss, so rays 'hit' empty space and the views rank its variance. Fit partial "
                          "scans with fit_cloud(..., representation='siren', outside_weight=100).", UserWarning,
                          stacklevel=3)


def _best_starts(score_of, dirs, starts, mid):
    """The ``starts`` of the candidate directions (k, 3) whose cameras (at stand-off ``mid``, aimed at the centre)
    score best, in one pass without gradients."""
    with torch.no_grad():
        pool = torch.tensor(dirs, dtype=torch.float32)
        first = score_of(pool * mid, -pool).double().numpy()
    return dirs[np.argsort(-np.nan_to_num(first, nan=-np.inf))[:starts]]


def _ascend(score_of, dirs0, steps, lr, standoff, aim_weight, aim_tolerance):
    """Adam ascent of the normalised score minus the aim penalty from cameras at ``dirs0`` (k, 3) x mid stand-off,
    aimed at the centre; positions q (in radii around the centre) and directions a are projected back onto the
    stand-off shell and the aim cone after every step. Returns (q (k, 3), a (k, 3)) tensors."""
    lo_r, hi_r = standoff
    # optimise in units of the radius around the centre, so one learning rate fits parts of any size
    q = torch.tensor(dirs0 * (lo_r + hi_r) / 2, dtype=torch.float32, requires_grad=True)
    a = torch.tensor(-dirs0, dtype=torch.float32, requires_grad=True)
    opt = torch.optim.Adam([q, a], lr=lr)

    with torch.no_grad():
        scale = score_of(q, a).mean().clamp_min(1e-30)
    for _ in range(steps):
        opt.zero_grad(set_to_none=True)
        s = score_of(q, a) / scale
        d = a / a.norm(dim=1, keepdim=True)
        # distance of the centre from the optical axis, in radii: |(-q) - ((-q).d) d|
        off_axis = (-q - ((-q) * d).sum(1, keepdim=True) * d).norm(dim=1)
        penalty = aim_weight * torch.relu(off_axis - aim_tolerance) ** 2
        (-(s - penalty).sum()).backward()
        # a start whose rays graze the part can get a non-finite gradient (the orthant probabilities' derivatives
        # at the clamped tails); it must not poison the others: zero it, and undo any step that left a start
        # non-finite
        for p_ in (q, a):
            p_.grad = torch.nan_to_num(p_.grad, nan=0.0, posinf=0.0, neginf=0.0)
        before = q.detach().clone(), a.detach().clone()
        opt.step()
        with torch.no_grad():
            r = q.norm(dim=1, keepdim=True)
            q.mul_(r.clamp(lo_r, hi_r) / r.clamp_min(1e-12))
            a.copy_(_project_to_cone(a, -q, aim_tolerance))
            broken = ~(torch.isfinite(q).all(1) & torch.isfinite(a).all(1))
            if bool(broken.any()):
                q[broken], a[broken] = before[0][broken], before[1][broken]
    return q, a


def _separated_best(scores, offsets, n_views, min_separation_deg):
    """Indices of up to ``n_views`` cameras, best ``scores`` (k,) first, each at least ``min_separation_deg`` in angle
    around the centre from those chosen before it (greedy); ``offsets`` (k, 3) are positions minus the centre."""
    chosen = []
    cos_sep = np.cos(np.radians(min_separation_deg))
    for i in np.argsort(-scores):
        u = offsets[i] / np.linalg.norm(offsets[i])
        if all(np.dot(u, offsets[j] / np.linalg.norm(offsets[j])) < cos_sep for j in chosen):
            chosen.append(i)
        if len(chosen) == n_views:
            break
    return chosen
