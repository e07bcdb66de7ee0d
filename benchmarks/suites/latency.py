"""Where a scan's inspection time goes: seconds per scan and per stage at the defaults, one torch thread.

The built-in part's cached synthetic collection (:func:`benchmarks.cache.synth_collection`, 4,000-point scans) and
its model trained with the defaults (:func:`benchmarks.cache.trained_model`), calibrated once
(``inspection.Inspector(model).fit(collection)``, :func:`benchmarks.inspect_api.fit_inspector`); then every timed
scan goes through ``Inspector.inspect`` with its stage timings (:func:`benchmarks.inspect_api.timed_inspect`):
sample (a scan denser than the training scans is scored on a random subset at their density,
:mod:`inspection.resolution`), load, projection, field quantities, grazing factors, stray points, reference (the
joint point scores), aggregate, rays, combine; then the anomaly map of every point (what a PLY map shows), timed
apart, and how many points were scored. Each point count of ``--points`` other than 4,000 gets its own cached
collection of the same part and seed (the same frame; ``--scans`` test scans of it are timed under the same
calibration). Beside it the nearest-neighbour baseline's seconds per scan (:func:`benchmarks.baselines.nn_baseline`,
on the model's training scans' points). One warm-up scan per size is not counted. The process's peak resident memory
is printed after the calibration and after each size's inspections (before its baseline's: whether a
full-resolution scan stays within what the calibration needed). ``--before``: the sizes whose scans were thinned,
scored again on every point (:func:`benchmarks.inspect_api.every_point_scored`), after every size at the defaults.
Then the throughput of ``python -m inspection score --jobs N`` over the 4,000-point test split for each ``--jobs`` N
(:func:`benchmarks.inspect_api.scoring_seconds`: wall time of the whole command, worker start-up included, and
whether every N gave the same scores).
"""
import time

import numpy as np

from benchmarks import baselines, cache, inspect_api
from benchmarks.table import format_table

DESCRIPTION = ("seconds per scan and per stage of Inspector.inspect at the defaults (one thread), 4,000, 30,000 and "
               "1,000,000 points, next to the nearest-neighbour baseline")
STAGES = ("sample", "load", "projection", "field", "grazing", "stray", "reference", "aggregate", "rays", "combine")


def add_arguments(p):
    p.add_argument("--part", default="builtin", help="the part (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="synthesis and training seed (default: %(default)s)")
    p.add_argument("--points", default="4000,30000,1000000",
                   help="comma-separated points per scan; 4000 is the training collection (default: %(default)s)")
    p.add_argument("--scans", type=int, default=12,
                   help="test scans timed per size, spread over the test split (default: %(default)s)")
    p.add_argument("--large-scans", type=int, default=4,
                   help="test scans of each other size's collection: good and defective, per defect type "
                        "(default: %(default)s good, 1 per defect type)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s)")
    p.add_argument("--cache", default=cache.CACHE, help="collections and models (default: %(default)s)")
    p.add_argument("--jobs", default="1,2",
                   help="throughput: the test split scored by `python -m inspection score --jobs N` for each N "
                        "(comma-separated; 'none': skip; default: %(default)s)")
    p.add_argument("--work", default="results/latency", help="the throughput runs' folder (default: %(default)s)")
    p.add_argument("--before", action="store_true",
                   help="also every size whose scans were thinned to the training density, scored on every point "
                        "as before (after the defaults' runs: the peak memory then is the larger of the two)")
    p.add_argument("--progress", action="store_true", help="progress bars")


def _spread(indices, n):
    indices = list(indices)
    if len(indices) <= n:
        return indices
    return [indices[i] for i in np.linspace(0, len(indices) - 1, n).round().astype(int)]


def _peak_rss_mb():
    """The process's peak resident memory so far (MB): after the calibration, then after each size's scans (a
    size that needs more than all before it raises it)."""
    import resource
    import sys

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0 if sys.platform == "darwin" else 1024.0)  # bytes on macOS, kB on Linux


def _time_scans(insp, scans):
    """Per scan: score and timings (a warm-up scan first, not counted)."""
    inspect_api.timed_inspect(insp, scans[0])
    return [inspect_api.timed_inspect(insp, s) for s in scans]


def _size_figures(timed, scans, nn_seconds, scored_as):
    """One size's figures from its scans' :func:`benchmarks.inspect_api.timed_inspect` results."""
    stages = {k: float(np.mean([t.get(k, 0.0) for _, _, t in timed])) for k in STAGES}
    total = [t["total"] for _, _, t in timed]
    return {"scans": len(scans), "points": float(np.mean([len(s.points) for s in scans])), "scored_as": scored_as,
            "points_scored": float(np.mean([t["points_scored"] for _, _, t in timed])),
            "seconds_per_scan": float(np.mean(total)), "seconds_max": float(np.max(total)), "stages": stages,
            "other": float(np.mean(total) - sum(stages.values())),
            "map_seconds": float(np.mean([t["map"] for _, _, t in timed])), "nn_seconds_per_scan": nn_seconds,
            "scores": {s.name: v for s, (v, _, _) in zip(scans, timed)}, "peak_rss_mb": _peak_rss_mb()}


def run(args):
    import torch

    from datasets import ScanCollection

    torch.set_num_threads(args.threads)
    sizes = [int(v) for v in args.points.split(",")]
    data = cache.synth_collection(args.part, seed=args.seed, root=args.cache, progress=args.progress)
    model = cache.trained_model(data, root=args.cache, seed=args.seed)
    info = inspect_api.model_info(model)
    t0 = time.perf_counter()
    insp = inspect_api.fit_inspector(model, data, progress=args.progress)
    calibrate_seconds = time.perf_counter() - t0
    figures_peak = _peak_rss_mb()
    with ScanCollection(data) as c:
        names = c.names
        train_points = np.concatenate([s.points for s in c.read_many(
            [i for i in c.select(split="train") if names[i] not in set(info["heldback_names"])])])
    figures = {"part": args.part, "threads": args.threads, "calibrate_seconds": calibrate_seconds,
               "peak_rss_mb_after_calibration": figures_peak, "sizes": {}}
    rows, measured = [], []
    for n in sizes:  # at the defaults first (the peak memory after each size is then its own)
        if n == cache.COLLECTION_DEFAULTS["n_points"]:
            path = data
        else:
            path = cache.synth_collection(args.part, seed=args.seed, root=args.cache, progress=args.progress,
                                          n_points=n, n_train=4, n_test_good=args.large_scans, n_test_defective=1)
        with ScanCollection(path) as c:
            scans = c.read_many(_spread(c.select(split="test"), args.scans))
        one = _size_figures(_time_scans(insp, scans), scans, None, "defaults")  # its peak memory before the baseline's
        t_nn = time.perf_counter()
        baselines.nn_baseline(train_points, scans)
        one["nn_seconds_per_scan"] = nn_seconds = (time.perf_counter() - t_nn) / len(scans)
        figures["sizes"][str(n)] = one
        measured.append((n, scans, nn_seconds, one))
    if args.before:  # then every point of the thinned sizes scored, as before dense scans were thinned
        with inspect_api.every_point_scored():
            for n, scans, nn_seconds, one in measured:
                if one["points_scored"] < one["points"]:
                    figures["sizes"][f"{n} every point"] = _size_figures(_time_scans(insp, scans), scans, nn_seconds,
                                                                         "every point (before)")
    for f in figures["sizes"].values():
        rows.append({"points": f"{f['points']:,.0f}", "scored": f"{f['points_scored']:,.0f}", "as": f["scored_as"],
                     "scans": f["scans"], "s/scan": f["seconds_per_scan"], "max": f["seconds_max"],
                     **{k: f["stages"][k] for k in STAGES}, "other": f["other"], "map": f["map_seconds"],
                     "NN s/scan": f["nn_seconds_per_scan"], "peak MB": f["peak_rss_mb"]})
    print(f"{args.part}, seed {args.seed}: calibrated in {calibrate_seconds:.1f} s (peak memory then "
          f"{figures_peak:.0f} MB); seconds per scan and per stage, {args.threads} torch thread(s); peak MB: the "
          f"process's peak resident memory after each size's scans")
    columns = [("points", "points", ""), ("scored", "scored", ""), ("as", "scored as", ""), ("scans", "scans", "d"),
               ("s/scan", "s/scan", ".3f"),
               ("max", "max", ".3f")] + [(k, k, ".3f") for k in STAGES] + \
        [("other", "other", ".3f"), ("map", "map", ".3f"), ("NN s/scan", "NN s/scan", ".4f"),
         ("peak MB", "peak MB", ".0f")]
    print(format_table(rows, columns))
    if args.jobs != "none":
        jobs = [int(v) for v in args.jobs.split(",")]
        throughput = inspect_api.scoring_seconds(model, data, args.work, jobs, progress=args.progress)
        first = throughput["jobs"][str(jobs[0])]["scores"]
        throughput["same_scores"] = all(np.array_equal(one["scores"], first, equal_nan=True)
                                        for one in throughput["jobs"].values())
        figures["throughput"] = throughput
        print(f"throughput, {throughput['scans']} test scans of {cache.COLLECTION_DEFAULTS['n_points']:,} points "
              f"through `score --maps none` (calibrated in {throughput['calibration_seconds']:.1f} s); the same "
              f"scores with every N: {throughput['same_scores']}")
        print(format_table([{"jobs": n, "seconds": one["seconds"], "scans/s": one["scans_per_second"]}
                            for n, one in throughput["jobs"].items()],
                           [("jobs", "--jobs", ""), ("seconds", "seconds", ".1f"), ("scans/s", "scans/s", ".2f")]))
    return figures
