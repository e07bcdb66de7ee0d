"""When inspection registers scans: ``align='auto'`` decided from how far the good training scans' poses spread.

The registration itself (coarse-to-fine robust ICP with a placement prior, group registration of the training
scans) is :mod:`datasets.registration`'s, imported here under the names inspection has always used.
"""
import numpy as np

from datasets.registration import (  # noqa: F401 (inspection's names for the registration)
    ALIGN_SCANS, DEFAULT_LEVELS, GROUP_ROUNDS, GROUP_SETTLED, HUBER, MAX_SOURCE, PRIOR_DEGREES, PRIOR_SIZE,
    START_DEGREES, START_ITERATIONS, Aligner, _starts, moved_by, register_group)

AUTO_RATIO = 1.1  # align='auto' registers scans when registration lowers the training scans' residuals this much
AUTO_SCANS = 12  # training scans registered onto the others to decide it


def pose_spread(scans, max_scans=AUTO_SCANS, seed=0):
    """How far good scans' poses spread: each of up to ``max_scans`` of them (evenly chosen) registered onto the
    others (:meth:`Aligner.from_scans` without it), the ratio of its median point-to-plane residual before and after
    the registration; returns the median ratio over those scans (1.0: registration changes nothing).

    Why this statistic: a residual ratio is free of the part's size and of the sensor's noise (both scale the
    residuals before and after alike), and a part in a fixture gives 1.0 within 1 % whatever its shape, while a
    few degrees of hand placement give 1.3 and more (docs/results.md#parts-placed-by-hand-alignment-in-the-calibration-issue-27).
    Fewer than 3 scans: 1.0 (nothing to compare).
    """
    from datasets.validation import points_and_normals

    scans = list(scans)
    if len(scans) < 3:
        return 1.0
    aligner = Aligner.from_scans(scans, seed=seed)
    pick = np.unique(np.linspace(0, len(scans) - 1, min(max_scans, len(scans))).round().astype(int))
    ratios = []
    for i in pick:
        scan = scans[i]
        others = aligner.without(str(getattr(scan, "name", "") or f"scan {i}"))
        pts = np.asarray(points_and_normals(scan)[0], dtype=np.float64).reshape(-1, 3)
        T = others.transform(pts)
        residuals = []
        for p in (pts, pts @ T[:3, :3].T + T[:3, 3]):
            ok, distances = others.plane_distances(p, 12.0 * others.spacing)
            if ok.sum() < 10:
                break
            residuals.append(np.median(distances))
        if len(residuals) == 2 and residuals[1] > 0:
            ratios.append(residuals[0] / residuals[1])
    return float(np.median(ratios)) if ratios else 1.0
