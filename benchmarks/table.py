"""Plain-text tables of the suites' figures: one row per method, columns aligned, NaN and None shown as '-'."""
import math


def cell(value, fmt):
    """``value`` formatted with ``fmt`` (a format spec such as '.3f'), '-' for None and NaN."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return format(value, fmt)


def format_table(rows, columns):
    """Rows of dicts as an aligned text table.

    Parameters
    ----------
    rows : list of dict
    columns : list of (key, header, fmt)
        ``fmt`` a format spec ('' for text); text columns are left-aligned, the others right-aligned.

    Returns
    -------
    str
    """
    texts = [[cell(r.get(key), fmt) for key, _, fmt in columns] for r in rows]
    widths = [max([len(h)] + [len(t[i]) for t in texts]) for i, (_, h, _) in enumerate(columns)]

    def line(cells):
        return " ".join(c.ljust(w) if not fmt else c.rjust(w) for c, w, (_, _, fmt) in zip(cells, widths, columns))

    return "\n".join([line([h for _, h, _ in columns])] + [line(t) for t in texts])


def verdicts_table(rows):
    """The inspection suites' table: per part and method, object AUROC overall and per defect type, the fractions of
    defective and good test scans flagged, the threshold's basis and predicted false-alarm rate, seconds per scan.

    Parameters
    ----------
    rows : list of dict
        ``part``, ``method``, ``auroc`` ({'overall', <type>: float}), ``flagged`` (:func:`benchmarks.metrics.flagged`),
        ``threshold`` (``basis``, ``predicted_far``, ``far_interval``; optional), ``oracle`` (the defective scans a
        threshold just above the worst good test scan flags; optional), ``seconds_per_scan`` (optional).
    """
    from inspection.threshold import format_rate

    kinds = sorted({k for r in rows for k in r["auroc"] if k != "overall"})
    flat = []
    for r in rows:
        t = r.get("threshold") or {}
        far = None
        if t.get("predicted_far") is not None:
            lo, hi = t["far_interval"]
            far = f"{format_rate(t['predicted_far'])} ({format_rate(lo)}-{format_rate(hi)})".replace(" %", "%")
        f = r["flagged"]
        flat.append({"part": r["part"], "method": r["method"], "auroc": r["auroc"]["overall"],
                     **{k: r["auroc"].get(k) for k in kinds}, "def": f["defective"],
                     "good": f"{round(f['good'] * f['n_good'])} of {f['n_good']}", "oracle": r.get("oracle"),
                     "basis": t.get("basis"), "far": far, "sec": r.get("seconds_per_scan")})
    return format_table(flat, [("part", "part", ""), ("method", "method", ""), ("auroc", "AUROC", ".3f"),
                               *[(k, k, ".3f") for k in kinds], ("def", "def flagged", ".3f"),
                               ("good", "good flagged", ">"), ("oracle", "oracle", ".3f"), ("basis", "basis", ">"),
                               ("far", "pred. FAR (90% int.)", ">"), ("sec", "s/scan", ".3f")])
