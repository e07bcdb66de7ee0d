"""Tables of the suites' figures: plain text for the terminal (one row per method, columns aligned, NaN and None
shown as '-') and markdown for docs/results.md (:mod:`benchmarks.results_doc`, :mod:`benchmarks.renderers`)."""
import math

MAX_ROWS = 20  # rows of one rendered markdown table at most


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
        threshold just above the worst good test scan flags; optional), ``seconds_per_scan`` (optional). Where the
        verdicts were counted (``flagged['good_rejected']``, ``['defective_told']``): the good scans and the share of
        defective ones whose verdict is 'defective' (not 'uncertain').
    """
    kinds = sorted({k for r in rows for k in r["auroc"] if k != "overall"})
    flat = []
    for r in rows:
        t = r.get("threshold") or {}
        far = rate_text(t.get("predicted_far"), t.get("far_interval")) if t.get("predicted_far") is not None else None
        f = r["flagged"]
        rejected = f.get("good_rejected")
        flat.append({"part": r["part"], "method": r["method"], "auroc": r["auroc"]["overall"],
                     **{k: r["auroc"].get(k) for k in kinds}, "def": f["defective"],
                     "good": f"{round(f['good'] * f['n_good'])} of {f['n_good']}", "oracle": r.get("oracle"),
                     "told": None if rejected is None else f"{round(rejected * f['n_good'])} of {f['n_good']}",
                     "def_told": f.get("defective_told"), "basis": t.get("basis"), "far": far,
                     "sec": r.get("seconds_per_scan")})
    return format_table(flat, [("part", "part", ""), ("method", "method", ""), ("auroc", "AUROC", ".3f"),
                               *[(k, k, ".3f") for k in kinds], ("def", "def flagged", ".3f"),
                               ("def_told", "def told def", ".3f"), ("good", "good flagged", ">"),
                               ("told", "good told def", ">"), ("oracle", "oracle", ".3f"), ("basis", "basis", ">"),
                               ("far", "pred. FAR (90% int.)", ">"), ("sec", "s/scan", ".3f")])


# ------------------------------------------------------------------------------------------------ markdown
def markdown_cell(value, fmt=None):
    """A table cell: with ``fmt`` (a format spec, '' for text) :func:`benchmarks.table.cell`'s text, else by the
    value's type; '-' for None and NaN."""
    if fmt:
        try:
            return cell(value, fmt)
        except (TypeError, ValueError):  # a figure of another type than the renderer expects: as it is
            return str(value)
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.3f}" if abs(value) < 100 else f"{value:.0f}"
    if isinstance(value, (list, tuple)):
        return ", ".join(markdown_cell(v) for v in value) if len(value) <= 6 else f"{len(value)} values"
    if isinstance(value, dict):
        return ", ".join(f"{k} {markdown_cell(v)}" for k, v in value.items()) if len(value) <= 6 else f"{len(value)} values"
    return str(value).replace("|", "\\|").replace("\n", " ")


def markdown_table(rows, columns, limit=MAX_ROWS):
    """Rows of dicts as a markdown table: ``columns`` a list of (key, header, fmt) (``fmt`` as :func:`cell`'s;
    a callable key is given the row); at most ``limit`` rows, then a line saying how many more the record holds."""
    def value(row, key):
        return key(row) if callable(key) else row.get(key)

    lines = ["| " + " | ".join(h for _, h, _ in columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(markdown_cell(value(r, k), f) for k, _, f in columns) + " |" for r in rows[:limit]]
    if len(rows) > limit:
        lines += ["", f"({len(rows) - limit} more rows in the record.)"]
    return lines


def pivot(rows, row_key, column_key, text, first="", limit=MAX_ROWS):
    """Rows of dicts as a markdown table with one line per value of ``row_key`` and one column per value of
    ``column_key`` (both in order of appearance), each cell ``text(row)`` ('' where no row has the pair)."""
    keys = list(dict.fromkeys(r[row_key] for r in rows))
    columns = list(dict.fromkeys(r[column_key] for r in rows))
    cells = {(r[row_key], r[column_key]): text(r) for r in rows}
    table = [{"": k, **{str(c): cells.get((k, c), "") for c in columns}} for k in keys]
    return markdown_table(table, [("", first, "")] + [(str(c), str(c), "") for c in columns], limit)


def listed(label, items):
    """'label: none' or 'label: N (a; b; ...)'."""
    return f"{label}: {len(items)}" + (f" ({'; '.join(map(str, items))})" if items else "")


def rate_text(predicted, interval):
    """A predicted false-alarm rate with its interval as the suites print it ('2% (0.086-7%)'); '-' without one."""
    if predicted is None:
        return "-"
    from inspection.threshold import format_rate

    text = format_rate(predicted)
    if interval:
        text += f" ({format_rate(interval[0])}-{format_rate(interval[1])})"
    return text.replace(" %", "%")


def of_text(count, total):
    """'3 of 16'; '-' without either."""
    return "-" if count is None or total is None else f"{count} of {total}"


def defect_kinds(aurocs):
    """The defect types of AUROC dicts ({'overall', type: value}), sorted."""
    return sorted({k for a in aurocs if isinstance(a, dict) for k in a if k != "overall"})
