"""Whether the sensor's rays ever cost a verdict (issue 46): the defaults next to the point score alone, on sensors
as users have them.

Each tree of :data:`benchmarks.trees.RAY_TREES` is one run of another suite at the defaults (``real`` or
``inspection``), per seed (the tree's synthesis and its training; the real trees: ``--seed`` and ``--train-seed``),
in a process of its own (:func:`benchmarks.trees.run_trees`). From each run's ``scores.csv``, printed per tree and
seed: object AUROC at the defaults, of the point score alone and of the ray score alone (the two columns the
default combines, from the same calibration: ``score_points``, ``score_rays``), the defaults' AUROC on missing
material, the fractions of defective and of good test scans flagged (score above the threshold, ``uncertain``
included) and how many of them were told ``defective``, the points-alone oracle (the defective scans a
threshold just above the worst good scan's point score flags), the defective scans the point score alone flags at
its own calibrated threshold (the same calibration scans' point scores: what ``--no-rays`` gives; where the defaults
miss the oracle and this misses as much, the miss is the threshold's calibration, not the rays'), and the rays'
false accusations: the good test
scans' largest ray score (nats, as the field gives it), their largest ray evidence as the calibration weighs it
(``ray_nats``, with how many good scans had any) and the share of all rays that passed through their own scan's
surface (``rays_through``: how far off the sidecar origins are). Then the issue's targets: the default at least the
points alone - 0.005 on every run; defective flagged within 0.05 of the points-alone oracle wherever that oracle is
at least 0.9, with at most 1 of 16 good scans flagged; missing material at least 0.9 on the thin-walled trees
(:data:`benchmarks.trees.THIN_WALLED`).

About 3-5 minutes a run on 2 shared cores when the tree and model are not cached, 1-2 when they are.
"""
import numpy as np

from benchmarks import inspect_api, metrics
from benchmarks.table import format_table
from benchmarks.trees import RAY_TREES, THIN_WALLED, add_tree_arguments, check_names, part_figures, run_trees

DESCRIPTION = ("whether the sensor's rays ever cost a verdict (issue 46): the defaults next to the point score "
               "alone and the rays alone, on real and virtual trees with approximate sensor origins, a line scanner "
               "and thin walls, per seed")
WORK = "results/rays"

TARGET_AUROC_LOSS = 0.005  # the default may rank at most this much below the point score alone
TARGET_ORACLE = 0.9  # where the points-alone oracle reaches this ...
TARGET_ORACLE_GAP = 0.05  # ... defective flagged within this of it
TARGET_MAX_GOOD = 1 / 16  # at most this share of good scans flagged
TARGET_MISSING = 0.9  # missing material's AUROC on the thin-walled trees


def add_arguments(p):
    add_tree_arguments(p, RAY_TREES, WORK)
    p.add_argument("--from-record", default=None, metavar="RECORD",
                   help="no runs: the table of a recorded run of this suite, read again from its run folders")


def run(args):
    if args.from_record:
        return _from_record(args.from_record)
    names = [t.strip() for t in args.trees.split(",") if t.strip()]
    check_names(names, "rays", RAY_TREES)
    seeds = [int(s) for s in args.seeds.split(",")]
    jobs = [(name, seed) for seed in seeds for name in names]
    results = {}

    def done(name, seed, result):
        results[(name, seed)] = run_figures(name, *result)
        r = results[(name, seed)]
        print(f"{name}, seed {seed}: default {r['auroc']:.3f}, points alone {r['points_alone']:.3f}, rays alone "
              f"{r['rays_alone']:.3f}, defective flagged {r['defective']:.3f}, good flagged {r['good_text']}, "
              f"points-alone oracle {r['points_oracle']:.3f} ({r['seconds']:.0f} s; log {r['log']})", flush=True)

    run_trees(jobs, args.cache, args.work, args.jobs, done=done, trees=RAY_TREES, reuse=args.reuse)
    return _report([dict(tree=name, seed=seed, **results[(name, seed)]) for name, seed in jobs])


def _from_record(path):
    """The table and targets of a recorded run of this suite, read again from its run folders (which must still
    be there): the same figures, with the columns of today's suite."""
    import json

    runs = json.loads(open(path).read())["figures"]["runs"]
    return _report([dict(tree=r["tree"], seed=r["seed"], **run_row(r["run"], r.get("log", ""), r.get("seconds")))
                    for r in runs])


def _report(rows):
    """Print the table and the targets of ``rows``; returns the suite's figures."""
    for r in rows:  # the rays' false accusations: the good test scans' largest evidence, and how many had any
        r["good_nats_text"] = "-" if np.isnan(r["good_nats"]) else f"{r['good_nats']:.1f} ({r['good_accused']})"
    print()
    print(format_table(rows, [("tree", "tree", ""), ("seed", "seed", "d"), ("auroc", "default", ".3f"),
                              ("points_alone", "points alone", ".3f"), ("rays_alone", "rays alone", ".3f"),
                              ("missing", "missing", ".3f"), ("defective", "def flagged", ".3f"),
                              ("defective_rejected", "of them 'defective'", ".3f"),
                              ("good_text", "good flagged", ">"), ("rejected_text", "of them 'defective'", ">"),
                              ("points_oracle", "points-alone oracle", ".3f"),
                              ("points_flagged", "points alone flagged", ".3f"),
                              ("good_rays_max", "good scans' rays (nats)", ".1f"),
                              ("good_nats_text", "their evidence", ">"), ("rays_through", "through own", ".3f")]))
    targets = check_targets(rows)
    print()
    for line in targets["lines"]:
        print(line)
    return {"runs": rows, "targets": {k: v for k, v in targets.items() if k != "lines"}}


def run_figures(name, figures, log, seconds):
    """One run's row (see the module docstring) from its suite's figures (:func:`benchmarks.trees.run_tree`)."""
    one = part_figures(name, figures, RAY_TREES)
    return run_row(one.get("run") or one["run_nofolds"], log, seconds)


def run_row(run_dir, log="", seconds=float("nan")):
    """One run's row from its folder (``model.pt`` calibrated, ``results/scores.csv``)."""
    from pathlib import Path

    run_dir = Path(run_dir)
    scored = inspect_api.read_scores(run_dir / "results")
    labels, defects = scored["label"], scored["defect"]
    bad = labels != metrics.GOOD
    points = scored.get("score_points", scored["score"])
    rays = scored.get("score_rays")
    auroc = metrics.auroc_per_defect(scored["score"], labels, defects)
    n_good = int((~bad).sum())
    good_flagged = int(scored["flagged"][~bad].sum())
    # the point score alone at its own calibrated threshold (the same calibration scans): what the rays are judged
    # against, apart from the threshold's own calibration
    alone = points > inspect_api.points_alone_threshold(run_dir / "model.pt")
    good_rejected = int((scored["verdict"][~bad] == "defective").sum())
    nats = scored.get("ray_nats")  # (runs before the rays were weighed by good scans have none)
    return {"auroc": auroc["overall"], "missing": auroc.get("missing", np.nan),
            "good_nats": np.nan if nats is None else float(np.nanmax(nats[~bad])),
            "good_accused": np.nan if nats is None else int((nats[~bad] > 0).sum()),
            "good_rays_max": np.nan if rays is None else float(np.nanmax(rays[~bad])),
            "rays_through": float(np.nanmean(scored["rays_through"])) if "rays_through" in scored else np.nan,
            "points_alone": metrics.auroc(bad, points),
            "rays_alone": np.nan if rays is None else metrics.auroc(bad, rays),
            "defective": float(scored["flagged"][bad].mean()),
            "defective_rejected": float((scored["verdict"][bad] == "defective").mean()),
            "good": good_flagged / max(n_good, 1), "n_good": n_good,
            "good_text": f"{good_flagged} of {n_good}", "rejected_text": f"{good_rejected} of {n_good}",
            "points_oracle": metrics.oracle_flagged(points, labels), "oracle": metrics.oracle_flagged(scored["score"],
                                                                                                      labels),
            "points_flagged": float(alone[bad].mean()), "points_good": int(alone[~bad].sum()),
            "rays": rays is not None, "run": str(run_dir), "seconds": seconds, "log": str(log)}


def check_targets(rows):
    """The issue's targets over ``rows`` (dicts with tree, seed and :func:`run_figures`' keys). Returns a dict:
    ``ranking`` (runs where the default ranks more than ``TARGET_AUROC_LOSS`` below the points alone),
    ``detection`` (runs whose points-alone oracle is at least ``TARGET_ORACLE`` and whose defective flagged falls
    more than ``TARGET_ORACLE_GAP`` short of it), ``calibration`` (those of them where the point score alone at its
    own calibrated threshold flags no more defective scans than the defaults: the miss is the threshold's
    calibration, not the rays'), ``false_alarms`` (runs judged for detection with more than 1 of 16 good scans
    flagged), ``missing`` (thin-walled runs below ``TARGET_MISSING`` on missing material) and ``lines``."""
    def label(r, text):
        return f"{r['tree']} seed {r['seed']} ({text})"

    ranking = [label(r, f"{r['auroc']:.3f} vs {r['points_alone']:.3f}") for r in rows
               if r["auroc"] < r["points_alone"] - TARGET_AUROC_LOSS]
    judged = [r for r in rows if r["points_oracle"] >= TARGET_ORACLE]
    detection = [label(r, f"{r['defective']:.3f} vs oracle {r['points_oracle']:.3f}") for r in judged
                 if r["defective"] < r["points_oracle"] - TARGET_ORACLE_GAP]
    false_alarms = [label(r, r["good_text"]) for r in judged if r["good"] > TARGET_MAX_GOOD + 1e-9]
    # of the detection misses, those where the point score alone at its own calibrated threshold misses as much: the
    # threshold's calibration, not the rays
    calibration = [m for m, r in zip(detection, [r for r in judged if r["defective"] < r["points_oracle"]
                                                 - TARGET_ORACLE_GAP])
                   if r.get("points_flagged", np.nan) <= r["defective"] + 1e-9]
    missing = [label(r, f"{r['missing']:.3f}") for r in rows
               if r["tree"] in THIN_WALLED and not r["missing"] >= TARGET_MISSING]
    lines = [f"targets (issue 46) over {len(rows)} runs:",
             f"  default >= points alone - {TARGET_AUROC_LOSS}: {len(rows) - len(ranking)} of {len(rows)}"
             + (f"; short: {', '.join(ranking)}" if ranking else ""),
             f"  defective flagged within {TARGET_ORACLE_GAP} of the points-alone oracle where it is >= "
             f"{TARGET_ORACLE}: {len(judged) - len(detection)} of {len(judged)}"
             + (f"; short: {', '.join(detection)}" if detection else ""),
             f"    of them where the point score alone, at its own calibrated threshold, flags no more (the "
             f"threshold's calibration, not the rays): {len(calibration)}"
             + (f" ({', '.join(m.split(' (')[0] for m in calibration)})" if calibration else ""),
             f"  at most 1 of 16 good scans flagged there: {len(judged) - len(false_alarms)} of {len(judged)}"
             + (f"; over: {', '.join(false_alarms)}" if false_alarms else ""),
             f"  missing material >= {TARGET_MISSING} on the thin-walled trees: "
             f"{sum(r['tree'] in THIN_WALLED for r in rows) - len(missing)} of "
             f"{sum(r['tree'] in THIN_WALLED for r in rows)}" + (f"; short: {', '.join(missing)}" if missing else "")]
    return {"ranking": ranking, "detection": detection, "calibration": calibration, "false_alarms": false_alarms,
            "missing": missing, "lines": lines}
