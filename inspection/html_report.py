"""The inspection run as one self-contained web page: the decision, the verdicts, the scores and the 3D anomaly maps.

``results/report.html`` opens from disk in any browser with no network: plotly's JavaScript (shipped inside the
plotly package) is inlined once, the data sit in the page as JSON, and nothing is fetched at run time. One 3D viewer
shows one scan at a time (a browser keeps only about 16 WebGL contexts alive, so a view per scan would go blank past
that); the scan list, the table's "3D" links and the arrow buttons switch it. Its points are a seeded subsample of
the scan's (:func:`scan_view`), coloured on the fixed scale of the PLY maps (:mod:`inspection.maps`).

For tests and headless browsers the page keeps its own state in ``window.reportStatus`` (``ready``, ``errors`` from
``window.onerror`` and rejected promises, and per plot its trace count, and for the 3D view whether WebGL drew) and
copies it as JSON into ``<pre id="report-status">`` once every plot has drawn.
"""
import base64
import html
import json
import math
from datetime import datetime, timezone

import numpy as np

from .html_page import EMPHASIS, PAGE, SCRIPT, STATUS_HEAD, STYLE
from .maps import MAP_CMAP, MAP_LABEL, MAP_RANGE, RAY_MAP_LABEL, RAY_MAP_RANGE
from .report import VERDICTS, verdict_counts

VIEW_POINTS = 3000  # points shown per scan in the 3D view
RAY_EMPHASIS = 0.5  # ray map: P(blocked) above which a point is drawn larger
VERDICT_COLOURS = {"good": "#2e7d32", "defective": "#c62828", "uncertain": "#ef6c00", "error": "#6d4c41"}
LABEL_COLOURS = {"good": "#2e7d32", "defective": "#c62828", "unknown": "#757575"}


def scan_view(name, points, values, ray_values=None, n_points=VIEW_POINTS, seed=0, regions=None):
    """One scan's 3D view data: a seeded subsample of its points with their map values.

    Every point above :data:`EMPHASIS` (or, with rays, whose ray value is above :data:`RAY_EMPHASIS`) is kept, up
    to half of ``n_points``, and a uniform random sample of the rest fills the remainder, so that a small defect
    stays visible however large the scan.

    Parameters
    ----------
    name : str
    points : (m, 3) array
        The scan's points, in the scan's frame.
    values : (m,) array
        Per-point patch residuals (the PLY map's values, :func:`inspection.maps.map_values`; scale ``MAP_RANGE``).
    ray_values : (m,) array, optional
        Per-point ray map (scale ``RAY_MAP_RANGE``).
    regions : (m,) int array, optional
        Each point's defect region id (:mod:`inspection.regions`; -1: none): a region's points are kept like the
        emphasised ones, so that selecting it shows it.
    n_points : int
        How many points to keep at most.
    seed : int

    Returns
    -------
    dict with ``name``, ``n`` (points in the scan), ``points`` (k, 3) float32, ``values`` (k,) float32,
    ``ray_values`` (k,) float32 or None and ``regions`` (k,) int16 or None
    """
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    values = np.asarray(values, dtype=np.float32).reshape(-1)
    if len(values) != len(points):
        raise ValueError(f"values must have one entry per point ({len(points)}), got {len(values)}")
    rays = None if ray_values is None else np.asarray(ray_values, dtype=np.float32).reshape(-1)
    if rays is not None and len(rays) != len(points):
        raise ValueError(f"ray_values must have one entry per point ({len(points)}), got {len(rays)}")
    ids = None if regions is None else np.asarray(regions, dtype=np.int16).reshape(-1)
    if ids is not None and len(ids) != len(points):
        raise ValueError(f"regions must have one entry per point ({len(points)}), got {len(ids)}")
    if n_points < 1:
        raise ValueError(f"n_points must be >= 1, got {n_points}")
    m = len(points)
    if m > n_points:
        rng = np.random.default_rng(seed)
        hot = values > EMPHASIS
        if rays is not None:
            hot |= rays > RAY_EMPHASIS
        if ids is not None:
            hot |= ids >= 0
        hot_idx, cold_idx = np.flatnonzero(hot), np.flatnonzero(~hot)
        hot_idx = rng.permutation(hot_idx)[:n_points // 2]
        cold_idx = rng.choice(cold_idx, size=min(len(cold_idx), n_points - len(hot_idx)), replace=False)
        keep = np.sort(np.concatenate([hot_idx, cold_idx]))
    else:
        keep = np.arange(m)
    return {"name": str(name), "n": int(m), "points": points[keep], "values": values[keep],
            "ray_values": None if rays is None else rays[keep], "regions": None if ids is None else ids[keep]}


def write_html_report(path, rows, summary, scan_views=(), title="Inspection report", defects=()):
    """Write the run's page to ``path`` (atomically); returns the path.

    Parameters
    ----------
    path : str or Path
    rows : list of dict
        ``scores.csv``'s rows (name, split, label, defect, score, p_value, verdict, flagged, reason, uncovered,
        why; with rays score_points, score_rays, ray_nats and rays_through).
    summary : dict
        ``summary.json``'s content (:func:`inspection.results.summarize_run`).
    scan_views : list of dict
        The scans to show in 3D (:func:`scan_view`), in any order.
    title : str
    defects : list of dict
        ``defects.csv``'s rows (:meth:`inspection.regions.DefectRegion.row` with the scan's ``name``): a table
        whose rows select their region in the 3D view (as does the page's address with ``#region=<scan>|<id>``).
    """
    from .report import atomic_write_text

    return atomic_write_text(path, report_html(rows, summary, scan_views, title, defects))


def report_html(rows, summary, scan_views=(), title="Inspection report", defects=()):
    """The page of :func:`write_html_report` as a string."""
    import plotly.offline

    rows = list(rows)
    views = sorted(scan_views, key=lambda v: -_score_of(rows, v["name"]))
    figures = {"histogram": _histogram_figure(rows, summary)}
    roc = _roc_figure(rows, summary)
    if roc is not None:
        figures["roc"] = roc
    data = {"figures": figures, "views": [_view_json(v) for v in views], "scale": _scale_json(),
            "view_of": {v["name"]: i for i, v in enumerate(views)}}
    body = "\n".join([
        _header_html(rows, summary, title),
        _decision_html(rows, summary),
        _plots_html(figures),
        _viewer_html(rows, views),
        _regions_html(defects, {v["name"] for v in views}),
        _table_html(rows, summary, {v["name"] for v in views}),
        _settings_html(summary),
    ])
    return PAGE.format(title=html.escape(title), style=STYLE, plotly=plotly.offline.get_plotlyjs(),
                       data=json.dumps(data, separators=(",", ":"), default=_json_default).replace("</", "<\\/"),
                       body=body, script=SCRIPT, status_head=STATUS_HEAD)


# ----------------------------------------------------------------------------------------------- page sections
def _header_html(rows, summary, title):
    counts = verdict_counts(rows)
    n = len(rows)
    parts = [f'<span class="pill" style="background:{VERDICT_COLOURS[v]}">{counts[v]} {v}</span>'
             for v in ("defective", "uncertain", "good", "error") if counts[v] or v in ("defective", "good")]
    when = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return (f'<header><h1>{html.escape(title)}</h1><div class="verdicts">{n} scans: {" ".join(parts)}</div>'
            f'<div class="sub">data {_e(summary.get("data", ""))}'
            f'{" (split " + _e(summary["split"]) + ")" if summary.get("split") else ""}, model '
            f'{_e(summary.get("model", ""))}, written {when}</div></header>')


def _decision_html(rows, summary):
    lines = []
    decision = summary.get("decision")
    if decision:
        lines.append(_threshold_line(summary.get("threshold"), decision, summary.get("n_calibration")))
    for part, one in sorted((summary.get("parts") or {}).items()):
        lines.append(f"part {_e(part)}: " + _threshold_line(one.get("threshold"), one.get("decision") or {},
                                                             one.get("n_calibration")))
    if not lines:
        lines.append("no threshold: nothing is flagged")
    counts = verdict_counts(rows)
    items = "".join(f"<li>{li}</li>" for li in lines)
    verdicts = ", ".join(f"<b>{counts[v]}</b> {v}" for v in VERDICTS)
    metrics = summary.get("metrics") or {}
    known = []
    for key, what in (("auroc", "AUROC"), ("detection_rate", "detection rate"),
                      ("false_alarm_rate", "false-alarm rate (test)"), ("point_auroc", "point AUROC"),
                      ("ray_point_auroc", "ray point AUROC")):
        if metrics.get(key) is not None:
            known.append(f"{what} {metrics[key]:.3f}")
    warnings = "".join(f'<p class="warn"><b>Warning:</b> {_e(w)}</p>' for w in summary.get("warnings") or [])
    return ('<section id="decision"><h2>Decision</h2>' + warnings +
            f'<ul>{items}</ul><p>Verdicts: {verdicts}. A scan is <i>defective</i> when its score exceeds the '
            'threshold, <i>uncertain</i> (rescan it) when its p-value lies within the threshold\'s own false-alarm '
            'interval, <i>error</i> when it could not be scored (see its reason).</p>'
            + (f'<p>Against the known labels: {", ".join(known)}.</p>' if known else "") + "</section>")


def _threshold_line(value, decision, n_calibration=None):
    """The threshold in plain words first (:func:`inspection.threshold.describe_decision`), its statistics after."""
    from .threshold import describe_decision

    line = f"threshold <b>{_num(value)}</b> (score above it: defective)"
    if decision.get("far_interval") and decision.get("predicted_far") is not None and decision.get("basis"):
        plain, stats = describe_decision(decision)
        return f'{line}: {_e(plain)}<br><span class="note">{_e(stats)}</span>'
    if decision.get("alpha") is not None:
        line += f", at alpha = {decision['alpha']:g}"
    if n_calibration:
        line += f", {n_calibration} calibration scans"
    return line


def _plots_html(figures):
    boxes = "".join(f'<div class="plot" id="plot-{k}"></div>' for k in figures)
    return f'<section id="scores"><h2>Scores</h2><div class="plots">{boxes}</div></section>'


def _viewer_html(rows, views):
    if not views:
        return ('<section id="maps"><h2>3D anomaly maps</h2><p>No scan to show: none was flagged (or the run '
                'was made with <code>--maps none</code>).</p></section>')
    options = "".join(f'<option value="{i}">{_e(v["name"])} ({_e(_row_of(rows, v["name"]).get("verdict", ""))}'
                      f', score {_num(_row_of(rows, v["name"]).get("score"))})</option>' for i, v in enumerate(views))
    rays = any(v["ray_values"] is not None for v in views)
    n_shown = max(len(v["values"]) for v in views)
    lo, hi = MAP_RANGE
    legend = (f"Colour: {MAP_CMAP} over the {_e(MAP_LABEL)}, fixed scale {lo:g} (dark blue) to {hi:g} (dark red), the "
              f"scale of <code>maps/*.ply</code>; points above {EMPHASIS:g} are drawn larger.")
    if rays:
        legend += (f" Right: the ray map, {_e(RAY_MAP_LABEL)}, {RAY_MAP_RANGE[0]:g} to {RAY_MAP_RANGE[1]:g}; "
                   f"points above {RAY_EMPHASIS:g} drawn larger.")
    return ('<section id="maps"><h2>3D anomaly maps</h2>'
            f'<div class="viewer-bar"><button id="prev" title="previous scan">&#9664;</button>'
            f'<select id="scan-select">{options}</select><button id="next" title="next scan">&#9654;</button>'
            f' <span id="scan-info"></span></div>'
            f'<div id="view3d" class="view3d"></div>'
            f'<p class="note">{legend} Drag to rotate, scroll to zoom, double-click to reset. Subsampled: at most '
            f'{n_shown:,} points a scan are shown (every point above the emphasis threshold up to half of them, a '
            f'seeded random sample of the rest); the PLY maps hold every point. {len(views)} scan'
            f'{"s" if len(views) != 1 else ""} shown here, highest score first.</p></section>')


def _regions_html(defects, viewed):
    """The defect regions' table (:mod:`inspection.regions`): a row per region, its link selecting it in the 3D
    view when its scan has one."""
    if not defects:
        return ""
    cols = [("type", "type"), ("deviation", "deviation"), ("deviation_sd", "sd"), ("area", "area"),
            ("extent", "extent"), ("volume", "volume"), ("x", "x"), ("y", "y"), ("z", "z")]
    body = []
    for d in defects:
        name = str(d["name"])
        link = (f'<a href="#maps" class="region3d" data-name="{_e(name)}" data-region="{int(d["region"])}">'
                f'{_e(name)} #{int(d["region"])}</a>' if name in viewed else f'{_e(name)} #{int(d["region"])}')
        cells = "".join(f"<td>{_e(d[k])}</td>" if k == "type" else f'<td class="num">{_num(d.get(k), 4)}</td>'
                        for k, _ in cols)
        below = " (below the level)" if d.get("above_level") is False else ""
        body.append(f"<tr><td>{link}{below}</td>{cells}</tr>")
    head = "".join(f"<th>{h}</th>" for h in ["region"] + [h for _, h in cols])
    return ('<section id="regions"><h2>Defect regions</h2><p class="note">Lengths, areas and volumes in the scans\' '
            'own units (deviation: from where good parts put the surface, + outside); x, y, z: the centroid in the '
            'part\'s frame. A scan called defective whose map passes the region level nowhere shows its strongest '
            'region, "below the level". Click a region to show it in the 3D view.</p>'
            f'<table id="region-table"><thead><tr>{head}</tr></thead><tbody>{"".join(body)}</tbody></table>'
            '</section>')


def _table_html(rows, summary, viewed):
    rays = any("score_rays" in r for r in rows)
    labelled = any(r.get("label") not in (None, "", "unknown") for r in rows)
    cols = [("name", "scan"), ("score", "score"), ("p_value", "p-value"), ("verdict", "verdict")]
    if rays:
        cols += [("score_points", "point score"), ("score_rays", "ray score"), ("ray_nats", "ray evidence")]
    if any(r.get("uncovered") is not None for r in rows):  # the share on surface no good scan saw (coverage)
        cols += [("uncovered", "uncovered")]
    if labelled:
        cols += [("truth", "truth")]
    cols += [("reason", "reason"), ("view", "map")]
    numeric = ("score", "p_value", "score_points", "score_rays", "ray_nats", "uncovered")
    head = "".join(f'<th data-col="{i}" data-type="{"num" if k in numeric else "text"}">{h}</th>'
                   for i, (k, h) in enumerate(cols))
    body = []
    for r in sorted(rows, key=lambda r: -(r["score"] if r.get("score") is not None else -math.inf)):
        cells = []
        for k, _ in cols:
            if k == "name":
                cells.append(f"<td>{_e(r['name'])}</td>")
            elif k == "verdict":
                v = r.get("verdict", "")
                cells.append(f'<td><span class="verdict" style="color:{VERDICT_COLOURS.get(v, "#000")}">'
                             f"{_e(v)}</span></td>")
            elif k == "truth":
                truth = r.get("label", "")
                if truth == "defective" and r.get("defect"):
                    truth += f" ({r['defect']})"
                cells.append(f"<td>{_e(truth)}</td>")
            elif k == "view":
                cells.append(f'<td><a href="#maps" class="show3d" data-name="{_e(r["name"])}">3D</a></td>'
                             if r["name"] in viewed else "<td></td>")
            elif k == "reason":
                cells.append(f"<td>{_e(r.get('reason') or r.get('why') or '')}</td>")  # an error's, or the verdict's
            else:
                x = r.get(k)
                sort = "" if x is None else f' data-sort="{float(x):.9g}"'
                cells.append(f'<td class="num"{sort}>{_num(x, 4 if k == "p_value" else 5)}</td>')
        body.append(f'<tr class="v-{_e(r.get("verdict", ""))}">{"".join(cells)}</tr>')
    return ('<section id="verdicts"><h2>Verdicts</h2><p class="note">Click a column heading to sort.</p>'
            f'<table id="verdict-table"><thead><tr>{head}</tr></thead><tbody>{"".join(body)}</tbody></table>'
            '</section>')


def _settings_html(summary):
    keys = ("aggregate", "point_score", "noise", "projection", "n_calibration", "calibration_source", "aligned",
            "common_frame", "seconds_per_scan", "model_kind")
    items = "".join(f"<tr><th>{k}</th><td>{_e(_short(summary[k]))}</td></tr>" for k in keys if k in summary)
    if summary.get("term_variances"):  # the point score's two terms, each weighed by its spread on good scans
        v_d, v_s = summary["term_variances"]
        items += (f"<tr><th>point score's terms</th><td>weighed by their spread on the good calibration scans: the "
                  f"field's {v_d ** 0.5:.2f}, the good points' {v_s ** 0.5:.2f} standard deviations</td></tr>")
    if summary.get("rays"):
        items += f"<tr><th>rays</th><td>{_e(summary['rays'].get('score', 'on'))}</td></tr>"
        if summary["rays"].get("weighing"):
            items += f"<tr><th>rays' weight</th><td>{_e(summary['rays']['weighing'])}</td></tr>"
    return (f'<section id="settings"><h2>How the scores were made</h2><table class="kv">{items}</table>'
            '<p class="note">Everything here is also in summary.json and scores.csv beside this page.</p></section>')


# ----------------------------------------------------------------------------------------------------- figures
def _histogram_figure(rows, summary):
    """Step histograms of the scores by label (log bins when the scores span more than a factor 20) and the
    threshold(s)."""
    import plotly.graph_objects as go

    scored = [r for r in rows if r.get("score") is not None and math.isfinite(r["score"])]
    scores = np.array([r["score"] for r in scored], dtype=float)
    thresholds = _thresholds(summary)
    allv = np.concatenate([scores, [t for _, t in thresholds]])
    fig = go.Figure()
    log = bool(len(allv) and allv.min() > 0 and allv.max() / allv.min() > 20)
    if len(allv):
        lo, hi = float(allv.min()), float(allv.max())
        if hi <= lo:
            lo, hi = lo - 0.5, hi + 0.5
        edges = np.geomspace(lo, hi * (1 + 1e-9), 31) if log else np.linspace(lo, hi + 1e-12 * abs(hi), 31)
        for lab in ("good", "defective", "unknown"):
            sel = np.array([r.get("label") == lab for r in scored], dtype=bool)
            if sel.any():
                counts, _ = np.histogram(scores[sel], edges)
                fig.add_trace(go.Scatter(x=edges, y=np.r_[counts, counts[-1]], mode="lines", line_shape="hv",
                                         fill="tozeroy", name=f"{lab} ({int(sel.sum())})", opacity=0.6,
                                         line_color=LABEL_COLOURS[lab], hoverinfo="skip"))
                fig.add_trace(go.Scatter(x=scores[sel], y=np.zeros(int(sel.sum())), mode="markers",
                                         marker=dict(symbol="line-ns-open", size=12, color=LABEL_COLOURS[lab]),
                                         text=[r["name"] for r, s in zip(scored, sel) if s], showlegend=False,
                                         hovertemplate="%{text}<br>score %{x:.4g}<extra>" + lab + "</extra>"))
    for i, (name, t) in enumerate(thresholds):
        fig.add_vline(x=math.log10(t) if log else t, line_dash="dash", line_color="black",
                      annotation_text=f"threshold{' ' + name if name else ''} {t:.4g}",
                      annotation_position="top right" if i % 2 == 0 else "bottom right")
    fig.update_layout(title="Scan scores (higher = more anomalous)", xaxis_title="score", yaxis_title="scans",
                      xaxis_type="log" if log else "linear", margin=dict(l=50, r=20, t=50, b=45),
                      legend=dict(orientation="h", y=-0.2), height=360, plot_bgcolor="#fafafa")
    return fig


def _roc_figure(rows, summary):
    import plotly.graph_objects as go

    known = [r for r in rows if r.get("score") is not None and r.get("label") in ("good", "defective")]
    y = np.array([r["label"] == "defective" for r in known], dtype=bool)
    if not (0 < y.sum() < len(y)):
        return None
    s = np.array([r["score"] for r in known], dtype=float)
    fpr, tpr = _roc(y, s)
    auroc = float(np.trapezoid(tpr, fpr)) if hasattr(np, "trapezoid") else float(np.trapz(tpr, fpr))
    fig = go.Figure()
    fig.add_trace(go.Scatter(x=fpr, y=tpr, mode="lines", name=f"ROC (AUROC {auroc:.3f})", line_shape="hv",
                             line_color="#1565c0"))
    fig.add_trace(go.Scatter(x=[0, 1], y=[0, 1], mode="lines", line=dict(dash="dot", color="#9e9e9e"),
                             name="chance", hoverinfo="skip"))
    flagged = np.array([bool(r.get("flagged", r["verdict"] == "defective")) for r in known])
    fig.add_trace(go.Scatter(x=[flagged[~y].mean()], y=[flagged[y].mean()], mode="markers", name="the threshold",
                             marker=dict(size=11, color="black", symbol="x")))
    fig.update_layout(title="ROC against the known labels", xaxis_title="false-alarm rate",
                      yaxis_title="detection rate", xaxis_range=[-0.02, 1.02], yaxis_range=[-0.02, 1.02],
                      margin=dict(l=50, r=20, t=50, b=45), legend=dict(orientation="h", y=-0.2), height=360)
    return fig


def _roc(y, s):
    """(fpr, tpr) of scores ``s`` against boolean truth ``y``, one step per distinct score (ties together)."""
    order = np.argsort(-s, kind="stable")
    s, y = s[order], y[order]
    last = np.r_[np.flatnonzero(np.diff(s)), len(s) - 1]
    tp, fp = np.cumsum(y)[last], np.cumsum(~y)[last]
    return np.r_[0.0, fp / max(fp[-1], 1)], np.r_[0.0, tp / max(tp[-1], 1)]


def _thresholds(summary):
    out = []
    if summary.get("threshold") is not None:
        out.append(("", float(summary["threshold"])))
    for part, one in sorted((summary.get("parts") or {}).items()):
        if one.get("threshold") is not None and math.isfinite(one["threshold"]):
            out.append((f"part {part}", float(one["threshold"])))
    return out


# -------------------------------------------------------------------------------------------------- view data
def _view_json(v):
    """A view's arrays as base64 little-endian float32 (decoded by the page, which splits off the emphasised
    points)."""
    values = np.nan_to_num(np.asarray(v["values"], dtype=np.float32), nan=0.0, posinf=MAP_RANGE[1])
    out = {"name": v["name"], "n": int(v["n"]), "k": int(len(values)), "hot": int((values > EMPHASIS).sum()),
           "xyz": _b64(np.asarray(v["points"], dtype=np.float32)), "v": _b64(values)}
    if v.get("ray_values") is not None:
        out["r"] = _b64(np.nan_to_num(np.asarray(v["ray_values"], dtype=np.float32), nan=0.0))
    if v.get("regions") is not None:
        out["g"] = base64.b64encode(np.asarray(v["regions"], dtype="<i2").tobytes()).decode("ascii")
    return out


def _scale_json():
    import matplotlib

    cmap = matplotlib.colormaps[MAP_CMAP]
    stops = np.linspace(0, 1, 17)
    colorscale = [[float(t), "rgb({},{},{})".format(*(int(round(255 * c)) for c in cmap(t)[:3]))] for t in stops]
    return {"colorscale": colorscale, "range": list(MAP_RANGE), "ray_range": list(RAY_MAP_RANGE),
            "emphasis": EMPHASIS, "ray_emphasis": RAY_EMPHASIS,
            "label": MAP_LABEL, "ray_label": RAY_MAP_LABEL}


def _b64(a):
    return base64.b64encode(np.ascontiguousarray(a, dtype="<f4").tobytes()).decode("ascii")


# ---------------------------------------------------------------------------------------------------- helpers
def _row_of(rows, name):
    return next((r for r in rows if r["name"] == name), {})


def _score_of(rows, name):
    s = _row_of(rows, name).get("score")
    return -math.inf if s is None else s


def _e(x):
    return html.escape(str(x), quote=True)


def _num(x, digits=5):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "&ndash;"
    return f"{x:.{digits}g}"


def _short(x):
    if isinstance(x, float):
        return f"{x:.4g}"
    if isinstance(x, dict):
        return ", ".join(f"{k} {_short(v)}" for k, v in x.items())
    return str(x)


def _json_default(o):
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o) if math.isfinite(o) else None
    if isinstance(o, np.ndarray):
        return o.tolist()
    if hasattr(o, "to_plotly_json"):  # a plotly figure: its JSON (numpy arrays as typed-array dicts)
        return json.loads(o.to_json())
    return str(o)


# ------------------------------------------------------------------------------------------------------ page
