"""Reports of an inspection run: the scores table (CSV), the metrics summary (JSON), the terminal table."""
import csv
import io
import json
import math
from pathlib import Path

import numpy as np

from datasets.atomic import atomic_path

# ``verdict``: good, defective, uncertain (the score lies within the threshold's own uncertainty, or its evidence on
# surface no good scan saw: rescan, or add good scans of it) or error; ``flagged``: whether the score exceeds the
# threshold (true / false; empty for an error); ``reason``: why a scan whose verdict is ``error`` could not be scored,
# else a note on the scan itself (its size); ``uncovered``: the share of the scan's points on surface no good scan saw
# from their side (inspection.coverage; empty when coverage does not apply): its score counts the others; ``why``:
# the verdict in words (:meth:`inspection.Inspector.verdicts_from_results`), what report.html shows;
# ``points_scored`` and ``spacing``: for a scan much denser than the training scans, how many of its points were
# scored, a random subset at the training scans' point spacing ``spacing`` (the scans' units; inspection.resolution);
# empty for a scan scored on every point; ``beyond_family``: for a model of a family whose members differ, the share
# of the surface where they differ that the scan shows on which it lies beyond every trained member
# (inspection.family_range; at 0.25 or more the scan is outside the trained family, 'uncertain'); empty otherwise
CSV_COLUMNS = ("name", "split", "label", "defect", "score", "p_value", "verdict", "flagged", "reason", "uncovered",
               "why", "regions", "tolerance", "decided_by", "points_scored", "spacing", "beyond_family")
# defects.csv: one row per defect region (inspection.regions.DefectRegion.row), lengths in the scans' units
DEFECT_COLUMNS = ("name", "region", "type", "deviation", "deviation_sd", "area", "area_low", "area_high", "extent",
                  "volume", "volume_sd", "fill", "points", "peak", "x", "y", "z", "scan_x", "scan_y", "scan_z",
                  "feature", "above_level")
# with rays: the score's two components (the point score; the rays' surprisal aggregate in nats, as the field gives
# it), the rays' evidence that entered the score (nats, as good scans weigh it: inspection.ray_calibration) and the
# share of the scan's returned rays that passed through its own surface (not tested: its sensor origin is off)
RAY_CSV_COLUMNS = CSV_COLUMNS + ("score_points", "score_rays", "ray_nats", "rays_through")
_FLOAT_COLUMNS = ("score", "score_points", "score_rays", "ray_nats", "rays_through", "uncovered", "spacing",
                  "beyond_family")
ERROR_VERDICT = "error"
UNCERTAIN_VERDICT = "uncertain"  # the score lies within the threshold's own uncertainty: rescan
VERDICTS = ("defective", UNCERTAIN_VERDICT, "good", ERROR_VERDICT)  # in the order a quality engineer reads them


def atomic_write_text(path, text):
    """Write ``text`` (UTF-8) to ``path`` through :func:`datasets.atomic.atomic_path`."""
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8", newline="")
    return Path(path)


def write_scores_csv(path, rows, columns=CSV_COLUMNS):
    """``rows``: dicts with the keys of ``columns`` (CSV_COLUMNS, or RAY_CSV_COLUMNS; scores and p_value
    floats, absent or None for a scan whose verdict is ``error``). Written atomically."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for r in rows:
        floats = {k: "" if r.get(k) is None else f"{r[k]:.9g}" for k in _FLOAT_COLUMNS}
        p_value = "" if r.get("p_value") is None else f"{r['p_value']:.6g}"
        flagged = "" if r["verdict"] == ERROR_VERDICT else str(_flagged(r)).lower()
        writer.writerow({**r, **floats, "p_value": p_value, "flagged": flagged, "reason": r.get("reason", "")})
    return atomic_write_text(path, buf.getvalue())


def write_defects_csv(path, rows):
    """``defects.csv``: one row per defect region (``DEFECT_COLUMNS``; floats to 6 significant digits, an unknown
    volume empty). Written atomically."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=DEFECT_COLUMNS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: ("" if v is None else f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return atomic_write_text(path, buf.getvalue())


def _finite(x):
    return None if x is None or not math.isfinite(x) else float(x)


def summarize(rows, threshold, alpha, point_labels=None, point_scores=None, extra=None):
    """Counts and, when labels exist, detection metrics (positive class = defective).

    Parameters
    ----------
    rows : list of dict
        One per scan with 'label' ('good' / 'defective' / 'unknown'), 'defect', 'score', 'p_value', 'verdict'
        (``'error'``: the scan could not be scored; counted in ``n_errors``, left out of the metrics;
        ``'uncertain'``: counted in ``n_uncertain``), and ``'flagged'``, whether the score exceeds the threshold
        (default: the verdict is ``'defective'``): the detection metrics are the threshold's.
    threshold, alpha : float
    point_labels, point_scores : list of (m_i,) arrays, optional
        Per-point ground truth and per-point values (the anomaly maps', :func:`inspection.maps.map_values`) of the
        scans that have ground truth, pooled for the point-level AUROC.
    extra : dict, optional
        Merged into the summary (model, aggregate, ...).

    Returns
    -------
    dict (JSON-ready; infinities as null)
    """
    from sklearn.metrics import average_precision_score, confusion_matrix, precision_recall_fscore_support, \
        roc_auc_score

    errors = [r for r in rows if r["verdict"] == ERROR_VERDICT]
    rows = [r for r in rows if r["verdict"] != ERROR_VERDICT]
    labels = [r["label"] for r in rows]
    summary = {
        "n_scans": len(rows) + len(errors),
        "n_errors": len(errors),
        "counts": {lab: labels.count(lab) for lab in ("good", "defective", "unknown")},
        "counts_by_defect": {},
        "n_flagged": sum(_flagged(r) for r in rows),
        "n_uncertain": sum(r["verdict"] == UNCERTAIN_VERDICT for r in rows),
        "verdict_counts": verdict_counts(rows + errors),
        "alpha": float(alpha),
        "threshold": _finite(threshold),
        "threshold_note": "a scan is defective when its score > threshold; 'decision' says how the threshold was "
                          "obtained and the false-alarm rate it predicts; null threshold: nothing is flagged",
    }
    for r in rows:
        if r["label"] == "defective":
            summary["counts_by_defect"][r["defect"]] = summary["counts_by_defect"].get(r["defect"], 0) + 1
    known = [r for r in rows if r["label"] in ("good", "defective")]
    metrics = {}
    if known:
        y = np.array([r["label"] == "defective" for r in known], dtype=int)
        s = np.array([r["score"] for r in known])
        pred = np.array([_flagged(r) for r in known], dtype=int)
        good = y == 0
        # what each labelled scan was told: 'uncertain' (rescan) is flagged by the threshold but not a rejection
        metrics["verdicts"] = {lab: {v: sum(r["label"] == lab and r["verdict"] == v for r in known)
                                     for v in ("good", UNCERTAIN_VERDICT, "defective")}
                               for lab in ("good", "defective")}
        if good.any():
            metrics["false_alarm_rate"] = float(pred[good].mean())
        if y.any():
            metrics["detection_rate"] = float(pred[~good].mean())
        if 0 < y.sum() < len(y):
            metrics["auroc"] = float(roc_auc_score(y, s))
            metrics["aupr"] = float(average_precision_score(y, s))
            per = {}
            for d in sorted({r["defect"] for r in known if r["label"] == "defective"}):
                sel = np.array([r["label"] == "good" or r["defect"] == d for r in known])
                per[d] = float(roc_auc_score(y[sel], s[sel]))
            metrics["auroc_per_defect"] = per
        if 0 < y.sum() < len(y):  # precision and recall mean nothing without both good and defective scans
            p, rc, f1, _ = precision_recall_fscore_support(y, pred, average="binary", pos_label=1, zero_division=0)
            metrics.update(precision=float(p), recall=float(rc), f1=float(f1))
        tn, fp, fn, tp = confusion_matrix(y, pred, labels=[0, 1]).ravel()
        metrics["confusion_matrix"] = {"tn": int(tn), "fp": int(fp), "fn": int(fn), "tp": int(tp),
                                       "rows": "true label (good, defective)",
                                       "matrix": [[int(tn), int(fp)], [int(fn), int(tp)]]}
    if point_labels:
        yl = np.concatenate([np.asarray(v).reshape(-1) for v in point_labels]).astype(int)
        sl = np.concatenate([np.asarray(v).reshape(-1) for v in point_scores])
        if 0 < yl.sum() < len(yl):
            metrics["point_auroc"] = float(roc_auc_score(yl, sl))
            metrics["point_n"] = int(len(yl))
    summary["metrics"] = metrics
    summary.update(extra or {})
    return summary


def _flagged(row):
    return bool(row.get("flagged", row["verdict"] == "defective"))


def verdict_counts(rows):
    """{verdict: scans} over :data:`VERDICTS`, in that order (zeros included), of rows with a 'verdict'."""
    counts = dict.fromkeys(VERDICTS, 0)
    for r in rows:
        counts[r.get("verdict", ERROR_VERDICT)] = counts.get(r.get("verdict", ERROR_VERDICT), 0) + 1
    return counts


def format_verdict_counts(counts):
    """'1 defective (flagged), 1 uncertain (rescan), 1 good': the scans by verdict, an 'uncertain' never counted as
    flagged; errors only when there are some."""
    words = {"defective": "defective (flagged)", UNCERTAIN_VERDICT: "uncertain (rescan)", "good": "good",
             ERROR_VERDICT: "could not be scored (error)"}
    return ", ".join(f"{counts.get(v, 0)} {words[v]}" for v in VERDICTS if v != ERROR_VERDICT or counts.get(v))


def write_json(path, obj):
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return _finite(float(o))
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def format_table(rows, summary, max_rows=60):
    """The terminal table: one line per scan (up to ``max_rows``, flagged scans first) and the metrics."""
    lines = [f"{'name':<28} {'label':<9} {'defect':<9} {'score':>10} {'p_value':>8}  verdict"]
    shown = sorted(rows, key=lambda r: ({ERROR_VERDICT: 0, "defective": 1, UNCERTAIN_VERDICT: 2}.get(r["verdict"], 3),
                                        r["name"]))
    for r in shown[:max_rows]:
        if r["verdict"] == ERROR_VERDICT:
            lines.append(f"{r['name'][:28]:<28} {r['label']:<9} {r['defect'] or '-':<9} {'-':>10} {'-':>8}  error: "
                         f"{r.get('reason', '')}")
            continue
        mark = {"defective": "  <-- FLAGGED", UNCERTAIN_VERDICT: "  <-- RESCAN"}.get(r["verdict"], "")
        lines.append(f"{r['name'][:28]:<28} {r['label']:<9} {r['defect'] or '-':<9} {r['score']:>10.4g} "
                     f"{r['p_value']:>8.3g}  {r['verdict']}{mark}")
    if len(rows) > max_rows:
        lines.append(f"... {len(rows) - max_rows} more in scores.csv")
    t = summary.get("threshold")
    parts = summary.get("parts")  # a model of several part types: a threshold per part
    where = ("thresholds per part: " + ", ".join(f"{p} {v['threshold']:.4g}" for p, v in parts.items())) if parts \
        else f"threshold {'none' if t is None else f'{t:.4g}'}"
    lines.append(f"{summary['n_scans']} scans: {format_verdict_counts(verdict_counts(rows))} at "
                 f"alpha={summary['alpha']:g} ({where})")
    if summary.get("n_uncertain"):
        lines.append(f"{summary['n_uncertain']} scan(s) uncertain: their scores lie within the threshold's own "
                     f"uncertainty (verdict 'uncertain'): rescan them")
    if summary.get("n_errors"):
        lines.append(f"{summary['n_errors']} scan(s) could not be scored (verdict 'error', reason in scores.csv)")
    decision = summary.get("decision")
    if decision:  # the threshold in plain words first, its statistics after
        from .threshold import describe_decision

        plain, stats = describe_decision(decision)
        lines += [f"threshold {'none' if t is None else f'{t:.4g}'}: {plain}", stats]
    m = summary.get("metrics", {})
    bits = []
    for key in ("auroc", "aupr", "point_auroc", "ray_point_auroc", "precision", "recall", "f1", "false_alarm_rate"):
        if key in m:
            bits.append(f"{key} {m[key]:.3f}")
    if bits:
        lines.append("  ".join(bits))
    if m.get("auroc_per_defect"):
        lines.append("AUROC per defect: " + "  ".join(f"{k} {v:.3f}" for k, v in m["auroc_per_defect"].items()))
    return "\n".join(lines)
