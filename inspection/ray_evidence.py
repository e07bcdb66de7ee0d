"""The ray score of a scan: evidence of missing material from the sensor's rays, per point and per scan.

Per-point scores read the field at the points a scan returned, so they cannot see material that is missing where
no point lies: a hole in a thin wall shows only as points on good surfaces seen through it, or as no points at all.
The sensor's rays can (:mod:`autodecoder.scanning.free_space`). Two kinds of ray are tested under the scan's projected field:

* **returned rays**: from the sensor origin o to a subsample of the scan's points (``n_rays``, seeded). Each gets
  P(blocked): the probability that the field puts solid material on the ray, apart from the surface the point lies
  on (:func:`autodecoder.scanning.free_space.blocked_probability`). A point seen through a hole scores ~1.
* **missing returns**: rays through holes in the scan's image, i.e. directions inside the image that returned
  nothing although returns surround them. Only the points and o are stored, not the sensor's pixel grid, so the
  image is rebuilt: directions from o are mapped to the plane z = 1 of a camera looking along their mean
  (gnomonic projection, the image plane of a pinhole camera up to a homography), the pitch s is the mean spacing
  of the returns there (sqrt(hull area / m)), and a grid of pitch s is laid over it. Grid cells farther than
  ``gap`` x s from every return are empty; empty regions that do not reach the outside of the convex hull of the
  returns are holes (background around the part's silhouette reaches it). Up to ``n_empty`` hole cells (seeded)
  get P(hit): the probability that the field puts solid material on the ray within its box
  (:func:`autodecoder.scanning.free_space.missing_return_probability`). This assumes one pinhole-like view (all directions
  within ~85 degrees of their mean; otherwise this kind is skipped) and a sensor without dropouts: a dark or
  specular patch that returns nothing is a hole to it (the calibration scans, taken with the same sensor, set how
  much of that is normal).

On open and thin-walled parts the projected field of a partial scan is one-sided: negative everywhere behind the
surface the scan saw, the cavity behind a sheet included (figures in docs/results_archive.md,
thin-walled and open parts). A point seen through a hole in the sheet then lies deep inside that "solid", and so do
the rays of good scans through the part's real openings. Two things make the rays work there: ``own_depth`` (a
point's own surface lies at most that far before it; material farther back is tested) and the ``band``: only
samples within ``band`` kernel lengthscales of the good (training) scans' points are tested
(:class:`autodecoder.scanning.free_space.SurfaceBand`). A ray through a hole crosses the sheet where good scans
returned points; a good ray through an opening crosses only material the field extrapolated where no good part has
a surface. Within the band, a ray that skims past a good surface on its outer side (``skim_cos``) is not tested
there: it runs through the field's blurred rim, where nothing can be missing, and a good scan's rays past an edge
its view did not see scored hundreds of nats that way. (The rule before the band, a reference of where good scans'
rays enter expected material, left good scans with up to hundreds of nats on the benchmarks' parts and is retired:
docs/results_archive.md.) Without good scans'
points (a point score with no per-location reference), ``own_depth='auto'`` tests no deep material.

The scan's ray score aggregates the surprisals -log P(free) = -log(1 - P) of both kinds of ray together, in nats
(the rays' negative log likelihood, as the NLL is the points'; ``aggregate`` as for point scores: ``'top1'`` is the
mean of the worst 1 %). Measured on a thin-walled box (docs/results_archive.md), the surprisal separated
defective from good scans far better than the probabilities themselves, which saturate near 1 on rays the field is
merely unsure about as well as on rays through walls it is sure of. The per-point map gives every point the value of the nearest tested
returned ray (in space) and, where larger, of the hole rays within (``gap`` + 1.5) mean spacings of it in the
image (the rim of a hole). Its values are P(blocked) in [0, 1]; higher = more anomalous. The same rays'
surprisals per point (``point_surprisal``, nats) go into the anomaly map (:func:`inspection.maps.map_values`).
"""
import logging
from dataclasses import dataclass, field

import numpy as np

from autodecoder.scanning.sensor import image_holes

from .aggregates import aggregate as aggregate_values, check_aggregate

log = logging.getLogger(__name__)

RAY_DEFAULTS = {"n_rays": 384, "n_empty": 128, "gap": 2.0, "aggregate": "top1", "seed": 0, "clearance": None,
                "own_depth": "auto", "band": 0.5, "min_cos": 0.2, "skim_cos": 0.4, "occlusion": 2.0,
                "empty_to_rim": True}


@dataclass
class RayEvidence:
    """Ray score of one scan (see the module docstring).

    Attributes
    ----------
    score : float
        Aggregate of the surprisals -log P(free) of all tested rays, in nats (higher = more anomalous).
    point_map : (m,) float64 array
        Per-point ray score in [0, 1].
    point_surprisal : (m,) float64 array
        The same rays' surprisal -log P(free) at each point, in nats (>= 0): what :func:`inspection.maps.map_values`
        adds to the points' own negative log likelihood.
    ray_index : (R,) int array
        Points whose rays were tested.
    ray_values, ray_surprisal : (R,) float64 arrays
        P(blocked) of those rays and -log P(free) (nats).
    empty_directions : (E, 3) float64 array
        Unit directions of the tested missing returns.
    empty_values, empty_surprisal : (E,) float64 arrays
        P(hit) of those rays and -log P(no hit) (nats).
    ray_block, empty_block : (R, 3), (E, 3) float64 arrays
        Where each tested ray is most likely blocked (NaN where untested): the place it accuses.
    through_observed : (R,) bool array
        The returned rays that passed through the scan's own surface and were not tested
        (:func:`autodecoder.scanning.free_space.blocked_probability`).
    nearest : (m,) int array
        Each point's nearest tested returned ray (an index into ``ray_index``).
    rim_points, rim_rays : (K,) int arrays
        Points on the rim of a hole in the image and the missing-return ray (an index into ``empty_directions``)
        whose value they take where larger (:meth:`per_point`).
    """

    score: float
    point_map: np.ndarray
    ray_index: np.ndarray
    ray_values: np.ndarray
    ray_surprisal: np.ndarray
    point_surprisal: np.ndarray = None
    empty_directions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    empty_values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    empty_surprisal: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ray_block: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    empty_block: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    through_observed: np.ndarray = None
    nearest: np.ndarray = None
    rim_points: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    rim_rays: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def per_point(self, ray_values, empty_values):
        """Per-ray values (R,) and (E,) as a per-point map (m,): each point takes its nearest tested returned ray's
        value, and a hole's rim the larger of that and its missing return's (module docstring)."""
        out = np.asarray(ray_values, dtype=np.float64).reshape(-1)[self.nearest].copy()
        if len(self.rim_points):
            np.maximum.at(out, self.rim_points, np.asarray(empty_values, dtype=np.float64).reshape(-1)[self.rim_rays])
        return out


def check_ray_options(options):
    """Validated ray options: ``RAY_DEFAULTS`` updated by ``options`` (dict or None); unknown keys are errors."""
    opts = dict(RAY_DEFAULTS)
    unknown = sorted(set(options or {}) - set(RAY_DEFAULTS))
    if unknown:
        raise ValueError(f"unknown ray option(s) {unknown}; expected some of {sorted(RAY_DEFAULTS)}")
    opts.update(options or {})
    for key in ("n_rays", "n_empty", "seed"):
        if int(opts[key]) != opts[key] or opts[key] < (1 if key == "n_rays" else 0):
            raise ValueError(f"ray option {key} must be an integer (n_rays >= 1, others >= 0), got {opts[key]!r}")
        opts[key] = int(opts[key])
    if not float(opts["gap"]) > 1:
        raise ValueError(f"ray option gap must be > 1 (mean spacings of the returns), got {opts['gap']!r}")
    opts["gap"] = float(opts["gap"])
    if opts["clearance"] is not None:
        if not float(opts["clearance"]) >= 0:
            raise ValueError(f"ray option clearance must be None or >= 0 (world units), got {opts['clearance']!r}")
        opts["clearance"] = float(opts["clearance"])
    try:
        band = float(opts["band"])
    except (TypeError, ValueError):
        band = float("nan")
    if not band > 0:
        raise ValueError(f"ray option band must be > 0 (kernel lengthscales; band=None, the rule before it, is "
                         f"retired), got {opts['band']!r}")
    opts["band"] = band
    for key in ("min_cos", "skim_cos"):
        if not 0 <= float(opts[key]) < 1:
            raise ValueError(f"ray option {key} must be in [0, 1), got {opts[key]!r}")
        opts[key] = float(opts[key])
    if opts["occlusion"] is not None:
        if not float(opts["occlusion"]) > 0:
            raise ValueError(f"ray option occlusion must be None or > 0 (the scan's median point spacings), got "
                             f"{opts['occlusion']!r}")
        opts["occlusion"] = float(opts["occlusion"])
    if not isinstance(opts["empty_to_rim"], (bool, np.bool_)):
        raise ValueError(f"ray option empty_to_rim must be True or False, got {opts['empty_to_rim']!r}")
    opts["empty_to_rim"] = bool(opts["empty_to_rim"])
    if opts["own_depth"] not in (None, "auto"):
        if not float(opts["own_depth"]) > 0:
            raise ValueError(f"ray option own_depth must be None, 'auto' or > 0 (world units), got "
                             f"{opts['own_depth']!r}")
        opts["own_depth"] = float(opts["own_depth"])
    check_aggregate(opts["aggregate"])
    from .ray_calibration import top_count

    try:
        top_count(opts["aggregate"], 1)
    except ValueError as exc:
        raise ValueError(f"ray option aggregate: {exc}") from None
    return opts


def ray_evidence(field, points, origin, n_rays=RAY_DEFAULTS["n_rays"], n_empty=RAY_DEFAULTS["n_empty"],
                 gap=RAY_DEFAULTS["gap"], aggregate=RAY_DEFAULTS["aggregate"], seed=RAY_DEFAULTS["seed"],
                 clearance=RAY_DEFAULTS["clearance"], own_depth=RAY_DEFAULTS["own_depth"],
                 band=RAY_DEFAULTS["band"], surface=None, min_cos=RAY_DEFAULTS["min_cos"], grazing=None,
                 surface_normals=None, skim_cos=RAY_DEFAULTS["skim_cos"], occlusion=RAY_DEFAULTS["occlusion"],
                 empty_to_rim=RAY_DEFAULTS["empty_to_rim"], **check_options):
    """The ray score of one scan under its projected field.

    Parameters
    ----------
    field : StochasticField (or any field :func:`autodecoder.scanning.free_space.blocked_probability` takes)
        The scan's field, in the scan's frame.
    points : (m, 3) array
        The scan's points.
    origin : (3,) array
        The sensor position, same frame.
    n_rays : int
        Returned rays tested (a seeded subsample of the points; all of them when m <= n_rays).
    n_empty : int
        Most missing-return rays tested (a seeded subsample of the hole cells; 0: returned rays only).
    gap : float
        Empty-cell distance in mean spacings of the returns (see :func:`autodecoder.scanning.sensor.image_holes`).
    aggregate : str
        Per-scan aggregate of the ray values (:func:`inspection.aggregates.aggregate`).
    seed : int
        Subsampling (and the Genz estimator's scrambling) seed.
    clearance : float, optional
        Ray samples this close to any of the scan's points are left out (world units; default the field's kernel
        lengthscale; see :func:`autodecoder.scanning.free_space.blocked_probability`).
    own_depth : float, 'auto' or None
        How far before a point its own surface may lie (world units; None: no limit); material farther back on its
        ray is tested (:func:`autodecoder.scanning.free_space.blocked_probability`). 'auto': 3 kernel lengthscales when
        a ``surface`` band is given, else no limit. Without the band, the rays of good scans through an open part's
        openings enter the field's "solid" cavity as a hole's do, and testing deep material only adds their noise.
    band : float > 0
        With ``surface``: only ray samples within ``band`` kernel lengthscales of a good scan's point are tested
        (:class:`autodecoder.scanning.free_space.SurfaceBand`): the rays show a wall missing where good parts have
        one, not the field's extrapolation where they have none.
    surface : (n, 3) array, or a datasets.neighbours.NearestNeighbours (or scipy.spatial.cKDTree) over them, optional
        Points of good scans of the part (the model's training scans), the scan's frame.
    min_cos, grazing
        ``grazing`` (m,): 1 / cos^2 - 1 of the angle between each point's ray and its surface normal
        (:func:`autodecoder.scanning.sensor.grazing_factor`); rays to points with |cos| < ``min_cos`` are not tested. A ray
        that grazes a surface runs along it, inside the band of good surfaces and beyond ``own_depth`` of its
        point, where the field's blurred surface puts material (on the inspection benchmark's enclosure a good scan
        seen level with the top sheet scored 400 nats); a ray through a hole crosses the wall. None: every ray.
    surface_normals : (index, (n2, 3) array), optional
        Good scans' points with their unit outward normals
        (:meth:`inspection.reference.LocalReference.oriented_surface`), the scan's frame; with ``surface``.
    skim_cos : float in [0, 1)
        With ``surface_normals``: a ray sample on the outer side of the nearest good point's tangent plane, the ray
        making |cos| < ``skim_cos`` with that point's normal, is not tested: the ray skims past the good surface
        there, through the field's blurred rim, where nothing can be missing
        (:class:`autodecoder.scanning.free_space.SurfaceBand`; 0: every sample in the band is tested).
    occlusion : float > 0 or None
        A returned ray that comes within this many of the scan's median point spacings (and within the clearance) of
        one of its own points more than ``own_depth`` before its point passed through the scan's own surface: the
        sensor did not travel it, and it is not tested
        (:func:`autodecoder.scanning.free_space.blocked_probability`'s ``occlusion_radius``; None: every ray). Not
        beyond the clearance: a ray through a hole that passes the hole's rim closer than that is untested where it
        crosses the wall anyway, so the rule costs the holes nothing.
    empty_to_rim : bool
        A missing return is tested only up to ``own_depth`` beyond the nearest return around it in the image (its
        rim; :func:`_rim_depth`); False: through the field's box.
    **check_options
        Passed to :func:`autodecoder.scanning.free_space.blocked_probability` (``outside_sigma``, ``step``, ...).

    Returns
    -------
    RayEvidence
    """
    from scipy.spatial import cKDTree

    from autodecoder.scanning.free_space import blocked_probability, median_spacing, missing_return_probability

    points = np.asarray(points, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    rng = np.random.default_rng(seed)
    m = len(points)
    eligible = np.arange(m)
    if grazing is not None and min_cos > 0:
        eligible = np.flatnonzero(np.asarray(grazing, dtype=np.float64) <= 1.0 / min_cos**2 - 1.0)
        if len(eligible) == 0:
            eligible = np.arange(m)
    index = eligible if len(eligible) <= n_rays else np.sort(rng.choice(eligible, n_rays, replace=False))
    surface_band = None
    if surface is not None:
        from autodecoder.scanning.free_space import SurfaceBand

        if field.lengthscale is None:
            raise ValueError("ray_evidence: band is in kernel lengthscales, and the field does not say its own")
        surface_band = SurfaceBand(surface, band * field.lengthscale, normals=surface_normals, min_cos=skim_cos)
    if own_depth == "auto" and surface_band is None:
        own_depth = None
    # one tree over the scan's points for both kinds of rays
    observed = cKDTree(points)
    check_options = dict(check_options, observed=observed, clearance=clearance, seed=seed, band=surface_band)
    radius = None
    if occlusion is not None:  # never beyond the clearance: a hole's rays that pass its rim closer are untested there
        reach = clearance if clearance is not None else field.lengthscale
        radius = occlusion * median_spacing(observed)
        radius = radius if reach is None else min(radius, float(reach))
    check = blocked_probability(field, origin, points[index], own_depth=own_depth,
                                occlusion_radius=radius if radius else None, **check_options)
    values, surprisal = check.p_blocked, np.maximum(-check.log_free, 0.0)
    ray_block = _block_points(origin, points[index] - origin, check)
    # every point takes the value of the nearest tested ray: the points seen through a hole lie together
    nearest = cKDTree(points[index]).query(points, k=1)[1]
    rim_points, rim_rays = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    e_dirs, e_values, e_surprisal, e_block = np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros((0, 3))
    if n_empty > 0:
        dirs, h_uv, uv, pitch = image_holes(points, origin, gap)
        if len(dirs):
            pick = np.arange(len(dirs)) if len(dirs) <= n_empty else \
                np.sort(rng.choice(len(dirs), n_empty, replace=False))
            e_dirs, h_uv = dirs[pick], h_uv[pick]
            depth = np.linalg.norm(points - origin, axis=1)
            t_far = 2.0 * float(depth.max())
            options = {k: v for k, v in check_options.items() if k != "outside_sigma"}
            rim = _rim_depth(uv, depth, h_uv, own_depth, field) if empty_to_rim else None
            empty = missing_return_probability(field, origin, e_dirs, t_far=t_far, t_max=rim, **options)
            e_values, e_surprisal = empty.p_blocked, np.maximum(-empty.log_free, 0.0)
            e_block = _block_points(origin, e_dirs, empty)
            # the rim of a hole shows what its missing returns say
            rims = cKDTree(uv).query_ball_point(h_uv, (gap + 1.5) * pitch)
            rim_points = np.array([i for near in rims for i in near], dtype=np.int64)
            rim_rays = np.repeat(np.arange(len(rims)), [len(near) for near in rims]).astype(np.int64)
    # the surprisal of what the sensor saw, -log P(free): the rays' negative log likelihood. Probabilities near 1
    # all look alike, so a top-k mean of them cannot tell a ray the field is unsure about from one through a wall
    # it is sure of; their surprisals can (P = 0.99: 4.6 nats; a wall 5 sd deep: ~15)
    score = aggregate_values(np.concatenate([surprisal, e_surprisal]), aggregate)
    out = RayEvidence(score=score, point_map=None, ray_index=index, ray_values=values, ray_surprisal=surprisal,
                      empty_directions=e_dirs, empty_values=e_values, empty_surprisal=e_surprisal,
                      ray_block=ray_block, empty_block=e_block, through_observed=check.through_observed,
                      nearest=nearest, rim_points=rim_points, rim_rays=rim_rays)
    out.point_map = out.per_point(values, e_values)
    out.point_surprisal = out.per_point(surprisal, e_surprisal)
    return out


RIM_RETURNS = 8  # the returns nearest a hole cell in the image that give its rim's depth


def _rim_depth(uv, depth, hole_uv, own_depth, field):
    """How deep each missing-return ray is tested (world units from the origin): the nearest of the
    ``RIM_RETURNS`` returns around its cell in the image plus ``own_depth`` ('auto': 3 kernel lengthscales; None:
    no limit). A hole in a wall is missing where its rim is; material far behind the nearest return around a gap is
    the shadow of an edge that an approximate origin uncovers (:mod:`autodecoder.scanning.free_space`)."""
    from scipy.spatial import cKDTree

    from autodecoder.scanning.free_space import OWN_DEPTH_FACTOR

    if own_depth == "auto":
        own_depth = None if field.lengthscale is None else OWN_DEPTH_FACTOR * field.lengthscale
    if own_depth is None:
        return None
    rows = cKDTree(uv).query(hole_uv, k=min(RIM_RETURNS, len(uv)))[1].reshape(len(hole_uv), -1)
    return depth[rows].min(axis=1) + float(own_depth)


def _block_points(origin, directions, check):
    """(B, 3): ``origin`` + t_block x the unit ``directions`` of a :class:`FreeSpaceCheck` (NaN where untested)."""
    d = np.asarray(directions, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return origin + check.t_block[:, None] * d
