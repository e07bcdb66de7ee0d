"""Free space seen by a sensor: how likely a stochastic field puts solid material on the rays a scan travelled.

A depth sensor at o that returned a point p saw free space from o up to p: had there been material on the way, the
ray would have stopped there. A ray that returned nothing saw free space all the way through. Under a stochastic
field f (f < 0 inside) the probability that a segment of the ray x(t) = o + t d is free is a correlated survival
(an orthant probability, see :mod:`autodecoder.scanning.rays`)::

    P(free) = P(f(x(t)) > 0 for every tested t),      P(blocked) = 1 - P(free),

and -log P(free) is the ray's negative log likelihood: how surprising it is, under the field, that the sensor saw
free space there. A scan of a good part gives P(blocked) ~ 0 on every ray. Material missing from the part shows as
rays the model expects to be blocked: a point seen through a hole in a thin wall lies on a good surface behind the
hole (its own residual is small) but its ray went through where the wall should be; a hole with nothing behind it
returns no points at all, but the rays through it should have hit the wall.

Which samples of a ray are tested
---------------------------------
* **Start.** t_near is where the ray enters the field's box (``field.bounds``; 0 when the field has none): outside
  it the field was never trained, and the sensor's surroundings are no concern of the model.
* **End, for a returned point p** (:func:`blocked_probability`): the last *clearly outside* sample before p, where
  E f >= ``outside_sigma`` sd f (default 2), or ``own_depth`` before p, whichever comes later. Between that end and
  p lies the point's own surface, left out however far the field's mean surface sits from p up to ``own_depth``:
  the latent fields are not distances (E f saturates a short way off the surface) and their mean surface sits up
  to a few lengthscales off good points at features the projection cannot follow, as deep as a pit
  (docs/results.md#free-space-along-the-sensors-rays). Without the depth limit (``own_depth=None``) the test is only for
  material *separated from the point by free space*; that misses the case the rays exist for on thin-walled parts
  (the benchmarks' thin-walled enclosure; docs/results_archive.md): seen through a hole in a sheet, a point on the far side of a cavity lies deep inside
  what a one-sided view's field calls solid (a partial scan's Poisson field is negative everywhere behind the
  surface it saw), so no sample after the sheet is clearly outside and the whole ray, sheet included, was taken
  for the point's own surface. With the limit, material more than ``own_depth`` before the point is tested
  whatever lies between: a point that deep inside the expected material was seen through it. Default (
  :data:`OWN_DEPTH_FACTOR` = 3 kernel lengthscales): beyond the kernel's support (2 lengthscales), so the
  blur of the point's own surface never counts.
* **End, for a ray with no return** (:func:`missing_return_probability`): where the ray leaves the box.
* **Observed surfaces.** Given the scan's points (``observed``), samples within ``clearance`` (default the kernel
  lengthscale) of any of them are left out: material next to a surface the scan saw is that surface, blurred by the
  field's resolution. Rays that graze the rim of a wall on their way to the far wall pass through the field's
  rounded rim, many sd deep, on good scans; a hole's middle is more than a lengthscale from its rim.
* **Rays that pass through the scan's own surface** (:func:`blocked_probability`, with ``observed``): a returned
  ray that comes within ``occlusion_radius`` (default twice the observed points' median spacing, at most the
  clearance) of one of the scan's own points more than ``own_depth`` before its point, that point being the nearest
  and the ray on the side of it where the surface the scan saw is (beside a hole's rim or a silhouette, only
  where the surface goes on: :func:`surface_sides`), is not tested at all (``through_observed``). Had the sensor looked
  along it, that surface would have hidden the point: the ray is not one the sensor travelled, and the sensor origin
  it was drawn from is wrong (users write a nominal stand-off and axis, not a calibrated optical centre; a line
  scanner has no single centre). Such a ray runs beside the true one, past the edge of something the scan saw, and
  through the unseen far side of it that good scans have: on real range scans with approximate origins every
  accusation of a good scan's returned rays was of this kind (within 0.05-0.4 lengthscales of the scan's own
  points), while the rays through missing material passed 0.5-3 lengthscales from them (docs/results.md). A ray
  seen through a hole in a sheet passes the hole's rim, the border of the surface, not through it: where the origin
  is right the rule costs the holes nothing. The share of such rays says how far off the origin is.
* **Missing returns end at their rim** (:func:`missing_return_probability`, ``t_max``): a ray that returned nothing
  is tested only up to a given depth per ray; the inspection gives the nearest return around the gap plus
  ``own_depth``. A hole in a wall is missing where its rim is; material far behind the nearest return around a gap
  is what an origin error uncovers beside a depth jump (the shadow of an edge, which the sensor never saw), not a
  hole.
* **Where good parts have a surface** (``band``, a :class:`SurfaceBand` of good scans' points): only samples
  within its radius of a good scan's point are tested. A partial scan's Poisson field is one-sided: it is negative
  everywhere behind the surface the scan saw, so on an open or thin-walled part it fills the cavity behind a sheet
  and the part's real openings too, and the rays of good scans through an opening cross that extrapolated
  "material" (a ray through a wall 5 sd deep costs ~15 nats). What the sensor can show missing is a wall that good
  parts have: a ray through a hole in a sheet crosses the sheet where good scans returned points. Material the
  field extrapolated where no good scan ever saw a surface is the field's business, not evidence of a defect.
* **Not where the ray skims past a good surface** (the band's ``normals`` and ``min_cos``): a sample on the outer
  side of the nearest good surface point, whose normal makes |cos| < ``min_cos`` with the ray, is left out. A ray
  that passes a silhouette edge runs along the surface there, outside it, through the field's blurred (and, where
  the scan saw no point, extrapolated) rim, and a good scan's rays were accused there by hundreds of nats (fandisk:
  docs/results.md, issue 29). A ray through a hole in a wall crosses the wall, and one through missing material runs
  inside where good parts have material; one that runs along a surface's outer side has nothing to see missing
  there.

How the probability is computed
-------------------------------
1. **Marginals on a dense grid.** E f and Var f at samples spaced at most ``step`` apart (default half the kernel
   lengthscale: the field represents nothing thinner) give q_j = P(f_j <= 0). They are read only where they can
   matter: at the samples the rules above leave testable (observed surfaces, the band, the skim rule: none of these
   reads the field) and within ``own_depth`` of the point, where the segment's end is decided; every earlier sample
   lies outside the tested segment whatever the field says there.
2. **Correlated survival on the samples that matter.** The ``n_select`` tested samples with the largest q_j (in ray
   order) get their full covariance (:func:`autodecoder.scanning.rays.ray_gaussian`) and the Genz orthant probability
   (:func:`autodecoder.scanning.rays.orthant_survival`). Leaving samples out can only raise the survival, so the value is a
   lower bound of the blocked probability of the whole tested segment, and at least max_j q_j (one sample alone).
   Rays with max_j q_j below ``q_floor`` skip this step and report max_j q_j. log P(free) is kept apart from
   P(blocked) (1 - P(blocked) cancels to 0 for rays through material many sd deep), floored at log(1e-300).

Cost: one mean and one variance evaluation per dense sample that can matter (with a band, a small share of them),
plus n_select (n_select + 1) / 2 covariance pairs per ray above the floor (timings: docs/results.md#free-space-along-the-sensors-rays).
"""
import math
from dataclasses import dataclass

import numpy as np
import torch

from autodecoder.scanning.own_surface import (BOUNDARY_GAP, BOUNDARY_NEIGHBOURS, median_spacing, passes_through,
                                              surface_sides)
from autodecoder.scanning.rays import orthant_survival, ray_gaussian
from autodecoder.scanning.surface_band import SurfaceBand
from datasets.validation import check_points

__all__ = ["blocked_probability", "missing_return_probability", "FreeSpaceCheck", "box_interval", "SurfaceBand",
           "median_spacing", "passes_through", "surface_sides", "MAX_SURPRISAL", "OWN_DEPTH_FACTOR",
           "OCCLUSION_SPACINGS", "BOUNDARY_NEIGHBOURS", "BOUNDARY_GAP", "SUSPECT_NATS", "DEFAULT_OUTSIDE_SIGMA",
           "DEFAULT_MAX_SAMPLES", "DEFAULT_SELECT", "DEFAULT_Q_FLOOR"]

DEFAULT_OUTSIDE_SIGMA = 2.0
DEFAULT_MAX_SAMPLES = 128
DEFAULT_SELECT = 8
DEFAULT_Q_FLOOR = 1e-3
OWN_DEPTH_FACTOR = 3.0  # default own_depth in kernel lengthscales (see the module docstring)
SUSPECT_NATS = 1e-3  # rays with less surprisal are not checked for passing through the scan's own surface
# how close to a scan's own point a ray must come to have passed through its surface, in the points' median spacing:
# the point nearest to where a ray crosses a randomly sampled surface is within 2 spacings 19 times in 20 (its
# distance from a random place of a Poisson pattern exceeds r with probability exp(-pi r^2 / (4 s^2)), s the mean
# spacing; the samples along the ray, half that apart, add little)
OCCLUSION_SPACINGS = 2.0
_MIN_VARIANCE = 1e-20
MAX_SURPRISAL = -math.log(1e-300)  # the largest surprisal -log P(free) a ray can have: 690.8 nats (P(free) is floored)
_LOG_FLOOR = -MAX_SURPRISAL


@dataclass
class FreeSpaceCheck:
    """Result of :func:`blocked_probability` for B rays (numpy arrays, world frame).

    Attributes
    ----------
    p_blocked : (B,) float64
        P(the segment [t_near, t_end] crosses f <= 0): the free-space violation of each ray, in [0, 1].
    log_free : (B,) float64
        log(1 - p_blocked), computed without cancellation (the rays' log likelihood; >= log(1e-300)).
    max_marginal : (B,) float64
        max_j P(f <= 0) over the dense samples (a lower bound of ``p_blocked``).
    t_near, t_end, t_obs : (B,) float64
        Start and end of the tested segment and the distance to the observed point (t_end <= t_near: nothing was
        tested, p_blocked = 0).
    t_block : (B,) float64
        Distance of the sample most likely inside (where the blocking material would be; NaN when untested).
    t_enter : (B,) float64
        Distance of the first tested sample with P(f <= 0) >= 1/2: where the ray enters the expected material
        (NaN when it never does).
    through_observed : (B,) bool
        The ray passes through the scan's own surface before its point (module docstring): not tested, p_blocked 0.
    """

    p_blocked: np.ndarray
    log_free: np.ndarray
    max_marginal: np.ndarray
    t_near: np.ndarray
    t_end: np.ndarray
    t_obs: np.ndarray
    t_block: np.ndarray
    t_enter: np.ndarray = None
    through_observed: np.ndarray = None


def box_interval(origin, directions, bounds):
    """Where rays from ``origin`` (3,) along unit ``directions`` (B, 3) enter and leave a box (2, 3) (min, max
    corners): (t_in, t_out), (B,) each, t_in >= 0; rays that miss the box (or leave it behind the origin) get
    t_in = t_out = 0."""
    lo, hi = np.asarray(bounds, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - origin) / directions
        t2 = (hi - origin) / directions
    # 0 / 0: the ray runs in a face's plane; treat that axis as no constraint
    t_min = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2)).max(1)
    t_max = np.where(np.isnan(t1), np.inf, np.maximum(t1, t2)).min(1)
    hit = (t_max >= np.maximum(t_min, 0.0))
    return np.where(hit, np.maximum(t_min, 0.0), 0.0), np.where(hit, t_max, 0.0)


@dataclass
class _Options:
    """Settings shared by both public functions (see :func:`blocked_probability`)."""

    step: float = None
    max_samples: int = DEFAULT_MAX_SAMPLES
    n_select: int = DEFAULT_SELECT
    q_floor: float = DEFAULT_Q_FLOOR
    qmc_samples: int = 256
    seed: int = 0
    chunk: int = 256
    observed: np.ndarray = None
    clearance: float = None
    own_depth: float = None
    band: object = None
    occlusion_radius: object = None

    def resolved_occlusion_radius(self, tree):
        """``occlusion_radius`` in world units: 'auto' is ``OCCLUSION_SPACINGS`` x the median spacing of the
        observed points in ``tree``, at most the clearance (a ray through a hole that passes the hole's rim closer
        than that is untested where it crosses the wall anyway)."""
        if self.occlusion_radius != "auto":
            return float(self.occlusion_radius)
        return min(OCCLUSION_SPACINGS * median_spacing(tree), self.clearance)

    @property
    def observed_count(self):
        """How many observed points there are (0: none)."""
        if self.observed is None:
            return 0
        return int(self.observed.n) if hasattr(self.observed, "n") else len(self.observed)

    def check(self, field):
        if not (int(self.max_samples) >= 3 and int(self.n_select) >= 1 and self.q_floor >= 0):
            raise ValueError(f"need max_samples >= 3, n_select >= 1, q_floor >= 0; got {self.max_samples}, "
                             f"{self.n_select}, {self.q_floor}")
        if self.step is not None and not self.step > 0:
            raise ValueError(f"step must be > 0 (world units), got {self.step}")
        scale = field.lengthscale
        if self.observed is not None:
            from scipy.spatial import cKDTree

            if isinstance(self.observed, cKDTree):  # a tree over them, used as it is (no second build)
                check_points(self.observed.data, "observed points", min_points=0)
            else:
                self.observed = check_points(self.observed, "observed points", min_points=0)
            if self.clearance is None:
                if scale is None:
                    raise ValueError("the field does not say its lengthscale: give clearance (world units) with the "
                                     "observed points")
                self.clearance = scale
            if not self.clearance >= 0:
                raise ValueError(f"clearance must be >= 0 (world units), got {self.clearance}")
        if self.own_depth == "auto":
            self.own_depth = None if scale is None else OWN_DEPTH_FACTOR * scale
        if self.occlusion_radius not in (None, "auto") and not float(self.occlusion_radius) > 0:
            raise ValueError(f"occlusion_radius must be None, 'auto' or > 0 (world units), got "
                             f"{self.occlusion_radius!r}")
        if self.own_depth is not None and not float(self.own_depth) > 0:
            raise ValueError(f"own_depth must be None, 'auto' or > 0 (world units), got {self.own_depth!r}")
        return self


def _check_origin(origin):
    origin = np.asarray(origin, dtype=np.float64).reshape(-1)
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise ValueError(f"origin must be 3 finite numbers (the sensor position), got {origin.tolist()}")
    return origin


def blocked_probability(field, origin, points, outside_sigma=DEFAULT_OUTSIDE_SIGMA, observed=None, clearance=None,
                        step=None, max_samples=DEFAULT_MAX_SAMPLES, n_select=DEFAULT_SELECT,
                        q_floor=DEFAULT_Q_FLOOR, qmc_samples=256, seed=0, chunk=256, own_depth="auto", band=None,
                        occlusion_radius="auto"):
    """Probability that the field puts solid material on the sensor's rays to observed points, apart from the
    surface the points lie on (see the module docstring for which part of each ray is tested).

    Parameters
    ----------
    field : autodecoder.field.protocol.Field
        World frame; its ``bounds`` and ``lengthscale`` are used when it has them.
    origin : (3,) array
        The sensor position, in the field's frame (outside the part).
    points : (B, 3) array
        Observed points (returns of rays from ``origin``), in the field's frame.
    outside_sigma : float
        A sample is clearly outside when E f >= outside_sigma x sd f (P(f <= 0) <= Phi(-outside_sigma)).
    observed : (n, 3) array or a scipy.spatial.cKDTree over them, optional
        Every point the scan returned (usually a superset of ``points``): samples within ``clearance`` of one of
        them are left out (see the module docstring). None: no sample is left out for it. A tree is used as it is
        (a caller testing several sets of rays of one scan builds it once).
    clearance : float, optional
        World units; default the field's kernel lengthscale.
    step : float, optional
        Largest spacing of the dense samples (world units); default half the field's kernel lengthscale, else
        the longest segment / (max_samples - 1).
    max_samples : int
        Cap on the dense samples per ray (>= 3): the spacing grows beyond ``step`` when a segment is longer.
    n_select : int
        Samples per ray in the correlated (orthant) probability (>= 1; 1: the largest marginal alone).
    q_floor : float
        Rays whose largest marginal is below it skip the orthant probability.
    qmc_samples, seed : int
        Sobol points and scrambling seed of the Genz estimator (deterministic for a given seed).
    chunk : int
        Rays per batch (bounds the memory: chunk x max_samples points at a time).
    own_depth : float, 'auto' or None
        The point's own surface is at most this far before it (world units): material farther back is tested even
        when no clearly outside sample separates it from the point. 'auto': ``OWN_DEPTH_FACTOR`` x the field's
        kernel lengthscale (None when the field does not say it); None: no limit (only material separated from
        the point by a clearly outside sample is tested).
    band : SurfaceBand, optional
        Where good parts have a surface (field frame): only samples inside it are tested. None: every sample.
    occlusion_radius : float, 'auto' or None
        With ``observed``: a ray that comes this close to an observed point more than ``own_depth`` (without a depth
        limit, ``OWN_DEPTH_FACTOR`` kernel lengthscales) before its point passed through the scan's own surface and
        is not tested (module docstring; world units). 'auto': ``OCCLUSION_SPACINGS`` (2) x the observed points'
        median spacing, at most the clearance; None: every ray is tested.

    Returns
    -------
    FreeSpaceCheck

    Raises
    ------
    ValueError
        Bad shapes, non-finite values, a point at the sensor origin, or bad settings.
    """
    points = check_points(points, "points")
    origin = _check_origin(origin)
    if not outside_sigma >= 0:
        raise ValueError(f"outside_sigma must be >= 0, got {outside_sigma}")
    opts = _Options(step, max_samples, n_select, q_floor, qmc_samples, seed, chunk, observed, clearance,
                    own_depth, band, occlusion_radius).check(field)
    offsets = points - origin
    t_obs = np.linalg.norm(offsets, axis=1)
    if (t_obs <= 0).any():
        raise ValueError(f"{int((t_obs <= 0).sum())} points coincide with the sensor origin {origin.tolist()}")
    d = offsets / t_obs[:, None]
    bounds = field.bounds
    t_near = np.zeros(len(points)) if bounds is None else np.minimum(box_interval(origin, d, bounds)[0], t_obs)
    q_out = 0.5 * math.erfc(outside_sigma / math.sqrt(2))
    return _segments(field, origin, d, t_near, t_obs, q_out, opts)


def missing_return_probability(field, origin, directions, t_far=None, observed=None, clearance=None, step=None,
                               max_samples=DEFAULT_MAX_SAMPLES, n_select=DEFAULT_SELECT, q_floor=DEFAULT_Q_FLOOR,
                               qmc_samples=256, seed=0, chunk=256, band=None, t_max=None):
    """Probability that rays which returned nothing should have hit solid material under the field.

    Parameters
    ----------
    field : see :func:`blocked_probability`
    origin : (3,) array
        The sensor position (field frame).
    directions : (B, 3) array
        Directions of rays that returned no point (normalised here).
    t_far : float, optional
        Where the rays end when the field has no ``bounds``; with bounds, each ray is tested through the box
        (rays that miss the box get 0). The whole range is tested: a ray that returned nothing has no surface of
        its own to leave out.
    observed, clearance, step, max_samples, n_select, q_floor, qmc_samples, seed, chunk, band
        As in :func:`blocked_probability`.
    t_max : (B,) array, optional
        Each ray is tested no farther than this (world units from ``origin``; module docstring, "Missing returns
        end at their rim"). None: through the box (or to ``t_far``).

    Returns
    -------
    FreeSpaceCheck
        ``t_obs`` holds the end of each ray's range (the box exit, or ``t_far``, or ``t_max`` where nearer).
    """
    d = check_points(directions, "directions")
    origin = _check_origin(origin)
    opts = _Options(step, max_samples, n_select, q_floor, qmc_samples, seed, chunk, observed, clearance,
                    band=band).check(field)
    length = np.linalg.norm(d, axis=1)
    if (length <= 0).any():
        raise ValueError(f"{int((length <= 0).sum())} ray directions have zero length")
    d = d / length[:, None]
    bounds = field.bounds
    if bounds is not None:
        t_near, t_stop = box_interval(origin, d, bounds)
    elif t_far is not None and t_far > 0:
        t_near, t_stop = np.zeros(len(d)), np.full(len(d), float(t_far))
    else:
        raise ValueError("the field has no bounds: give t_far (> 0), where the rays end")
    if t_max is not None:
        t_max = np.asarray(t_max, dtype=np.float64).reshape(-1)
        if t_max.shape != (len(d),) or np.isnan(t_max).any():
            raise ValueError(f"t_max: one number per ray ({len(d)}), got shape {t_max.shape}")
        t_stop = np.minimum(t_stop, np.maximum(t_max, t_near))
    return _segments(field, origin, d, t_near, t_stop, None, opts)


def _segments(field, origin, d, t_near, t_stop, q_out, opts):
    """Both public functions: rays from ``origin`` along unit ``d`` (B, 3), tested on [t_near, end <= t_stop];
    ``q_out`` None tests the whole range."""
    step = opts.step
    if step is None:
        scale = field.lengthscale
        longest = float((t_stop - t_near).max()) if len(d) else 0.0
        step = 0.5 * scale if scale else max(longest, 1e-12) / (opts.max_samples - 1)
    tree = None
    if opts.observed is not None and opts.observed_count and opts.clearance > 0:
        from scipy.spatial import cKDTree

        tree = opts.observed if isinstance(opts.observed, cKDTree) else cKDTree(opts.observed)
    keys = ("log_free", "max_marginal", "t_end", "t_block", "t_enter")
    out = {k: np.empty(len(d)) for k in keys}
    with torch.no_grad():
        for s in range(0, len(d), opts.chunk):
            sl = slice(s, s + opts.chunk)
            res = _check_segments(field, origin, d[sl], t_near[sl], t_stop[sl], step, q_out, tree, opts)
            for k in keys:
                out[k][sl] = res[k]
    through = np.zeros(len(d), dtype=bool)
    if q_out is not None and opts.observed_count and opts.occlusion_radius is not None:
        # only a ray with something to clear is checked: below SUSPECT_NATS its surprisal changes nothing
        suspect = np.flatnonzero(out["log_free"] < -SUSPECT_NATS)
        if len(suspect):
            if tree is None:
                from scipy.spatial import cKDTree

                tree = opts.observed if isinstance(opts.observed, cKDTree) else cKDTree(opts.observed)
            # the point's own surface: within own_depth before it (without a depth limit, OWN_DEPTH_FACTOR kernel
            # lengthscales: a ray that meets its surface at |cos| >= 0.2 is then a spacing above it and more)
            scale = field.lengthscale
            depth = opts.own_depth if opts.own_depth is not None else \
                (OWN_DEPTH_FACTOR * scale if scale else opts.clearance)
            radius = opts.resolved_occlusion_radius(tree)
            if radius > 0:
                through[suspect] = passes_through(tree, origin, d[suspect], t_near[suspect],
                                                  t_stop[suspect] - depth, radius)
            out["log_free"][through] = 0.0
            out["max_marginal"][through] = 0.0
            out["t_block"][through] = np.nan
    return FreeSpaceCheck(p_blocked=-np.expm1(out["log_free"]), log_free=out["log_free"],
                          max_marginal=out["max_marginal"], t_near=t_near, t_end=out["t_end"], t_obs=t_stop,
                          t_block=out["t_block"], t_enter=out["t_enter"], through_observed=through)


def _check_segments(field, origin, d, t_near, t_stop, step, q_out, tree, opts):
    """The dense marginals, the end of the tested segment and its orthant probability for b rays; (b,) arrays."""
    b = len(d)
    max_q, t_block, t_end = np.zeros(b), np.full(b, np.nan), t_near.copy()
    length = np.maximum(t_stop - t_near, 0.0)
    n = int(min(opts.max_samples, max(3, np.ceil(float(length.max()) / step) + 1)))
    u = np.linspace(0.0, 1.0, n)[:-1]  # the last sample is the point itself (or the box exit)
    t = t_near[:, None] + length[:, None] * u  # (b, n - 1)
    x = origin + t[..., None] * d[:, None, :]  # (b, n - 1, 3)
    # which samples a ray may test at all (neither test reads the field): off the surface the scan saw, and where
    # good parts have a surface
    tested = np.ones(t.shape, dtype=bool)
    if tree is not None:
        # material next to a surface the scan saw is that surface, blurred by the field's resolution: a ray that
        # grazes an observed edge is not evidence of anything missing
        tested = ~np.isfinite(tree.query(x, k=1, distance_upper_bound=opts.clearance)[0])
    if opts.band is not None:
        # only where good parts have a surface: elsewhere the field's material is its own extrapolation
        rows, cols = np.nonzero(tested)
        untested = ~opts.band.tested(x[rows, cols], d[rows])
        tested[rows[untested], cols[untested]] = False
    # the field is read only where it can matter: at the samples a ray may test, and within own_depth of the point,
    # where the tested segment's end is decided (every sample before that is outside it whatever the field says)
    if q_out is None:
        read = tested
    elif opts.own_depth is not None:
        read = tested | (t > (t_stop - opts.own_depth)[:, None])
    else:
        read = np.ones(t.shape, dtype=bool)
    mean, var = np.zeros(t.shape), np.ones(t.shape)  # unread samples: never tested, never the segment's end
    if read.any():
        xt = torch.as_tensor(x[read], dtype=torch.float32)
        mean[read] = field.torch_mean(xt).double().numpy()
        var[read] = np.maximum(field.torch_variance(xt).double().numpy(), _MIN_VARIANCE)
    ratio = torch.as_tensor(mean / np.sqrt(var))
    q = torch.special.ndtr(-ratio).numpy()  # P(f <= 0), (b, n - 1)
    log_p_out = torch.special.log_ndtr(ratio).numpy()  # log P(f > 0), accurate where q is ~1
    if q_out is None:
        has_out = length > 0
        j_end = np.where(has_out, t.shape[1] - 1, -1)
    else:
        # the tested segment ends at the last clearly outside sample, or own_depth before the point if that is
        # later: between the end and the point lies the point's own surface
        outside = (q <= q_out) & (length[:, None] > 0)
        if opts.own_depth is not None:
            outside |= (t <= (t_stop - opts.own_depth)[:, None]) & (length[:, None] > 0)
        has_out = outside.any(1)
        j_end = np.where(has_out, outside.shape[1] - 1 - np.argmax(outside[:, ::-1], axis=1), -1)
    keep = (np.arange(t.shape[1]) <= j_end[:, None]) & tested
    q = np.where(keep, q, 0.0)
    log_p_out = np.where(keep, log_p_out, 0.0)
    rows = np.flatnonzero(has_out)
    t_end[rows] = t[rows, j_end[rows]]
    j_max = log_p_out.argmin(1)
    max_q[:] = q[np.arange(b), j_max]
    log_free = np.maximum(log_p_out[np.arange(b), j_max], _LOG_FLOOR)  # one sample alone: an upper bound of P(free)
    t_block[rows] = t[rows, j_max[rows]]
    entering = q >= 0.5
    t_enter = np.where(entering.any(1), t[np.arange(b), np.argmax(entering, axis=1)], np.nan)
    hot = np.flatnonzero(max_q >= max(opts.q_floor, 1e-300))
    k = min(opts.n_select, t.shape[1])
    if len(hot) and k >= 2:
        pick = np.sort(np.argpartition(-q[hot], k - 1, axis=1)[:, :k], axis=1)  # (H, k) in ray order
        xs = torch.as_tensor(x[hot[:, None], pick], dtype=torch.float32)  # (H, k, 3)
        m, c = ray_gaussian(field, xs)
        # a ray with fewer than k tested samples fills its pick with left-out ones: make those surely outside
        left_out = torch.as_tensor(~keep[hot[:, None], pick])
        sd = torch.diagonal(c, dim1=1, dim2=2).clamp_min(0).sqrt()
        m = torch.where(left_out, m.abs() + 40 * sd + 1e-12, m)
        survival = orthant_survival(m.double(), c.double(), method="genz", n_samples=opts.qmc_samples,
                                    seed=opts.seed)
        with np.errstate(divide="ignore"):
            log_s = np.log(survival[:, -1].numpy())
        # the orthant estimate carries QMC error: it never goes above the exact single-sample bound
        log_free[hot] = np.maximum(np.minimum(log_s, log_free[hot]), _LOG_FLOOR)
    return {"log_free": log_free, "max_marginal": max_q, "t_end": t_end, "t_block": t_block, "t_enter": t_enter}
