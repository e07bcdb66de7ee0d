"""Defects made in a scan's own points, for real scans with no mesh to cut: a dent or bump moves the points of a
disc along the site's normal, missing material and a foreign object replace them by where the sensor's rays would
have met the surface behind or the object (:func:`defect_in_points`). The sites, sizes and kinds are those of the
mesh synthesis (:mod:`datasets.defects`), so that both kinds of tree hold comparable defects.
"""
import numpy as np

from datasets.defects import DEFECT_KINDS, HEIGHT_RANGE, RADIUS_RANGE, patch_normal, pick_site


def defect_in_points(points, normals, sensor, kind, diagonal, noise=0.0, seed=None, size=1.0,
                     with_deviation=False):
    """Make one defect in a scan's own points (a real scan, with no mesh to cut): everything outside it stays as
    measured.

    The site is drawn by :func:`pick_site` (normals within 35 degrees over the disc, at least 0.6 of the most
    neighbours: estimated normals of real points are rougher than a noise-free preview's), its normal by
    :func:`patch_normal` over the disc's inner half. Sizes as :func:`datasets.defects.make_defect`'s.

    - dent / bump: the points of the disc facing like the site (normal within 60 degrees) moved along the site's
      normal by ``(1 - (r/R)^2)^2 * height``, the profile of the mesh defects;
    - missing: a ball of radius R centred on the site removed; each point inside it replaced by where its sensor ray
      leaves the ball (the pit's back wall as the sensor sees it) plus ``noise``;
    - foreign: a sphere or a box about 1.6 R across, partly sunk (as :func:`datasets.defects.make_defect`'s), put on
      the surface; every point whose sensor ray meets it first replaced by the hit plus ``noise`` (its visible side, and the
      surface it hides).

    Parameters
    ----------
    points, normals : (n, 3) arrays
        The scan and its unit normals facing the sensor, in any frame (the sensor's too); not modified.
    sensor : (3,) array
        Where the points were seen from: every point's ray starts there.
    kind : {'dent', 'bump', 'missing', 'foreign'}
    diagonal : float
        The part's bounding-box diagonal, in the points' units: the sizes are fractions of it (`RADIUS_RANGE`,
        `HEIGHT_RANGE`).
    noise : float
        Standard deviation of the range noise added along the rays to the points a missing or foreign defect
        replaces (the scan's own, in the points' units).
    seed : int, numpy Generator or None
    size : float > 0
        Both sizes times this.
    with_deviation : bool
        Also return each point's deviation (below). Draws nothing: the defect is the same either way.

    Returns
    -------
    points : (n, 3) float64 array
        The defective scan, row for row with the input.
    labels : (n,) uint8 array
        1 on the points the defect moved or replaced.
    info : dict
        ``kind``, ``center``, ``normal`` (lists), ``radius``, and ``height`` (dent / bump), ``depth`` (missing) or
        ``shape`` (foreign): JSON-serialisable.
    deviation : (n,) float64 array
        Only with ``with_deviation``: the ground truth of how far each point lies off the scan's surface, in the
        points' units (``Scan.point_deviation``): ``(x_i - p_i) . n_i``, the displacement of the labelled point
        ``p_i`` along its own unit normal ``n_i`` (which faces the sensor: outward), where ``x_i`` is its new place
        before the range noise a missing or foreign defect adds (the noise is the sensor's, not the defect's): so
        negative for a dent or a missing pit, positive for a bump or a foreign object (on a flat patch, a dent's is
        ``-height (1 - (r/R)^2)^2``), and 0 on the points left as they were. The measured points stand for the good
        surface: their own noise is in it.
    """
    if kind not in DEFECT_KINDS:
        raise ValueError(f"unknown defect kind {kind!r}; expected one of {DEFECT_KINDS}")
    if not float(size) > 0:
        raise ValueError(f"size must be > 0 (a factor on the defect's sizes), got {size!r}")
    if not (np.isfinite(diagonal) and float(diagonal) > 0 and float(noise) >= 0):
        raise ValueError(f"diagonal must be a finite length > 0 (the part's bounding-box diagonal) and noise >= 0 (a "
                         f"standard deviation), got {diagonal!r} and {noise!r}")
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    out, exact, labels, info = _defect(points, normals, np.asarray(sensor, dtype=np.float64), kind, diagonal, noise,
                                       np.random.default_rng(seed), size)
    if not with_deviation:
        return out, labels, info
    unit = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    deviation = np.where(labels > 0, np.einsum("ij,ij->i", exact - points, unit), 0.0)
    return out, labels, info, deviation


def _defect(points, normals, sensor, kind, diagonal, noise, rng, size):
    """:func:`defect_in_points`' defect: (points, the same before the range noise, labels, info)."""
    radius = rng.uniform(*RADIUS_RANGE) * diagonal * size
    height = rng.uniform(*HEIGHT_RANGE) * diagonal * size
    i = pick_site(points, normals, sensor, radius, seed=rng, max_normal_deg=35.0, min_facing=0.6, min_share=0.6)
    c = points[i]
    n0 = patch_normal(points, normals, c, 0.5 * radius)
    out = points.copy()
    labels = np.zeros(len(points), np.uint8)
    info = {"kind": kind, "center": c.tolist(), "normal": n0.tolist(), "radius": radius}
    if kind in ("dent", "bump"):
        r = np.linalg.norm(points - c, axis=1)
        moving = (r < radius) & (normals @ n0 > 0.5)
        profile = (1.0 - (r[moving] / radius) ** 2) ** 2
        out[moving] += ((height if kind == "bump" else -height) * profile)[:, None] * n0
        labels[moving] = 1
        info["height"] = height
        return out, out, labels, info
    dirs = points - sensor
    dist = np.linalg.norm(dirs, axis=1)
    dirs /= dist[:, None]
    if kind == "missing":
        inside = np.linalg.norm(points - c, axis=1) < radius
        _, t_exit = _ray_sphere(sensor, dirs[inside], c, radius)
        hit = np.isfinite(t_exit)
        idx = np.flatnonzero(inside)[hit]
        t = t_exit[hit] + rng.normal(0.0, noise, len(idx))
        out[idx] = sensor + t[:, None] * dirs[idx]
        exact = out.copy()
        exact[idx] = sensor + t_exit[hit][:, None] * dirs[idx]
        labels[idx] = 1
        info["depth"] = radius
        return out, exact, labels, info
    shape = ("sphere", "box")[rng.integers(2)]
    if shape == "sphere":
        r_obj, sink = 0.8 * radius, 0.4 * radius
        t_hit, _ = _ray_sphere(sensor, dirs, c + n0 * (r_obj - sink), r_obj)
    else:
        half = np.array([0.8, 0.65, 0.65]) * radius
        a = np.cross(n0, rng.normal(size=3))
        a /= np.linalg.norm(a)
        axes = np.stack([a, np.cross(n0, a), n0])  # local z along the normal, a random turn about it
        t_hit = _ray_box(sensor, dirs, c + n0 * (half[2] - 0.35 * radius), axes, half)
    hit = np.isfinite(t_hit) & (t_hit < dist)
    t = t_hit[hit] + rng.normal(0.0, noise, hit.sum())
    out[hit] = sensor + t[:, None] * dirs[hit]
    exact = out.copy()
    exact[hit] = sensor + t_hit[hit][:, None] * dirs[hit]
    labels[hit] = 1
    info["shape"] = shape
    return out, exact, labels, info


def _ray_sphere(origin, dirs, center, radius):
    """Entry and exit distances (m,) of rays ``origin`` + t ``dirs`` (unit, (m, 3)) through a sphere (NaN where
    they miss it)."""
    oc = origin - center
    b = dirs @ oc
    disc = b * b - (oc @ oc - radius * radius)
    s = np.sqrt(np.where(disc >= 0, disc, np.nan))
    return -b - s, -b + s


def _ray_box(origin, dirs, center, axes, half):
    """Entry distance (m,) of rays ``origin`` + t ``dirs`` into an oriented box (``axes`` rows: its unit axes,
    ``half``: its half extents), NaN where they miss it or it lies behind them."""
    o = axes @ (origin - center)
    d = dirs @ axes.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - o) / d, (half - o) / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    return np.where((t_near <= t_far) & (t_far > 0), t_near, np.nan)


# --------------------------------------------------------------------------------------------------------------------
# dent / bump
