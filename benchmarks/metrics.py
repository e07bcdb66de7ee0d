"""The benchmarks' detection metrics: AUROC (objects and points, overall and per defect type) and flagged fractions.

AUROC here is the Mann-Whitney statistic: the probability that a random defective item scores above a random good
one, ties counting one half (what ``sklearn.metrics.roc_auc_score`` computes), from average ranks in O(n log n).
"""
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
