"""The benchmark trees the issues' targets are checked on, and one run of one of them in a process of its own.

A tree is one run of a suite (``inspection``, ``inspection --templates`` or ``real``) with its options, per seed (the
tree's synthesis and its training; the real trees: ``--seed`` and ``--train-seed``). The ``verdicts`` suite runs
them at the defaults; the ``ablation`` suite with ``--trees`` runs them with the point scores taken apart.

Each run is ``python -m benchmarks SUITE ...`` in a process of its own (one thread; its output in ``WORK/logs/``,
its record in ``WORK/records/``, whose figures are read back): the suites stay independent of each other.
"""
import json
import os
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

# name -> (suite, its options); the trees: solid (fandisk, the bracket) and thin-walled parts (cup,
# enclosure), 5 degrees of placement jitter with --align, 8 training scans (+2 held back, 50 good test scans), the
# real bunny (2 degrees of per-scan pose change; half-depth defects), four complete templates (Real3D-AD layout)
TREES = {
    "fandisk": ("inspection", ["--parts", "fandisk"]),
    "bracket": ("inspection", ["--parts", "builtin"]),
    "cup": ("inspection", ["--parts", "cup"]),
    "enclosure": ("inspection", ["--parts", "enclosure"]),
    "bracket-jitter5-align": ("inspection", ["--parts", "builtin", "--jitter", "5", "--align"]),
    "fandisk-8train": ("inspection", ["--parts", "fandisk", "--train", "10", "--test-good", "50",
                                      "--per-defect", "4"]),
    "cup-8train": ("inspection", ["--parts", "cup", "--train", "10", "--test-good", "50", "--per-defect", "4"]),
    "bunny": ("real", []),
    "bunny-half-depth": ("real", ["--size", "0.5"]),
    "templates-bracket": ("inspection", ["--templates", "--parts", "builtin"]),
    "templates-fandisk": ("inspection", ["--templates", "--parts", "fandisk"]),
}


# the trees the sensor's rays are judged on (issue 46): real range scans whose sidecar origins are written as users
# write them (a nominal stand-off along the view's axis: 0.3 m where 1 m gives the sweep's near-parallel rays, or
# 3 m; the axis off by up to 5 degrees), half-depth defects and full ones, placed by hand; a virtual intricate part
# (the ogre: deep concavities, thin protrusions) seen by a pinhole camera whose origins are off by 0.5-3x the
# stand-off and 5 degrees, and by a line scanner (no single centre); half-size defects there (at full size every
# score ranks them perfectly); the thin-walled parts, with exact origins and with the pinhole's approximate ones
RAY_TREES = {
    "bunny-near-origins": ("real", ["--standoff", "0.3", "--origin-tilt", "5", "--size", "0.5"]),
    "bunny-near-origins-full": ("real", ["--standoff", "0.3", "--origin-tilt", "5"]),
    "bunny-far-origins": ("real", ["--standoff", "3", "--origin-tilt", "5", "--size", "0.5"]),
    "bunny-near-origins-placed": ("real", ["--standoff", "0.3", "--origin-tilt", "5", "--size", "0.5",
                                           "--jitter", "3", "--shift", "0.02", "--align"]),
    "ogre-pinhole-approx": ("inspection", ["--parts", "ogre", "--origin-standoff", "0.5,3", "--origin-tilt", "5",
                                           "--defect-size", "0.5"]),
    "ogre-line": ("inspection", ["--parts", "ogre", "--sensor", "line", "--defect-size", "0.5"]),
    "cup": TREES["cup"],
    "enclosure": TREES["enclosure"],
    "enclosure-approx": ("inspection", ["--parts", "enclosure", "--origin-standoff", "0.5,3", "--origin-tilt", "5"]),
}
THIN_WALLED = ("cup", "enclosure", "enclosure-approx")  # where missing material must be found (issue 46, item 3)


def add_tree_arguments(parser, trees, work):
    """A trees suite's options: ``--trees`` (names of ``trees``, default all), ``--seeds``, ``--jobs``, ``--cache``,
    ``--work`` (default ``work``) and ``--reuse``."""
    from benchmarks import cache

    parser.add_argument("--trees", default=",".join(trees), help="comma-separated tree names (default: all: "
                                                                 "%(default)s)")
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default: %(default)s)")
    parser.add_argument("--jobs", type=int, default=1, help="(tree, seed) runs at once, each a process (default 1)")
    parser.add_argument("--cache", default=cache.CACHE, help="collections and models (default: %(default)s)")
    parser.add_argument("--work", default=work, help="scored runs and logs (default: %(default)s)")
    parser.add_argument("--reuse", action="store_true",
                        help="a (tree, seed) whose record an earlier run of the same command left in WORK/records/ "
                             "is read, not run again (finishes a run that stopped partway)")


def check_names(names, who, trees=TREES):
    """``names`` (list of str) all known ``trees``, else SystemExit naming ``who`` (the suite) and the known ones."""
    unknown = [n for n in names if n not in trees]
    if unknown:
        raise SystemExit(f"{who}: unknown tree(s) {unknown}; known: {list(trees)}")


def tree_command(name, seed, cache_root, work, extra=(), trees=TREES):
    """The arguments after ``python -m benchmarks`` of tree ``name`` at ``seed``, and its log and records folder.

    ``extra``: more options for its suite, a list (every suite's) or {suite: list} (a suite not named gets none).
    Returns (argv list of str, log Path, records Path)."""
    suite, options = trees[name]
    if isinstance(extra, dict):
        extra = extra.get(suite, ())
    seeds = ["--seed", str(seed)] + (["--train-seed", str(seed)] if suite == "real" else [])
    slug = f"{slug_of(name)}_seed{seed}"
    log, records = Path(work) / "logs" / f"{slug}.log", Path(work) / "records" / slug
    argv = ["--records", str(records), suite, *options, *seeds, *map(str, extra), "--cache", str(cache_root),
            "--work", str(Path(work) / "runs" / suite)]
    return argv, log, records


def reusable_record(argv, records):
    """The newest record in ``records`` (a tree's folder) whose command is ``python -m benchmarks`` ``argv``, or
    None (no record, or only records of other commands); a :class:`benchmarks.results_doc.RecordError` naming a file
    there that is not a run record."""
    from benchmarks.record import command_line
    from benchmarks.results_doc import read_record

    suite = argv[argv.index("--records") + 2]
    for path in sorted(Path(records).glob(f"{suite}_*.json"), reverse=True):
        record = read_record(path)  # a file there that is not a record: a RecordError naming it
        if record.get("command") == command_line(argv):
            return record
    return None


def run_tree(name, seed, cache_root, work, extra=(), trees=TREES, reuse=False):
    """Run tree ``name`` of ``trees`` at ``seed`` (``extra``: more options for its suite, :func:`tree_command`) in a
    process of its own, its output to a log file. With ``reuse``, a record of the same command already in the tree's
    records folder is read instead (0 seconds). Returns (its record's figures, log path, seconds); a RuntimeError
    naming the log when the run fails."""
    argv, log, records = tree_command(name, seed, cache_root, work, extra, trees)
    if reuse:
        record = reusable_record(argv, records)
        if record is not None:
            return record["figures"], log, 0.0
    suite = argv[argv.index("--records") + 2]
    log.parent.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(records, ignore_errors=True)
    t0 = time.perf_counter()
    with open(log, "w") as out:
        done = subprocess.run([sys.executable, "-m", "benchmarks", *argv], stdout=out, stderr=subprocess.STDOUT,
                              env={**os.environ, "OMP_NUM_THREADS": "1"})
    found = sorted(records.glob(f"{suite}_*.json"))
    if done.returncode != 0 or not found:
        raise RuntimeError(f"{name}, seed {seed} failed (exit status {done.returncode}); see {log}")
    return json.loads(found[-1].read_text())["figures"], log, time.perf_counter() - t0


def run_trees(runs, cache_root, work, at_once=1, extra=(), done=None, trees=TREES, reuse=False):
    """:func:`run_tree` for each (name, seed) of ``runs`` (names of ``trees``), ``at_once`` processes at a time.
    ``done(name, seed, result)`` is called as each finishes, result being :func:`run_tree`'s (figures, log,
    seconds). Returns {(name, seed): result}."""
    results = {}
    with ThreadPoolExecutor(max(1, at_once)) as pool:  # threads that wait on one process each
        futures = {pool.submit(run_tree, name, seed, cache_root, work, extra, trees, reuse): (name, seed)
                   for name, seed in runs}
        for fut in as_completed(futures):
            results[futures[fut]] = fut.result()
            if done is not None:
                done(*futures[fut], results[futures[fut]])
    return results


def part_figures(name, figures, trees=TREES):
    """The figures of the tree's one part out of its suite's figures: the ``real`` suite's whole figures, else
    ``figures['parts'][part]``."""
    suite, options = trees[name]
    if suite == "real":
        return figures
    return figures["parts"][options[options.index("--parts") + 1]]


def slug_of(name):
    return "".join(c if c.isalnum() else "_" for c in name).strip("_")


def run_folders(work, match=""):
    """The run folders below ``work`` with a calibrated model and a scoring summary whose path contains one of the
    comma-separated texts of ``match`` (all when empty), sorted."""
    texts = [t for t in match.split(",") if t] or [""]
    return sorted(p.parent for p in Path(work).rglob("model.pt")
                  if (p.parent / "results" / "summary.json").is_file() and any(t in str(p.parent) for t in texts))
