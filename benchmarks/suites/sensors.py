"""Whether the threshold holds when the test scans' sensor is not the one the calibration saw (issue 47): the template
regime's trees scored with test scans from other virtual sensors, and the placement-jitter trees.

A template tree (``templates-bracket``, ``templates-fandisk``, ``templates-ogre``) is the ``inspection --templates``
regime of one part at one seed: 4 complete templates written as a Real3D-AD class folder with the synthetic test
scans, imported (:func:`benchmarks.cache.template_collection`), a model trained on the templates' views with the
trainer's defaults and calibrated as ``inspection --templates`` calibrates it (held-back and cross-fitted views, no
fold models): the ``same`` run is that tree's run. The model is trained and calibrated ONCE per part and seed; each
other sensor of :data:`SENSORS` changes only the test scans: synthesised with the same seed and counts (each good
scan seen from the same direction, :func:`datasets.synth.synthesise`), written beside the same templates and
imported the same way (the same training views, held-back views and frame), then scored by a copy of the calibrated
model (:func:`benchmarks.inspect_api.score_calibrated`). With ``--site-scans N`` (default 8) each sensor has a
second run, ``<sensor>+site``: another copy of the calibrated model is given N good scans of that sensor (another
seed's views, imported the same way: :func:`site_collection`) by ``calibrate --data`` (they set the threshold's level,
:meth:`inspection.Inspector.fit_level`), as a user with a first shift's good scans does, and scores the same test
scans. The placement-jitter tree (``bracket-jitter5-align``,
:data:`benchmarks.trees.TREES`) is its ``inspection`` run at the defaults; its test scans come from its training
scans' sensor (``same``).

Printed per run: object AUROC, defective flagged, good flagged and of them told ``defective`` (out of the good test
scans, 16), the threshold's alpha, predicted false-alarm rate and 90 % interval (summary.json's), the calibration gap
(the good test scans' mean log score minus the held-back views' and the cross-fitted training views'), the good test
scans' mean log score minus that of the same tree and seed's ``same`` run (the sensor's own shift, paired: the same
views), and whether the score summary's batch check fired (:func:`batch_warning`; '-' where the summary has none).
Then per sensor over trees and seeds, and the issue's targets: at most 1 of 16 good scans flagged on every run, or
the warning fired and no good scan told ``defective``; defective flagged at least 0.9 wherever the AUROC is at least
0.99 and the warning did not fire; on the ``+site`` runs at most 1 of 16 good scans flagged and defective flagged
at least 0.9, everywhere.

Each tree and seed is a process of its own (:func:`benchmarks.trees.run_trees`: ``--jobs 2`` runs two at once, each
one's output in ``WORK/logs/``); a template tree's process is this suite with ``--tree NAME --seed S``. About 5-10
minutes a template tree and seed on 2 shared cores with the model to train, 3-5 with it cached.
"""
import json
import time
from pathlib import Path

import numpy as np

from benchmarks import cache, inspect_api, metrics
from benchmarks.table import format_table
from benchmarks.trees import TREES, add_tree_arguments, check_names, part_figures, run_trees

DESCRIPTION = ("whether the threshold holds when the test scans' sensor differs from the calibration's (issue 47): "
               "template trees x test sensors (noise, density, stand-off and field of view, ragged borders, a line "
               "scanner) x seeds, and the placement-jitter trees; gap, flagged, warning")
WORK = "results/sensors"

# the template trees: name -> part
TEMPLATE_PARTS = {"templates-bracket": "builtin", "templates-fandisk": "fandisk", "templates-ogre": "ogre"}
# the placement-jitter trees, as the verdicts suite runs them (the calibration's sensor)
JITTER_TREES = ("bracket-jitter5-align",)
DEFAULT_TREES = ("templates-bracket", "templates-fandisk", "bracket-jitter5-align")

# the test sensors, as datasets.synth.synthesise's options over the templates' own sensor (depth noise 0.002 x the
# diagonal, 4,000 points, 1.5-2.2 diagonals away, 40 degrees, a pinhole camera, clean borders)
SENSORS = {
    "same": {},
    "noise0.25": {"noise": 0.0005},
    "noise2": {"noise": 0.004},
    "noise4": {"noise": 0.008},
    "sparse": {"n_points": 2000},  # half the points
    "far-narrow": {"radius_range": (2.25, 3.3), "fov_deg": 27.0},  # 1.5x the stand-off, 2/3 of the field of view
    "ragged": {"ragged": 0.03, "grazing_dropout": 1.0},  # borders eaten back by up to 3 % of the diagonal, Lambertian
    "line": {"sensor": "line"},
}

TARGET_MAX_GOOD = 1 / 16  # good scans flagged, unless the warning fired and none was told 'defective'
TARGET_DETECTION = 0.9  # defective flagged where the AUROC is at least TARGET_AUROC and the warning did not fire
TARGET_AUROC = 0.99
SITE_SCANS = 8  # a first shift's good scans of the test sensor, given to 'calibrate --data' (the '+site' runs)
SITE_SEED_OFFSET = 1000  # their views: another seed's, so none is a test scan's
SITE = "+site"


def add_arguments(p):
    add_tree_arguments(p, dict.fromkeys(DEFAULT_TREES), WORK)
    for action in p._actions:  # the trees' option: more trees than the default ones
        if action.dest == "trees":
            action.help = (f"comma-separated tree names, of {', '.join([*TEMPLATE_PARTS, *JITTER_TREES])} "
                           f"(default: %(default)s)")
    p.add_argument("--sensors", default=",".join(SENSORS),
                   help="comma-separated test sensors of the template trees (default: all: %(default)s)")
    p.add_argument("--epochs", type=int, default=None, help="training epochs (default: the trainer's; a smoke run)")
    p.add_argument("--test-good", type=int, default=None, help="good test scans (default: 16; a smoke run)")
    p.add_argument("--per-defect", type=int, default=None,
                   help="test scans per defect type (default: 8 on the template trees, 16 on the jitter trees)")
    p.add_argument("--site-scans", type=int, default=SITE_SCANS,
                   help="good scans of each test sensor given to 'calibrate --data' on the template trees' calibrated "
                        "model (the '<sensor>+site' runs; 0: none; default: %(default)s)")
    p.add_argument("--from-record", default=None, metavar="RECORD",
                   help="no runs: the table of a recorded run of this suite, read again from its run folders")
    p.add_argument("--tree", default=None, help=f"(one template tree in this process, with --seed: "
                                                f"{', '.join(TEMPLATE_PARTS)})")
    p.add_argument("--seed", type=int, default=0, help="(with --tree: its seed)")
    p.add_argument("--progress", action="store_true", help="progress bars (with --tree)")


def run(args):
    if args.from_record:
        return _from_record(args.from_record)
    sensors = _sensor_names(args.sensors)
    if args.tree:
        return _one_tree(args.tree, args.seed, sensors, args)
    names = [t.strip() for t in args.trees.split(",") if t.strip()]
    trees = _trees(sensors)
    check_names(names, "sensors", trees)
    seeds = [int(s) for s in args.seeds.split(",")]
    common = [*(["--epochs", str(args.epochs)] if args.epochs else []),
              *(["--test-good", str(args.test_good)] if args.test_good else []),
              *(["--per-defect", str(args.per_defect)] if args.per_defect else [])]
    # the site scans are this suite's option (the template trees'); the jitter trees run the inspection suite
    extra = {"sensors": [*common, "--site-scans", str(args.site_scans)], "inspection": common}
    jobs = [(name, seed) for seed in seeds for name in names]
    runs = {}

    def done(name, seed, result):
        figures, log, seconds = result
        runs[(name, seed)] = _tree_runs(name, figures, trees)
        for sensor, run_dir in runs[(name, seed)].items():
            r = run_row(run_dir)
            print(f"{name}, seed {seed}, {sensor}: AUROC {r['auroc']:.3f}, defective flagged {r['defective']:.3f}, "
                  f"good flagged {r['good_text']} ({r['told_text']} told defective), gap {_signed(r['gap'])}, "
                  f"warning {_fired(r['warning'])} ({seconds:.0f} s for the tree; log {log})", flush=True)

    run_trees(jobs, args.cache, args.work, args.jobs, extra=extra, done=done, trees=trees, reuse=args.reuse)
    rows = [dict(tree=name, seed=seed, sensor=sensor, **run_row(run_dir))
            for name, seed in jobs for sensor, run_dir in runs[(name, seed)].items()]
    return _report(rows)


def _sensor_names(text):
    names = [s.strip() for s in text.split(",") if s.strip()]
    unknown = [s for s in names if s not in SENSORS]
    if unknown or not names:
        raise SystemExit(f"sensors: unknown test sensor(s) {unknown}; known: {list(SENSORS)}")
    return names


def _trees(sensors):
    """{tree: (suite, options)} of :func:`benchmarks.trees.run_tree`: the template trees as this suite's ``--tree``
    runs of ``sensors``, the jitter trees as :data:`benchmarks.trees.TREES` has them."""
    trees = {name: ("sensors", ["--tree", name, "--sensors", ",".join(sensors)]) for name in TEMPLATE_PARTS}
    trees.update({name: TREES[name] for name in JITTER_TREES})
    return trees


def _tree_runs(name, figures, trees):
    """{sensor: run folder} of one tree's recorded figures."""
    if name in TEMPLATE_PARTS:
        return dict(figures["runs"])
    one = part_figures(name, figures, trees)
    return {"same": one.get("run") or one["run_nofolds"]}


# ------------------------------------------------------------------------------------------------ one template tree
def sensor_collection(part, seed, sensor, args):
    """The template tree's collection of ``part`` at ``seed`` with the test scans of ``sensor`` (cached; ``same``: the
    ``inspection --templates`` tree's own collection). Returns its ``data.h5``."""
    options = {"n_points": 4000, **SENSORS[sensor]}
    test = cache.synth_collection(part, seed, root=args.cache, n_train=0, n_test_good=args.test_good or 16,
                                  n_test_defective=args.per_defect or 8, **options)
    return cache.template_collection(part, test, seed, root=args.cache)


def site_collection(part, seed, sensor, args):
    """``args.site_scans`` good scans of ``sensor`` (another seed's views: none is a test scan), written as the template
    tree's test scans are: what a user scans on the line after the first shift and gives to ``calibrate --data``.
    Returns the folder of their ``.pcd`` files (file units, no sensor origins; read as the calibration reads files)."""
    options = {"n_points": 4000, **SENSORS[sensor]}
    good = cache.synth_collection(part, seed + SITE_SEED_OFFSET, root=args.cache, n_train=0,
                                  n_test_good=args.site_scans, n_test_defective=0, **options)
    return cache.template_collection(part, good, seed, root=args.cache).parent / "tree" / "test"


def _site_run(model_path, part, seed, sensor, data, run_dir, args):
    """The '<sensor>+site' run: a copy of the calibrated model given the folder of the sensor's own good scans
    (:func:`site_collection`) by ``calibrate --data FOLDER``, then ``data``'s test split scored with it
    (:func:`benchmarks.inspect_api.score_calibrated` with ``good_folder``)."""
    inspect_api.score_calibrated(model_path, data, run_dir, good_folder=site_collection(part, seed, sensor, args),
                                 progress=args.progress)


def _one_tree(name, seed, sensors, args):
    """One template tree at one seed: trained and calibrated once, each sensor's test scans scored by that calibration
    and, with ``args.site_scans``, by a copy whose level that sensor's own good scans set ('<sensor>+site').
    Returns {"tree", "seed", "part", "model", "collections", "runs"} ({sensor: path})."""
    if name not in TEMPLATE_PARTS:
        raise SystemExit(f"sensors: --tree takes a template tree, one of {list(TEMPLATE_PARTS)}; got {name!r}")
    part = TEMPLATE_PARTS[name]
    clock = time.perf_counter()

    def lap():
        nonlocal clock
        seconds, clock = time.perf_counter() - clock, time.perf_counter()
        return seconds

    base = sensor_collection(part, seed, "same", args)
    model = cache.trained_model(base, root=args.cache, seed=seed, epochs=args.epochs)
    info = inspect_api.model_info(model)
    root = Path(args.work) / base.parent.name / ("defaults" + (f"_e{args.epochs}" if args.epochs else ""))
    print(f"{name}, seed {seed}: collection {base}, model {model} (trained in "
          f"{info['train_seconds'] or float('nan'):.0f} s; both ready after {lap():.0f} s here)", flush=True)
    inspect_api.calibrate_and_score(model, base, root / "same", maps="none", folds=False, progress=args.progress,
                                    echo=lambda line: print(f"  {name}: {line}"))
    runs, collections, seconds = {}, {}, {"calibrated_and_same_scored": lap()}
    for sensor in sensors:
        if sensor == "same":
            collections[sensor], runs[sensor] = str(base), str(root / "same")
        else:
            data = sensor_collection(part, seed, sensor, args)
            seconds[f"{sensor}_collection"] = lap()
            inspect_api.score_calibrated(root / "same" / "model.pt", data, root / sensor, progress=args.progress)
            seconds[f"{sensor}_scored"] = lap()
            collections[sensor], runs[sensor] = str(data), str(root / sensor)
        if args.site_scans:
            _site_run(root / "same" / "model.pt", part, seed, sensor, collections[sensor], root / (sensor + SITE), args)
            seconds[f"{sensor}{SITE}"] = lap()
            runs[sensor + SITE] = str(root / (sensor + SITE))
        r = run_row(runs[sensor])
        print(f"  {sensor}: AUROC {r['auroc']:.3f}, defective flagged {r['defective']:.3f}, good flagged "
              f"{r['good_text']}, gap {_signed(r['gap'])}, warning {_fired(r['warning'])}"
              + (f" (test scans {seconds[f'{sensor}_collection']:.0f} s, scored in {seconds[f'{sensor}_scored']:.0f} s)"
                 if sensor != "same" else f" (calibrated and scored in {seconds['calibrated_and_same_scored']:.0f} s)"),
              flush=True)
        if args.site_scans:
            r = run_row(runs[sensor + SITE])
            print(f"  {sensor}{SITE} (level from {args.site_scans} good scans of the sensor): AUROC {r['auroc']:.3f}, "
                  f"defective flagged {r['defective']:.3f}, good flagged {r['good_text']}, warning "
                  f"{_fired(r['warning'])} ({seconds[f'{sensor}{SITE}']:.0f} s)", flush=True)
    return {"tree": name, "seed": seed, "part": part, "model": str(model), "train_seconds": info["train_seconds"],
            "collections": collections, "runs": runs, "seconds": seconds}


# ------------------------------------------------------------------------------------------------ figures
def batch_warning(summary):
    """Whether a score summary's batch check ("these scans do not look like the calibration's") fired: True or
    False, None where the summary has no such check (summary.json's ``batch_check``: ``fired``, or one such dict per
    part type, any of which firing counts)."""
    check = summary.get("batch_check")
    if not isinstance(check, dict):
        return None
    if "fired" in check:
        return bool(check["fired"])
    parts = [one.get("fired") for one in check.values() if isinstance(one, dict) and "fired" in one]
    return any(parts) if parts else None


def run_row(run_dir):
    """One scored run's figures (see the module docstring) from its folder (``model.pt`` calibrated,
    ``results/summary.json``, ``results/scores.csv``)."""
    run_dir = Path(run_dir)
    summary = json.loads((run_dir / "results" / "summary.json").read_text())
    figures = inspect_api.summary_figures(summary)
    scored = inspect_api.read_scores(run_dir / "results")
    bad = scored["label"] != metrics.GOOD
    n_good = int((~bad).sum())
    good_flagged = int(scored["flagged"][~bad].sum())
    told = int((scored["verdict"][~bad] == "defective").sum())
    gap = inspect_api.calibration_gap(run_dir)
    threshold = figures["threshold"] or {}
    return {"auroc": metrics.auroc(bad, scored["score"]), "defective": float(scored["flagged"][bad].mean()),
            "good": good_flagged / max(n_good, 1), "n_good": n_good, "good_flagged": good_flagged,
            "good_told_defective": told, "good_text": f"{good_flagged} of {n_good}",
            "told_text": f"{told} of {n_good}", "alpha": figures["alpha"], "threshold": threshold.get("value"),
            "predicted_far": threshold.get("predicted_far"), "far_interval": threshold.get("far_interval"),
            "gap": gap.get("minus_held-back"), "gap_cross_fitted": gap.get("minus_cross-fitted"),
            "good_mean_log": gap["good_test_mean_log"], "warning": batch_warning(summary), "run": str(run_dir)}


def _from_record(path):
    """The table and targets of a recorded run of this suite, read again from its run folders (which must still be
    there)."""
    runs = json.loads(Path(path).read_text())["figures"]["runs"]
    return _report([dict(tree=r["tree"], seed=r["seed"], sensor=r["sensor"], **run_row(r["run"])) for r in runs])


def _signed(value):
    return "-" if value is None else f"{value:+.3f}"


def _fired(value):
    return {True: "fired", False: "no", None: "-"}[value]


def _rate(r):
    """The predicted false-alarm rate and its interval as text, '-' without one."""
    from inspection.threshold import format_rate

    if r.get("predicted_far") is None:
        return "-"
    lo, hi = r["far_interval"]
    return f"{format_rate(r['predicted_far'])} ({format_rate(lo)}-{format_rate(hi)})".replace(" %", "%")


def _report(rows):
    """Print the runs' table, the per-sensor summary and the targets of ``rows``; returns the suite's figures."""
    same = {(r["tree"], r["seed"]): r["good_mean_log"] for r in rows if r["sensor"] == "same"}
    for r in rows:
        base = same.get((r["tree"], r["seed"]))
        r["shift"] = None if base is None else r["good_mean_log"] - base
        r["far_text"] = _rate(r)
        r["warning_text"] = _fired(r["warning"])
    print()
    print(format_table(rows, [("tree", "tree", ""), ("sensor", "sensor", ""), ("seed", "seed", "d"),
                              ("auroc", "AUROC", ".3f"), ("defective", "def flagged", ".3f"),
                              ("good_text", "good flagged", ">"), ("told_text", "told defective", ">"),
                              ("alpha", "alpha", "g"), ("far_text", "pred. FAR (90% int.)", ">"),
                              ("gap", "gap held-back", "+.3f"), ("gap_cross_fitted", "gap cross-fitted", "+.3f"),
                              ("shift", "shift vs same", "+.3f"), ("warning_text", "warning", ">")]))
    print()
    print(format_table(_per_sensor(rows), [("sensor", "sensor", ""), ("runs", "runs", "d"),
                                           ("auroc", "mean AUROC", ".3f"), ("defective", "mean def flagged", ".3f"),
                                           ("good_text", "good flagged", ">"), ("told_text", "told defective", ">"),
                                           ("gap", "mean gap held-back", "+.3f"),
                                           ("shift", "mean shift vs same", "+.3f"), ("fired", "warnings", ">")]))
    targets = check_targets(rows)
    print()
    for line in targets["lines"]:
        print(line)
    return {"runs": [{k: v for k, v in r.items() if not k.endswith("_text")} for r in rows],
            "per_sensor": _per_sensor(rows), "targets": {k: v for k, v in targets.items() if k != "lines"}}


def _per_sensor(rows):
    """Per sensor over its runs: mean AUROC and defective flagged, good scans flagged and told defective in all,
    mean gap (held-back) and shift against ``same``, warnings fired (of the runs with a batch check)."""
    out = []
    for sensor in dict.fromkeys(r["sensor"] for r in rows):
        mine = [r for r in rows if r["sensor"] == sensor]
        checked = [r for r in mine if r["warning"] is not None]
        shifts = [r["shift"] for r in mine if r.get("shift") is not None]
        gaps = [r["gap"] for r in mine if r["gap"] is not None]
        n_good = sum(r["n_good"] for r in mine)
        out.append({"sensor": sensor, "runs": len(mine), "auroc": float(np.mean([r["auroc"] for r in mine])),
                    "defective": float(np.mean([r["defective"] for r in mine])),
                    "good_text": f"{sum(r['good_flagged'] for r in mine)} of {n_good}",
                    "told_text": f"{sum(r['good_told_defective'] for r in mine)} of {n_good}",
                    "gap": float(np.mean(gaps)) if gaps else None, "shift": float(np.mean(shifts)) if shifts else None,
                    "fired": f"{sum(bool(r['warning']) for r in checked)} of {len(checked)}" if checked else "-"})
    return out


def check_targets(rows):
    """The issue's targets over ``rows`` (dicts with tree, sensor, seed and :func:`run_row`'s keys). Returns a dict:
    ``false_alarms`` (template-calibrated runs with more than 1 of 16 good scans flagged, unless the warning fired and
    no good scan was told 'defective'), ``detection`` (those runs with AUROC at least ``TARGET_AUROC`` and no warning
    whose defective flagged falls below ``TARGET_DETECTION``), ``site`` (the '<sensor>+site' runs, whose level the
    sensor's own good scans set, with more than 1 of 16 good scans flagged or defective flagged below
    ``TARGET_DETECTION``: no excuse there) and ``lines``."""
    def label(r, text):
        return f"{r['tree']} {r['sensor']} seed {r['seed']} ({text})"

    site = [r for r in rows if r["sensor"].endswith(SITE)]
    rows = [r for r in rows if not r["sensor"].endswith(SITE)]
    false_alarms = [label(r, f"{r['good_text']}, {r['told_text']} told defective, warning {_fired(r['warning'])}")
                    for r in rows if r["good"] > TARGET_MAX_GOOD + 1e-9
                    and not (r["warning"] and r["good_told_defective"] == 0)]
    judged = [r for r in rows if r["auroc"] >= TARGET_AUROC and not r["warning"]]
    detection = [label(r, f"{r['defective']:.3f}") for r in judged if r["defective"] < TARGET_DETECTION]
    site_short = [label(r, f"{r['good_text']} good, {r['defective']:.3f} defective flagged") for r in site
                  if r["good"] > TARGET_MAX_GOOD + 1e-9 or r["defective"] < TARGET_DETECTION]
    lines = [f"targets (issue 47) over {len(rows)} template-calibrated runs:",
             f"  at most 1 of 16 good scans flagged, or the warning fired and none told defective: "
             f"{len(rows) - len(false_alarms)} of {len(rows)}" + (f"; over: {', '.join(false_alarms)}"
                                                                   if false_alarms else ""),
             f"  defective flagged >= {TARGET_DETECTION} where AUROC >= {TARGET_AUROC} and no warning: "
             f"{len(judged) - len(detection)} of {len(judged)}" + (f"; short: {', '.join(detection)}"
                                                                   if detection else "")]
    if site:
        lines.append(f"  the level from the sensor's own good scans ('{SITE}' runs): at most 1 of 16 good flagged and "
                     f"defective flagged >= {TARGET_DETECTION}: {len(site) - len(site_short)} of {len(site)}"
                     + (f"; short: {', '.join(site_short)}" if site_short else ""))
    return {"false_alarms": false_alarms, "detection": detection, "site": site_short, "lines": lines}
