"""The defaults taken apart: one trained model per part rescored with each point score and each aggregate.

Per part, the collection and model of the ``inspection`` suite (the same cache keys: the same seed and sizes give the
same files), then :func:`benchmarks.inspect_api.calibrate_and_score` once per setting: each point score the
inspection package offers at the default aggregate, and each aggregate of ``--aggregates`` at the default point
score (``--grid``: every pair), without the ray score unless ``--rays`` (so that the point score is measured alone).
Every score is the library's: nothing is re-implemented here. Printed per setting: object AUROC overall and per
defect type, the fractions of defective and good test scans flagged at alpha, the threshold's basis and predicted
false-alarm rate, seconds per scan.

``--trees``: issue 28's table, whether the model earns its keep: each named tree of :data:`benchmarks.trees.TREES`
(per seed of ``--seeds``, each a process of its own, ``--jobs`` at once) scored at the defaults and with each point
score of ``--point-scores`` alone (no ray score, one calibration each): the default, the field alone
(``distance``), the good scans' points alone (``surface``, no model), the paper's per-cloud NLL (``nll`` with the
``mean`` aggregate) and the nearest-neighbour baseline, object AUROC overall and per defect type, and the default's
point AUROC. Then the issue's targets per tree: field alone >= points alone; the default >= both; with 8 training
scans the default >= 0.90 and >= the baseline + 0.1; point AUROC >= 0.92.

(``--ray-gate``, the ``gated-log`` combination's gate re-evaluated offline, is retired with the rule: the rays are
judged by the ``rays`` suite, issue 46.)
"""
from pathlib import Path

from benchmarks import cache, inspect_api
from benchmarks.table import format_table, verdicts_table
from benchmarks.trees import TREES, check_names, part_figures, run_trees

DESCRIPTION = ("the same trained model rescored with each point score and aggregate of the inspection package "
               "(--grid: every pair); --trees: issue 28's table")
WORK = "results/ablation"
AGGREGATES = "top1,top2,top5,mean,q99"
# --trees: the terms of the default taken apart (issue 28): the field alone, the good points alone, the paper's NLL
TREE_POINT_SCORES = "distance,surface,nll:mean"
TREE_TARGETS = {"point_auroc": 0.92, "few_scans_auroc": 0.90, "few_scans_margin": 0.1}


def add_arguments(p):
    p.add_argument("--parts", default="fandisk,builtin", help="comma-separated parts (default: %(default)s); see "
                                                              "the inspection suite")
    p.add_argument("--seed", type=int, default=0, help="synthesis and training seed (default: %(default)s)")
    p.add_argument("--point-scores", default=None,
                   help="comma-separated point scores (default: every one the inspection package offers)")
    p.add_argument("--aggregates", default=AGGREGATES, help="comma-separated aggregates (default: %(default)s)")
    p.add_argument("--grid", action="store_true", help="every point score with every aggregate")
    p.add_argument("--rays", action="store_true", help="calibrate every setting with the ray score too")
    p.add_argument("--trees", default=None, metavar="NAMES",
                   help="issue 28's table on these trees of the verdicts suite ('all': every one but the template "
                        "trees; see the module docstring) instead of --parts")
    p.add_argument("--seeds", default="0", help="--trees: comma-separated seeds (default: %(default)s)")
    p.add_argument("--jobs", type=int, default=1, help="--trees: runs at once, each a process (default 1)")
    p.add_argument("--cache", default=cache.CACHE, help="collections and models (default: %(default)s)")
    p.add_argument("--work", default=WORK, help="scored runs (default: %(default)s)")
    p.add_argument("--progress", action="store_true", help="progress bars")


def settings(point_scores, aggregates, default_score, default_aggregate, grid=False):
    """The (point score, aggregate) pairs to score: every pair with ``grid``, else each point score at the default
    aggregate and each aggregate at the default point score (the defaults' pair once, first)."""
    if grid:
        return [(s, a) for s in point_scores for a in aggregates]
    pairs = [(default_score, default_aggregate)]
    pairs += [(s, default_aggregate) for s in point_scores if s != default_score]
    pairs += [(default_score, a) for a in aggregates if a != default_aggregate]
    return pairs


def run(args):
    if args.trees:
        return _trees(args)
    defaults = inspect_api.defaults()
    scores = args.point_scores.split(",") if args.point_scores else inspect_api.point_score_names()
    pairs = settings(scores, args.aggregates.split(","), defaults["point_score"], defaults["aggregate"], args.grid)
    figures, rows = {}, []
    for part in args.parts.split(","):
        data, model = _inputs(part, args)
        figures[part] = {}
        for point_score, aggregate in pairs:
            run_dir = Path(args.work) / data.parent.name / f"{point_score}_{aggregate}{'_rays' if args.rays else ''}"
            summary = inspect_api.calibrate_and_score(model, data, run_dir, rays=args.rays, point_score=point_score,
                                                      aggregate=aggregate, maps="none", progress=args.progress,
                                                      echo=None)
            one = inspect_api.summary_figures(summary)
            figures[part][f"{point_score}/{aggregate}"] = one
            rows.append(dict(part=part, method=f"{point_score}/{aggregate}" + (" +rays" if args.rays else ""), **one))
            print(f"{part}: {point_score}/{aggregate}: AUROC {one['auroc']['overall']:.3f}", flush=True)
    print()
    print(verdicts_table(rows))
    return {"parts": figures}


def _inputs(part, args):
    """The inspection suite's collection and model of ``part`` (same cache keys). Returns (tree.h5, model.pt)."""
    data = cache.synth_collection(part, args.seed, root=args.cache, progress=args.progress)
    return data, cache.trained_model(data, root=args.cache, seed=args.seed)


def _trees(args):
    names = [n for n in TREES if "--templates" not in TREES[n][1]] if args.trees == "all" else \
        [t.strip() for t in args.trees.split(",") if t.strip()]
    check_names(names, "ablation")
    if any("--templates" in TREES[n][1] for n in names):
        raise SystemExit("ablation: the template trees have no point scores taken apart (--point-scores does not go "
                         "with --templates)")
    jobs = [(name, int(seed)) for seed in args.seeds.split(",") for name in names]
    extra = ["--point-scores", TREE_POINT_SCORES]
    results = {}

    def done(name, seed, result):
        figures, log, seconds = result
        results[(name, seed)] = tree_rows(name, part_figures(name, figures))
        print(f"{name}, seed {seed}: done ({seconds:.0f} s; log {log})", flush=True)

    run_trees(jobs, args.cache, args.work, args.jobs, extra, done)
    rows = [dict(tree=name, seed=seed, **row) for name, seed in jobs for row in results[(name, seed)]]
    kinds = sorted({k for r in rows for k in r["auroc"] if k != "overall"})
    print()
    print(format_table([{**{k: v for k, v in r.items() if k != "auroc"}, "overall": r["auroc"].get("overall"),
                         **{k: r["auroc"].get(k) for k in kinds}} for r in rows],
                       [("tree", "tree", ""), ("seed", "seed", "d"), ("method", "method", ""),
                        ("overall", "AUROC", ".3f"), *[(k, k, ".3f") for k in kinds],
                        ("point_auroc", "point AUROC", ".3f")]))
    targets = tree_targets(rows)
    print()
    for line in targets["lines"]:
        print(line)
    return {"rows": rows, "targets": {k: v for k, v in targets.items() if k != "lines"}}


METHODS = {"default": "default", "distance": "field alone (distance)", "surface": "good points alone (surface)",
           "nll:mean": "paper's NLL (nll, mean)", "nn": "nearest-neighbour"}


def tree_rows(name, one):
    """The table's rows of one tree's part figures: dicts with ``method`` (a value of METHODS), ``auroc`` (overall
    and per defect type) and ``point_auroc`` (None where not measured: the real suite's baseline)."""
    suite, options = TREES[name]
    if suite == "real":
        default, nn = one["verdicts"][0], {"auroc": one["nn"]}
    else:
        default, nn = one["toolkit_nofolds"], one["nn"]
    rows = [{"method": "default", "auroc": default["auroc"], "point_auroc": default.get("point_auroc")}]
    for spec, figures in (one.get("point_scores") or {}).items():
        rows.append({"method": spec, "auroc": figures["auroc"], "point_auroc": figures.get("point_auroc")})
    rows.append({"method": "nn", "auroc": nn["auroc"], "point_auroc": nn.get("point_auroc")})
    for r in rows:
        r["method"] = METHODS.get(r["method"], r["method"])
    return rows


def few_training_scans(tree):
    """Whether a tree trains on a handful of good scans (``--train`` at most 10: 8 trained on, 2 held back)."""
    options = TREES[tree][1]
    return "--train" in options and int(options[options.index("--train") + 1]) <= 10


def tree_targets(rows):
    """Issue 28's targets over the table's rows (dicts: tree, seed, method (METHODS' values), auroc, point_auroc).
    Returns ``misses`` (one line each) and ``lines`` (the printed verdict)."""
    by_run = {}
    for r in rows:
        by_run.setdefault((r["tree"], r["seed"]), {})[r["method"]] = r
    misses = []
    for (tree, seed), m in by_run.items():
        auc = {k: v["auroc"]["overall"] for k, v in m.items()}
        field, points, default = (auc.get(METHODS[k]) for k in ("distance", "surface", "default"))
        where = f"{tree} seed {seed}"
        if field is not None and points is not None:
            if field < points:
                misses.append(f"{where}: field alone {field:.3f} < good points alone {points:.3f}")
            if default < max(field, points):
                misses.append(f"{where}: default {default:.3f} < max of the two {max(field, points):.3f}")
        if few_training_scans(tree):
            nn = auc[METHODS["nn"]]
            if default < TREE_TARGETS["few_scans_auroc"] or default < nn + TREE_TARGETS["few_scans_margin"]:
                misses.append(f"{where}: with 8 training scans default {default:.3f} (target >= "
                              f"{TREE_TARGETS['few_scans_auroc']} and >= nearest-neighbour {nn:.3f} + "
                              f"{TREE_TARGETS['few_scans_margin']})")
        point = m[METHODS["default"]].get("point_auroc")
        if point is not None and point < TREE_TARGETS["point_auroc"]:
            misses.append(f"{where}: default point AUROC {point:.3f} < {TREE_TARGETS['point_auroc']}")
    lines = [f"issue 28's targets over {len(by_run)} runs: {len(misses)} missed"] + [f"  {x}" for x in misses]
    return {"misses": misses, "lines": lines}
