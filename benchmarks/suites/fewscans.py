"""Few good scans (issue 48): what the defaults decide from 4, 8 and 16 good training scans, and which next good scans
help most.

Per part, number of training scans and seed: the synthetic collection (:func:`benchmarks.cache.synth_collection`
with ``round(n / 0.8)`` good scans, of which the trainer holds back a fifth for calibration: 4 + 1, 8 + 2, 16 + 4;
``--test-good`` good and ``--per-defect`` per defect type test scans from views like the training ones, 4,000
points), the model the inspection suite trains on it (the same cache), calibrated and scored as the README's path
does (:func:`benchmarks.inspect_api.calibrate_and_score`). Per run: object AUROC, the defective test scans flagged
(score above the threshold) and told ``uncertain``, the good ones told ``defective`` and ``uncertain``, the defects
on covered surface (at least half of a defect's labelled points covered by the good scans,
:func:`benchmarks.inspect_api.coverage_figures`) and the share of them flagged, the unflagged defective scans told
``uncertain`` with the coverage reason, and the nearest-neighbour baseline's AUROC.

``--loop``: the closed loop at ``--loop-scans`` (8) training scans: 4 good scans added from the views
``nsspr-inspect coverage`` proposes for the test scans (:func:`benchmarks.inspect_api.proposed_views`), from 4
random views drawn as the training views are, and from the 4 candidate views furthest from the training views
(greedy farthest-point over directions); each model trained again on the 12 with the same held-back scans and the
same test scans scored.

``--existing DIR``: no calibration or scoring here; the figures of the runs already scored under DIR (the same
layout, ``DIR/<collection>/defaults_nofolds`` or ``defaults_folds<K>``), e.g. by another checkout's inspection suite
(``--folds 0``): how "before" is read; the closed loop (``--loop``) then reads the runs its work folder holds.
"""
import time
from pathlib import Path

import numpy as np

from benchmarks import baselines, cache, inspect_api, metrics
from benchmarks.table import format_table

DESCRIPTION = ("few good scans (issue 48): AUROC, flagged, uncertain and the defects on covered surface at 4, 8 and "
               "16 training scans; --loop: 4 more good scans from proposed, random or furthest views")
WORK = "results/fewscans"
HELD_SHARE = 0.2  # the trainer's calibration_fraction: the collection holds n / (1 - HELD_SHARE) good scans
ADDED_VIEWS = 4
STRATEGIES = ("proposed", "random", "furthest")


def add_arguments(p):
    p.add_argument("--parts", default="fandisk,cup", help="comma-separated parts (default: %(default)s)")
    p.add_argument("--scans", default="4,8,16", help="good training scans, comma-separated (default: %(default)s)")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default: %(default)s)")
    p.add_argument("--test-good", type=int, default=16, help="good test scans (default: %(default)s)")
    p.add_argument("--per-defect", type=int, default=16, help="test scans per defect type (default: %(default)s)")
    p.add_argument("--loop", action="store_true", help="also the closed loop at --loop-scans training scans")
    p.add_argument("--loop-only", action="store_true", help="only the closed loop")
    p.add_argument("--loop-scans", type=int, default=8, help="training scans of the closed loop (default 8)")
    p.add_argument("--folds", default="auto", metavar="K",
                   help="calibrate with K fold models trained into the model (train_latent.py --calibration-folds "
                        "K; 0: none); default auto, the trainer's (one per training scan with few scans, else none)")
    p.add_argument("--existing", default=None, metavar="DIR",
                   help="read runs already scored under DIR instead of scoring them")
    p.add_argument("--cache", default=cache.CACHE, help="collections and models (default: %(default)s)")
    p.add_argument("--work", default=WORK, help="scored runs (default: %(default)s)")
    p.add_argument("--progress", action="store_true", help="progress bars")


def _ints(text, what):
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise SystemExit(f"fewscans: {what} takes whole numbers separated by commas, got {text!r}") from None


def run(args):
    parts, seeds = args.parts.split(","), _ints(args.seeds, "--seeds")
    figures = {"runs": [], "loop": []}
    if not args.loop_only:
        for part in parts:
            for n in _ints(args.scans, "--scans"):
                for seed in seeds:
                    figures["runs"].append(_one(part, n, seed, args))
        print()
        print(_table(figures["runs"]))
    if args.loop or args.loop_only:
        for part in parts:
            for seed in seeds:
                figures["loop"] += _loop(part, seed, args)
        print()
        print(_table(figures["loop"], loop=True))
        print(_loop_means(figures["loop"]))
    return figures


def _collection(part, n, seed, args):
    return cache.synth_collection(part, seed, root=args.cache, progress=args.progress,
                                  n_train=int(round(n / (1 - HELD_SHARE))), n_test_good=args.test_good,
                                  n_test_defective=args.per_defect, n_points=4000, jitter_deg=0.0)


def _folds(args, n):
    """The fold models of a model of ``n`` training scans: ``--folds`` or, for 'auto', the trainer's default."""
    if args.folds == "auto":
        return inspect_api.default_folds(n)
    try:
        return int(args.folds)
    except ValueError:
        raise SystemExit(f"fewscans: --folds takes a whole number or 'auto', got {args.folds!r}") from None


def _model(data, seed, args, n):
    return cache.trained_model(data, root=args.cache, seed=seed, epochs=None, calibration_fraction=None,
                               representation=None, lengthscale=None, width=None, depth=None, grid_mean=None,
                               calibration_folds=_folds(args, n) or None)


def _run_name(args, n):
    k = _folds(args, n)
    return f"defaults_folds{k}" if k else "defaults_nofolds"


def _one(part, n, seed, args):
    t0 = time.perf_counter()
    data = _collection(part, n, seed, args)
    model = _model(data, seed, args, n)
    root = Path(args.existing or args.work)
    run_dir = root / data.parent.name / _run_name(args, n)
    if not args.existing:
        inspect_api.calibrate_and_score(model, data, run_dir, progress=args.progress, folds=bool(_folds(args, n)),
                                        maps="none",
                                        echo=lambda line: print(f"  {part} {n} s{seed}: {line}"))
    row = dict(part=part, scans=n, seed=seed, **run_figures(run_dir, model, data))
    print(f"{part}, {n} training scans, seed {seed}: AUROC {row['auroc']:.3f}, defective flagged "
          f"{row['flagged']:.3f}, good told defective {row['good_defective']} of {row['n_good']} "
          f"({time.perf_counter() - t0:.0f} s)", flush=True)
    return row


def run_figures(run_dir, model, data):
    """The figures of one scored run (``run_dir/results/scores.csv``), the defects' coverage measured against the
    run's calibrated model (``run_dir/model.pt``; coverage at the default radius whatever the calibration scores
    with: :func:`benchmarks.inspect_api.coverage_figures`) and the nearest-neighbour baseline's AUROC on the same
    scans."""
    scored = inspect_api.read_scores(Path(run_dir) / "results")
    labels, verdict, flagged = scored["label"], scored["verdict"], scored["flagged"]
    bad = labels != metrics.GOOD
    coverage = inspect_api.coverage_figures(run_dir, data)
    on_covered = np.array([coverage["on_covered"].get(str(n), False) for n in scored["name"]])
    missed = bad & ~flagged
    why = scored.get("why")
    nn = baselines.nn_figures(data, coverage["heldback_names"], coverage["alpha"])
    covered_bad = bad & on_covered
    return {"auroc": metrics.auroc_per_defect(scored["score"], labels, scored["defect"])["overall"],
            "flagged": float(flagged[bad].mean()), "uncertain": int((verdict[bad] == "uncertain").sum()),
            "n_defective": int(bad.sum()), "good_defective": int((verdict[~bad] == "defective").sum()),
            "good_uncertain": int((verdict[~bad] == "uncertain").sum()), "n_good": int((~bad).sum()),
            "on_covered": int(covered_bad.sum()),
            "covered_flagged": float(flagged[covered_bad].mean()) if covered_bad.any() else float("nan"),
            "missed_uncertain": int((verdict[missed] == "uncertain").sum()), "missed": int(missed.sum()),
            "missed_not_covered": None if why is None else int(sum("not covered" in w for w in why[missed])),
            "nn_auroc": nn["auroc"]["overall"], "threshold": coverage["threshold"],
            "far_interval": coverage["far_interval"], "gap": inspect_api.calibration_gap(run_dir)}


def _table(rows, loop=False):
    flat = [{**r, "good": f"{r['good_defective']} / {r['good_uncertain']} of {r['n_good']}",
             "missed": f"{r['missed_uncertain']} of {r['missed']}", "covered": f"{r['on_covered']}",
             "what": r.get("strategy", r["scans"])} for r in rows]
    return format_table(flat, [("part", "part", ""), ("what", "added" if loop else "scans", ">"), ("seed", "seed", ">"),
                               ("auroc", "AUROC", ".3f"), ("nn_auroc", "NN", ".3f"), ("flagged", "def flagged", ".3f"),
                               ("uncertain", "def uncertain", ">"), ("good", "good def / unc", ">"),
                               ("covered", "defects on covered", ">"), ("covered_flagged", "of them flagged", ".3f"),
                               ("missed", "missed: uncertain", ">")])


def _loop_means(rows):
    lines = ["closed loop, mean over parts and seeds:"]
    for strategy in ("base",) + STRATEGIES:
        mine = [r for r in rows if r["strategy"] == strategy]
        if mine:
            lines.append(f"  {strategy:9s} AUROC {np.mean([r['auroc'] for r in mine]):.3f}, defective flagged "
                         f"{np.mean([r['flagged'] for r in mine]):.3f}, good told defective "
                         f"{sum(r['good_defective'] for r in mine)} of {sum(r['n_good'] for r in mine)}")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------- closed loop
def _loop(part, seed, args):
    """The closed loop of one part and seed: the base run and one run per strategy (rows with ``strategy``)."""
    n = args.loop_scans
    data = _collection(part, n, seed, args)
    model = _model(data, seed, args, n)
    base_dir = Path(args.work) / data.parent.name / _run_name(args, n)
    if not (base_dir / "results" / "scores.csv").exists():
        inspect_api.calibrate_and_score(model, data, base_dir, progress=args.progress, folds=bool(_folds(args, n)),
                                        maps="none")
    rows = [dict(part=part, scans=n, seed=seed, strategy="base", **run_figures(base_dir, model, data))]
    for strategy in STRATEGIES:
        t0 = time.perf_counter()
        if args.existing and not (Path(args.work) / "loop" / f"{data.parent.name}_{strategy}" / "tree.h5").exists():
            print(f"{part} s{seed} +{ADDED_VIEWS} {strategy}: not run (--existing reads what was run)", flush=True)
            continue
        grown = _grown_collection(part, seed, data, base_dir / "model.pt", strategy, args)
        grown_model = _model(grown, seed, args, n + ADDED_VIEWS)
        run_dir = grown.parent / _run_name(args, n + ADDED_VIEWS)
        if args.existing and not (run_dir / "results" / "scores.csv").exists():
            print(f"{part} s{seed} +{ADDED_VIEWS} {strategy}: not scored (--existing reads what was run)", flush=True)
            continue
        if not (run_dir / "results" / "scores.csv").exists():
            inspect_api.calibrate_and_score(grown_model, grown, run_dir, progress=args.progress,
                                            folds=bool(_folds(args, n + ADDED_VIEWS)), maps="none")
        row = dict(part=part, scans=n + ADDED_VIEWS, seed=seed, strategy=strategy,
                   **run_figures(run_dir, grown_model, grown))
        print(f"{part} s{seed} +{ADDED_VIEWS} {strategy}: AUROC {row['auroc']:.3f}, defective flagged "
              f"{row['flagged']:.3f} ({time.perf_counter() - t0:.0f} s)", flush=True)
        rows.append(row)
    return rows


def _grown_collection(part, seed, data, calibrated_model, strategy, args):
    """The base collection with ``ADDED_VIEWS`` good training scans from ``strategy``'s views, its held-back scans
    as the 'validation' split (so the grown model calibrates on the same ones). Written once under the work folder;
    returns its ``tree.h5``."""
    from datasets import Scan, ScanCollection
    from datasets.scanner import VirtualScanner

    folder = Path(args.work) / "loop" / f"{data.parent.name}_{strategy}"
    path = folder / "tree.h5"
    if path.exists():
        return path
    held = set(inspect_api.model_info(calibrated_model)["heldback_names"])
    with ScanCollection(data) as c:
        frame = c.frame
        scans = c.read_many(range(len(c)))
    training = [s for s in scans if s.split == "train" and s.name not in held]
    positions = _views(strategy, part, seed, data, calibrated_model, training, frame)
    mesh = cache.part_mesh(part)
    scanner = VirtualScanner(mesh)
    rng = np.random.default_rng([seed, 48])
    added = []
    for k, position in enumerate(positions):
        result = scanner.scan(frame.to_file(position[None])[0], look_at=scanner.center, noise=0.002 * scanner.diagonal,
                              n_points=4000, seed=rng)
        added.append(frame.apply(Scan(name=f"train/good/added{k}", points=result.points, normals=result.normals,
                                      split="train", label="good", sensor_origin=result.sensor_origin,
                                      extra={"pose": result.pose, "strategy": strategy})))
    for s in scans:
        if s.name in held:
            s.split = "validation"
    folder.mkdir(parents=True, exist_ok=True)
    ScanCollection.create(path, scans + added, frame=frame, provenance={"benchmark": "fewscans", "part": part,
                                                                        "seed": seed, "strategy": strategy},
                          overwrite=True)
    return path


def _views(strategy, part, seed, data, calibrated_model, training, frame):
    """``ADDED_VIEWS`` sensor positions (collection frame) for ``strategy``."""
    from datasets.scanner import VirtualScanner

    origins = np.array([s.sensor_origin for s in training], dtype=np.float64)
    points = np.vstack([s.points for s in training])
    center = (points.min(0) + points.max(0)) / 2
    standoff = float(np.median(np.linalg.norm(origins - center, axis=1)))
    if strategy == "proposed":
        positions = list(inspect_api.proposed_views(calibrated_model, data, ADDED_VIEWS, split="test"))
        while len(positions) < ADDED_VIEWS:  # nothing left to cover: the first view again
            positions.append(positions[0] if positions else center + standoff * np.array([0, 0, 1.0]))
        return np.array(positions)
    if strategy == "random":
        scanner = VirtualScanner(cache.part_mesh(part))
        rng = np.random.default_rng([seed, 4848])
        views = [scanner.random_view(seed=rng) for _ in range(ADDED_VIEWS)]
        return np.array([frame.to_collection(v.camera_position[None])[0] for v in views])
    directions = inspect_api.candidate_directions(256)
    have = (origins - center) / np.linalg.norm(origins - center, axis=1, keepdims=True)
    chosen = []
    for _ in range(ADDED_VIEWS):
        nearest = (directions @ np.vstack([have] + chosen).T).max(1)  # cosine to the nearest view so far
        chosen.append(directions[int(np.argmin(nearest))][None])
    return center + standoff * np.vstack(chosen)
