"""The benchmarks' detection metrics: AUROC (objects and points, overall and per defect type), flagged fractions,
and a scored run's rows as the inspection wrote them (``read_scores``, ``verdicts_turned``).

AUROC here is the Mann-Whitney statistic: the probability that a random defective item scores above a random good
one, ties counting one half (what ``sklearn.metrics.roc_auc_score`` computes), from average ranks in O(n log n).
"""
import csv
from pathlib import Path

import numpy as np

GOOD = "good"


def auroc(y, scores):
    """Area under the ROC curve of ``scores`` (higher = more anomalous) for binary labels ``y``.

    Parameters
    ----------
    y : (n,) array of bool or {0, 1}
        True / 1 for defective (the positive class).
    scores : (n,) float array

    Returns
    -------
    float
        NaN when one of the two classes is empty.
    """
    from scipy.stats import rankdata

    y = np.asarray(y).astype(bool)
    scores = np.asarray(scores, dtype=np.float64)
    if y.shape != scores.shape or y.ndim != 1:
        raise ValueError(f"y and scores must be (n,) arrays of the same length, got {y.shape} and {scores.shape}")
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    ranks = rankdata(scores)  # average ranks: ties count one half
    return float((ranks[y].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def _defective(labels):
    return np.asarray(labels) != GOOD


def auroc_per_defect(scores, labels, defects):
    """Object AUROC overall (``'overall'``) and per defect type (that type's scans against the good ones).

    Parameters
    ----------
    scores : (n,) float array
    labels : (n,) str array
        ``'good'`` or anything else (defective).
    defects : (n,) str array
        The defect type of each defective scan.

    Returns
    -------
    dict
        ``{'overall': float, <defect type>: float, ...}``
    """
    scores = np.asarray(scores, dtype=np.float64)
    bad, defects = _defective(labels), np.asarray(defects)
    out = {"overall": auroc(bad, scores)}
    for kind in sorted(set(defects[bad].tolist())):
        keep = ~bad | (defects == kind)
        out[kind] = auroc(bad[keep], scores[keep])
    return out


def flagged(scores, labels, threshold):
    """Fractions flagged (score > ``threshold``) of the defective and of the good scans, and the number of good ones.

    Returns
    -------
    dict
        ``{'defective': float, 'good': float, 'n_good': int, 'n_defective': int}``
    """
    scores = np.asarray(scores, dtype=np.float64)
    bad = _defective(labels)
    above = scores > threshold
    return {"defective": float(above[bad].mean()) if bad.any() else float("nan"),
            "good": float(above[~bad].mean()) if (~bad).any() else float("nan"),
            "n_good": int((~bad).sum()), "n_defective": int(bad.sum())}


def point_auroc(point_labels, point_scores):
    """Point AUROC over several scans: every point of every scan pooled (label > 0: on a defect).

    Parameters
    ----------
    point_labels, point_scores : sequences of (m_i,) arrays
        A label array may be None: a scan without ground truth, every point good.
    """
    scores = [np.asarray(s, dtype=np.float64) for s in point_scores]
    labels = [np.zeros(len(s), bool) if p is None else np.asarray(p) > 0 for p, s in zip(point_labels, scores)]
    return auroc(np.concatenate(labels), np.concatenate(scores))


def point_auroc_per_defect(point_labels, point_scores, labels, defects):
    """Point AUROC overall and per defect type (the points of that type's scans and of the good scans).

    Returns
    -------
    dict
        ``{'overall': float, <defect type>: float, ...}``
    """
    bad, defects = _defective(labels), np.asarray(defects)
    out = {"overall": point_auroc(point_labels, point_scores)}
    for kind in sorted(set(defects[bad].tolist())):
        idx = np.flatnonzero(~bad | (defects == kind))
        out[kind] = point_auroc([point_labels[i] for i in idx], [point_scores[i] for i in idx])
    return out



def exact_alpha_flagged(scores, labels, alpha):
    """The fraction of defective scans flagged by the threshold a calibration that knew the good test scans' own
    distribution would set: the 1 - ``alpha`` quantile of the log-normal fitted to the good test scans' scores (the
    toolkit's tail model, ``inspection.threshold``). What a threshold whose false-alarm rate is exactly ``alpha``
    detects, so a detection target is a test of the calibration only where this meets it. NaN where fewer than 3
    good scores are finite and positive, or no defective score is finite."""
    from scipy.stats import norm

    scores, labels = np.asarray(scores, dtype=np.float64), np.asarray(labels)
    ok = np.isfinite(scores)
    bad = _defective(labels) & ok
    good = scores[~_defective(labels) & ok]
    if not bad.any() or len(good) < 3 or not np.all(good > 0):
        return float("nan")
    logs = np.log(good)
    threshold = float(np.exp(logs.mean() + norm.ppf(1.0 - float(alpha)) * logs.std(ddof=1)))
    return float((scores[bad] > threshold).mean())


def oracle_flagged(scores, labels):
    """The fraction of defective scans a threshold just above the worst good scan would flag (what the best threshold
    that flags no good scan finds; 'the oracle column' the verdicts are judged against). NaN scores are left out."""
    scores, labels = np.asarray(scores, dtype=np.float64), np.asarray(labels)
    ok = np.isfinite(scores)
    bad = _defective(labels) & ok
    good = ~_defective(labels) & ok
    if not bad.any() or not good.any():
        return float("nan")
    return float((scores[bad] > scores[good].max()).mean())


# ------------------------------------------------------------------- region-level metrics (MVTec 3D-AD's scoring)
LINK_SPACINGS = 3.0  # default link of the ground-truth regions, in the scan's median nearest-neighbour spacings


def _point_labels(labels, m, name="point_labels"):
    """(m,) bool array of a scan's 0/1 labels (None: every point normal), checked."""
    if labels is None:
        return np.zeros(m, bool)
    labels = np.asarray(labels)
    if labels.shape != (m,):
        raise ValueError(f"{name}: a scan's labels must be an ({m},) array like its points, got shape {labels.shape}")
    if labels.size and not np.isin(labels, (0, 1)).all():
        raise ValueError(f"{name} must hold 0 (normal) or 1 (defect) only, got values {np.unique(labels)[:5]}")
    return labels.astype(bool)


def _scan_points(points):
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points: a scan's points must be an (m, 3) array, got shape {points.shape}")
    return points


def _same_count(**lists):
    counts = {name: len(value) for name, value in lists.items()}
    if len(set(counts.values())) != 1:
        raise ValueError(f"one entry per scan in each list expected, got {counts}")


def truth_regions(points, labels, link=None):
    """The ground-truth regions of one scan: the connected components of its labelled points, two labelled points
    linked when closer than ``link`` (strictly; normal points never link anything).

    Parameters
    ----------
    points : (m, 3) float array
    labels : (m,) array of {0, 1} or bool, or None
        1 / True: the point lies on a defect. None: every point normal.
    link : float, optional
        World units; default ``LINK_SPACINGS`` (3) x the median over all the scan's points of the distance to the
        nearest other point (0 for a scan of fewer than 2 points: every labelled point its own region).

    Returns
    -------
    (m,) int array
        -1 on normal points, the region id 0 .. k-1 on labelled points (ids in order of each region's first point).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    points = _scan_points(points)
    on = _point_labels(labels, len(points), "labels")
    if link is None:
        if len(points) < 2:
            link = 0.0
        else:
            link = LINK_SPACINGS * float(np.median(cKDTree(points).query(points, k=2)[0][:, 1]))
    elif not link >= 0:
        raise ValueError(f"link must be >= 0 (world units), got {link}")
    out = np.full(len(points), -1, dtype=np.int64)
    rows = np.flatnonzero(on)
    if not len(rows):
        return out
    pairs = cKDTree(points[rows]).query_pairs(link, output_type="ndarray") if link > 0 else np.empty((0, 2), int)
    if len(pairs):  # query_pairs keeps distance <= link: drop the pairs exactly at the link
        pairs = pairs[np.linalg.norm(points[rows[pairs[:, 0]]] - points[rows[pairs[:, 1]]], axis=1) < link]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(rows), len(rows)))
    _, component = connected_components(graph, directed=False)
    _, first, ids = np.unique(component, return_index=True, return_inverse=True)
    out[rows] = np.argsort(np.argsort(first))[ids]  # renumber the components by their first point
    return out


def pro_curve(points, point_labels, point_maps, link=None):
    """The per-region-overlap (PRO) curve of anomaly maps over several scans, as MVTec AD / MVTec 3D-AD compute it
    (``compute_pro`` of the MVTec AD evaluation code, ``pro_curve_util.py``), on point clouds.

    Every distinct map value ``s`` over all scans gives one point of the curve: the points with map >= ``s`` are
    positive; FPR = the share of all normal points (every scan) that are positive, PRO = the mean over all
    ground-truth regions (:func:`truth_regions`, every scan) of the share of that region's points that are positive.
    As in the reference: one sort of all values (descending) and cumulative sums, the last point of each run of equal
    values kept, the values clipped at 1, and (0, 0) prepended and (1, 1) appended.

    Parameters
    ----------
    points : list of (m_i, 3) float arrays
        One entry per scan, good and defective.
    point_labels : list of (m_i,) arrays of {0, 1} (or None: every point normal)
    point_maps : list of (m_i,) float arrays
        Anomaly map values (higher = more anomalous), finite.
    link : float, optional
        Passed to :func:`truth_regions` (default: per scan, 3 x its median nearest-neighbour spacing).

    Returns
    -------
    fprs, pros : (c,) float arrays
        Non-decreasing, from 0 to 1; c = the number of distinct map values + 2.
    """
    _same_count(points=points, point_labels=point_labels, point_maps=point_maps)
    scores, fp_change, pro_change, n_regions = [], [], [], 0
    for i, (xyz, labels, values) in enumerate(zip(points, point_labels, point_maps)):
        xyz = _scan_points(xyz)
        values = np.asarray(values, dtype=np.float64)
        if values.shape != (len(xyz),):
            raise ValueError(f"point_maps[{i}] must be an ({len(xyz)},) array like points[{i}], got {values.shape}")
        if not np.isfinite(values).all():
            raise ValueError(f"point_maps[{i}] holds non-finite values")
        region = truth_regions(xyz, labels, link)
        sizes = np.bincount(region[region >= 0])
        change = np.zeros(len(xyz))
        change[region >= 0] = 1.0 / sizes[region[region >= 0]]
        scores.append(values)
        fp_change.append(region < 0)
        pro_change.append(change)
        n_regions += len(sizes)
    scores, fp_change, pro_change = np.concatenate(scores), np.concatenate(fp_change), np.concatenate(pro_change)
    n_normal = int(fp_change.sum())
    if n_regions == 0:
        raise ValueError("no labelled point in any scan: the PRO curve needs at least one ground-truth region")
    if n_normal == 0:
        raise ValueError("no normal point in any scan: the false-positive rate is undefined")
    order = np.argsort(scores, kind="stable")[::-1]  # descending
    scores = scores[order]
    fprs = np.cumsum(fp_change[order], dtype=np.int64) / n_normal
    pros = np.cumsum(pro_change[order]) / n_regions
    keep = np.append(np.diff(scores) != 0, True)  # the last point of each run of equal values takes them all in
    fprs, pros = np.minimum(fprs[keep], 1.0), np.minimum(pros[keep], 1.0)
    return np.concatenate(([0.0], fprs, [1.0])), np.concatenate(([0.0], pros, [1.0]))


def _trapezoid(x, y, x_max):
    """The area under the curve (x, y) (x sorted ascending, repeats allowed) from x[0] to ``x_max``, by the
    trapezoid rule, y at ``x_max`` interpolated linearly between its neighbours where ``x_max`` is not an x
    (``trapezoid`` of the MVTec AD evaluation code, ``generic_util.py``)."""
    from bisect import bisect

    correction = 0.0
    if x_max not in x:
        ins = bisect(x, x_max)  # x[ins - 1] < x_max < x[ins], the last of the repeats of x[ins - 1]
        y_at = y[ins - 1] + (y[ins] - y[ins - 1]) * (x_max - x[ins - 1]) / (x[ins] - x[ins - 1])
        correction = 0.5 * (y_at + y[ins - 1]) * (x_max - x[ins - 1])
    keep = x <= x_max
    x, y = x[keep], y[keep]
    return float(np.sum(0.5 * (y[1:] + y[:-1]) * (x[1:] - x[:-1])) + correction)


def au_pro(points, point_labels, point_maps, max_fpr=0.3, link=None):
    """The normalised area under the PRO curve up to a false-positive rate ``max_fpr`` (MVTec 3D-AD's AU-PRO, by
    default at 0.3): the trapezoid integral of :func:`pro_curve` from FPR 0 to ``max_fpr`` (the curve's PRO at
    ``max_fpr`` interpolated linearly between its neighbours, as the reference's ``trapezoid`` does), divided by
    ``max_fpr``. A perfect map (every labelled point above every normal one) gives 1; a map equal on every point
    gives ``max_fpr`` / 2 (the curve then jumps from (0, 0) to (1, 1)).

    Parameters
    ----------
    points : list of (m_i, 3) float arrays
        One entry per scan, good and defective; the points find the ground-truth regions (:func:`truth_regions`).
    point_labels : list of (m_i,) arrays of {0, 1} (or None: every point normal)
    point_maps : list of (m_i,) float arrays
        Anomaly map values, higher = more anomalous, finite.
    max_fpr : float in (0, 1]
    link : float, optional
        Two labelled points closer than this (world units) are in the same region; default per scan 3 x its median
        nearest-neighbour spacing.

    Returns
    -------
    float
        In [0, 1].

    Raises
    ------
    ValueError
        Lists of different lengths, a label or map array not as long as its scan's points, labels other than 0/1,
        non-finite map values, no labelled point in any scan, no normal point in any scan, ``max_fpr`` outside (0, 1].
    """
    if not 0.0 < max_fpr <= 1.0:
        raise ValueError(f"max_fpr must lie in (0, 1], got {max_fpr}")
    fprs, pros = pro_curve(points, point_labels, point_maps, link)
    return _trapezoid(fprs, pros, float(max_fpr)) / float(max_fpr)


def _predicted(regions, m, name):
    regions = np.asarray(regions)
    if regions.shape != (m,) or (regions.size and not np.issubdtype(regions.dtype, np.integer)):
        raise ValueError(f"{name}: a scan's predicted regions must be an ({m},) int array, got {regions.dtype} "
                         f"{regions.shape}")
    if regions.size and regions.min() < -1:
        raise ValueError(f"{name} must hold -1 (no region) or region ids >= 0, got {regions.min()}")
    return regions.astype(np.int64)


def region_overlap(points, truth_labels, predicted_regions, min_iou=0.3, link=None):
    """Which ground-truth regions a segmentation found: a true region (:func:`truth_regions`) is detected when some
    predicted region of the same scan has an intersection over union (over point sets) >= ``min_iou`` with it.

    Each true region is matched to the predicted region of its scan with the largest IoU (ties: the smallest id); a
    predicted region may be the match of several true regions (with ``min_iou`` > 0.5 at most one can be detected
    by it).

    Parameters
    ----------
    points : list of (m_i, 3) float arrays
        One entry per scan.
    truth_labels : list of (m_i,) arrays of {0, 1} (or None: every point normal)
    predicted_regions : list of (m_i,) int arrays
        -1: the point is in no predicted region; k >= 0: in the scan's predicted region k.
    min_iou : float in (0, 1]
    link : float, optional
        For :func:`truth_regions` (default per scan 3 x its median nearest-neighbour spacing).

    Returns
    -------
    dict
        ``detected``: the share of the true regions detected (NaN when there is none); ``regions``: how many true
        regions; ``matches``: one dict per true region, in scan order then region id, ``{'scan': i, 'region': the id
        :func:`truth_regions` gives it, 'points': its (n,) int point indices, 'predicted': the best-matching
        predicted region's id (-1 when none overlaps it), 'iou': that IoU (0.0 when none), 'detected': bool}``.
    """
    if not 0.0 < min_iou <= 1.0:
        raise ValueError(f"min_iou must lie in (0, 1], got {min_iou}")
    _same_count(points=points, truth_labels=truth_labels, predicted_regions=predicted_regions)
    matches = []
    for i, (xyz, labels, predicted) in enumerate(zip(points, truth_labels, predicted_regions)):
        truth = truth_regions(xyz, labels, link)
        predicted = _predicted(predicted, len(truth), f"predicted_regions[{i}]")
        predicted_size = np.bincount(predicted[predicted >= 0], minlength=1)
        for k in range(int(truth.max()) + 1 if len(truth) else 0):
            inside = np.flatnonzero(truth == k)
            hit = predicted[inside]
            overlap = np.bincount(hit[hit >= 0], minlength=len(predicted_size))  # |truth & predicted j|, per j
            iou = overlap / (len(inside) + predicted_size - overlap)
            best = int(np.argmax(iou)) if overlap.any() else -1
            best_iou = float(iou[best]) if best >= 0 else 0.0
            matches.append({"scan": i, "region": k, "points": inside, "predicted": best, "iou": best_iou,
                            "detected": best_iou >= min_iou})
    found = [m["detected"] for m in matches]
    return {"detected": float(np.mean(found)) if found else float("nan"), "regions": len(matches),
            "matches": matches}


def false_regions_per_scan(predicted_regions, point_labels):
    """The mean number of false predicted regions per scan: predicted regions that contain no labelled point,
    summed over the scans and divided by the number of scans given (good scans included).

    Parameters
    ----------
    predicted_regions : list of (m_i,) int arrays
        -1: no region; k >= 0: the scan's predicted region k.
    point_labels : list of (m_i,) arrays of {0, 1} (or None: every point normal)

    Returns
    -------
    float
    """
    _same_count(predicted_regions=predicted_regions, point_labels=point_labels)
    if not len(predicted_regions):
        raise ValueError("no scan given")
    false = 0
    for i, (predicted, labels) in enumerate(zip(predicted_regions, point_labels)):
        predicted = _predicted(predicted, len(np.asarray(predicted)), f"predicted_regions[{i}]")
        on = _point_labels(labels, len(predicted), f"point_labels[{i}]")
        ids = np.unique(predicted[predicted >= 0])
        false += len(np.setdiff1d(ids, predicted[on & (predicted >= 0)]))
    return false / len(predicted_regions)


def read_scores(results_dir):
    """The per-scan rows a scored run wrote (``results/scores.csv``), as arrays: ``name``, ``label``, ``defect``,
    ``verdict`` ('good', 'defective', 'uncertain' (within the threshold's own uncertainty) or 'error': a scan that
    could not be scored, score NaN), ``score``, ``flagged`` (bool: the score exceeds the threshold, whatever the
    verdict) and, with rays, ``score_points``, ``score_rays`` (and where the run wrote them ``ray_nats``, the rays'
    evidence that entered the score, and ``rays_through``)."""
    with open(Path(results_dir) / "scores.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    out = {k: np.array([r[k] for r in rows]) for k in ("name", "label", "defect")}
    out["verdict"] = np.array([r["verdict"] for r in rows])
    if rows and "why" in rows[0]:  # the verdict in words (runs scored since issue 48)
        out["why"] = np.array([r["why"] for r in rows])
    out["flagged"] = np.array([r["flagged"] == "true" for r in rows])
    for k in ("score", "score_points", "score_rays", "ray_nats", "rays_through"):
        if rows and k in rows[0]:
            out[k] = np.array([float(r[k]) if r[k] not in ("", None) else np.nan for r in rows])
    return out


def verdicts_turned(scored, reason):
    """How a verdict rule that tells scans 'uncertain' with a reason starting ``reason`` turned a scored run's
    verdicts (``scored``: :func:`read_scores`' arrays): per label ('good', and 'defective' for every other label),
    ``n``, ``outside`` (scans told so), ``told`` (verdict 'defective') and ``told_without`` (scans whose verdict would
    be 'defective' without the rule: told so, or told ``reason`` where their threshold said 'defective', 'above the
    threshold' in their reason). None for a run without the verdicts' reasons."""
    if "why" not in scored:
        return None
    why = scored["why"].astype(str)
    outside = np.char.startswith(why, reason)
    was_defective = outside & (np.char.find(why, "above the threshold") >= 0)
    out = {}
    for label, keep in (("good", scored["label"] == GOOD), ("defective", scored["label"] != GOOD)):
        told = (scored["verdict"] == "defective") & keep
        out[label] = {"n": int(keep.sum()), "outside": int((outside & keep).sum()), "told": int(told.sum()),
                      "told_without": int((told | (was_defective & keep)).sum())}
    return out
