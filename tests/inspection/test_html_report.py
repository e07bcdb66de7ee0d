"""inspection.html_report: report.html written by `score`, self-contained (no URL fetched), naming every scan, holding
the threshold; the 3D views' subsampling; and, when Chromium is installed, the page rendered in a headless browser."""
import csv
import json
import os
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from inspection.__main__ import main
from inspection.html_report import EMPHASIS, VIEW_POINTS, report_html, scan_view, write_html_report

from .tiny import half_sphere as _scan, tiny_field_model

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """`score --maps all` of a tiny collection (6 train, 3 good + 2 dented test scans) on an untrained tiny field
    model; returns the results folder."""
    scans = [_scan(f"train/good/{i:03d}", "train", "good", seed=i) for i in range(6)]
    scans += [_scan(f"test/good/{i:03d}", "test", "good", seed=10 + i) for i in range(3)]
    scans += [_scan(f"test/dent/{i:03d}", "test", "defective", "dent", seed=20 + i, dent=0.1) for i in range(2)]
    root = tiny_field_model(tmp_path_factory.mktemp("html"), scans)
    out = root / "results"
    assert main(["score", "--model", str(root / "model.pt"), "--data", str(root / "tree.h5"), "--out", str(out),
                 "--maps", "all", "--alpha", "0.3", "--quiet"]) == 0
    return out


class _Page(HTMLParser):
    """Collects the tags with a network-looking src/href, the scripts' text and the visible text."""

    def __init__(self):
        super().__init__()
        self.external, self.scripts, self.text, self.tags, self._in = [], [], [], [], None

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        for k, v in attrs:
            if k in ("src", "href", "data") and v and re.match(r"^(https?:)?//", v.strip()):
                self.external.append((tag, k, v))
        if tag == "link" and dict(attrs).get("rel") == "stylesheet":
            self.external.append((tag, "rel", "stylesheet"))
        self._in = tag

    def handle_endtag(self, tag):
        self._in = None

    def handle_data(self, data):
        (self.scripts if self._in == "script" else self.text).append(data)


def _parse(text):
    page = _Page()
    page.feed(text)
    page.close()
    return page


def test_score_writes_a_self_contained_report(results):
    text = (results / "report.html").read_text(encoding="utf-8")
    page = _parse(text)
    assert {"html", "head", "body", "table", "script"} <= set(page.tags)
    assert page.external == []  # no script, stylesheet, image or frame from the network
    # plotly's bundle is inlined (it mentions URLs in strings and comments, never fetched); outside it, no URL at all
    bundle = max(page.scripts, key=len)
    assert "Plotly" in bundle and len(bundle) > 1_000_000
    rest = text.replace(bundle, "")
    assert not re.search(r"https?://|//cdn|\bimport\s*\(|fetch\(|XMLHttpRequest", rest)
    visible = " ".join(page.text)
    with open(results / "scores.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 5
    for r in rows:  # every scan of scores.csv, with its verdict
        assert r["name"] in visible
    summary = json.loads((results / "summary.json").read_text())
    threshold = summary["threshold"]
    assert f"{threshold:.5g}" in visible and summary["decision"]["basis"] in visible
    assert "predicted false-alarm rate" in visible
    assert summary["point_score"] == "joint"  # its terms' weights, as calibrate printed them
    assert f"the good points' {summary['term_variances'][1] ** 0.5:.2f} standard deviations" in visible
    # the data: one 3D view per scan (--maps all), the histogram and the ROC (labels exist)
    data = json.loads(re.search(r'<script type="application/json" id="report-data">(.*?)</script>', text,
                                re.S).group(1))
    assert sorted(v["name"] for v in data["views"]) == sorted(r["name"] for r in rows)
    assert set(data["figures"]) == {"histogram", "roc"}
    assert all(v["k"] == v["n"] == 300 for v in data["views"])  # small scans: every point shown


def test_maps_none_still_writes_the_report(results, tmp_path):
    model, tree = results.parent / "model.pt", results.parent / "tree.h5"
    out = tmp_path / "r"
    assert main(["score", "--model", str(model), "--data", str(tree), "--out", str(out), "--maps", "none",
                 "--quiet"]) == 0
    text = (out / "report.html").read_text(encoding="utf-8")
    assert "No scan to show" in text and 'id="view3d"' not in text


def test_scan_view_subsample_is_seeded_and_keeps_the_anomalous_points():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(20_000, 3))
    values = np.abs(rng.normal(size=20_000))
    values[:200] = EMPHASIS + 1  # a small defect
    a = scan_view("s", points, values, n_points=3000, seed=1)
    b = scan_view("s", points, values, n_points=3000, seed=1)
    c = scan_view("s", points, values, n_points=3000, seed=2)
    assert a["n"] == 20_000 and len(a["points"]) == len(a["values"]) == 3000
    assert np.array_equal(a["points"], b["points"]) and not np.array_equal(a["points"], c["points"])
    assert (a["values"] > EMPHASIS).sum() == (values > EMPHASIS).sum()  # every emphasised point kept
    # each kept point is one of the scan's, with its own value
    idx = [int(np.flatnonzero((points.astype(np.float32) == p).all(1))[0]) for p in a["points"][:50]]
    assert np.allclose(values[idx], a["values"][:50])
    small = scan_view("s", points[:10], values[:10], ray_values=np.zeros(10))
    assert len(small["points"]) == 10 and small["ray_values"].shape == (10,)
    with pytest.raises(ValueError, match="values"):
        scan_view("s", points, values[:5])


def test_size_of_100_scan_views_stays_under_30_mb(tmp_path):
    rng = np.random.default_rng(0)
    rows, views = [], []
    for i in range(100):
        name = f"test/scan/{i:03d}"
        rows.append({"name": name, "split": "test", "label": "unknown", "defect": "", "score": float(i),
                     "p_value": 0.5, "verdict": "defective", "flagged": True, "reason": ""})
        views.append(scan_view(name, rng.normal(size=(50_000, 3)), 5 * rng.random(50_000),
                               rng.random(50_000), seed=i))
    path = write_html_report(tmp_path / "report.html", rows, {"threshold": 1.0}, views)
    size = path.stat().st_size
    assert size < 30e6, size
    assert VIEW_POINTS == 3000


def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        if shutil.which(name):
            return shutil.which(name)
    return None


def _headless(exe, *args, timeout=180):
    # --no-sandbox: test containers run as root; SwiftShader: WebGL without a GPU
    cmd = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
           "--hide-scrollbars", "--virtual-time-budget=20000", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


@pytest.mark.skipif(_chromium() is None, reason="no Chromium on this machine: `make test` installs Debian's chromium "
                                                 "where apt and root are available; elsewhere apt-get install chromium")
def test_report_renders_in_headless_chromium(results):
    """Load report.html from disk, let its plots draw, read the page's own state (window.reportStatus, copied into
    #report-status) and save a screenshot (results/report_screenshot.png of this checkout)."""
    exe = _chromium()
    url = (results / "report.html").resolve().as_uri()
    dom = _headless(exe, "--dump-dom", url).stdout
    m = re.search(r'<pre id="report-status">(.*?)</pre>', dom, re.S)
    assert m and m.group(1).strip(), "the page never reported its state"
    import html

    status = json.loads(html.unescape(m.group(1)))
    assert status["errors"] == [] and status["ready"] is True, status
    assert status["plots"]["histogram"]["traces"] > 0 and status["plots"]["roc"]["traces"] > 0
    view = status["plots"]["view3d"]
    assert view["webgl"] and view["canvases"] > 0 and view["objects"] > 0 and view["points"] > 0, view
    shot_dir = REPO / "results"
    shot_dir.mkdir(exist_ok=True)
    shot = shot_dir / "report_screenshot.png"
    _headless(exe, "--window-size=1400,1800", f"--screenshot={shot}", url)
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_every_defect_region_is_listed_in_the_report(results):
    """The regions' table links every region of defects.csv (the rows a click selects; no browser needed)."""
    defects = list(csv.DictReader(open(results / "defects.csv")))
    assert defects, "the dented test scans have defect regions"
    text = (results / "report.html").read_text()
    for d in defects:
        assert f'data-name="{d["name"]}" data-region="{d["region"]}"' in text


# a browser is a system binary, not a Python package: `make test` (what CI runs) installs Debian's chromium, so the
# test runs there and here; it can only be skipped on a machine where neither apt nor a chromium is available
@pytest.mark.skipif(_chromium() is None, reason="no Chromium on this machine: `make test` installs Debian's chromium "
                                                 "where apt and root are available; elsewhere apt-get install chromium")
def test_a_defect_region_is_selected_in_the_3d_view(results):
    """The page's address #region=<scan>|<id> (what a click on a row of the regions' table does) draws that region's
    points over its scan in headless Chromium."""
    defects = list(csv.DictReader(open(results / "defects.csv")))
    assert defects, "the dented test scans have defect regions"
    exe = _chromium()
    first = defects[0]
    url = (results / "report.html").resolve().as_uri() + f"#region={first['name']}|{first['region']}"
    dom = _headless(exe, "--dump-dom", url).stdout
    import html

    status = json.loads(html.unescape(re.search(r'<pre id="report-status">(.*?)</pre>', dom, re.S).group(1)))
    assert status["errors"] == [] and status["ready"] is True, status
    view = status["plots"]["view3d"]
    assert view["scan"] == first["name"] and view["region"] == int(first["region"]) and view["region_points"] > 0


def test_report_html_escapes_scan_names():
    rows = [{"name": "<script>alert(1)</script>", "split": "", "label": "unknown", "defect": "", "score": 1.0,
             "p_value": 0.5, "verdict": "good", "flagged": False, "reason": ""}]
    text = report_html(rows, {"threshold": 2.0})
    assert "<script>alert(1)</script>" not in text and "&lt;script&gt;alert(1)&lt;/script&gt;" in text
