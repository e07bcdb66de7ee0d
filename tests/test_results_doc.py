"""docs/results.md as one table per suite (issue 50): its length, a block per suite, ``python -m benchmarks table``
rewriting exactly the blocks of the suites with a record (from the record's figures, command and commit) and no
other byte, one clear error for a file that is not a record, a write that is whole or nothing, the suites' renderers
on figures shaped as the suites return them, and the links into results.md and its archive. No benchmark is run."""
import json
import re
from pathlib import Path

import pytest

from benchmarks import results_doc
from benchmarks.__main__ import main as benchmarks_main

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "results.md"
COMMIT = "0123456789abcdef0123456789abcdef01234567"


def _record(suite, figures, command=None, date="2026-11-29T10:00:00+00:00", commit=COMMIT):
    return {"suite": suite, "command": command or f"python -m benchmarks {suite} --seeds 0", "commit": commit,
            "dirty": False, "date": date, "seconds": 12.5,
            "load": {"start": [1.0, 1, 1], "end": [2.0, 2, 2], "cpus": 2},
            "figures": figures}


def _write(folder, name, record):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_text(json.dumps(record, indent=1))
    return folder / name


def _verdicts_figures():
    from benchmarks.suites.verdicts import check_targets

    rows = [dict(tree=tree, seed=seed, auroc=auroc, defective=0.938, good=good / 16, n_good=16,
                 good_text=f"{good} of 16", rejected=0.0, rejected_text="0 of 16", oracle=1.0, exact_alpha=0.95,
                 basis="log-normal", predicted=0.02, alpha=0.02, seconds=100.0, log="x.log")
            for tree, auroc, good in (("fandisk", 0.9871, 0), ("cup", 0.5, 2)) for seed in (0, 1)]
    targets = check_targets(rows)
    return {"runs": rows, "targets": {k: v for k, v in targets.items() if k != "lines"}}


def _sensors_figures():
    """Figures as the sensors suite returns them (its own report on synthetic runs), '+site' runs included."""
    from benchmarks.suites import sensors

    rows = []
    for seed in (0, 1):
        for i, sensor in enumerate(("same", "same+site", "noise4", "noise4+site")):
            rows.append(dict(tree="templates-bracket", seed=seed, sensor=sensor, auroc=0.9876 - 0.01 * i,
                             defective=0.9, good=(i % 3) / 16, n_good=16, good_flagged=i % 3,
                             good_told_defective=i % 2, good_text=f"{i % 3} of 16", told_text=f"{i % 2} of 16",
                             alpha=0.02, threshold=3.2, predicted_far=0.02, far_interval=[0.001, 0.07],
                             gap=0.1 * i, gap_cross_fitted=0.05, good_mean_log=1.0 + 0.1 * i,
                             warning={0: None, 1: False, 2: True, 3: False}[i], run=f"/runs/{seed}/{sensor}"))
    return json.loads(json.dumps(sensors._report(rows)))  # as the record stores them


def _rays_figures():
    from benchmarks.suites import rays

    rows = [dict(tree="cup", seed=seed, auroc=0.9991, missing=0.97, good_nats=2.0, good_accused=1,
                 good_rays_max=19.5, rays_through=0.1, points_alone=0.987, rays_alone=0.6, defective=0.95,
                 defective_rejected=0.9, good=0.0, n_good=16, good_text="0 of 16", rejected_text="0 of 16",
                 points_oracle=0.9, oracle=1.0, points_flagged=0.9, points_good=0, rays=True, run="/r", seconds=1.0,
                 log="l") for seed in (0, 1)]
    return json.loads(json.dumps(rays._report(rows)))


# ------------------------------------------------------------------------------------------------ the document
def test_results_md_is_short():
    lines = DOC.read_text().count("\n")
    assert lines <= results_doc.LINE_LIMIT, (f"docs/results.md has {lines} lines (at most {results_doc.LINE_LIMIT}): "
                                             f"history goes to docs/results_archive.md")


def test_every_suite_has_one_block():
    spans = results_doc.blocks(DOC.read_text(), str(DOC))
    suites = results_doc.suite_names()
    assert sorted(spans) == suites, f"blocks {sorted(spans)} against suites {suites}"


def test_blocks_are_found_and_a_broken_block_is_named():
    text = "a\n<!-- table: x -->\nX\n<!-- /table -->\nb `<!-- table: SUITE -->` inline\n<!-- table: y -->\nY\n" \
           "<!-- /table -->\n"
    spans = results_doc.blocks(text)
    assert [text[slice(*spans[k])] for k in ("x", "y")] == ["X\n", "Y\n"]
    with pytest.raises(results_doc.DocError, match="two blocks of 'x'"):
        results_doc.blocks(text + "<!-- table: x -->\n<!-- /table -->\n")
    with pytest.raises(results_doc.DocError, match="markers"):
        results_doc.blocks(text + "<!-- table: z -->\nZ\n")


# ------------------------------------------------------------------------------------------------ the command
def test_table_rewrites_exactly_the_blocks_with_a_record(tmp_path, capsys):
    doc = tmp_path / "results.md"
    doc.write_text(DOC.read_text())
    before = results_doc.blocks(doc.read_text())
    records = tmp_path / "records"
    _write(records, "sensors_20261129T100000Z.json", _record("sensors", _sensors_figures(),
                                                              "python -m benchmarks sensors --seeds 0,1 --jobs 2"))
    _write(records, "verdicts_20261129T090000Z.json",
           _record("verdicts", _verdicts_figures(), date="2026-11-29T09:00:00+00:00"))
    # an older record of the same suite does not win
    _write(records, "verdicts_20261128T090000Z.json", _record("verdicts", {"runs": []}, "python -m benchmarks verdicts "
                                                              "--old", date="2026-11-28T09:00:00+00:00"))
    assert benchmarks_main(["table", "--records", str(records), "--doc", str(doc)]) == 0
    out = capsys.readouterr().out
    assert "sensors: regenerated" in out and "verdicts: regenerated" in out and "rays: kept (no record)" in out
    old, new = DOC.read_text(), doc.read_text()
    after = results_doc.blocks(new)
    assert sorted(after) == sorted(before)
    for suite in before:
        body_old, body_new = old[slice(*before[suite])], new[slice(*after[suite])]
        if suite in ("sensors", "verdicts"):
            assert body_new != body_old
            assert "commit `0123456`" in body_new and "2026-11-29" in body_new
        else:
            assert body_new == body_old, suite
    # nothing outside the two blocks moved
    def outside(text, spans):
        cut = [spans[s] for s in ("sensors", "verdicts")]
        pieces, at = [], 0
        for start, end in sorted(cut):
            pieces.append(text[at:start])
            at = end
        return pieces + [text[at:]]

    assert outside(old, before) == outside(new, after)
    sensors = new[slice(*after["sensors"])]
    assert "python -m benchmarks sensors --seeds 0,1 --jobs 2" in sensors
    assert "| noise4+site |" in sensors and "0.988 / 0.900 / 0 of 16 (0)" in sensors  # a run's cell from its figures
    assert "level 8 good scans of that sensor set" in sensors
    verdicts = new[slice(*after["verdicts"])]
    assert "verdicts --seeds 0" in verdicts and "--old" not in verdicts
    assert "| fandisk | 0.987 / 0.938 / 0 of 16 (0) |" in verdicts and "cup seed 0 (2 of 16)" in verdicts
    # run again: the same document, and --check says it is current
    assert benchmarks_main(["table", "--records", str(records), "--doc", str(doc)]) == 0
    assert doc.read_text() == new
    assert benchmarks_main(["table", "--records", str(records), "--doc", str(doc), "--check"]) == 0
    doc.write_text(old)
    assert benchmarks_main(["table", "--records", str(records), "--doc", str(doc), "--check"]) == 1
    assert doc.read_text() == old  # --check writes nothing


def test_table_suites_option_keeps_the_others(tmp_path, capsys):
    doc = tmp_path / "results.md"
    doc.write_text(DOC.read_text())
    records = tmp_path / "records"
    _write(records, "sensors_1.json", _record("sensors", _sensors_figures()))
    _write(records, "verdicts_1.json", _record("verdicts", _verdicts_figures()))
    assert results_doc.main(["--records", str(records), "--doc", str(doc), "--suites", "verdicts"]) == 0
    assert "sensors: kept (not asked for (--suites))" in capsys.readouterr().out
    new = doc.read_text()
    spans_old, spans_new = results_doc.blocks(DOC.read_text()), results_doc.blocks(new)
    assert new[slice(*spans_new["sensors"])] == DOC.read_text()[slice(*spans_old["sensors"])]


@pytest.mark.parametrize("content, message", [("{not json", "not a readable run record"),
                                              (json.dumps({"suite": "verdicts"}), "no command, commit, date, figures"),
                                              (json.dumps(_record("nosuchsuite", {})), "unknown suite 'nosuchsuite'")])
def test_a_file_that_is_not_a_record_is_one_error_naming_it(tmp_path, capsys, content, message):
    doc = tmp_path / "results.md"
    doc.write_text(DOC.read_text())
    records = tmp_path / "records"
    _write(records, "sensors_1.json", _record("sensors", _sensors_figures()))
    bad = records / "broken_20261129.json"
    bad.write_text(content)
    assert benchmarks_main(["table", "--records", str(records), "--doc", str(doc)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and message in err and err.count("\n") == 1
    assert doc.read_text() == DOC.read_text()  # not even the good record's block was written


@pytest.mark.parametrize("key, value", [("commit", 12345), ("seconds", "12"), ("load", [1])])
def test_a_record_with_entries_of_the_wrong_kind_is_one_error_naming_it(tmp_path, capsys, key, value):
    """A record with every key but one of the wrong kind (hand-edited, another version) is exit 2 and one line
    naming the file, the document untouched."""
    doc = tmp_path / "results.md"
    doc.write_text(DOC.read_text())
    bad = _write(tmp_path / "records", "sensors_1.json", {**_record("sensors", _sensors_figures()), key: value})
    assert benchmarks_main(["table", "--records", str(tmp_path / "records"), "--doc", str(doc)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "not what a sensors record holds" in err and err.count("\n") == 1
    assert doc.read_text() == DOC.read_text()


def test_the_write_is_whole_or_nothing(tmp_path, monkeypatch, capsys):
    doc = tmp_path / "results.md"
    doc.write_text(DOC.read_text())
    records = tmp_path / "records"
    _write(records, "sensors_1.json", _record("sensors", _sensors_figures()))
    real_write = Path.write_text

    def half_then_fail(self, text, *args, **kwargs):
        if self.name.startswith("."):  # the temporary file beside the document
            real_write(self, text[: len(text) // 2], *args, **kwargs)
            raise OSError(28, "No space left on device")
        return real_write(self, text, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", half_then_fail)
    assert results_doc.main(["--records", str(records), "--doc", str(doc)]) == 2
    monkeypatch.undo()
    assert "cannot write" in capsys.readouterr().err
    assert doc.read_text() == DOC.read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["records", "results.md"]  # no temporary file left


def test_no_records_folder_keeps_every_block(tmp_path, capsys):
    doc = tmp_path / "results.md"
    doc.write_text(DOC.read_text())
    assert results_doc.main(["--records", str(tmp_path / "none"), "--doc", str(doc)]) == 0
    assert doc.read_text() == DOC.read_text()
    assert capsys.readouterr().out.count("kept (no record)") == len(results_doc.suite_names())


# ------------------------------------------------------------------------------------------------ renderers
def _renders_itself(suite, figures, record=None):
    body, used = results_doc.render_block(suite, record or _record(suite, figures))
    assert used == suite, f"{suite}'s renderer fell back to the generic one"
    assert body.endswith("\n") and "Command: `OMP_NUM_THREADS=1 .venv/bin/python -m benchmarks" in body
    return body


def test_the_sensors_renderer_summarises_per_sensor_and_run():
    figures = _sensors_figures()
    body = _renders_itself("sensors", figures, _record("sensors", figures,
                                                       "python -m benchmarks sensors --site-scans 6"))
    # the per-sensor means, then each run's cell: noise4 at seeds 0 and 1
    assert "| noise4 | 0.968 | 0.900 | 4 of 32 | 0 of 32 | +0.200 |" in body
    assert "| 0.968 / 0.900 / 2 of 16 (0) warning | 0.968 / 0.900 / 2 of 16 (0) warning |" in body
    assert "level 6 good scans of that sensor set" in body
    assert "Targets over 4 template-calibrated runs" in body


def test_the_suites_renderers_know_their_figures():
    _renders_itself("verdicts", _verdicts_figures())
    assert "| cup | 0.999 / 0.987 / 0.950 / 0 of 16; 19.5, 0.970 |" in _renders_itself("rays", _rays_figures())
    one = {"auroc": {"overall": 1.0, "bump": 0.9}, "point_auroc": 0.95,
           "flagged": {"defective": 1.0, "good": 0.0625, "n_good": 16}, "threshold": {
               "basis": "log-normal", "predicted_far": 0.02, "far_interval": [0.001, 0.07]}, "seconds_per_scan": 0.2,
           "oracle": 1.0, "method": "toolkit joint/top1 +rays, no folds"}
    body = _renders_itself("inspection", {"parts": {"builtin": {"toolkit_nofolds": one, "nn": dict(one, method="nn")}},
                                          "multi_part": None})
    assert "| builtin | toolkit joint/top1 +rays, no folds | 1.000 | 0.900 | 0.950 | 1.000 | 1 of 16 |" in body
    _renders_itself("ablation", {"parts": {"builtin": {"joint/top1": one}}})
    body = _renders_itself("ablation", {"rows": [
        {"tree": "fandisk", "seed": 0, "method": "default", "auroc": {"overall": 1.0}, "point_auroc": 0.99},
        {"tree": "fandisk", "seed": 0, "method": "nearest-neighbour", "auroc": {"overall": 0.9}, "point_auroc": None}],
        "targets": {"misses": []}})
    assert "| fandisk s0 | 1.000 (0.990) | 0.900 |" in body
    _renders_itself("real", {"toolkit": {"overall": 1.0, "bump": 1.0}, "nn": {"overall": 0.9, "bump": 0.8},
                             "terms": {"point score alone": {"overall": 1.0, "bump": 1.0}},
                             "flagged": {"good": 0.0, "defective": 0.9}, "seconds_per_scan": 0.7,
                             "nn_seconds_per_scan": 0.01, "train_seconds": 90})
    _renders_itself("maps", {"neighbours": [1, 32], "default": 32, "runs": [
        {"run": "a/defaults", "points": 4000, "defect": "60/99/228", "k1": 0.9, "k32": 0.99, "patch": 0.98}],
        "per_type": [{"run": "a/defaults", "patch": 32, "overall": 0.99, "bump": 0.98}]})
    _renders_itself("latency", {"part": "builtin", "threads": 1, "calibrate_seconds": 20.0, "sizes": {"4000": {
        "scans": 12, "points": 4000.0, "seconds_per_scan": 0.2, "seconds_max": 0.3, "stages": {"rays": 0.03},
        "other": 0.01, "nn_seconds_per_scan": 0.007, "peak_rss_mb": 900.0}}})  # a record from before issue 51
    body = _renders_itself("latency", {"part": "builtin", "threads": 1, "calibrate_seconds": 20.0, "sizes": {
        "1000000": {"scans": 8, "points": 1e6, "points_scored": 7200.0, "scored_as": "defaults",
                    "seconds_per_scan": 0.6, "seconds_max": 0.7, "stages": {"sample": 0.18}, "other": 0.01,
                    "map_seconds": 0.04, "nn_seconds_per_scan": 0.6, "peak_rss_mb": 1000.0}}})
    assert "| 1,000,000 | 7,200 | defaults | 8 | 0.600 | 0.700 | 0.180 | 0.010 | 0.040 | 0.6000 | 1000 |" in body
    body = _renders_itself("training", {"seed": 0, "runs": [
        {"part": "fandisk", "epochs": "450", "epochs_run": 450, "scans": 26, "seconds": 200.0, "loss": 0.0066,
         "stages": {"family": 19.0, "pose": 8.0, "read": 0.1, "targets": 1.5, "epochs": 170.0}, "other": 1.4}]})
    assert "| fandisk | 450 (450) | 26 | 200.0 | 19.0 | 8.0 | 0.1 | 1.5 | 170.0 | 1.4 | 0.0066 |" in body


def test_the_fewscans_renderer_sums_over_the_seeds_and_shows_the_loop():
    def run(part, scans, seed, auroc, flagged, **kw):
        return {"part": part, "scans": scans, "seed": seed, "auroc": auroc, "nn_auroc": 0.7, "flagged": flagged,
                "uncertain": 10, "n_defective": 64, "good_defective": 0, "good_uncertain": 2, "n_good": 16,
                "on_covered": 50, "covered_flagged": flagged, "missed_uncertain": 3, "missed": 4, **kw}

    runs = [run("fandisk", 8, 0, 1.0, 0.9), run("fandisk", 8, 1, 0.9, 0.7)]
    loop = [run("fandisk", 12, s, 0.95, 0.8, strategy=k) for s in (0, 1) for k in ("base", "proposed", "random")]
    body = _renders_itself("fewscans", {"runs": runs, "loop": loop})
    assert "| fandisk | 8 | 2 | 0.950 | 0.700 | 0.800 | 20 of 128 | 0 / 4 of 32 | 0.800 of 100 | 6 of 8 |" in body
    assert "| all | proposed | 2 | 0.950 |" in body and "Closed loop" in body and "| fandisk | proposed" not in body


def test_the_defects_renderer_lists_each_run_and_sums_the_types():
    kinds = {"bump": {"defects": 16, "found": 16, "typed": 15}, "dent": {"defects": 16, "found": 14, "typed": 14}}
    runs = [{"part": "fandisk", "seed": s, "au_pro": 0.95, "found": 0.9, "below": 0.1 * s, "typed": 0.95,
             "depth_error": 0.1, "area_error": 0.05, "false_per_good": 0.0625, "false_shown": 0.0, "per_kind": kinds,
             "matched": []} for s in (0, 1)]
    body = _renders_itself("defects", {"runs": runs})
    assert ("| fandisk | 0, 1 | 0.950 | 0.900 | 0.050 | 0.950 | 0.100 | 0.050 | 0.062 | 0.000 | bump 30/32/32, dent "
            "28/28/32 |") in body
    assert "| false regions / good scan, above the level | shown |" in body


def test_the_generic_renderer_shows_the_figures_tables_within_bounds():
    figures = {"mode": "io", "scans": 80, "rows": [{"name": f"r{i}", "seconds": i / 3, "log": "x"} for i in range(50)],
               "nested": {"a": {"x": 1.0}, "b": {"x": 2.0}}}
    body, used = results_doc.render_block("walk", _record("walk", figures))
    assert used == "generic"
    assert "Figures: mode io, scans 80." in body and "| r0 | 0.000 |" in body and "log" not in body.split("Command")[0]
    assert f"({50 - results_doc.MAX_ROWS} more rows in the record.)" in body
    assert "| a | 1.000 |" in body
    # figures a suite's renderer does not know fall back to the generic renderer
    assert results_doc.render_block("sensors", _record("sensors", {"skipped": "no runs"}))[1] == "generic"


# ------------------------------------------------------------------------------------------------ links
def _slug(heading):
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(path):
    """The anchors a markdown file offers: its headings' (GitHub's rule, repeats numbered) and its <a id>s."""
    text, seen, out = path.read_text(), {}, set()
    for m in re.finditer(r"^#{1,6} (.*)$", text, re.M):
        s = _slug(m.group(1))
        out.add(s if s not in seen else f"{s}-{seen[s]}")
        seen[s] = seen.get(s, 0) + 1
    return out | set(re.findall(r'<a id="([^"]+)"></a>', text))


def test_links_into_the_results_land_on_an_anchor():
    """Every results.md#... and results_archive.md#... link in the docs, the READMEs and the sources, and every
    in-page link of the two files, names an anchor the file has (old links into results.md land on its index of
    moved sections)."""
    targets = {name: _anchors(ROOT / "docs" / name) for name in ("results.md", "results_archive.md")}
    files = [*sorted((ROOT / "docs").glob("*.md")), ROOT / "README.md", ROOT / "benchmarks" / "README.md",
             *[p for package in ("datasets", "autodecoder", "inspection", "benchmarks") for p in
               sorted((ROOT / package).rglob("*.py"))], ROOT / "train_latent.py"]
    broken = []
    for path in files:
        text = path.read_text()
        for m in re.finditer(r"(results(?:_archive)?\.md)#([\w\-]+)", text):
            if m.group(2) not in targets[m.group(1)]:
                broken.append(f"{path.relative_to(ROOT)}: {m.group(0)}")
        if path.name in targets:
            for m in re.finditer(r"\]\(#([\w\-]+)\)", text):
                if m.group(1) not in targets[path.name]:
                    broken.append(f"{path.relative_to(ROOT)}: #{m.group(1)}")
    assert not broken, "links to no anchor:\n" + "\n".join(broken)
