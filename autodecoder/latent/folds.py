"""Fold models: latent models each trained without one fold of the training scans, so that every training scan can be
scored by a model that never saw it (out-of-sample calibration, cross-validation+ style: Barber et al., "Predictive
inference with the jackknife+", 2021).

A model's training scans are split into ``k`` folds (:func:`assign_folds`: per part type, seeded). Fold model j is
trained from scratch, with the main model's settings (the same kernel lengthscale, the same epochs, i.e. as many
updates of every code), on the training scans outside fold j and the model's held-back scans (``FOLD_RULE``); it
scores the scans of fold j as new scans. The held-back scans are scored by the main model alone, which never saw
them, so every calibration score stays out of sample, and each fold model sees more scans: with 26 training and 6
held-back scans in 2 folds, 19 scans against the main model's 26 instead of 13. The fold models are stored inside
the main checkpoint under ``FOLDS_KEY`` (the record and its reader, :func:`read_folds`, live with the checkpoint
format in :mod:`autodecoder.latent.model`): a list of ``{"scored_names", "checkpoint", "rule"}``, each checkpoint a
complete latent checkpoint whose ``train_names`` exclude its ``scored_names``; reading one that does not is an
error, so a fold model never scores a scan it trained on. :func:`train_collection_with_folds` is what
``train_latent.py --calibration-folds K`` runs; :func:`add_folds` adds them to a trained model.

Off by default (``DEFAULT_FOLDS``) but with few training scans (``FEW_SCANS``, :func:`default_folds`: then one per
training scan): measured in docs/results.md (issue 27), with 26 training scans their calibration scores lay above
new good scans' (leaving a scan out of the reference opens holes new scans do not meet) and set thresholds that
found fewer defects at no lower false-alarm rate; with 8, the held-back level rests on 2 scores (issue 48).

Cost: with the default epochs every code is updated the same number of times whatever the number of scans, so a
fold model costs its share of the main model's steps (rounded up to whole batches: 3 of 4 for the 19 of 26 scans
above); ``jobs`` worker processes (one torch thread each) train them side by side.
"""
import os
from collections import Counter
from dataclasses import fields

import numpy as np

from autodecoder.latent.model import FOLD_RULE, FOLDS_KEY, CalibrationFold, read_folds  # noqa: F401 (the record)

# fold models are trained only when asked for (train_latent.py --calibration-folds K): on the benchmark's trees their
# out-of-sample scores lay above the good test scans' and the thresholds they set found fewer defects than the
# held-back level, at no lower false-alarm rate (docs/results.md#out-of-sample-calibration-by-fold-models-issue-27)
DEFAULT_FOLDS = 0
# the number of folds when fold models are asked for without a number (two: the fold models together cost about
# one main training on two cores)
SUGGESTED_FOLDS = 2
# with at most this many good training scans of each part, a training asked for no number of fold models trains one
# per training scan (leave-one-out): with 2 held-back scans the threshold's level rested on 2 scores and its
# false-alarm interval reached <0.001 %, so nearly every defective scan was 'uncertain'; scored out of sample, all
# 10 set it (docs/results.md, fewscans). Cost: about as many main trainings as scans, each of a few scans
FEW_SCANS = 8


def default_folds(counts):
    """The fold models a training asked for no number trains: one per training scan (leave-one-out) when every part
    type has 2 to ``FEW_SCANS`` training scans, else ``DEFAULT_FOLDS``. ``counts``: the training scans of each part
    type (an int for one part)."""
    counts = [int(counts)] if np.ndim(counts) == 0 else [int(c) for c in counts]
    if counts and 2 <= min(counts) and max(counts) <= FEW_SCANS:
        return min(counts)
    return DEFAULT_FOLDS


def assign_folds(train_names, part_ids=None, k=SUGGESTED_FOLDS, seed=0):
    """Split training scans into ``k`` folds: each part type's scans shuffled with ``seed`` and dealt round-robin,
    so that every fold holds about 1 / k of every part.

    Parameters
    ----------
    train_names : list of str
    part_ids : list of str, optional
        One per name (default: one part).
    k : int >= 2
    seed : int

    Returns
    -------
    list of k lists of str
        The scans each fold scores (every name exactly once; each fold non-empty).

    Raises
    ------
    ValueError
        k < 2, or fewer scans of a part than 2 (a fold model needs a scan to train on and one to score) or than k.
    """
    k = int(k)
    if k < 2:
        raise ValueError(f"calibration folds: k must be >= 2, got {k}")
    names = [str(n) for n in train_names]
    parts = [str(p) for p in (part_ids or [""] * len(names))]
    if len(parts) != len(names):
        raise ValueError(f"calibration folds: {len(parts)} part ids for {len(names)} training scans")
    groups = {}
    for name, part in zip(names, parts):
        groups.setdefault(part, []).append(name)
    folds = [[] for _ in range(k)]
    for part, members in sorted(groups.items()):
        if len(members) < k:
            what = f" of part {part!r}" if part else ""
            raise ValueError(f"calibration folds: {len(members)} training scans{what} cannot be split into {k} folds "
                             f"(each fold model trains on the others and scores its own; use fewer folds)")
        order = np.random.default_rng(seed).permutation(len(members))
        for rank, i in enumerate(order):
            folds[rank % k].append(members[i])
    return [sorted(f, key=names.index) for f in folds]


def fold_options(config):
    """The :class:`~autodecoder.latent.options.LatentOptions` of a fold model of a main model with ``config``:
    the same settings, the same kernel lengthscale and epochs (not re-derived from the fold's scans: the fold
    model is the main model's training on fewer scans), no intermediate checkpoints."""
    from autodecoder.latent.options import LatentOptions

    names = {f.name for f in fields(LatentOptions)}
    options = {k: v for k, v in dict(config).items() if k in names}
    options.update(lengthscale=float(config["lengthscale"]), epochs=int(config["epochs"]), checkpoint_every=0)
    return LatentOptions.from_dict(options)


def _train_one(collection_path, names, options, threads, family=None):
    """One fold model trained on the scans ``names`` of the collection; returns its checkpoint (:func:`model_state`).
    ``family``: the main model's family frame (its checkpoint's ``'family'``), which the fold model's scans are
    brought to as the main model's were, so that a scan it scores is registered the way the main model's are."""
    from datasets.collection import ScanCollection

    from autodecoder.latent.collection_split import CollectionScans
    from autodecoder.latent.distributed import training_threads
    from autodecoder.latent.train import train_latent

    with ScanCollection(collection_path) as collection, training_threads(threads):
        index = {n: i for i, n in enumerate(collection.names)}
        missing = [n for n in names if n not in index]
        if missing:
            raise ValueError(f"{collection_path}: no scan named {missing[0]!r} (the model's training scan)")
        scans = CollectionScans(collection, [index[n] for n in names])
        if family is not None:
            from autodecoder.latent.family import FamilyFrame, NormalisedScans

            scans = NormalisedScans(scans, FamilyFrame.from_dict(family))
        model = train_latent(scans, None, options, frame=collection.frame, fingerprint=collection.fingerprint(),
                             quiet=True, family=family)
    return model_state(model)


def _train_in_processes(collection_path, plans, options, threads, jobs, progress, family=None):
    """Each plan (training scan names) trained by ``python -m autodecoder.latent.folds`` in its own process, at most
    ``jobs`` at a time (a fresh interpreter: nothing of the caller's script is re-run, as multiprocessing's spawn
    would). Returns the checkpoints in plan order."""
    import json
    import subprocess
    import sys
    import tempfile
    from dataclasses import asdict

    from autodecoder.field.checkpoint_io import load_torch_file

    env = {**os.environ, "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
    states, running, pending = [None] * len(plans), {}, list(range(len(plans)))
    with tempfile.TemporaryDirectory(prefix="nsspr-folds-") as tmp:
        family_path = None
        if family is not None:
            import torch

            family_path = os.path.join(tmp, "family.pt")
            torch.save(family, family_path)

        def start(j):
            spec = os.path.join(tmp, f"fold{j}.json")
            with open(spec, "w") as f:
                json.dump({"collection": os.fspath(collection_path), "names": plans[j], "options": asdict(options),
                           "threads": threads, "out": os.path.join(tmp, f"fold{j}.pt"), "family": family_path}, f)
            log = open(os.path.join(tmp, f"fold{j}.log"), "w+")
            return subprocess.Popen([sys.executable, "-m", "autodecoder.latent.folds", spec], stdout=log,
                                    stderr=subprocess.STDOUT, env=env), log

        try:
            while pending or running:
                while pending and len(running) < jobs:
                    j = pending.pop(0)
                    running[j] = start(j)
                j = next(iter(running))
                proc, log = running.pop(j)
                if proc.wait() != 0:
                    log.seek(0)
                    tail = log.read().strip().splitlines()[-1:] or ["(no output)"]
                    raise RuntimeError(f"calibration fold {j + 1}: its training process failed: {tail[0]}")
                log.close()
                states[j] = load_torch_file(os.path.join(tmp, f"fold{j}.pt"), what="fold model")
                if progress:
                    progress(f"fold {j + 1} of {len(plans)} trained")
        finally:
            for proc, log in running.values():
                proc.kill()
                proc.wait()
                log.close()
    return states


def model_state(model):
    """A trained :class:`~autodecoder.latent.model.LatentModel`'s checkpoint, without what only resuming its
    training needs (optimiser moments, random states): a fold model is used, never trained further."""
    return {k: v for k, v in model.state.items() if k != "resume"}


def train_folds(checkpoint, collection_path, k=SUGGESTED_FOLDS, jobs=None, threads=None, progress=None):
    """Train the fold models of a main model's checkpoint on its training collection.

    Parameters
    ----------
    checkpoint : dict
        The main model's checkpoint (:func:`autodecoder.latent.model.read_checkpoint`).
    collection_path : str or Path
        Its training collection (same fingerprint).
    k : int >= 2
    jobs : int, optional
        Worker processes (default: min(k, the cores this process may use, ``datasets.parallel.usable_cores``));
        1 trains in this process.
    threads : int, optional
        torch threads per fold training (default: the trainer's ``TRAINING_THREADS``).
    progress : callable, optional
        Called with one line per finished fold.

    Returns
    -------
    list of dict
        ``{"scored_names", "checkpoint", "rule"}`` per fold, ready for ``checkpoint[FOLDS_KEY]``; fold j trained on
        the training scans outside fold j and the held-back scans (``FOLD_RULE``).
    """
    from datasets.collection import ScanCollection
    from datasets.parallel import usable_cores

    with ScanCollection(collection_path) as collection:
        if checkpoint.get("fingerprint") and collection.fingerprint() != checkpoint["fingerprint"]:
            raise ValueError(f"{collection_path}: not the collection the model was trained on (fingerprint "
                             f"{collection.fingerprint()[:12]}... vs the model's {checkpoint['fingerprint'][:12]}...)")
    train_names = list(checkpoint["train_names"])
    folds = assign_folds(train_names, checkpoint.get("train_part_ids"), k, int(checkpoint["config"].get("seed", 0)))
    options = fold_options(checkpoint["config"])
    jobs = min(len(folds), usable_cores()) if jobs is None else max(1, int(jobs))
    with ScanCollection(collection_path) as collection:
        present = set(collection.names)
    held = [n for n in checkpoint.get("calibration_names", []) if n in present]
    plans = [[n for n in train_names if n not in set(scored)] + held for scored in folds]
    if jobs == 1:
        states = []
        for j, names in enumerate(plans):
            states.append(_train_one(collection_path, names, options, threads, checkpoint.get("family")))
            if progress:
                progress(f"fold {j + 1} of {len(folds)} trained")
    else:
        states = _train_in_processes(collection_path, plans, options, threads, jobs, progress,
                                     checkpoint.get("family"))
    return [{"scored_names": list(scored), "checkpoint": state, "rule": FOLD_RULE}
            for scored, state in zip(folds, states)]


def add_folds(model_path, collection_path, k=SUGGESTED_FOLDS, jobs=None, threads=None, progress=None):
    """Train the fold models of the checkpoint at ``model_path`` on its training collection and store them in it
    (the file is rewritten atomically; fold models it already had are replaced).

    Returns
    -------
    list of CalibrationFold
    """
    from autodecoder.latent.model import read_checkpoint, save_checkpoint

    state = read_checkpoint(model_path)
    state[FOLDS_KEY] = train_folds(state, collection_path, k, jobs, threads, progress)
    save_checkpoint(state, model_path)
    return read_folds(state, os.fspath(model_path))


def _worker_main(spec_path):
    """``python -m autodecoder.latent.folds SPEC.json``: train one fold model as :func:`_train_in_processes` asks
    and save its checkpoint (atomically) where the spec says."""
    import json

    from autodecoder.field.checkpoint_io import atomic_torch_save
    from autodecoder.latent.options import LatentOptions

    with open(spec_path) as f:
        spec = json.load(f)
    family = spec.get("family")
    if family is not None:
        from autodecoder.field.checkpoint_io import load_torch_file

        family = load_torch_file(family)
    state = _train_one(spec["collection"], spec["names"], LatentOptions.from_dict(spec["options"]), spec["threads"],
                       family)
    atomic_torch_save(state, spec["out"])


if __name__ == "__main__":
    import sys

    _worker_main(sys.argv[1])


def train_collection_with_folds(data, out, *, calibration_folds=None, fold_jobs=None, quiet=False, **kwargs):
    """:func:`autodecoder.latent.train.train_collection`, then ``calibration_folds`` fold models trained into the
    checkpoint (what ``train_latent.py --calibration-folds K`` runs).

    Parameters
    ----------
    data, out, quiet, **kwargs
        As ``train_collection``.
    calibration_folds : int, optional
        Fold models to add; 0: none; None: :func:`default_folds` (leave-one-out with few training scans, else none).
        A number the training scans cannot be split into is refused before training (a fresh run).
    fold_jobs : int, optional
        Processes training the fold models side by side (default: one per fold, at most one per CPU core).

    Returns
    -------
    LatentModel
    """
    from datasets.collection import ScanCollection

    from autodecoder.latent.collection_split import split_training_scans
    from autodecoder.latent.model import load_model
    from autodecoder.latent.options import LatentOptions, TrainingInputError
    from autodecoder.latent.train import train_collection

    k = None if calibration_folds is None else int(calibration_folds)
    if k != 0 and not kwargs.get("resume"):  # before the long work
        try:
            with ScanCollection(data) as collection:
                train, _ = split_training_scans(collection, kwargs.get("split", "train"),
                                                kwargs.get("calibration_fraction", 0.2),
                                                kwargs.get("seed", LatentOptions.seed))
                meta = collection.metadata()
                parts = [meta[i]["part_id"] for i in train]
                if k is None:
                    k = default_folds(list(Counter(parts).values()))
                if k:
                    assign_folds(train, parts, k)
        except ValueError as exc:
            raise TrainingInputError(f"{data}: {exc}") from None
        except OSError:  # no readable collection: the training says so in its own words
            if k is not None:
                raise
    k = k or 0
    model = train_collection(data, out, quiet=quiet, **kwargs)
    if not k or int(os.environ.get("RANK", "0")) != 0:
        return model
    echo = None if quiet else (lambda line: print(f"calibration {line}", flush=True))
    if echo:
        echo(f"folds: training {k} fold models (each without 1/{k} of the training scans, which it scores as new)")
    add_folds(out, data, k, jobs=fold_jobs, progress=echo)
    return load_model(out)
