"""A threshold that holds when the test scans do not look like the calibration's (issue 47): good scans of the
inspection's own sensor set the level (role 'site'), the batch check fires on a batch of another sensor and not on
the calibration's own, a scan in other units is told why, a level from rendered views only says so."""
import csv
import json
import math

import numpy as np
import pytest

from datasets import write_cloud
from inspection.__main__ import main
from inspection.batch_check import check_batch
from inspection.calibration import read_calibration
from inspection.threshold import conformal_threshold, fit_threshold

from .tiny import FRAME, half_sphere, tiny_field_model


# ------------------------------------------------------------------------------------------ the site's level
def _roles(**groups):
    scores, roles = [], []
    rng = np.random.default_rng(1)
    for role, (n, mu) in groups.items():
        scores += list(np.exp(rng.normal(mu, 0.3, n)))
        roles += [role.replace("_", "-")] * n
    return np.array(scores), roles


def test_site_scores_alone_set_the_lognormal_level_and_every_group_its_spread():
    scores, roles = _roles(held_back=(6, 1.0), cross_fitted=(26, 0.9), site=(8, 1.8))
    t = fit_threshold(scores, 0.02, roles)
    y = np.log(scores)
    r = np.array(roles)
    # independently: the level is the site's mean log score; the spread pools the three groups around their means
    m = y[r == "site"].mean()
    squares = sum(((y[r == g] - y[r == g].mean()) ** 2).sum() for g in ("held-back", "cross-fitted", "site"))
    df = 6 - 1 + 26 - 1 + 8 - 1
    sd = math.sqrt(squares / df)
    from scipy import stats

    expected = math.exp(m + stats.t.ppf(0.98, df) * sd * math.sqrt(1 + 1 / 8))
    assert t.basis == "log-normal" and t.fit["df"] == df and t.fit["n_level"] == 8
    assert t.value == pytest.approx(expected, rel=1e-9)
    assert t.fit["site_shift"] == pytest.approx(m - y[r == "held-back"].mean())
    without = fit_threshold(scores[r != "site"], 0.02, list(r[r != "site"]))
    assert t.value > 1.5 * without.value  # the site's scans score higher: the level moved up to them
    assert "8 good scans of the inspection's own sensor" in t.note and "higher than the model's own" in t.note
    # the p-values agree with the threshold: p <= alpha exactly above it
    assert t.p_values([t.value * 1.001])[0] <= 0.02 < t.p_values([t.value * 0.999])[0]


def test_enough_site_scores_give_the_exact_conformal_threshold_on_them_alone():
    scores, roles = _roles(held_back=(6, 1.0), site=(60, 1.8))
    t = fit_threshold(scores, 0.02, roles)
    site = scores[np.array(roles) == "site"]
    assert t.basis == "conformal" and t.n == 60
    assert t.value == conformal_threshold(site, 0.02)


# ------------------------------------------------------------------------------------------ the batch check
def _calibration(rng, n=32):
    cal = np.exp(rng.normal(1.0, 0.3, n))
    return cal, fit_threshold(cal[:6], 0.02, ["held-back"] * 6)


def _binomial_tail_above(k, n, p):  # P(X >= k), summed by hand (independent of scipy)
    return sum(math.comb(n, j) * p ** j * (1 - p) ** (n - j) for j in range(k, n + 1))


def test_the_binomial_tails_are_the_closed_forms():
    rng = np.random.default_rng(0)
    cal, t = _calibration(rng)
    scores = np.exp(rng.normal(1.0, 0.3, 40))
    scores[:30] *= 20  # 30 far above
    c = check_batch(scores, t.p_values(scores), t.value, t.alpha_used, float(np.median(cal[:6])), 0.5)
    assert c.p_above == pytest.approx(_binomial_tail_above(c.above, 40, 0.5 + 0.5 * 0.02), rel=1e-9)
    below = sum(math.comb(40, j) * 0.25 ** j * 0.75 ** (40 - j) for j in range(0, c.below_median + 1))
    assert c.p_below_median == pytest.approx(below, rel=1e-9)


def test_it_fires_on_good_scans_of_another_sensor_and_not_on_the_calibrations_own():
    rng = np.random.default_rng(3)
    fired_own = fired_mixed = 0
    cal, t = _calibration(rng)
    med = float(np.median(cal[:6]))
    for _ in range(300):
        own = np.exp(rng.normal(1.0, 0.3, 50))  # good scans of the calibration's sensor
        fired_own += check_batch(own, t.p_values(own), t.value, t.alpha_used, med).fired
        mixed = np.r_[np.exp(rng.normal(1.0, 0.3, 16)), np.exp(rng.normal(3.0, 0.4, 64))]  # the benchmarks' batch
        fired_mixed += check_batch(mixed, t.p_values(mixed), t.value, t.alpha_used, med).fired
    assert fired_own <= 15 and fired_mixed <= 15  # at most ~the check's level (0.02) + sampling slack, of 300
    other = np.exp(rng.normal(1.0 + 0.9, 0.3, 50))  # another sensor: every score a factor 2.5 higher
    c = check_batch(other, t.p_values(other), t.value, t.alpha_used, float(np.median(cal[:6])))
    assert c.fired and c.above >= 1 and c.below_median == 0 and "do not look like" in c.message
    # no good scan of the other sensor is called defective; a scan beyond any shift still is
    assert all(c.verdict(s, "defective" if s > t.value else "good") != "defective" for s in other)
    assert c.verdict(50 * other.max(), "defective") == "defective"
    # a smaller stated share makes a batch of 16 enough
    small = other[:16]
    assert not check_batch(small, t.p_values(small), t.value, t.alpha_used, float(np.median(cal[:6]))).fired
    assert check_batch(small, t.p_values(small), t.value, t.alpha_used, float(np.median(cal[:6])), 0.2).fired


def test_bad_shares_are_refused():
    with pytest.raises(ValueError, match="max_defective_share"):
        check_batch([1.0], [0.5], 2.0, 0.02, 1.0, 1.0)


# ------------------------------------------------------------------------------------------ the command lines
@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A tiny model calibrated on its training collection (3 training + 3 held-back half-spheres)."""
    scans = [half_sphere(f"train/good/{i:03d}", "train", "good", seed=i) for i in range(6)]
    root = tiny_field_model(tmp_path_factory.mktemp("shift"), scans)
    assert main(["calibrate", "--model", str(root / "model.pt"), "--data", str(root / "tree.h5"), "--quiet",
                 "--alpha", "0.1"]) == 0
    return root


def _folder(root, name, scans, scale=1.0):
    folder = root / name
    folder.mkdir()
    for s in scans:
        write_cloud(folder / f"{s.name.split('/')[-1]}.ply", FRAME.to_file(s.points) * scale, s.normals)
    return folder


def _noisy(name, seed, sigma):
    s = half_sphere(name, "test", "good", seed=seed)
    s.points = s.points + np.random.default_rng(seed).normal(0, sigma, s.points.shape).astype(s.points.dtype)
    return s


def _off(name, seed, factor=1.3):
    """A good half-sphere as a sensor off in its depth scale sees it (smooth, not noise: every point moved)."""
    s = half_sphere(name, "test", "good", seed=seed)
    s.points = (s.points * factor).astype(s.points.dtype)
    return s


def test_calibrate_with_real_good_scans_moves_the_level_to_them(calibrated, tmp_path, capsys):
    model = tmp_path / "model.pt"
    model.write_bytes((calibrated / "model.pt").read_bytes())
    before = read_calibration(model)
    good8 = _folder(tmp_path, "good8", [_noisy(f"s{i}", 100 + i, 0.02) for i in range(8)])
    (good8 / "README").write_text("not a cloud")
    capsys.readouterr()
    assert main(["calibrate", "--model", str(model), "--data", str(good8), "--alpha", "0.1"]) == 0
    out = capsys.readouterr().out
    assert "taking the 8 unlabelled scans" in out and "set its threshold's level" in out
    after = read_calibration(model)
    site = [s for s, r in zip(after.scores, after.roles) if r == "site"]
    assert len(site) == 8 and [r for r in after.roles if r != "site"] == list(before.roles)
    t = after.threshold()
    assert t.fit.get("level_from") == "site"
    assert t.fit["mean"] == pytest.approx(float(np.mean(np.log(site))))  # the level is theirs
    assert "8 good scans of the inspection's own sensor" in t.note
    # again with other scans: they replace the first ones
    good4 = _folder(tmp_path, "good4", [_noisy(f"t{i}", 200 + i, 0.02) for i in range(4)])
    assert main(["calibrate", "--model", str(model), "--data", str(good4), "--quiet", "--alpha", "0.1"]) == 0
    assert sum(r == "site" for r in read_calibration(model).roles) == 4



def test_score_warns_and_tells_uncertain_on_a_batch_of_another_sensor(calibrated, tmp_path):
    noisy = _folder(tmp_path, "noisy", [_off(f"n{i:02d}", 300 + i) for i in range(20)])
    out = tmp_path / "out"
    assert main(["score", "--model", str(calibrated / "model.pt"), "--data", str(noisy), "--out", str(out),
                 "--quiet", "--max-defective-share", "0.2", "--maps", "none"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    check = summary["batch_check"]
    assert check["fired"] and check["n"] == 20
    assert any("do not look like" in w for w in summary["warnings"])
    rows = list(csv.DictReader(open(out / "scores.csv", newline="")))
    assert not any(r["verdict"] == "defective" and float(r["score"]) <= check["shifted_threshold"] for r in rows)
    assert "Warning:" in (out / "report.html").read_text()
    # the calibration's own kind of scans: no warning
    same = _folder(tmp_path, "same", [half_sphere(f"g{i:02d}", "test", "good", seed=400 + i) for i in range(20)])
    out2 = tmp_path / "out2"
    assert main(["score", "--model", str(calibrated / "model.pt"), "--data", str(same), "--out", str(out2),
                 "--quiet", "--max-defective-share", "0.2", "--maps", "none"]) == 0
    summary2 = json.loads((out2 / "summary.json").read_text())
    assert not summary2["batch_check"]["fired"] and not summary2["warnings"]


def test_a_scan_in_millimetres_is_told_its_size(calibrated, tmp_path):
    folder = _folder(tmp_path, "mm", [half_sphere("big", "test", "good", seed=7)], scale=1000.0)
    out = tmp_path / "out"
    assert main(["score", "--model", str(calibrated / "model.pt"), "--data", str(folder), "--out", str(out),
                 "--quiet", "--maps", "none"]) == 0
    row = next(csv.DictReader(open(out / "scores.csv", newline="")))
    assert "size is about" in row["reason"] and "units" in row["reason"]
    assert float(row["reason"].split("about ")[1].split("x")[0]) > 100


def test_a_level_from_rendered_views_only_is_said_on_every_verdict(tmp_path):
    """A calibration whose held-back scans are views rendered from templates says so in each reason."""
    from inspection import Inspector
    from inspection.verdicts import LEVEL_RENDERED_NOTE
    from inspection.model_io import load_model_handle

    scans = [half_sphere(f"train/good/{i:03d}", "train", "good", seed=i) for i in range(6)]
    for s in scans:
        s.extra = {"template": "1_template"}
    root = tiny_field_model(tmp_path, scans)
    handle = load_model_handle(root / "model.pt")
    insp = Inspector.from_config(handle.model, None, verbose=False).fit(scans)
    assert insp.level_rendered_
    new = [half_sphere("test/good/000", "test", "good", seed=50)]
    verdicts, reasons = insp.predict_verdict(new, return_reasons=True)
    assert LEVEL_RENDERED_NOTE in reasons[0]
    restored = Inspector.from_calibration(handle.model, insp.calibration(), verbose=False)
    assert restored.level_rendered_
    restored.fit_level([_noisy(f"s{i}", 60 + i, 0.0) for i in range(4)])
    assert not restored.level_rendered_
    assert LEVEL_RENDERED_NOTE not in restored.predict_verdict(new, return_reasons=True)[1][0]
    with pytest.raises(ValueError, match="train/good/001"):  # a scan it trained on would be optimistic: refused
        restored.fit_level([scans[1]])


def test_watch_warns_once_and_tells_uncertain_over_its_window(calibrated, tmp_path):
    from inspection.watch import JOURNAL, watch

    drop = _folder(tmp_path, "drop", [_off(f"n{i:02d}", 500 + i) for i in range(12)])
    said = []
    watch(calibrated / "model.pt", drop, tmp_path / "line", once=True, settle=0, echo=said.append, maps="none",
          max_defective_share=0.2, window=12)
    warnings = [line for line in said if line.startswith("warning:")]
    assert len(warnings) == 1 and "do not look like" in warnings[0]
    entries = [json.loads(line) for line in (tmp_path / "line" / JOURNAL).read_text().splitlines()]
    assert len(entries) == 12
    # once the window fired, no scan within its shift is 'defective'; each retold one says why
    retold = [e for e in entries if "the batch does not look like" in e["why"]]
    assert retold and all(e["verdict"] == "uncertain" for e in retold)
    assert "Warning:" in (tmp_path / "line" / "report.html").read_text()
