"""The nearest-neighbour baseline every inspection suite prints beside the toolkit's scores, thresholded the way the
toolkit thresholds its own."""
import time

import numpy as np

from benchmarks import metrics

TOP_PERCENT = 5.0


def nn_baseline(train_points, scans, top=TOP_PERCENT):
    """Per scan: each point's distance to the nearest training point, and the scan score = the mean of the worst
    ``top`` % of them.

    Parameters
    ----------
    train_points : (n, 3) array
        The good training scans' points, in the scans' frame.
    scans : sequence of objects with ``points`` (m_i, 3)
    top : float in (0, 100]

    Returns
    -------
    list of (float, (m_i,) array)
        (scan score, per-point distances) per scan.
    """
    from scipy.spatial import cKDTree

    tree = cKDTree(train_points)
    out = []
    for s in scans:
        d = tree.query(s.points, k=1, workers=2)[0]
        k = max(1, int(np.ceil(top / 100 * len(d))))
        out.append((float(np.sort(d)[-k:].mean()), d))
    return out


def nn_point_maps(scans, distances):
    """The baseline's anomaly maps, made as the toolkit makes its own (:func:`benchmarks.inspect_api.patch_map`):
    each point's root mean square distance over its patch of nearest scan points, so that point AUROCs compare
    the two scores and not the maps' smoothing.

    Parameters
    ----------
    scans : sequence of objects with ``points`` (m_i, 3)
    distances : sequence of (m_i,) arrays (:func:`nn_baseline`'s per-point distances)

    Returns
    -------
    list of (m_i,) arrays
    """
    from benchmarks import inspect_api

    return [inspect_api.patch_map(s.points, d) for s, d in zip(scans, distances)]


def nn_verdicts(collection, heldback_names, alpha):
    """The baseline on a collection's test scans, with a threshold fitted like the toolkit's: on the held-back good
    scans and the training scans cross-fitted (each against the other training scans' points), at ``alpha``.

    Parameters
    ----------
    collection : str or Path
        A scan collection with train and test splits.
    heldback_names : collection of str
        The scans the model held back for calibration (not part of the baseline's training points).
    alpha : float

    Returns
    -------
    dict
        ``scores``, ``point_maps`` (per test scan, :func:`nn_point_maps`), ``labels``, ``defects``, ``point_labels``, ``threshold``
        (an ``inspection.threshold.Threshold``), ``seconds_per_scan`` (scoring the test scans).
    """
    from datasets import ScanCollection
    from inspection.threshold import fit_threshold

    held = set(heldback_names)
    with ScanCollection(collection) as c:
        names = c.names
        train = c.read_many([i for i in c.select(split="train") if names[i] not in held])
        cal = c.read_many([i for i, n in enumerate(names) if n in held])
        test = c.read_many(c.select(split="test"))
    train_points = np.concatenate([s.points for s in train])
    t0 = time.perf_counter()
    scored = nn_baseline(train_points, test)
    seconds = (time.perf_counter() - t0) / len(test)
    cal_scores = [v for v, _ in nn_baseline(train_points, cal)]
    crossed = [nn_baseline(np.concatenate([t.points for j, t in enumerate(train) if j != i]), [s])[0][0]
               for i, s in enumerate(train)]
    threshold = fit_threshold(np.r_[cal_scores, crossed], alpha,
                              ["held-back"] * len(cal_scores) + ["cross-fitted"] * len(crossed))
    return {"scores": np.array([v for v, _ in scored]), "point_maps": nn_point_maps(test, [d for _, d in scored]),
            "labels": np.array([s.label for s in test]), "defects": np.array([s.defect for s in test]),
            "point_labels": [s.point_labels for s in test], "threshold": threshold, "seconds_per_scan": seconds}


def nn_figures(collection, heldback_names, alpha, method="nearest-neighbour top5%"):
    """The baseline's row of a verdicts table: :func:`nn_verdicts` summed up the way the suites print it.

    Parameters
    ----------
    collection, heldback_names, alpha
        As :func:`nn_verdicts`.
    method : str
        The row's label.

    Returns
    -------
    dict
        ``method``, ``auroc`` (overall and per defect type), ``point_auroc``, ``flagged``
        (:func:`benchmarks.metrics.flagged`), ``threshold`` (``value``, ``basis``, ``predicted_far``,
        ``far_interval``), ``seconds_per_scan``: the keys :func:`benchmarks.table.verdicts_table` reads.
    """
    nn = nn_verdicts(collection, heldback_names, alpha)
    t = nn["threshold"]
    return {"method": method, "auroc": metrics.auroc_per_defect(nn["scores"], nn["labels"], nn["defects"]),
            "point_auroc": metrics.point_auroc(nn["point_labels"], nn["point_maps"]),
            "flagged": metrics.flagged(nn["scores"], nn["labels"], t.value),
            "threshold": {"value": t.value, "basis": t.basis, "predicted_far": t.predicted_far,
                          "far_interval": list(t.far_interval)},
            "seconds_per_scan": nn["seconds_per_scan"]}
