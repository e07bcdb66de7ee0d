"""inspection.threshold: split-conformal and log-normal thresholds against hand computations and simulation."""
import math

import numpy as np
import pytest
from scipy import stats

from inspection.threshold import (FAR_INTERVAL_LEVEL, conformal_far_interval, conformal_p_values,
                                  conformal_threshold, fit_threshold, lognormal_far_interval, lognormal_p_values,
                                  lognormal_threshold)


# ------------------------------------------------------------------------------------------- split-conformal
def test_p_values_by_hand_with_ties():
    cal = [1.0, 2.0, 2.0, 3.0]  # n = 4
    p = conformal_p_values(cal, [0.5, 1.0, 2.0, 2.5, 3.0, 3.5])
    # (1 + #{c >= s}) / 5
    np.testing.assert_allclose(p, [5 / 5, 5 / 5, 4 / 5, 2 / 5, 2 / 5, 1 / 5])


def test_conformal_threshold_by_hand():
    cal = np.arange(1.0, 20.0)  # 1..19, n = 19
    # alpha 0.1: k = floor(0.1 * 20 - 1) = 1 -> flagged iff at most one calibration score >= s -> s > 18
    assert conformal_threshold(cal, 0.1) == 18.0
    # alpha 0.05: k = 0 -> s > 19
    assert conformal_threshold(cal, 0.05) == 19.0
    # ties at the threshold: with 18 twice, s = 18.5 has two scores >= it and p = 3/20 > 0.1
    cal2 = np.r_[np.arange(1.0, 18.0), 18.0, 18.0]
    t = conformal_threshold(cal2, 0.1)
    assert t == 18.0 and conformal_p_values(cal2, [18.0 + 1e-9])[0] == pytest.approx(1 / 20)


def test_conformal_threshold_with_too_few_scans_flags_nothing():
    assert conformal_threshold([1.0, 2.0, 3.0], 0.01) == math.inf  # 1/(n+1) = 0.25 > 0.01
    assert conformal_threshold(np.arange(99.0), 0.01) == 98.0  # 1/100 = alpha: enough


def test_conformal_threshold_agrees_with_p_values_randomly():
    rng = np.random.default_rng(1)
    for n in (9, 19, 50, 99, 200):
        cal = np.round(rng.normal(size=n), 1)  # rounded: many ties
        s = np.round(rng.normal(size=300) * 1.5, 1)
        for alpha in (0.01, 0.05, 0.1, 0.2):
            t = conformal_threshold(cal, alpha)
            np.testing.assert_array_equal(s > t, conformal_p_values(cal, s) <= alpha)


def test_conformal_far_interval_is_the_beta_of_the_order_statistic():
    # n = 199, alpha = 0.05: k = 9, the rate of the 10th largest score is Beta(10, 190)
    lo, hi = conformal_far_interval(199, 0.05)
    assert lo == pytest.approx(stats.beta.ppf(0.05, 10, 190)) and hi == pytest.approx(stats.beta.ppf(0.95, 10, 190))
    # by simulation from a distribution the statistics know nothing of: the realised rates fall in the interval
    # FAR_INTERVAL_LEVEL of the time and average (k + 1) / (n + 1)
    rng = np.random.default_rng(0)
    n, alpha = 39, 0.05
    rates = np.array([stats.gamma(2.0).sf(conformal_threshold(rng.gamma(2.0, size=n), alpha)) for _ in range(3000)])
    lo, hi = conformal_far_interval(n, alpha)
    assert rates.mean() == pytest.approx(2 / 40, abs=0.004)
    assert np.mean((rates >= lo) & (rates <= hi)) == pytest.approx(FAR_INTERVAL_LEVEL, abs=0.02)


# ------------------------------------------------------------------------------------------- log-normal tail
def test_lognormal_threshold_by_hand():
    cal = np.array([2.0, 3.0, 2.5, 4.0, 3.5, 2.2])
    y = np.log(cal)
    m, s, n = y.mean(), y.std(ddof=1), len(y)
    q = stats.t.ppf(0.99, n - 1) * math.sqrt(1 + 1 / n)
    assert lognormal_threshold(cal, 0.01) == pytest.approx(math.exp(m + q * s), rel=1e-12)
    # the p-value at the threshold is alpha, and flagging p <= alpha is flagging s > t
    t = lognormal_threshold(cal, 0.01)
    assert lognormal_p_values(cal, [t])[0] == pytest.approx(0.01, rel=1e-9)
    s_new = np.geomspace(1, 50, 400)
    np.testing.assert_array_equal(s_new > t, lognormal_p_values(cal, s_new) <= 0.01)


@pytest.mark.parametrize("n", [4, 6, 12])
def test_lognormal_threshold_holds_its_rate_and_interval_in_simulation(n):
    """Good scores drawn from a log-normal with unknown parameters: over many calibration draws the false-alarm
    rate averages alpha and each draw's own rate falls in the reported interval FAR_INTERVAL_LEVEL of the time."""
    rng = np.random.default_rng(n)
    alpha, mu, sigma = 0.01, 1.3, 0.4
    rates = []
    for _ in range(4000):
        t = lognormal_threshold(np.exp(rng.normal(mu, sigma, n)), alpha)
        rates.append(stats.norm.sf((math.log(t) - mu) / sigma))
    rates = np.array(rates)
    lo, hi = lognormal_far_interval(n, alpha)
    se = rates.std() / math.sqrt(len(rates))
    assert abs(rates.mean() - alpha) < 4 * se
    tail = (1 - FAR_INTERVAL_LEVEL) / 2
    tol = 4 * math.sqrt(tail * (1 - tail) / len(rates))
    assert abs(np.mean(rates > hi) - tail) < tol
    # the lower end is reported as 0 when the rate falls below 1e-12 with probability > tail (n = 4)
    assert abs(np.mean(rates < lo) - (tail if lo > 0 else 0.0)) < tol


def test_lognormal_rejects_what_it_cannot_model():
    with pytest.raises(ValueError, match="positive"):
        lognormal_threshold([1.0, 0.0, 2.0], 0.01)
    with pytest.raises(ValueError, match=">= 3"):
        lognormal_threshold([1.0, 2.0], 0.01)


# ------------------------------------------------------------------------------------------- the choice
def test_fit_threshold_is_conformal_with_enough_scans_and_log_normal_below():
    rng = np.random.default_rng(3)
    many = np.exp(rng.normal(size=120))
    t = fit_threshold(many, 0.01)
    assert t.basis == "conformal" and t.value == conformal_threshold(many, 0.01) and t.note == ""
    assert t.predicted_far == pytest.approx(1 / 121)
    few = many[:6]
    t = fit_threshold(few, 0.01)
    assert t.basis == "log-normal" and t.value == pytest.approx(lognormal_threshold(few, 0.01))
    assert t.predicted_far == 0.01 and t.far_interval == pytest.approx(lognormal_far_interval(6, 0.01))
    assert "6 held-back scans" in t.note and "99" in t.note and "log-normal" in t.note
    np.testing.assert_array_equal(t.p_values(many) <= t.alpha_used, many > t.value)


def test_fit_threshold_with_two_scans_uses_the_smallest_reachable_rate():
    t = fit_threshold([1.0, 2.0], 0.01)
    assert t.basis == "conformal" and t.value == 2.0 and t.alpha_used == pytest.approx(1 / 3)
    assert "too few" in t.note
    s = np.array([0.5, 1.5, 2.0, 2.5])
    np.testing.assert_array_equal(t.p_values(s) <= t.alpha_used, s > t.value)


def test_cross_fitted_scores_set_the_spread_and_never_the_level():
    """Held-back scores set the level, cross-fitted ones (possibly optimistic: lower) only the pooled spread: by
    hand, and by simulation with cross-fitted scores biased low the rate still averages alpha."""
    rng = np.random.default_rng(5)
    held, crossed = np.exp(rng.normal(1.0, 0.3, 6)), np.exp(rng.normal(0.6, 0.3, 26))
    t = fit_threshold(np.r_[held, crossed], 0.01, ["held-back"] * 6 + ["cross-fitted"] * 26)
    y, x = np.log(held), np.log(crossed)
    df = 6 + 26 - 2
    sd = math.sqrt((np.sum((y - y.mean()) ** 2) + np.sum((x - x.mean()) ** 2)) / df)
    assert t.value == pytest.approx(math.exp(y.mean() + stats.t.ppf(0.99, df) * math.sqrt(1 + 1 / 6) * sd))
    assert t.value == pytest.approx(lognormal_threshold(held, 0.01, spread_scores=crossed))
    assert t.fit["cross_fit_shift"] == pytest.approx(y.mean() - x.mean()) and "lower" in t.note
    assert t.far_interval == pytest.approx(lognormal_far_interval(6, 0.01, df=df))
    # the p-values of new scores need nothing but the threshold
    s_new = np.geomspace(1, 30, 300)
    np.testing.assert_array_equal(t.p_values(s_new) <= 0.01, s_new > t.value)
    rates = []
    for _ in range(3000):
        held, crossed = rng.normal(1.0, 0.3, 6), rng.normal(0.5, 0.3, 26)  # cross-fitted 0.5 lower in log
        t = lognormal_threshold(np.exp(held), 0.01, spread_scores=np.exp(crossed))  # fit_threshold's value
        rates.append(stats.norm.sf((math.log(t) - 1.0) / 0.3))
    rates = np.array(rates)
    assert abs(rates.mean() - 0.01) < 4 * rates.std() / math.sqrt(len(rates))
    lo, hi = lognormal_far_interval(6, 0.01, df=30)
    assert abs(np.mean(rates > hi) - 0.05) < 0.02


def test_threshold_record_is_json_ready():
    import json

    d = fit_threshold(np.exp(np.random.default_rng(0).normal(size=8)), 0.01).as_dict()
    assert json.loads(json.dumps(d))["basis"] == "log-normal" and d["far_interval_level"] == FAR_INTERVAL_LEVEL
    assert set(d["fit"]) == {"mean", "sd", "n_level", "df"}


def test_alpha_validated():
    for bad in (0, 1, 1.5, "x", None):
        with pytest.raises(ValueError, match="alpha must be"):
            fit_threshold([1.0, 2.0, 3.0], bad)


def test_the_threshold_is_drawn_with_its_predicted_rate():
    from inspection.plots import score_histogram_figure

    rng = np.random.default_rng(0)
    good = np.exp(rng.normal(1.0, 0.3, 20))
    t = fit_threshold(good, 0.01)
    fig = score_histogram_figure(np.r_[good[:5], 40.0], np.array(["good"] * 5 + ["defective"]), t, good)
    ax = fig.axes[0]
    lines = [line for line in ax.get_lines() if np.allclose(line.get_xdata(), t.value)]
    assert len(lines) == 1
    legend = [text.get_text() for text in ax.get_legend().get_texts()]
    assert any("log-normal" in x and "predicted false-alarm rate 1 %" in x for x in legend)


def test_uncertain_scores_are_those_within_the_thresholds_own_interval():
    """Log-normal basis: the uncertain scores are exactly those between the thresholds whose predictive rates are
    the interval's ends, exp(m + t_{df}(1 - r) s sqrt(1 + 1/n)) for r = hi and r = lo; conformal basis: exactly
    those whose p-value (1 + #{c >= s}) / (n + 1) lies in the interval."""
    rng = np.random.default_rng(3)
    t = fit_threshold(np.exp(rng.normal(0.0, 0.4, 12)), 0.05)
    assert t.basis == "log-normal"
    f, (lo, hi) = t.fit, t.far_interval
    scale = f["sd"] * math.sqrt(1 + 1 / f["n_level"])
    low_end, high_end = (math.exp(f["mean"] + stats.t.ppf(1 - r, f["df"]) * scale) for r in (hi, lo))
    assert low_end < t.value < high_end
    scores = np.exp(np.linspace(-1.0, 3.0, 4001))
    inside = (scores >= low_end * (1 + 1e-9)) & (scores <= high_end * (1 - 1e-9))
    outside = (scores <= low_end * (1 - 1e-9)) | (scores >= high_end * (1 + 1e-9))
    mask = t.uncertain(scores)
    assert mask[inside].all() and not mask[outside].any() and inside.sum() > 10
    c = fit_threshold(np.arange(1.0, 100.0), 0.05)  # 99 held-back scores: conformal
    assert c.basis == "conformal"
    s = np.array([0.5, 90.0, 94.5, 96.5, 98.5, 120.0])
    p = conformal_p_values(np.arange(1.0, 100.0), s)
    np.testing.assert_array_equal(c.uncertain(s), (p >= c.far_interval[0]) & (p <= c.far_interval[1]))
    assert c.uncertain(s).any() and not c.uncertain(s).all()


def test_fold_scores_are_out_of_sample_they_set_the_level_and_make_conformal_reachable():
    """Scores of training scans by fold models that never saw them count as held-back ones: the log-normal level
    and spread of all of them (by hand), split-conformal (CV+) once there are 1 / alpha - 1 of them, and the fold
    models' shift against the held-back scores recorded."""
    rng = np.random.default_rng(11)
    held, folds = np.exp(rng.normal(1.0, 0.3, 6)), np.exp(rng.normal(1.1, 0.3, 26))
    t = fit_threshold(np.r_[held, folds], 0.02, ["held-back"] * 6 + ["fold"] * 26)
    both = np.r_[held, folds]
    assert t.basis == "log-normal" and t.n == 32 and t.fit["n_level"] == 32 and t.fit["df"] == 31
    assert t.value == pytest.approx(lognormal_threshold(both, 0.02))
    assert t.far_interval == pytest.approx(lognormal_far_interval(32, 0.02))
    assert t.fit["fold_shift"] == pytest.approx(np.log(folds).mean() - np.log(held).mean())
    assert "32 out-of-sample scores (6 held-back, 26 by fold models)" in t.note and "49" in t.note
    many = np.exp(rng.normal(size=60))
    roles = ["held-back"] * 10 + ["fold"] * 50
    t = fit_threshold(many, 0.02, roles)
    assert t.basis == "conformal" and t.value == conformal_threshold(many, 0.02) and t.n == 60
    assert "CV+" in t.note
    # cross-fitted scores beside fold scores still only widen the spread
    t = fit_threshold(np.r_[held, folds, 0.5 * folds], 0.02, ["held-back"] * 6 + ["fold"] * 26 + ["cross-fitted"] * 26)
    assert t.fit["n_level"] == 32
    assert t.value == pytest.approx(lognormal_threshold(both, 0.02, spread_scores=0.5 * folds))
    with pytest.raises(ValueError, match="roles"):
        fit_threshold([1.0, 2.0, 3.0], 0.02, ["held-back", "fold", "trained"])
