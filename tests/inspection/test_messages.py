"""What a quality engineer reads: the threshold in plain words first (its rate, its interval, what set it) and its
statistics after, the scans counted by verdict (an 'uncertain' never counted as flagged), no precision or recall
without both labels, the cross-fitted scans' shift said the right way round, each verdict's reason, and at training
time what so many good scans will give the threshold (the same rule fit_threshold then follows)."""
import math

import numpy as np
import pytest

from inspection.report import format_table, format_verdict_counts, summarize, verdict_counts
from inspection.threshold import (DEFAULT_ALPHA, calibration_outlook, describe_decision, fit_threshold, format_rate,
                                  lognormal_far_interval)


def _row(name, label, score, verdict, flagged):
    return {"name": name, "split": "test", "label": label, "defect": "dent" if label == "defective" else "",
            "score": score, "p_value": 0.5, "verdict": verdict, "flagged": flagged, "reason": ""}


def test_scans_are_counted_by_verdict_and_uncertain_is_never_flagged():
    rows = [_row("a", "unknown", 9.0, "defective", True), _row("b", "unknown", 5.1, "uncertain", True),
            _row("c", "unknown", 4.9, "uncertain", False), _row("d", "unknown", 1.0, "good", False)]
    summary = summarize(rows, 5.0, 0.02)
    assert summary["verdict_counts"] == {"defective": 1, "uncertain": 2, "good": 1, "error": 0}
    table = format_table(rows, summary)
    assert "4 scans: 1 defective (flagged), 2 uncertain (rescan), 1 good at alpha=0.02 (threshold 5)" in table
    assert "of 4 scans flagged" not in table  # the old count took the uncertain scan above the threshold as flagged
    counts = verdict_counts(rows + [{"name": "e", "verdict": "error"}])
    assert format_verdict_counts(counts).endswith("1 good, 1 could not be scored (error)")


def test_no_precision_or_recall_without_both_labels():
    good_only = [_row(f"g{i}", "good", float(i), "defective" if i == 3 else "good", i == 3) for i in range(4)]
    summary = summarize(good_only, 2.5, 0.02)
    m = summary["metrics"]
    assert not {"precision", "recall", "f1", "auroc"} & set(m)
    assert m["false_alarm_rate"] == 0.25 and m["confusion_matrix"]["fp"] == 1  # what a good-only set does say
    table = format_table(good_only, summary)
    assert "precision" not in table and "recall" not in table and "f1" not in table
    both = good_only + [_row("d0", "defective", 9.0, "defective", True)]
    m = summarize(both, 2.5, 0.02)["metrics"]
    assert m["precision"] == 0.5 and m["recall"] == 1.0  # one of the two flagged scans is defective
    assert "precision 0.500" in format_table(both, summarize(both, 2.5, 0.02))


@pytest.mark.parametrize("crossed_factor, words", [(0.6, " % lower"), (1.4, " % higher")])
def test_the_cross_fitted_shift_is_said_the_right_way_round(crossed_factor, words):
    rng = np.random.default_rng(0)
    held = np.exp(rng.normal(1.0, 0.2, 4))
    crossed = crossed_factor * np.exp(rng.normal(1.0, 0.2, 12))
    t = fit_threshold(np.r_[held, crossed], 0.02, ["held-back"] * 4 + ["cross-fitted"] * 12)
    ratio = math.exp(np.log(crossed).mean() - np.log(held).mean())
    expected = f"{100 * abs(1 - ratio):.0f}{words}"
    assert f"cross-fitted training scans scored {expected}" in t.note and "scored -" not in t.note


def test_the_threshold_is_said_in_plain_words_first_and_its_statistics_after():
    rng = np.random.default_rng(1)
    t = fit_threshold(np.exp(rng.normal(size=7)), 0.02, ["held-back"] + ["cross-fitted"] * 6)
    lo, hi = t.far_interval
    plain, stats = describe_decision(t.as_dict())
    # the rate, its interval, what set it, and what would narrow it; the numbers after
    assert plain.startswith(f"a good scan is flagged {format_rate(0.02)} of the time on average")
    assert f"between {format_rate(lo)} and {format_rate(hi)}" in plain and "1 held-back scan," in plain
    assert "--calibration-folds" in plain
    assert stats.startswith("statistics: basis log-normal on 7 calibration scores")
    table = format_table([_row("a", "unknown", 1.0, "good", False)],
                         summarize([_row("a", "unknown", 1.0, "good", False)], t.value, 0.02,
                                   extra={"decision": t.as_dict()}))
    lines = table.splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith(f"threshold {t.value:.4g}: a good scan"))
    assert lines[at + 1] == stats
    # an exact threshold has no note; its plain words say so
    many = fit_threshold(np.exp(rng.normal(size=60)), 0.02)
    assert many.note == "" and "set exactly (split-conformal) by 60 good scans" in describe_decision(many.as_dict())[0]


def test_a_verdicts_reason_names_the_score_the_threshold_and_the_rescan():
    rng = np.random.default_rng(2)
    t = fit_threshold(np.exp(rng.normal(size=6)), 0.02)
    assert t.reason(0.5 * t.value, "good").endswith("below the threshold")
    high = t.reason(3 * t.value, "defective")
    assert f"threshold {t.value:.4g}" in high and "above the threshold" in high
    assert "rescan" in t.reason(t.value, "uncertain")


def test_training_says_what_so_many_good_scans_give_the_threshold():
    # 1 held back, 6 cross-fitted: the log-normal tail fit_threshold will draw, with its interval
    line = calibration_outlook(1, 6)
    lo, hi = lognormal_far_interval(1, DEFAULT_ALPHA, df=5)
    assert "of the 7 good scans 6 train the model and 1 is held back" in line
    assert f"between {format_rate(lo)} and {format_rate(hi)}" in line and "49" in line
    lo2, hi2 = lognormal_far_interval(7, DEFAULT_ALPHA)  # all 7 scored out of sample by fold models
    assert f"--calibration-folds 2 would narrow that to {format_rate(lo2)} to {format_rate(hi2)}" in line
    assert "48 more good scans held back would make it exact" in line
    # the same rule fit_threshold follows on so many scores
    t = fit_threshold(np.exp(np.random.default_rng(3).normal(size=7)), DEFAULT_ALPHA,
                      ["held-back"] + ["cross-fitted"] * 6)
    assert t.basis == "log-normal" and t.far_interval == pytest.approx((lo, hi))
    with_folds = calibration_outlook(1, 6, folds=2)
    assert f"between {format_rate(lo2)} and {format_rate(hi2)}" in with_folds and "--calibration-folds 2" not in \
        with_folds
    assert calibration_outlook(60, 200) == ""  # enough held back: exact, nothing to say
    assert "no good scan is held back" in calibration_outlook(0, 5)
