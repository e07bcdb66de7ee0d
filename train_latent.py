"""Train the latent (autodecoder) model over a scan collection: ``python train_latent.py --data c.h5 --out model.pt``.

Many processes: ``torchrun --nproc_per_node=N train_latent.py ...`` (gloo on CPU, nccl on GPU).

The command line only: arguments are parsed and checked here, the training is
:func:`autodecoder.latent.train.train_collection` (imported when needed, so ``--help`` stays fast).
"""
import os
import sys
import time

from datasets.cli import OneLineParser

DEFAULTS = dict(latent_dim=32, width=64, depth=3, epochs=None, lr=1e-3, batch=8, seed=0)


class _UsageError(Exception):
    """A problem with the arguments: printed as one line, exit status 2 (problems with the input files are the
    library's ``TrainingInputError``, printed the same way)."""


def build_parser():
    p = OneLineParser(
        prog="train_latent.py",
        description="Train the latent NSSPR model (mean and covariance nets conditioned on one code per scan) over "
                    "the good scans of an HDF5 scan collection, and write one checkpoint that carries everything "
                    "(config, weights, codes, frame, noise level, held-back calibration scans). A per-epoch CSV log "
                    "(<out stem>.log.csv) and a loss plot (<out stem>.loss.png) are written beside it. Run under "
                    "'torchrun --nproc_per_node=N' to train with N processes (data parallel).")
    p.add_argument("--data", required=True, metavar="H5", help="scan collection file (datasets' HDF5 format)")
    p.add_argument("--out", required=True, metavar="PT",
                   help="checkpoint to write (atomically) in an existing folder, e.g. runs/a/model.pt")
    p.add_argument("--split", default="train",
                   help="collection split whose good scans are trained on (default: %(default)s)")
    p.add_argument("--latent-dim", type=int, default=DEFAULTS["latent_dim"],
                   help="dimension of each scan's latent code (default: %(default)s)")
    p.add_argument("--epochs", type=int, default=DEFAULTS["epochs"],
                   help="passes over the training scans (default: 450, fewer for collections of many thousand "
                        "scans; with --representation grid about 160 steps per part type); with --resume, the new "
                        "total (default: the checkpoint's)")
    p.add_argument("--representation", choices=("siren", "grid"), default=None,
                   help="the nets: 'siren' (the paper's SIRENs of --width x --depth) or 'grid' (B-spline feature "
                        "grids decoded with the code; docs/model.md) (default: the library's "
                        "LatentOptions.representation)")
    p.add_argument("--width", type=int, default=DEFAULTS["width"], help="SIREN hidden width (default: %(default)s)")
    p.add_argument("--depth", type=int, default=DEFAULTS["depth"],
                   help="SIREN hidden layers (default: %(default)s)")
    p.add_argument("--lr", type=float, default=DEFAULTS["lr"],
                   help="peak Adam learning rate of the nets, cosine decay (default: %(default)s)")
    p.add_argument("--code-lr", type=float, default=None,
                   help="peak Adam learning rate of the codes (default: the library's LatentOptions.code_lr)")
    p.add_argument("--batch", type=int, default=DEFAULTS["batch"],
                   help="scans per optimisation step, per process (default: %(default)s)")
    p.add_argument("--seed", type=int, default=DEFAULTS["seed"],
                   help="seeds initialisation, sampling and the calibration hold-out (default: %(default)s)")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                   help="where to train; auto: cuda when available (default: %(default)s)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run whose checkpoint is --out (same data, same number of processes; the run's "
                        "own settings are kept, only --epochs and --checkpoint-every apply); starts afresh when --out "
                        "does not exist yet")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out instead of refusing")
    p.add_argument("--calibration-fraction", type=float, default=0.2,
                   help="fraction of the good training scans held back (not trained on) for calibrating the "
                        "inspection threshold; ignored when the collection has a 'validation' split, whose good "
                        "scans are used instead (default: %(default)s)")
    p.add_argument("--calibration-folds", type=int, default=None, metavar="K",
                   help="after training, train K fold models, each without 1/K of the training scans, which it "
                        "scores as new scans for the inspection threshold (stored in the checkpoint; 0: none; "
                        "default: one per training scan with at most 8 training scans, where the held-back scans "
                        "are too few to set the threshold, else none: with more scans they found fewer defects "
                        "than the held-back scans' level, docs/results.md)")
    p.add_argument("--checkpoint-every", type=int, default=0, metavar="N",
                   help="also write the checkpoint every N epochs (default: only at the end)")
    p.add_argument("--samples", type=int, default=None,
                   help="mean-loss samples per scan and step (screening points: half as many). The default, 256, "
                        "trains a 32-scan collection in under 2 minutes; 1024 with --epochs 600 is the earlier "
                        "budget, about 3x the time (docs/results.md#latent-training-in-two-minutes-issue-19) "
                        "(default: the library's LatentOptions.mean_samples)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads of this process (0: torch's own choice, one per core). A latent training "
                        "step is many small tensor operations, which one thread runs faster than two on a 2-core "
                        "CPU (docs/results.md#latent-training-in-two-minutes-issue-19); a second core draws the next "
                        "step's targets meanwhile, and the family and pose decisions register scans on every core; "
                        "use more cores with torchrun processes (default: the trainer's TRAINING_THREADS, one)")
    p.add_argument("--family", choices=("auto", "on", "off"), default="auto",
                   help="bring the training scans to one size first: for a product family whose members differ in "
                        "length or width (every scan inspected later is registered the same way); 'auto': when "
                        "registering them onto each other spreads their sizes, and the sizes make them agree and "
                        "are reproducible (default: %(default)s)")
    p.add_argument("--pose", choices=("auto", "on", "off"), default="auto",
                   help="move the training scans into one common pose first, for parts placed by hand (every scan "
                        "inspected later is registered onto it); 'auto': when registering them onto each other "
                        "lowers their residuals, the rule with which inspection decides to register scans; not for a "
                        "family of sizes, whose registration already does it (default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    return p


def _parse(argv):
    args = build_parser().parse_args(argv)
    for name in ("latent_dim", "epochs", "width", "depth", "batch", "samples"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise _UsageError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    for name in ("lr", "code_lr"):
        if getattr(args, name) is not None and not getattr(args, name) > 0:
            raise _UsageError(f"--{name.replace('_', '-')} must be > 0, got {getattr(args, name)}")
    if not 0 <= args.calibration_fraction < 1:
        raise _UsageError(f"--calibration-fraction must be in [0, 1), got {args.calibration_fraction}")
    if args.calibration_folds is not None and args.calibration_folds != 0 and args.calibration_folds < 2:
        raise _UsageError(f"--calibration-folds must be 0 (none) or >= 2, got {args.calibration_folds}")
    if args.checkpoint_every < 0:
        raise _UsageError(f"--checkpoint-every must be >= 0, got {args.checkpoint_every}")
    if args.threads is not None and args.threads < 0:
        raise _UsageError(f"--threads must be >= 0, got {args.threads}")
    return args


def options_from_args(args):
    """The keyword arguments of :func:`autodecoder.latent.train.train_collection` for parsed arguments."""
    options = dict(split=args.split, calibration_fraction=args.calibration_fraction, resume=args.resume,
                   overwrite=args.overwrite, device=args.device, quiet=args.quiet, latent_dim=args.latent_dim,
                   width=args.width, depth=args.depth, epochs=args.epochs, lr=args.lr, batch=args.batch,
                   seed=args.seed, checkpoint_every=args.checkpoint_every,
                   family={"auto": "auto", "on": True, "off": False}[args.family],
                   pose={"auto": "auto", "on": True, "off": False}[args.pose])
    if args.code_lr is not None:
        options["code_lr"] = args.code_lr
    if args.calibration_folds is not None:
        options["calibration_folds"] = args.calibration_folds
    if args.representation is not None:
        options["representation"] = args.representation
    if args.samples is not None:
        options["mean_samples"], options["screen_samples"] = args.samples, max(1, args.samples // 2)
    return options


def run(args):
    """Train from parsed arguments; returns the LatentModel (raises TrainingInputError on bad input files)."""
    from autodecoder.latent.distributed import training_threads
    from autodecoder.latent.folds import train_collection_with_folds

    options = options_from_args(args)
    if not args.quiet and int(os.environ.get("RANK", "0")) == 0:
        options["announce"] = _outlook(options.get("calibration_folds"))
    with training_threads(args.threads):
        return train_collection_with_folds(args.data, args.out, **options)


def _outlook(folds):
    """The ``announce`` of a training (:func:`autodecoder.latent.train.train_collection`): one line, before the long
    work, when the good scans are few for the inspection threshold that follows
    (:func:`inspection.threshold.calibration_outlook`: how many will calibrate, what that means for the threshold,
    what ``--calibration-folds`` or more scans would give)."""
    def say(train_names, calibration_names):
        from autodecoder.latent.folds import default_folds
        from inspection.threshold import calibration_outlook

        k = default_folds(len(train_names)) if folds is None else folds  # None: the default (one part assumed)
        line = calibration_outlook(len(calibration_names), len(train_names), folds=k)
        if line:
            print(f"note: {line}", flush=True)
    return say


def main(argv=None):
    """Command-line entry point; returns the exit status (0 ok, 2 bad arguments or input files)."""
    # OpenMP threads that spin while waiting make small torch problems many times slower on a shared machine
    # (docs/results.md#threads); passive waiting costs nothing when the machine is idle. Only effective before
    # torch is first imported.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    started = time.perf_counter()
    try:
        args = _parse(argv)
    except SystemExit as exc:  # --help, or a usage error already printed as one line (datasets.cli)
        return int(exc.code or 0)
    except _UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from autodecoder.latent.options import TrainingInputError

    try:
        model = run(args)
    except TrainingInputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"train_latent.py: interrupted; continue with --resume (from the last checkpoint in {args.out})",
              file=sys.stderr)
        return 130
    if not args.quiet and int(os.environ.get("RANK", "0")) == 0:
        h = model.info.get("history", [])
        last = h[-1]["loss"] if h else float("nan")
        print(f"wrote {args.out}: {len(model.train_names)} training scans, {len(model.calibration_names)} held back "
              f"for calibration, epoch {model.epoch}, final loss {last:.4g}, noise {model.noise:.3g} "
              f"(collection units); {time.perf_counter() - started:.1f} s in all (the training epochs "
              f"{model.info.get('train_seconds', 0):.1f} s{' over every run of it' if args.resume else ''})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
