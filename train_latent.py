"""Train the latent (autodecoder) model over a scan collection: ``python train_latent.py --data c.h5 --out model.pt``.

Many processes: ``torchrun --nproc_per_node=N train_latent.py ...`` (gloo on CPU, nccl on GPU).
"""
import argparse
import os
import sys
from pathlib import Path

DEFAULTS = dict(latent_dim=32, width=64, depth=3, epochs=None, lr=1e-3, batch=8, seed=0)


class _UsageError(Exception):
    """A problem with the arguments or the input files: printed as one line, exit status 2."""


def build_parser():
    p = argparse.ArgumentParser(
        prog="train_latent.py",
        description="Train the latent NSSPR model (mean and covariance nets conditioned on one code per scan) over "
                    "the good scans of an HDF5 scan collection, and write one checkpoint that carries everything "
                    "(config, weights, codes, frame, noise level, held-back calibration scans). A per-epoch CSV log "
                    "(<out stem>.log.csv) and a loss plot (<out stem>.loss.png) are written beside it. Run under "
                    "'torchrun --nproc_per_node=N' to train with N processes (data parallel).")
    p.add_argument("--data", required=True, metavar="H5", help="scan collection file (datasets' HDF5 format)")
    p.add_argument("--out", required=True, metavar="PT", help="checkpoint to write (atomically), e.g. runs/a/model.pt")
    p.add_argument("--split", default="train",
                   help="collection split whose good scans are trained on (default: %(default)s)")
    p.add_argument("--latent-dim", type=int, default=DEFAULTS["latent_dim"],
                   help="dimension of each scan's latent code (default: %(default)s)")
    p.add_argument("--epochs", type=int, default=DEFAULTS["epochs"],
                   help="passes over the training scans (default: enough for ~2400 steps, between 150 and 600 "
                        "epochs); with --resume, the new total (default: the checkpoint's)")
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
    p.add_argument("--checkpoint-every", type=int, default=0, metavar="N",
                   help="also write the checkpoint every N epochs (default: only at the end)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    return p


def _parse(argv):
    args = build_parser().parse_args(argv)
    for name in ("latent_dim", "epochs", "width", "depth", "batch"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise _UsageError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if not args.lr > 0 or (args.code_lr is not None and not args.code_lr > 0):
        raise _UsageError("--lr and --code-lr must be > 0")
    if not 0 <= args.calibration_fraction < 1:
        raise _UsageError(f"--calibration-fraction must be in [0, 1), got {args.calibration_fraction}")
    if args.checkpoint_every < 0:
        raise _UsageError(f"--checkpoint-every must be >= 0, got {args.checkpoint_every}")
    return args


def split_training_scans(collection, split="train", calibration_fraction=0.2, seed=0):
    """(training indices, calibration names) of a collection.

    The good (or unlabelled) scans of ``split`` are trained on. Calibration scans: the good scans of the
    'validation' split when there are any; otherwise ``calibration_fraction`` of the training scans, drawn with
    ``seed``, held back from training.
    """
    import numpy as np

    candidates = collection.select(split=split, label=("good", "unknown"))
    if not candidates:
        raise _UsageError(f"{collection.path}: no good scans in split {split!r}")
    names = collection.names
    validation = collection.select(split="validation", label="good") if split != "validation" else []
    if validation:
        return candidates, [names[i] for i in validation]
    n_hold = int(round(calibration_fraction * len(candidates)))
    if len(candidates) - n_hold < 1:
        raise _UsageError(f"{collection.path}: {len(candidates)} good scans in split {split!r} leave none to train "
                          f"on after holding back {n_hold} for calibration (lower --calibration-fraction)")
    order = np.random.default_rng(seed).permutation(len(candidates))
    held = sorted(candidates[i] for i in order[:n_hold])
    train = sorted(candidates[i] for i in order[n_hold:])
    return train, [names[i] for i in held]


class CollectionScans:
    """A lazy sequence of some scans of an open collection (reads a scan when indexed)."""

    def __init__(self, collection, indices):
        self.collection, self.indices = collection, list(indices)
        all_names = collection.names
        self.names = [all_names[i] for i in self.indices]

    def __len__(self):
        return len(self.indices)

    def __getitem__(self, k):
        return self.collection[self.indices[k]]


def _setup_distributed(device_arg):
    """Initialise torch.distributed from torchrun's environment; returns (device, initialised here?)."""
    import torch

    if device_arg == "auto":
        device_arg = "cuda" if torch.cuda.is_available() else "cpu"
    if device_arg == "cuda" and not torch.cuda.is_available():
        raise _UsageError("--device cuda: no CUDA device is available")
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return torch.device(device_arg), False
    import torch.distributed as dist

    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if device_arg == "cuda":
        torch.cuda.set_device(local_rank)
        device = torch.device("cuda", local_rank)
    else:
        device = torch.device("cpu")
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        return device, True
    return device, False


def run(args):
    """Train from parsed arguments; returns the LatentModel."""
    from datasets.collection import ScanCollection

    data, out = Path(args.data), Path(args.out)
    if not data.is_file():
        raise _UsageError(f"{data}: no such scan collection")
    try:
        collection = ScanCollection(data)
    except (ValueError, OSError) as exc:
        raise _UsageError(f"{data}: not a readable scan collection ({str(exc).splitlines()[0]})") from None
    resume = None
    if out.exists():
        if args.resume:
            from autodecoder.latent.model import read_checkpoint

            try:
                resume = read_checkpoint(out)
            except (ValueError, FileNotFoundError) as exc:
                raise _UsageError(str(exc)) from None
            if resume.get("fingerprint", "") != collection.fingerprint():
                raise _UsageError(f"{out}: this checkpoint was trained on another collection than {data} "
                                  f"(fingerprints differ); use a new --out or the original data")
        elif not args.overwrite:
            raise _UsageError(f"{out}: already exists (pass --resume to continue it or --overwrite to replace it)")
    if resume is not None:
        names = collection.names
        index = {n: i for i, n in enumerate(names)}
        train = [index[n] for n in resume["train_names"]]
        calibration = list(resume["calibration_names"])
        seed = int(resume["config"]["seed"])
    else:
        train, calibration = split_training_scans(collection, args.split, args.calibration_fraction, args.seed)
        seed = args.seed
    device, initialised = _setup_distributed(args.device)
    from autodecoder.latent.train import train_latent

    overrides = dict(latent_dim=args.latent_dim, width=args.width, depth=args.depth, epochs=args.epochs, lr=args.lr,
                     batch=args.batch, seed=seed, checkpoint_every=args.checkpoint_every)
    if args.code_lr is not None:
        overrides["code_lr"] = args.code_lr
    try:
        model = train_latent(CollectionScans(collection, train), out, frame=collection.frame,
                             fingerprint=collection.fingerprint(), calibration_names=calibration, resume=resume,
                             device=device, quiet=args.quiet, **overrides)
    except ValueError as exc:
        raise _UsageError(f"{data}: {exc}") from None
    finally:
        collection.close()
        if initialised:
            import torch.distributed as dist

            dist.destroy_process_group()
    return model


def main(argv=None):
    """Command-line entry point; returns the exit status (0 ok, 2 bad arguments or input files)."""
    # OpenMP threads that spin while waiting make small torch problems many times slower on a shared machine
    # (docs/results.md#threads); passive waiting costs nothing when the machine is idle. Only effective before
    # torch is first imported.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    try:
        args = _parse(argv)
    except SystemExit as exc:  # argparse: --help (0) or a usage error (2), already printed
        return int(exc.code or 0)
    except _UsageError as exc:
        print(f"train_latent.py: error: {exc}", file=sys.stderr)
        return 2
    try:
        model = run(args)
    except _UsageError as exc:
        print(f"train_latent.py: error: {exc}", file=sys.stderr)
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
              f"(collection units), {model.info.get('train_seconds', 0):.1f} s training")
    return 0


if __name__ == "__main__":
    sys.exit(main())
