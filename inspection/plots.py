"""Pictures of an inspection run: ROC curve, score histograms with the threshold, the colour legend of the maps."""
from pathlib import Path

import numpy as np

from datasets.atomic import atomic_path


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path, dpi=110):
    """Save a figure through :func:`datasets.atomic.atomic_path` (a temporary PNG beside ``path``)."""
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=dpi)
    return Path(path)


def plot_roc(path, labels, scores, defects=None, title="ROC (object level)"):
    """ROC of defective (positive) vs good scans, overall and per defect type.

    Parameters
    ----------
    labels : (n,) array of 0 (good) / 1 (defective)
    scores : (n,) anomaly scores
    defects : (n,) array of str, optional
    """
    from sklearn.metrics import roc_auc_score, roc_curve

    plt = _pyplot()
    labels, scores = np.asarray(labels, dtype=int), np.asarray(scores, dtype=float)
    fig, ax = plt.subplots(figsize=(5.2, 5))
    if 0 < labels.sum() < len(labels):
        fpr, tpr, _ = roc_curve(labels, scores)
        ax.plot(fpr, tpr, "k-", lw=2, label=f"all (AUROC {roc_auc_score(labels, scores):.3f})")
        if defects is not None:
            defects = np.asarray(defects)
            for d in sorted(set(defects[labels == 1])):
                sel = (labels == 0) | (defects == d)
                fpr, tpr, _ = roc_curve(labels[sel], scores[sel])
                ax.plot(fpr, tpr, lw=1.2, label=f"{d} ({roc_auc_score(labels[sel], scores[sel]):.3f})")
    else:
        ax.text(0.5, 0.5, "needs good and defective scans", ha="center")
    ax.plot([0, 1], [0, 1], ":", color="grey")
    ax.set(xlabel="false-alarm rate (good scans flagged)", ylabel="detection rate", title=title, xlim=(0, 1),
           ylim=(0, 1.01))
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return Path(path)


def plot_score_histograms(path, scores, labels, threshold=None, calibration_scores=None, title="anomaly scores"):
    """Write :func:`score_histogram_figure` to ``path`` (PNG, atomically). Returns the path."""
    plt = _pyplot()
    fig = score_histogram_figure(scores, labels, threshold, calibration_scores, title)
    _save(fig, path)
    plt.close(fig)
    return Path(path)


def score_histogram_figure(scores, labels, threshold=None, calibration_scores=None, title="anomaly scores"):
    """Histograms of the scores of good and defective (and unknown) scans, calibration scores, and the threshold.

    Parameters
    ----------
    scores : (n,) anomaly scores
    labels : (n,) array of 'good' / 'defective' / 'unknown'
    threshold : inspection.threshold.Threshold or float, optional
        A vertical line (not drawn when infinite); a Threshold's legend entry gives its basis and predicted
        false-alarm rate with its interval.
    calibration_scores : (k,) array, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    plt = _pyplot()
    scores, labels = np.asarray(scores, dtype=float), np.asarray(labels)
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    allv = [scores] + ([np.asarray(calibration_scores, float)] if calibration_scores is not None else [])
    value = getattr(threshold, "value", threshold)
    if value is not None and np.isfinite(value):
        allv.append(np.array([value]))
    allv = np.concatenate(allv)
    positive = len(allv) and allv.min() > 0 and allv.max() / allv.min() > 20  # wide positive range: log bins
    if positive:
        bins = np.geomspace(allv.min(), allv.max() * (1 + 1e-9), 31)
        ax.set_xscale("log")
    else:
        bins = np.linspace(allv.min(), allv.max() + 1e-12, 31) if len(allv) else 10
    groups = [("good", "tab:green"), ("defective", "tab:red"), ("unknown", "tab:grey")]
    for lab, colour in groups:
        sel = labels == lab
        if sel.any():
            ax.hist(scores[sel], bins=bins, alpha=0.55, color=colour, label=f"{lab} ({sel.sum()})")
    if calibration_scores is not None and len(calibration_scores):
        ax.hist(calibration_scores, bins=bins, histtype="step", color="tab:blue", lw=1.5,
                label=f"calibration ({len(calibration_scores)})")
    if value is not None and np.isfinite(value):
        text = f"threshold {value:.3g}"
        if hasattr(threshold, "basis"):
            lo, hi = threshold.far_interval
            from .threshold import format_rate

            text += (f" ({threshold.basis}): predicted false-alarm rate {format_rate(threshold.predicted_far)}, "
                     f"90 % interval {format_rate(lo)} to {format_rate(hi)}")
        ax.axvline(value, color="k", ls="--", label=text)
    ax.set(xlabel="anomaly score (higher = more anomalous)", ylabel="scans", title=title)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def plot_legend(path, cmap, vmin, vmax, label):
    """A horizontal colour bar: the legend of the anomaly maps."""
    import matplotlib as mpl

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 1.1))
    norm = mpl.colors.Normalize(vmin=vmin, vmax=vmax)
    fig.colorbar(mpl.cm.ScalarMappable(norm=norm, cmap=cmap), cax=ax, orientation="horizontal",
                 label=label, extend="max")
    fig.subplots_adjust(bottom=0.55, top=0.9, left=0.05, right=0.95)
    _save(fig, path)
    plt.close(fig)
    return Path(path)


def plot_coverage(path, plan, max_points=6000, seed=0):
    """A picture of a :class:`inspection.coverage_views.CoveragePlan`: the target surface coloured by coverage (grey:
    covered by the good scans; a colour per proposed view: the uncovered points it would cover; red: uncovered and
    seen by no proposal) from two sides, with each proposed sensor's direction drawn from the part's centre and
    numbered in the order to take them; at most ``max_points`` covered points drawn (a seeded subsample). Written
    atomically."""
    plt = _pyplot()
    rng = np.random.default_rng(seed)
    pts = plan.points
    keep = np.arange(len(pts)) if len(pts) <= max_points else np.sort(rng.choice(len(pts), max_points, replace=False))
    uncovered = np.flatnonzero(~plan.covered)  # every uncovered point is drawn: they are the point of the picture
    keep = np.union1d(keep, uncovered if len(uncovered) <= 4 * max_points else uncovered[:4 * max_points])
    colours = np.tile(np.array([0.78, 0.78, 0.78, 0.35]), (len(keep), 1))
    palette = plt.get_cmap("tab10")
    first = plan.first_view[keep]
    todo = ~plan.covered[keep]
    colours[todo] = (0.85, 0.1, 0.1, 0.9)
    for k in range(len(plan.views)):
        colours[first == k] = (*palette(k % 10)[:3], 0.9)
    fig = plt.figure(figsize=(10, 5))
    scale = max(float(np.ptp(pts, axis=0).max()), 1e-12)
    for j, (elev, azim) in enumerate(((25, 45), (-35, 225))):
        ax = fig.add_subplot(1, 2, j + 1, projection="3d")
        order = np.argsort(todo)  # uncovered points drawn last, on top
        p = pts[keep][order]
        ax.scatter(p[:, 0], p[:, 1], p[:, 2], s=2, c=colours[order], depthshade=False)
        for k, view in enumerate(plan.views):
            d = view.position - plan.center
            tip = plan.center + 0.75 * scale * d / np.linalg.norm(d)
            ax.plot(*np.c_[plan.center, tip], color=palette(k % 10), lw=2)
            ax.text(*tip, f"{k + 1}", color=palette(k % 10), fontsize=11, weight="bold")
        ax.view_init(elev, azim)
        ax.set_box_aspect(np.maximum(np.ptp(pts, axis=0), 1e-3 * scale))
        ax.set_axis_off()
    covered = 100 * (1 - plan.uncovered_share)
    fig.suptitle(f"coverage by the good scans: {covered:.1f} % of {len(pts)} points (grey); uncovered in red, or "
                 f"in the colour of the proposed view that covers it", fontsize=9)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return Path(path)
