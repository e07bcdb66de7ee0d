"""Real range scans: a benchmark built from the Stanford bunny's ten Cyberware views, scored at the defaults.

The tree (built once, cached by its parameters: ``benchmarks.cache``) comes from ``../shared/realscans/bunny/`` (ten
real range images in metres, ``bun.conf`` aligning them: :mod:`benchmarks.suites.real.reading`), in the layout the
datasets importer reads, every scan one real view with defects made in its real points
(:mod:`benchmarks.suites.real.tree`).

The run: the tree imported (``datasets.importer.import_tree``, as ``python -m datasets import``), a model trained
with the trainer's defaults (``benchmarks.cache.trained_model``), scored the README's way on an uncalibrated copy
(``benchmarks.inspect_api.calibrate_and_score``, ``--maps all``: :mod:`benchmarks.suites.real.scoring`). Printed:
object AUROC per defect type and overall next to the nearest-neighbour baseline, and that of the default's two terms
alone (the point score, the ray score, from the same run's scores.csv), the fractions of good and defective test
scans flagged at the calibrated default, seconds per scan. ``--diagnose`` then reads the run's per-point scores (the
inspection API, as ``score`` computes them) and prints what the worst points of the good scans are (border,
grazing, sparse, stray, rarely covered by training), with pictures in the run's ``diagnosis/``
(:mod:`benchmarks.suites.real.diagnosis`).
"""
from pathlib import Path

from benchmarks import cache, inspect_api, options
from benchmarks.suites.real.diagnosis import diagnose
from benchmarks.suites.real.reading import BUNNY, SENSOR_DISTANCE
from benchmarks.suites.real.scoring import score
from benchmarks.suites.real.tree import real_collection

DESCRIPTION = ("real range scans: a benchmark tree from the Stanford bunny's ten Cyberware views with defects made "
               "in the real points, trained and scored at the defaults, next to the nearest-neighbour baseline")
WORK = "results/real"


def add_arguments(p):
    p.add_argument("--source", default=str(BUNNY), help="the range scans and bun.conf (default: %(default)s)")
    p.add_argument("--train", type=int, default=32, help="good training scans (default: %(default)s)")
    p.add_argument("--test-good", type=int, default=16, help="good test scans (default: %(default)s)")
    p.add_argument("--per-defect", type=int, default=16, help="test scans per defect type (default: %(default)s)")
    p.add_argument("--points", type=int, default=4000, help="points per scan (default: %(default)s)")
    p.add_argument("--jitter", type=float, default=2.0, help="pose change, degrees (default: %(default)s)")
    p.add_argument("--shift", type=float, default=0.0, help="and a shift of up to this fraction of the part's "
                                                            "diagonal, per scan (parts placed by hand; default none)")
    options.add_align_options(p)
    p.add_argument("--standoff", type=float, default=SENSOR_DISTANCE,
                   help="the sensor origin the sidecars record: this many metres along the view's axis from the "
                        "view's centre, as a user writes a nominal stand-off (default %(default)s: the sweep's "
                        "near-orthographic rays; the defects are made with that one either way)")
    p.add_argument("--origin-tilt", type=float, default=0.0, metavar="DEG",
                   help="and the recorded axis turned by up to DEG degrees per scan (default: none)")
    p.add_argument("--strays", type=int, default=4, help="up to this many spurious returns on half the scans "
                                                         "(default: %(default)s)")
    p.add_argument("--size", type=float, default=1.0, help="defect size factor on datasets.defects' ranges")
    p.add_argument("--seed", type=int, default=0, help="the tree's seed (default: %(default)s)")
    p.add_argument("--train-seed", type=int, default=0, help="the training's seed (default: %(default)s)")
    p.add_argument("--epochs", type=int, default=None, help="training epochs (default: the trainer's)")
    p.add_argument("--representation", choices=("siren", "grid"), default=None,
                   help="the latent model's representation (default: the trainer's)")
    p.add_argument("--no-rays", action="store_true", help="calibrate without the ray score (default: the "
                                                          "inspection's choice: with it, the scans have sensor origins)")
    p.add_argument("--diagnose", action="store_true", help="also the per-point analysis and pictures of the run")
    options.add_calibration_options(p, "tree, collection and model", WORK)


def run(args):
    data = real_collection(args)
    from autodecoder.latent.folds import SUGGESTED_FOLDS

    model = cache.trained_model(data, root=args.cache, seed=args.train_seed, epochs=args.epochs,
                                representation=args.representation,
                                calibration_folds=None if args.folds == "off" else SUGGESTED_FOLDS)
    run_dir = Path(args.work) / data.parent.name / ("defaults" + (f"_e{args.epochs}" if args.epochs else "")
                                                    + (f"_{args.representation}" if args.representation else "")
                                                    + (f"_t{args.train_seed}" if args.train_seed else "")
                                                    + ("_norays" if args.no_rays else "")
                                                    + {True: "_aligned", False: "_noalign", None: ""}[args.align])
    figures = score(data, model, run_dir, args)
    if args.diagnose:
        diagnose(data, Path(figures["run"]))
    return figures
