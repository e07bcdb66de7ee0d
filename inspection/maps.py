"""Anomaly maps: a scan's points coloured by the evidence of defect around them, written as PLY.

What a point's map value is: the **patch residual**, the root mean square of the standardized residuals of the
point's ``MAP_NEIGHBOURS`` nearest points of the scan (itself included; the scan's stray returns are left out of
every patch and keep their own residual). Under the model's Gaussian residuals this is the patch's negative log
likelihood, sqrt(2 NLL / k) up to a constant: the likelihood a patch of the scan has, in standard deviations. A
single point's residual is noisy (a grazing return, a point between two training scans' surfaces); a defect is a
patch of points that agree, so the patch is what the map shows. The scan's score does not come from the map: it
aggregates the points' own residuals (:mod:`inspection.aggregates`), so a missing-material border of a few points
counts at full weight there. ``MAP_NEIGHBOURS`` is a number of points, not a length: the evidence a patch gathers
is set by how many points agree, at any resolution; it is chosen no larger than the smallest defects of the
benchmarks, and beyond it a larger patch blurs those (docs/results.md, "Anomaly maps by the patch").

With rays (calibrations that score them), the map is the point's likelihood under both kinds of evidence: its
patch's, r^2 / 2 nats a point, plus the surprisal s of its ray (``RayEvidence.point_surprisal``, nats: the ray to
the point, or the nearest tested one, and a hole's missing returns at its rim), in standard deviations, sqrt(r^2 +
2 s). Why: the points a hole in a thin wall shows lie on good surface behind it, so their residuals say nothing;
the rays through the hole do. Folded in, the maps of thin-walled parts rank defect points markedly higher (point
AUROC, docs/results.md, "The rays in the anomaly map"), those of solids and of real scans as before. A ray with no
evidence (s = 0) leaves the patch residual as it is.

The standardized residual is the calibration's point score when it is one of the standardized ones
(``'distance'``: |d(p) - d_ref(p)| / sqrt(s_ref(p)^2 + noise^2) with d the first-order distance to the mean surface,
``'local'``: |E f(p) - m_ref(p)| / sqrt(s_ref(p)^2 + noise^2), ``'residual'``: |E f(p)| / sqrt(Var f(p) + noise^2),
``'joint'``, ``'surface'``), and the plain ``'residual'`` when the calibration scores the NLL.

Colour scale (fixed, so maps of different scans and runs compare): colormap ``turbo`` over the patch residual from
0 (dark blue: as expected) to 5 (dark red: 5 standard deviations off, or more; values above 5 are clipped). The
legend is written as ``legend.png`` beside the maps.

Ray maps (``maps/rays/<name>.ply``, calibrations with rays): the same colormap over the per-point ray score from 0
(dark blue: the sensor saw free space where the model expects it) to 1 (dark red: the model is sure there was
material on the ray, or that a ray with no return should have hit; see :mod:`inspection.ray_evidence`), with its
own ``legend.png``. Ray maps are per point, not per patch: a ray's evidence is already a line through the scene.
"""
from pathlib import Path

import numpy as np

MAP_CMAP = "turbo"
MAP_RANGE = (0.0, 5.0)
MAP_NEIGHBOURS = 32  # points per patch of the anomaly map (see the module's docstring)
MAP_LABEL = (f"patch residual (rms over {MAP_NEIGHBOURS} neighbouring points, with the rays' evidence where the "
             f"calibration scores rays), in standard deviations (clipped at 5)")
RAY_MAP_RANGE = (0.0, 1.0)
RAY_MAP_LABEL = "P(material on the sensor's ray where it saw free space)"


def patch_residuals(points, residuals, neighbours=MAP_NEIGHBOURS, excluded=None):
    """Each point's patch residual: the root mean square of ``residuals`` over its ``neighbours`` nearest points.

    Parameters
    ----------
    points : (m, 3) array
        The scan's points, finite, any frame and units (only their nearness counts).
    residuals : (m,) array
        Standardized residuals (standard deviations, >= 0), in the points' order.
    neighbours : int >= 1
        Points per patch, the point itself included (1: the residuals unchanged). Fewer when the scan has fewer
        points to take.
    excluded : (m,) bool array, optional
        Points that are in no patch (the scan's stray returns): each keeps its own residual, and no other point's
        patch takes it.

    Returns
    -------
    (m,) float64 array
        In standard deviations; a patch of residuals all equal to r gives r.
    """
    from datasets.neighbours import NearestNeighbours

    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(residuals, dtype=np.float64).reshape(-1)
    if len(r) != len(p):
        raise ValueError(f"patch_residuals: {len(p)} points but {len(r)} residuals")
    if int(neighbours) != neighbours or neighbours < 1:
        raise ValueError(f"patch_residuals: neighbours must be a positive integer, got {neighbours!r}")
    out = r.copy()
    kept = np.ones(len(p), dtype=bool) if excluded is None else ~np.asarray(excluded, dtype=bool).reshape(-1)
    if len(kept) != len(p):
        raise ValueError(f"patch_residuals: {len(p)} points but {len(kept)} exclusion flags")
    k = min(int(neighbours), int(kept.sum()))
    if k <= 1:
        return out
    _, idx = NearestNeighbours(p[kept]).query(p[kept], k)
    out[kept] = np.sqrt(np.mean(np.square(r[kept][idx]), axis=1))
    return out


def map_values(settings, scan, res, neighbours=MAP_NEIGHBOURS, rays=True):
    """What a scan's maps show: the patch residuals of its standardized residuals (:func:`patch_residuals`; its
    point scores when they are standardized, else the field's plain ``'residual'``), with rays sqrt(r^2 + 2 s) with
    each point's ray evidence s (module docstring: its rays' surprisal as the calibration weighs it,
    ``res.ray_point_nats``, else as the field gives it), and its ray map (m,) with rays, else None.

    Parameters
    ----------
    settings : the inspector's ``settings_``
    scan : datasets Scan, (m, 3) array or (points, normals), as the inspector takes it
    res : the scan's :class:`inspection.estimator.ScanResult` (its ``point_scores`` and ``stray`` in the same order)
    neighbours : int >= 1
        Points per patch (:func:`patch_residuals`); the default is the maps'.
    rays : bool
        False: the patch residuals alone, without the rays' evidence (what the maps showed before it; benchmarks).

    Returns
    -------
    values : (m,) float64 array, standard deviations
    rays : (m,) array in [0, 1], or None
    """
    from datasets.validation import points_and_normals

    from .scores import POINT_SCORES, point_scores

    points, _ = points_and_normals(scan)
    resid = res.point_scores if POINT_SCORES[settings.point_score].in_deviations else \
        point_scores(res.field, points, "residual", settings.noise)
    values = patch_residuals(points, resid, neighbours, excluded=res.stray)
    if not settings.rays:
        return values, None
    weighed = getattr(res, "ray_point_nats", None)  # the rays as the calibration weighs them, where it has
    return (with_ray_evidence(values, res.rays.point_surprisal if weighed is None else weighed) if rays else values), \
        res.rays.point_map


def with_ray_evidence(values, surprisal):
    """sqrt(values^2 + 2 surprisal): map values (m,) in standard deviations with each point's ray surprisal (m,)
    (nats, >= 0; None: the values as they are) added to their negative log likelihood (module docstring)."""
    values = np.asarray(values, dtype=np.float64)
    if surprisal is None:
        return values
    surprisal = np.asarray(surprisal, dtype=np.float64).reshape(-1)
    if surprisal.shape != values.shape:
        raise ValueError(f"with_ray_evidence: {len(surprisal)} ray surprisals for {len(values)} map values")
    return np.sqrt(values ** 2 + 2.0 * np.maximum(surprisal, 0.0))


def colours(values, cmap=MAP_CMAP, vrange=MAP_RANGE):
    """(m,) scores -> (m, 3) uint8 RGB on the fixed scale."""
    import matplotlib

    lo, hi = vrange
    t = np.clip((np.asarray(values, dtype=np.float64) - lo) / (hi - lo), 0.0, 1.0)
    rgba = matplotlib.colormaps[cmap](t)
    return np.round(rgba[:, :3] * 255).astype(np.uint8)


def safe_name(name):
    """A scan name as a file name: '/' -> '__', anything outside [A-Za-z0-9._-] -> '_'."""
    out = "".join(c if c.isalnum() or c in "._-" else ("__" if c == "/" else "_") for c in name)
    return out.strip(".") or "scan"


def write_map(path, points, normals, values, vrange=MAP_RANGE, regions=None):
    """Write the scan coloured by ``values`` (standardized residuals; ray scores with ``RAY_MAP_RANGE``) to a
    binary PLY (atomically); with ``regions`` ((m,) int, :mod:`inspection.regions`' ids, -1 outside any) also a
    vertex property ``region``."""
    from datasets import write_cloud

    return write_cloud(Path(path), np.asarray(points, dtype=np.float32),
                       None if normals is None else np.asarray(normals, dtype=np.float32), colours(values, vrange=vrange),
                       None if regions is None else {"region": np.asarray(regions, dtype=np.int32)})


def write_legend(path, vrange=MAP_RANGE, label=MAP_LABEL):
    from .plots import plot_legend

    return plot_legend(path, MAP_CMAP, *vrange, label)
