"""Where a training's time goes: seconds per stage of the trainer at its defaults (one torch thread), per part.

Each part's collection (the inspection suite's cached synthetic trees, :func:`benchmarks.cache.synth_collection`; a
stretched product family, :func:`benchmarks.cache.family_collection`; 'real': the real suite's bunny tree,
:func:`benchmarks.cache.real_tree`; any collection file given as ``--collection NAME=PATH``) is trained from scratch into ``--work`` with
:func:`autodecoder.latent.folds.train_collection_with_folds` with the trainer's one torch thread (what ``nsspr-train``
runs: 32 good scans, 26 trained on; the next step's targets are drawn beside it on another core, and the decisions'
registrations run on every core, :mod:`datasets.parallel`), once per value of
``--epochs`` ('default': the trainer's own; a number: that many, e.g. 450, the default before issue 51). The stages
come from the checkpoint's provenance (``autodecoder.latent.loop.TrainingState.info``): the family and pose
decisions, reading the scans, their GP targets, the epochs; ``other`` is the rest of the wall time (the checkpoint,
the log and its plot; the imports are done before the clock starts). Nothing is cached: every run trains.
"""
import time
from pathlib import Path

from benchmarks import cache
from benchmarks.table import format_table

DESCRIPTION = "seconds per stage of a training at the defaults (one torch thread), per part and epoch budget"
STAGES = ("family", "pose", "read", "targets", "epochs")


def add_arguments(p):
    p.add_argument("--parts", default="fandisk,cup,real,family",
                   help="comma-separated: a synthetic part (fandisk, cup, builtin, ...), 'real' (the real suite's "
                        "bunny tree of the seed) or 'family' (the bracket stretched 0.8-1.2) (default: %(default)s)")
    p.add_argument("--collection", action="append", default=[], metavar="NAME=PATH",
                   help="also train on this collection file, reported as NAME (repeatable; e.g. the real suite's "
                        "bunny tree: real=results/cache/real/<key>/bunny.h5)")
    p.add_argument("--seed", type=int, default=0, help="the trees' and the trainings' seed (default: %(default)s)")
    p.add_argument("--epochs", default="default",
                   help="comma-separated epoch budgets, each trained: 'default' (the trainer's) or a number "
                        "(default: %(default)s)")
    p.add_argument("--cache", default=cache.CACHE, help="the collections (default: %(default)s)")
    p.add_argument("--work", default="results/training", help="the trained models (default: %(default)s)")


def collection_of(part, seed, root):
    """The collection file a part's training reads (see the module docstring)."""
    if part == "real":
        try:
            return cache.real_tree(seed, root)
        except FileNotFoundError as exc:
            raise SystemExit(f"training: {exc}") from None
    if part == "family":
        return cache.family_collection("builtin", seed=seed, root=root)
    return cache.synth_collection(part, seed=seed, root=root)


def run(args):
    from autodecoder.latent.distributed import training_threads
    from autodecoder.latent.folds import train_collection_with_folds

    collections = [(part, collection_of(part, args.seed, args.cache)) for part in args.parts.split(",") if part]
    for given in args.collection:
        name, _, path = given.partition("=")
        if not path or not Path(path).is_file():
            raise SystemExit(f"--collection {given!r}: expected NAME=PATH of an existing collection file")
        collections.append((name, Path(path)))
    rows, figures = [], {"seed": args.seed, "runs": []}
    for part, data in collections:
        for budget in args.epochs.split(","):
            epochs = None if budget == "default" else int(budget)
            out = Path(args.work) / f"{part}_s{args.seed}_e{budget}" / "model.pt"
            out.parent.mkdir(parents=True, exist_ok=True)
            t0 = time.perf_counter()
            with training_threads(None):  # the trainer's one thread
                model = train_collection_with_folds(data, out, overwrite=True, quiet=True, seed=args.seed,
                                                    epochs=epochs)
            total = time.perf_counter() - t0
            info = model.info
            decisions = info.get("decision_seconds", {})
            stages = {"family": decisions.get("family", 0.0), "pose": decisions.get("pose", 0.0),
                      "read": info.get("read_seconds", 0.0), "targets": info.get("targets_seconds", 0.0),
                      "epochs": info.get("train_seconds", 0.0)}
            one = {"part": part, "collection": str(data), "epochs": budget, "epochs_run": int(model.config["epochs"]),
                   "scans": len(model.train_names), "seconds": total, "stages": stages,
                   "other": total - sum(stages.values()), "loss": float(info["history"][-1]["loss"]),
                   "family": model.family is not None, "model": str(out)}
            figures["runs"].append(one)
            rows.append({"part": part, "budget": f"{budget} ({one['epochs_run']})", "scans": one["scans"],
                         "total": total, **stages, "other": one["other"], "loss": one["loss"]})
            print(f"{part}, epochs {budget}: {total:.1f} s", flush=True)
    print(format_table(rows, [("part", "part", ""), ("budget", "epochs (run)", ""), ("scans", "scans", "d"),
                              ("total", "total s", ".1f"), *[(k, k, ".1f") for k in STAGES],
                              ("other", "other", ".1f"), ("loss", "final loss", ".4g")]))
    return figures
