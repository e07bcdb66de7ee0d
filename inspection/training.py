"""Training the latent model for the demo and the benchmark: ``train_latent.py`` when it is ready, else its Python API.

A fraction of the good training scans is held back (chosen with the seed) and recorded in the checkpoint as the
calibration scans, exactly as ``train_latent.py --calibration-fraction`` does.
"""
import numpy as np


def _cli_ready():
    import train_latent

    return "not yet implemented" not in (train_latent.__doc__ or "")


def train_model(collection, out, calibration_fraction=0.2, seed=0, quiet=True, epochs=None, overwrite=False,
                **options):
    """Train a latent model on a collection's good training scans (minus the held-back ones) into ``out``.

    Parameters
    ----------
    collection, out : str or Path
    calibration_fraction : float in [0, 1)
    seed : int
    epochs : int, optional
        Default: the trainer's.
    overwrite : bool
        Replace an existing ``out``.
    **options
        ``autodecoder.latent.train.LatentOptions`` fields (Python API only; the command line gets --epochs/--seed).

    Returns
    -------
    str : 'cli' or 'api', whichever trained it.
    """
    if _cli_ready() and not options:
        import train_latent

        argv = ["--data", str(collection), "--out", str(out), "--seed", str(seed),
                "--calibration-fraction", str(calibration_fraction)]
        if epochs is not None:
            argv += ["--epochs", str(epochs)]
        if quiet:
            argv.append("--quiet")
        if overwrite:
            argv.append("--overwrite")
        rc = train_latent.main(argv)
        if rc not in (0, None):
            raise RuntimeError(f"train_latent.py exited with status {rc}")
        return "cli"
    from autodecoder.latent.train import train_latent
    from datasets import ScanCollection

    with ScanCollection(collection) as c:
        idx = c.select(split="train", label="good")
        if len(idx) < 2:
            raise ValueError(f"{collection}: needs at least 2 good training scans, found {len(idx)}")
        rng = np.random.default_rng(seed)
        n_held = int(round(calibration_fraction * len(idx)))
        held = set(rng.choice(idx, n_held, replace=False).tolist()) if n_held else set()
        train = [i for i in idx if i not in held]
        scans = c.read_many(train)
        names = [c.names[i] for i in train]
        held_names = [c.names[i] for i in sorted(held)]
        frame, fp = c.frame, c.fingerprint()
    extra = {} if epochs is None else {"epochs": int(epochs)}
    train_latent(scans, out, names=names, frame=frame, fingerprint=fp, calibration_names=held_names, seed=seed,
                 quiet=quiet, **extra, **options)
    return "api"

