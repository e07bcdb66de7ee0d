"""A training run's history: the per-epoch CSV log, the loss plot and the training report written beside its
checkpoint."""
import html
import json
import math
import re
from datetime import datetime, timezone
from pathlib import Path

from datasets.atomic import atomic_path

# The log's columns, one record per completed epoch (made by the loop, kept in the checkpoint's info["history"]):
# epoch means of the loss and its terms, the codes' RMS, the nets' learning rate at the epoch's last step, wall time.
LOG_COLUMNS = ("epoch", "loss", "mean_dirichlet", "mean_screening", "cov_dirichlet", "cov_screening", "code_reg",
               "code_rms", "lr", "seconds")


def log_paths(out):
    """The CSV log and loss plot that go beside checkpoint ``out``: (model.log.csv, model.loss.png)."""
    out = Path(out)
    stem = out.name[:-len(out.suffix)] if out.suffix else out.name
    return out.with_name(stem + ".log.csv"), out.with_name(stem + ".loss.png")


def report_path(out):
    """The training report that goes beside checkpoint ``out``: model.report.html."""
    out = Path(out)
    stem = out.name[:-len(out.suffix)] if out.suffix else out.name
    return out.with_name(stem + ".report.html")


def write_log(out, history):
    """Write the CSV log of ``history`` (records of ``LOG_COLUMNS``) beside checkpoint ``out``, atomically."""
    csv_path, _ = log_paths(out)
    with atomic_path(csv_path) as tmp, open(tmp, "w") as fh:
        fh.write(",".join(LOG_COLUMNS) + "\n")
        for r in history:
            fh.write(",".join(f"{r[c]:.6g}" if isinstance(r[c], float) else str(r[c]) for c in LOG_COLUMNS) + "\n")


def plot_losses(out, history, settings=None):
    """Plot the loss and its four NSSPR terms per epoch (log scale) beside checkpoint ``out`` (PNG), and write the
    training report (:func:`write_report`: the same curves and the run's settings, one HTML page), atomically.

    Parameters
    ----------
    out : str or Path
        The checkpoint.
    history : list of dict
        Records of ``LOG_COLUMNS``, one per epoch.
    settings : dict, optional
        The run's configuration (the checkpoint's ``config``); None: read from the checkpoint at ``out``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    _, png = log_paths(out)
    fig = _loss_figure(history)
    with atomic_path(png, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=100)
    write_report(out, history, _checkpoint_config(out) if settings is None else settings, figure=fig)
    plt.close(fig)


def write_report(out, history, settings, figure=None):
    """Write the training report beside checkpoint ``out`` (:func:`report_path`), atomically: a self-contained HTML
    page (nothing fetched) with the loss curves as inline SVG, the per-epoch log and the run's settings.

    Parameters
    ----------
    out : str or Path
        The checkpoint.
    history : list of dict
        Records of ``LOG_COLUMNS``.
    settings : dict or None
        The run's configuration (the checkpoint's ``config``); None: not known.
    figure : matplotlib Figure, optional
        The loss plot (default: drawn here).
    """
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = _loss_figure(history) if figure is None else figure
    buf = io.StringIO()
    fig.savefig(buf, format="svg")
    if figure is None:
        plt.close(fig)
    svg = buf.getvalue()
    # inline SVG in HTML: no XML prologue, DOCTYPE, RDF metadata or namespace declarations (identifiers that look
    # like URLs, never fetched, but a page with no URL at all is easier to check)
    svg = re.sub(r"<metadata>.*?</metadata>", "", svg[svg.index("<svg"):], flags=re.S)
    svg = re.sub(r'\s+xmlns(:\w+)?="[^"]*"', "", svg)
    path = report_path(out)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(_report_html(Path(out), history, settings, svg), encoding="utf-8")
    return path


def _loss_figure(history):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    epochs = [r["epoch"] for r in history]
    fig, ax = plt.subplots(figsize=(7, 4))
    for key in ("loss", "mean_dirichlet", "mean_screening", "cov_dirichlet", "cov_screening"):
        values = [max(r[key], 1e-12) for r in history]
        ax.plot(epochs, values, label=key)
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss (epoch mean)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def _checkpoint_config(out):
    """The ``config`` of the checkpoint at ``out``, or None when it cannot be read."""
    from autodecoder.field.checkpoint_io import load_torch_file

    try:
        return dict(load_torch_file(out, "model checkpoint").get("config") or {}) or None
    except (OSError, ValueError, AttributeError):
        return None


def _report_html(out, history, settings, svg):
    e = html.escape
    last = history[-1] if history else {}
    seconds = sum(float(r.get("seconds", 0.0)) for r in history)
    facts = [("checkpoint", out.name), ("epochs", str(last.get("epoch", 0))),
             ("final loss", _fmt(last.get("loss"))), ("training time", f"{seconds:.1f} s"),
             ("written", datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"))]
    facts_html = "".join(f"<tr><th>{e(k)}</th><td>{e(v)}</td></tr>" for k, v in facts)
    if settings:
        rows = "".join(f"<tr><th>{e(str(k))}</th><td>{e(_setting(v))}</td></tr>" for k, v in sorted(settings.items()))
    else:
        rows = "<tr><td>not known (the checkpoint could not be read)</td></tr>"
    head = "".join(f"<th>{e(c)}</th>" for c in LOG_COLUMNS)
    body = "".join("<tr>" + "".join(f"<td>{e(_fmt(r.get(c)))}</td>" for c in LOG_COLUMNS) + "</tr>"
                   for r in history)
    return _REPORT.format(title=e(f"Training report: {out.name}"), style=_STYLE, facts=facts_html, svg=svg,
                          settings=rows, head=head, body=body, csv=e(log_paths(out)[0].name))


def _fmt(x):
    if x is None:
        return ""
    if isinstance(x, float):
        return f"{x:.6g}" if math.isfinite(x) else str(x)
    return str(x)


def _setting(v):
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, (dict, list, tuple)):
        return json.dumps(v, default=str)
    return str(v)


_STYLE = """body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 0; color: #212121; }
header { background: #263238; color: #fff; padding: 14px 24px; } header h1 { margin: 0; font-size: 22px; }
section { padding: 6px 24px 12px 24px; } h2 { font-size: 18px; border-bottom: 1px solid #cfd8dc; }
table { border-collapse: collapse; font-size: 13px; } th, td { padding: 3px 10px; border-bottom: 1px solid #eceff1;
text-align: left; } th { background: #eceff1; } .note { color: #546e7a; font-size: 13px; }
svg { max-width: 100%; height: auto; }"""

_REPORT = """<!DOCTYPE html>
<html lang="en">
<head><meta charset="utf-8"><title>{title}</title><style>{style}</style></head>
<body>
<header><h1>{title}</h1></header>
<section id="run"><table>{facts}</table></section>
<section id="losses"><h2>Loss curves</h2>{svg}
<p class="note">Epoch means of the loss and its four terms (log scale); the same numbers are in {csv}.</p></section>
<section id="settings"><h2>Settings</h2><table>{settings}</table></section>
<section id="log"><h2>Per-epoch log</h2><details><summary>{csv}</summary>
<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table></details></section>
</body>
</html>
"""
