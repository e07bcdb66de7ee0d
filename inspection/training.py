"""Training the latent model for the demo and the benchmarks: :func:`autodecoder.latent.train.train_collection`, the
function ``train_latent.py`` runs, with inspection's defaults (quiet, any device).

The calibration scans are held back by the trainer's one rule (:func:`autodecoder.latent.train.split_training_scans`)
and recorded in the checkpoint, exactly as ``train_latent.py --calibration-fraction`` does.
"""


def train_model(collection, out, calibration_fraction=0.2, seed=0, quiet=True, epochs=None, overwrite=False,
                threads=None, **options):
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
    threads : int, optional
        torch CPU threads during the training (restored afterwards); default: the trainer's ``TRAINING_THREADS``
        (one: faster than two on a 2-core CPU), 0: leave torch's setting.
    **options
        ``autodecoder.latent.train.LatentOptions`` fields, and ``calibration_folds`` / ``fold_jobs``
        (:func:`autodecoder.latent.folds.train_collection_with_folds`).

    Returns
    -------
    autodecoder.latent.model.LatentModel
    """
    from autodecoder.latent.distributed import training_threads
    from autodecoder.latent.folds import train_collection_with_folds

    with training_threads(threads):
        return train_collection_with_folds(collection, out, calibration_fraction=calibration_fraction, overwrite=overwrite,
                                quiet=quiet, seed=seed, epochs=epochs, **options)
