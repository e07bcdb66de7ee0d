"""The sensors suite's targets (issue 47), checked on hand-made rows: a template-calibrated run over the false-alarm
target is excused only when the batch warning fired and no good scan was told 'defective'; detection is judged
only where the ranking allows it and no warning fired; a '<sensor>+site' run (its level set by the sensor's own good
scans) has no excuse."""
from benchmarks.suites.sensors import SITE, check_targets


def _row(sensor, good_flagged, told, defective, warning, auroc=1.0, seed=0):
    return {"tree": "templates-bracket", "seed": seed, "sensor": sensor, "auroc": auroc, "defective": defective,
            "good": good_flagged / 16, "good_flagged": good_flagged, "good_told_defective": told,
            "good_text": f"{good_flagged} of 16", "told_text": f"{told} of 16", "warning": warning}


def test_false_alarms_are_excused_only_by_a_warning_that_told_no_good_scan_defective():
    rows = [_row("same", 1, 1, 0.95, False), _row("noise4", 16, 0, 0.3, True), _row("noise2", 5, 2, 0.9, True),
            _row("line", 3, 3, 0.95, False)]
    targets = check_targets(rows)
    assert [t.split(" (")[0] for t in targets["false_alarms"]] == ["templates-bracket noise2 seed 0",
                                                                   "templates-bracket line seed 0"]
    # detection: judged on the runs without a warning whose AUROC is at least 0.99 (same, line), both above 0.9
    assert targets["detection"] == []
    low = check_targets([_row("same", 0, 0, 0.85, False), _row("sparse", 0, 0, 0.5, False, auroc=0.98)])
    assert [t.split(" (")[0] for t in low["detection"]] == ["templates-bracket same seed 0"]


def test_site_runs_have_no_excuse_and_are_kept_apart():
    rows = [_row("same", 0, 0, 1.0, False), _row("noise4" + SITE, 2, 0, 0.95, True),
            _row("same" + SITE, 0, 0, 0.85, False, auroc=0.9), _row("noise2" + SITE, 1, 1, 0.95, False)]
    targets = check_targets(rows)
    assert targets["false_alarms"] == [] and targets["detection"] == []
    assert [t.split(" (")[0] for t in targets["site"]] == ["templates-bracket noise4+site seed 0",
                                                          "templates-bracket same+site seed 0"]
    assert "1 of 3" in targets["lines"][-1] and "over 1 template-calibrated runs" in targets["lines"][0]
