"""Anomaly maps: a scan's points coloured by their standardized residual, written as PLY.

Colour scale (fixed, so maps of different scans and runs compare): colormap ``turbo`` over the standardized residual
from 0 (dark blue: as expected) to 5 (dark red: 5 standard deviations off, or more; values above 5 are clipped).
The residual is the calibration's point score when it is one of the standardized ones (``'distance'``:
|d(p) - d_ref(p)| / sqrt(s_ref(p)^2 + noise^2) with d the first-order distance to the mean surface, ``'local'``:
|E f(p) - m_ref(p)| / sqrt(s_ref(p)^2 + noise^2), ``'residual'``: |E f(p)| / sqrt(Var f(p) + noise^2)), and the plain
``'residual'`` when the calibration scores the NLL. The legend is written as ``legend.png`` beside the maps.

Ray maps (``maps/rays/<name>.ply``, calibrations with rays): the same colormap over the per-point ray score from 0
(dark blue: the sensor saw free space where the model expects it) to 1 (dark red: the model is sure there was
material on the ray, or that a ray with no return should have hit; see :mod:`inspection.ray_evidence`), with its
own ``legend.png``.
"""
from pathlib import Path

import numpy as np

MAP_CMAP = "turbo"
MAP_RANGE = (0.0, 5.0)
MAP_LABEL = "standardized residual, in standard deviations (clipped at 5)"
RAY_MAP_RANGE = (0.0, 1.0)
RAY_MAP_LABEL = "P(material on the sensor's ray where it saw free space)"


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


def write_map(path, points, normals, values, vrange=MAP_RANGE):
    """Write the scan coloured by ``values`` (standardized residuals; ray scores with ``RAY_MAP_RANGE``) to a
    binary PLY (atomically)."""
    from datasets import write_cloud

    return write_cloud(Path(path), np.asarray(points, dtype=np.float32),
                       None if normals is None else np.asarray(normals, dtype=np.float32), colours(values, vrange=vrange))


def write_legend(path, vrange=MAP_RANGE, label=MAP_LABEL):
    from .plots import plot_legend

    return plot_legend(path, MAP_CMAP, *vrange, label)
