"""What every importer does with the scans it has read: voxel downsampling, stray points, the frame, the file.

Shared by the tree importer (:mod:`datasets.importer`) and the public-benchmark layouts (:mod:`datasets.layouts`).
"""
from dataclasses import replace

import numpy as np

from .collection import ScanCollection
from .frame import Frame
from .outliers import STRAY_FACTOR, STRAY_NEIGHBOURS, stray_points


def voxel_downsample(points, normals, labels, size):
    """One point per occupied voxel of side ``size``: the mean point, the renormalised mean normal, the max label.

    Own implementation (not open3d's) so per-point labels follow the points and the result is deterministic.

    Parameters
    ----------
    points : (N, 3) float64 array
    normals : (N, 3) float64 array, unit
    labels : (N,) uint8 array or None
    size : float > 0, same units as ``points``

    Returns
    -------
    points (M, 3), normals (M, 3), labels (M,) or None, with voxels in lexicographic order of their integer keys.
    """
    inverse, counts = _voxels(points, size)
    m = len(counts)
    out_p = np.stack([np.bincount(inverse, points[:, k], m) for k in range(3)], axis=1) / counts[:, None]
    out_n = np.stack([np.bincount(inverse, normals[:, k], m) for k in range(3)], axis=1)
    norm = np.linalg.norm(out_n, axis=1, keepdims=True)
    # opposite normals in one voxel (a thin wall) can cancel: keep one of the originals there instead
    first = np.full(m, len(points))
    np.minimum.at(first, inverse, np.arange(len(points)))
    out_n = np.where(norm > 1e-6, out_n / np.maximum(norm, 1e-12), normals[first])
    out_l = None
    if labels is not None:
        out_l = np.zeros(m, dtype=np.uint8)
        np.maximum.at(out_l, inverse, labels)
    return out_p, out_n, out_l


def voxel_mean(points, values, size):
    """The mean of a per-point quantity over each voxel of :func:`voxel_downsample`'s grid, in its voxels' order.

    How a per-point length (a ground-truth deviation, :attr:`datasets.scan.Scan.point_deviation`) follows the
    points: the voxel's point is the mean of its points, and on a surface smooth at the voxel's scale the mean
    point's deviation is the mean of theirs.

    Parameters
    ----------
    points : (N, 3) float64 array
        The points given to :func:`voxel_downsample`.
    values : (N,) float array
    size : float > 0

    Returns
    -------
    (M,) float64 array
    """
    inverse, counts = _voxels(points, size)
    return np.bincount(inverse, np.asarray(values, dtype=np.float64), len(counts)) / counts


def _voxels(points, size):
    """(inverse (N,), counts (M,)): each point's voxel, numbered in lexicographic order of the integer keys."""
    keys = np.floor((points - points.min(0)) / size).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return inverse.reshape(-1), counts


def write_scans(scans, out, provenance, overwrite=False, drop_strays=False):
    """Count each scan's stray points (:func:`datasets.outliers.stray_points`; removed with ``drop_strays``), fit
    the collection frame to the training points that are not stray (all scans' when there is no train split: one
    return 10 cm off the part would otherwise set the box), move the scans (file units) into it and write the
    collection atomically. Returns the summary dict of :func:`datasets.importer.import_tree` (without ``n_dropped``)."""
    strays = [stray_points(s.points) for s in scans]
    if drop_strays:
        scans = [_without(s, m) if m.any() else s for s, m in zip(scans, strays)]
    fit_on = [i for i, s in enumerate(scans) if s.split == "train"] or list(range(len(scans)))
    frame = Frame.fit(np.concatenate([scans[i].points if drop_strays else scans[i].points[~strays[i]]
                                      for i in fit_on]))
    counts = [int(m.sum()) for m in strays]
    provenance = dict(provenance, frame_fitted_on="train" if any(s.split == "train" for s in scans)
                      else "all (no train split)", stray_points=_stray_report(scans, counts, drop_strays))
    ScanCollection.create(out, (frame.apply(s) for s in scans), frame=frame, provenance=provenance,
                          overwrite=overwrite)
    sizes = np.array([len(s) for s in scans])
    return {"out": str(out), "n_scans": len(scans), "n_stray": int(sum(counts)), "strays_dropped": drop_strays,
            "frame": frame.as_dict(), "points_min": int(sizes.min()), "points_median": float(np.median(sizes)),
            "points_max": int(sizes.max()), "groups": group_counts((s.split, s.label, s.defect) for s in scans)}


def _without(scan, mask):
    """The scan without the points where ``mask`` is True (labels and deviations follow)."""
    keep = ~mask
    out = replace(scan, points=scan.points[keep], normals=scan.normals[keep],
                  point_labels=None if scan.point_labels is None else scan.point_labels[keep],
                  point_deviation=None if scan.point_deviation is None else scan.point_deviation[keep])
    out.points = np.asarray(scan.points[keep], dtype=np.float64)  # file-unit precision, as load_source keeps it
    return out


def _stray_report(scans, counts, dropped):
    """The provenance entry on stray points: the rule, totals, and the scans with the most."""
    counts = np.asarray(counts)
    worst = np.argsort(-counts, kind="stable")[:5]
    return {"rule": f"off the plane of its {STRAY_NEIGHBOURS} nearest neighbours by > {STRAY_FACTOR:g} local spacings",
            "total": int(counts.sum()), "scans_with": int(np.count_nonzero(counts)),
            "max_per_scan": int(counts.max(initial=0)), "dropped": bool(dropped), "in_frame_fit": False,
            "worst": [[scans[i].name, int(counts[i])] for i in worst if counts[i] > 0]}


def group_counts(rows):
    """{key: how many times it occurs} of an iterable of hashable keys, sorted by key."""
    groups = {}
    for key in rows:
        groups[key] = groups.get(key, 0) + 1
    return dict(sorted(groups.items()))
