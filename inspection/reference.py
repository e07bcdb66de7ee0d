"""A fixed reference field: one stochastic surface fitted to the union of a collection's good training scans.

The classical (non-latent) version of the pipeline and the fall-back of the demo while no latent model is available:
every scan is scored against the same field, with no projection. A fraction of the good training scans is held back
(not fitted) for calibration, and their names are stored with the field.
"""
import numpy as np


def fit_reference_field(collection, out, calibration_fraction=0.2, seed=0, max_points=60000, quiet=True,
                        **fit_options):
    """Fit ``autodecoder.fit_cloud`` to the good training scans of a collection (minus the held-back ones).

    Parameters
    ----------
    collection : str or Path
        A scan collection with a train split.
    out : str or Path
        Field file to write (:func:`inspection.model_io.save_reference_field`).
    calibration_fraction : float in [0, 1)
        Share of the good training scans held back for calibration (chosen with ``seed``).
    max_points : int
        The union is randomly subsampled to this many points.
    **fit_options
        Passed to ``fit_cloud`` (steps, width, ...).

    Returns
    -------
    Path
    """
    from autodecoder import fit_cloud
    from datasets import ScanCollection

    from .model_io import save_reference_field

    with ScanCollection(collection) as c:
        idx = c.select(split="train", label="good")
        if len(idx) < 2:
            raise ValueError(f"{collection}: needs at least 2 good training scans, found {len(idx)}")
        rng = np.random.default_rng(seed)
        n_held = int(round(calibration_fraction * len(idx)))
        held = set(rng.choice(idx, n_held, replace=False).tolist()) if n_held else set()
        train = [i for i in idx if i not in held]
        scans = c.read_many(train)
        held_names = [c.names[i] for i in sorted(held)]
        frame, fp = c.frame, c.fingerprint()
    pts = np.concatenate([s.points for s in scans])
    nrm = np.concatenate([s.normals for s in scans])
    if len(pts) > max_points:
        keep = rng.choice(len(pts), max_points, replace=False)
        pts, nrm = pts[keep], nrm[keep]
    field = fit_cloud(pts, nrm, seed=seed, quiet=quiet, **fit_options)
    return save_reference_field(field, out, frame=frame, fingerprint=fp, train_names=[s.name for s in scans],
                                heldback_names=held_names)
