"""A training run's history: the per-epoch CSV log and the loss plot written beside its checkpoint."""
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


def write_log(out, history):
    """Write the CSV log of ``history`` (records of ``LOG_COLUMNS``) beside checkpoint ``out``, atomically."""
    csv_path, _ = log_paths(out)
    with atomic_path(csv_path) as tmp, open(tmp, "w") as fh:
        fh.write(",".join(LOG_COLUMNS) + "\n")
        for r in history:
            fh.write(",".join(f"{r[c]:.6g}" if isinstance(r[c], float) else str(r[c]) for c in LOG_COLUMNS) + "\n")


def plot_losses(out, history):
    """Plot the loss and its four NSSPR terms per epoch (log scale) beside checkpoint ``out``, atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    _, png = log_paths(out)
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
    with atomic_path(png, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
