"""The scans of a collection a run trains on: the one rule for holding scans back for calibration, and a lazy view
of the training scans."""
import numpy as np

from autodecoder.latent.options import TrainingInputError


def split_training_scans(collection, split="train", calibration_fraction=0.2, seed=0):
    """(training indices, calibration names) of a collection: the one rule for holding scans back.

    The good (or unlabelled) scans of ``split`` are trained on. Calibration scans: the good scans of the
    'validation' split when there are any; otherwise ``calibration_fraction`` of the training scans, drawn with
    ``seed``, held back from training; in a collection of several part types (``part_id``) that fraction of each
    part's scans, drawn as in a collection of that part alone (so each part's held-back and training scans are
    those of its single-part collection, and every part can be calibrated on its own scans). Every way of training
    (``train_latent.py``, :func:`autodecoder.latent.train.train_collection`, ``inspection.training.train_model``)
    uses this rule, and the checkpoint records its choice (``calibration_names``), which is what inspection
    calibrates on.

    Parameters
    ----------
    collection : datasets.ScanCollection
        An open collection.
    split : str
    calibration_fraction : float in [0, 1)
    seed : int

    Returns
    -------
    train : list of int
        Collection indices, ascending.
    calibration : list of str
        Collection names.

    Raises
    ------
    TrainingInputError
        No good scans in ``split``, or none left to train on.
    """
    candidates = collection.select(split=split, label=("good", "unknown"))
    if not candidates:
        raise TrainingInputError(f"{collection.path}: no good scans in split {split!r} ({_holdings(collection)}); a "
                                 f"folder of good scans becomes one with `nsspr-data import FOLDER --split {split} "
                                 f"--label good --out COLLECTION` (a tree: FOLDER/{split}/good/), or train on another "
                                 f"split with --split")
    names = collection.names
    validation = collection.select(split="validation", label="good") if split != "validation" else []
    if validation:
        return candidates, [names[i] for i in validation]
    parts = [m["part_id"] for m in collection.metadata()]
    groups = {}
    for i in candidates:
        groups.setdefault(parts[i], []).append(i)
    train, held = [], []
    for part, members in groups.items():
        n_hold = int(round(calibration_fraction * len(members)))
        if len(members) - n_hold < 1:
            what = f"good scans in split {split!r}" + (f" of part {part!r}" if len(groups) > 1 else "")
            raise TrainingInputError(f"{collection.path}: {len(members)} {what} leave none to train on after holding "
                                     f"back {n_hold} for calibration (lower the calibration fraction)")
        order = np.random.default_rng(seed).permutation(len(members))
        held += [members[i] for i in order[:n_hold]]
        train += [members[i] for i in order[n_hold:]]
    return sorted(train), [names[i] for i in sorted(held)]


def _holdings(collection):
    """What a collection holds, in words: 'it holds 7 scans: 7 in split 'test' labelled 'unknown''."""
    from datasets.ingest import group_counts

    counts = group_counts((m["split"], m["label"]) for m in collection.metadata())
    if not counts:
        return "it holds no scans"
    return (f"it holds {sum(counts.values())} scans: "
            + ", ".join(f"{n} in split {s!r} labelled {lab!r}" for (s, lab), n in counts.items()))


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


def part_types(collection, indices):
    """The sorted part ids of the scans at ``indices`` of ``collection``: the trainer registers scans onto each other
    (a family's common size, the common pose of parts placed by hand) only when there is one
    (:func:`autodecoder.latent.train.train_collection`)."""
    meta = collection.metadata()
    return sorted({meta[i]["part_id"] for i in indices})
