"""The training report: train_latent.py writes model.report.html beside the checkpoint, with the loss curves (inline
SVG), one log row per epoch and the run's settings, self-contained (nothing fetched)."""
import re
from html.parser import HTMLParser

from autodecoder.latent.history import LOG_COLUMNS, log_paths, plot_losses, report_path
from train_latent import main

from .spheres import sphere_scans

TINY = ["--latent-dim", "2", "--width", "16", "--depth", "1", "--epochs", "3", "--quiet"]


class _Page(HTMLParser):
    def __init__(self):
        super().__init__()
        self.tags, self.text, self.urls = [], [], []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        self.urls += [v for k, v in attrs if k in ("src", "href") and v and not v.startswith("#")]

    def handle_data(self, data):
        self.text.append(data)


def test_train_latent_writes_the_training_report(tmp_path):
    from datasets.collection import ScanCollection

    data = tmp_path / "spheres.h5"
    ScanCollection.create(data, sphere_scans())
    out = tmp_path / "model.pt"
    assert main(["--data", str(data), "--out", str(out), *TINY]) == 0
    path = report_path(out)
    assert path.name == "model.report.html" and path.parent == out.parent
    text = path.read_text(encoding="utf-8")
    page = _Page()
    page.feed(text)
    page.close()
    assert {"html", "svg", "table"} <= set(page.tags)
    assert page.urls == [] and "<script" not in text and not re.search(r"https?://", text)
    visible = " ".join(page.text)
    for key in ("latent_dim", "width", "depth", "epochs", "lengthscale", "seed"):  # the run's settings
        assert key in visible, key
    for column in LOG_COLUMNS:
        assert column in visible
    log_rows = len(log_paths(out)[0].read_text().strip().splitlines()) - 1
    assert log_rows == 3 and text.count("<tr><td>") == log_rows  # one log row per epoch
    assert text.count("<path") > 0  # the curves


def test_plot_losses_without_a_checkpoint_says_the_settings_are_unknown(tmp_path):
    history = [{c: float(i + 1) for c in LOG_COLUMNS} | {"epoch": i + 1} for i in range(4)]
    out = tmp_path / "run.pt"
    plot_losses(out, history)  # no checkpoint at out: the report still comes, without settings
    text = report_path(out).read_text(encoding="utf-8")
    assert "not known" in text and log_paths(out)[1].stat().st_size > 1000
    plot_losses(out, history, settings={"epochs": 4, "latent_dim": 2})
    text = report_path(out).read_text(encoding="utf-8")
    assert "latent_dim" in text and "not known" not in text
