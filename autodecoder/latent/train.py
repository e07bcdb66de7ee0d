"""Training the latent model over many scans: a code table, the conditioned nets, checkpoints that resume, DDP.

:func:`train_latent` trains over scans in memory (or any lazy sequence of them); :func:`train_collection` over a
collection file, holding scans back for calibration by the one rule
:func:`autodecoder.latent.collection_split.split_training_scans` (what ``train_latent.py`` runs).

Distributed data parallel (``torchrun --nproc_per_node=N train_latent.py ...``): the training scans are sharded over
the ranks (rank r owns scans r, r + N, ...); each rank holds and optimises only its own scans' codes (outside DDP);
the two nets are wrapped in one :class:`torch.nn.parallel.DistributedDataParallel` module, so their gradients are
averaged over the ranks and the weights stay identical. At checkpoint time the codes, their optimiser moments and the
per-rank random states are gathered and rank 0 writes the file.

The pieces, one job a module: the settings (:mod:`~autodecoder.latent.options`), the processes
(:mod:`~autodecoder.latent.distributed`), the loop (:mod:`~autodecoder.latent.loop`), the training scans of a
collection (:mod:`~autodecoder.latent.collection_split`), checkpoints (:mod:`~autodecoder.latent.checkpoint`) and
the log and loss plot (:mod:`~autodecoder.latent.history`).
"""
import os
import time
from dataclasses import asdict
from pathlib import Path

from datasets.registration import registration_ticks

from autodecoder.latent.checkpoint import check_output, checkpoint_to_resume, gather_checkpoint
from autodecoder.latent.collection_split import CollectionScans, part_types, split_training_scans
from autodecoder.latent.distributed import setup_distributed
from autodecoder.latent.family import FamilyFrame, NormalisedScans, fit_family, fit_pose
from autodecoder.latent.loop import scan_names, start_run, train_epochs
from autodecoder.latent.model import LatentModel
from autodecoder.latent.options import LatentOptions, TrainingInputError


def train_latent(scans, out=None, options=None, *, names=None, frame=None, fingerprint="", calibration_names=(),
                 resume=None, device="cpu", quiet=False, stop_after=None, family=None, info=None, **overrides):
    """Train a latent model (autodecoder) over oriented scans, all in one collection frame.

    Parameters
    ----------
    scans : sequence of Scan
        The training scans (``len`` and ``scans[i]``; a lazy view over a collection works: each process reads only
        the scans it owns, plus up to 16 for the lengthscale). Points (N, 3) in the collection frame.
    out : str or Path, optional
        Checkpoint path; the log ``<stem>.log.csv`` and plot ``<stem>.loss.png`` go beside it. None: no files.
    options : LatentOptions, optional
        Overridden field by field by ``**overrides``.
    names : list of str, optional
        Scan names (default: ``scans.names`` or each scan's ``name``).
    frame : datasets.frame.Frame or dict, optional
        The collection's file -> collection frame, stored in the checkpoint (identity by default).
    fingerprint : str
        The training collection's fingerprint (stored; checked on resume).
    calibration_names : list of str
        Good scans held back for calibration (stored only).
    family : dict, optional
        :meth:`autodecoder.latent.family.FamilyFrame.as_dict` when ``scans`` were brought to one size (stored, so
        that every later scan is registered the same way); a resumed run keeps its own.
    resume : dict, optional
        A checkpoint (see :func:`autodecoder.latent.model.read_checkpoint`) to continue from; its configuration wins
        over ``options`` except ``epochs`` and ``checkpoint_every``.
    device : str or torch.device
    quiet : bool
        No progress bars (reading the scans, their GP targets, the epochs).
    stop_after : int, optional
        End this run (with a checkpoint) once this many epochs are complete, as if interrupted there.
    info : dict, optional
        Provenance the checkpoint's ``info`` records beside the run's own (e.g. ``decision_seconds``).

    Returns
    -------
    LatentModel
        On every rank (codes gathered from all ranks).
    """
    names = scan_names(scans, names)
    options = LatentOptions.from_dict({**asdict(options or LatentOptions()), **overrides})
    if resume is not None:
        family = resume.get("family")
    state, module, pools, scope, options = start_run(scans, names, options, resume=resume, frame=frame,
                                                     fingerprint=fingerprint, calibration_names=calibration_names,
                                                     device=device, family=family, progress=not quiet)
    state.info.update(info or {})
    end_epoch = options.epochs if stop_after is None else min(options.epochs, int(stop_after))
    checkpoint = train_epochs(state, module, pools, scope, options, out, end_epoch, show=not quiet and scope.rank == 0)
    if checkpoint is None:  # nothing left to train (resumed a finished run)
        checkpoint = gather_checkpoint(state, scope)
    return LatentModel(checkpoint, os.fspath(out) if out is not None else "<trained>")


def train_collection(data, out, *, split="train", calibration_fraction=0.2, resume=False, overwrite=False,
                     device="auto", quiet=False, family="auto", pose="auto", announce=None, **options):
    """Train a latent model over the good scans of a collection file and write its checkpoint (``train_latent.py``).

    The scans to hold back for calibration are chosen by :func:`split_training_scans`; the checkpoint records them.
    Under torchrun (``WORLD_SIZE`` > 1) each process trains its share (:func:`train_latent`).

    Parameters
    ----------
    data : str or Path
        The scan collection (``datasets`` HDF5 format).
    out : str or Path
        The checkpoint to write; the log and loss plot go beside it (:func:`autodecoder.latent.history.log_paths`).
    split : str
        The split whose good scans are trained on.
    calibration_fraction : float in [0, 1)
        Held back when the collection has no 'validation' split (see :func:`split_training_scans`).
    resume : bool
        Continue the run whose checkpoint is ``out`` (same data, same number of processes; its own settings are
        kept except ``epochs`` and ``checkpoint_every``); starts afresh when ``out`` does not exist yet.
    overwrite : bool
        Replace an existing ``out`` (otherwise refused unless ``resume``).
    device : {'auto', 'cpu', 'cuda'}
    quiet : bool
    family : {'auto', True, False}
        Bring the training scans to one size first (:mod:`autodecoder.latent.family`: a product family whose
        members differ in length or width); 'auto' (the default): when registering some of them onto each other
        spreads their sizes, and the sizes make them agree and are reproducible
        (:func:`autodecoder.latent.family.fit_family`). A resumed run keeps what it did.
    pose : {'auto', True, False}
        When the scans are not brought to one size: move them into one common pose first (parts placed by hand,
        :func:`autodecoder.latent.family.fit_pose`); 'auto' (the default): when their poses spread, by the rule
        with which inspection's ``align='auto'`` decides to register scans. Not for several part types (their scans
        stay where they lie). A resumed run keeps what it did.
    announce : callable, optional
        Called as ``announce(train_names, calibration_names)`` once the scans to train on and to hold back are
        chosen, before the long work (the family and pose decisions, the training): ``train_latent.py`` says there
        what so many scans will give the inspection threshold.
    **options
        :class:`LatentOptions` fields (``seed`` also seeds the hold-out).

    Returns
    -------
    LatentModel

    Raises
    ------
    TrainingInputError
        Naming the file: no such or unreadable collection, ``out`` exists, is a folder or cannot be written, a
        checkpoint of other data, no scans.
    """
    from datasets.collection import ScanCollection

    data, out = Path(data), Path(out)
    try:
        collection = ScanCollection(data)
    except (ValueError, OSError) as exc:  # the collection's own messages name the file and the problem
        message = str(exc).splitlines()[0]
        if not message.startswith(f"{data}:"):
            message = f"{data}: not a readable scan collection ({message})"
        raise TrainingInputError(message) from None
    initialised = False
    try:
        check_output(out)
        checkpoint = checkpoint_to_resume(out, collection, data, resume, overwrite)
        if checkpoint is not None:
            index = {n: i for i, n in enumerate(collection.names)}
            train = [index[n] for n in checkpoint["train_names"]]
            calibration = list(checkpoint["calibration_names"])
            options["seed"] = int(checkpoint["config"]["seed"])
        else:
            train, calibration = split_training_scans(collection, split, calibration_fraction,
                                                      options.get("seed", LatentOptions.seed))
        scans, family_frame = CollectionScans(collection, train), None
        if announce is not None:
            announce(list(scans.names), list(calibration))
        parts = part_types(collection, train)
        for flag, value in (("--family on", family), ("--pose on", pose)):
            if len(parts) > 1 and value is True:
                raise TrainingInputError(f"{data}: {flag} registers one part's scans onto each other, but the "
                                         f"training scans are of {len(parts)} part types ({parts})")
        if len(parts) > 1:  # several part types: their sizes differ by nature, not as a family's, and one part's
            family = pose = False  # scans are not to be registered onto another's (inspection registers per part)
        decision_seconds = {}
        if checkpoint is None:
            seed = options.get("seed", LatentOptions.seed)
            t0 = time.perf_counter()
            scans, family_frame = family_scans(scans, family, seed, quiet)
            decision_seconds["family"] = time.perf_counter() - t0
            if family_frame is None:
                t0 = time.perf_counter()
                scans, family_frame = pose_scans(scans, pose, seed, quiet)
                decision_seconds["pose"] = time.perf_counter() - t0
        elif checkpoint.get("family") is not None:
            scans = NormalisedScans(scans, FamilyFrame.from_dict(checkpoint["family"]))
        device, initialised = setup_distributed(device)
        try:
            return train_latent(scans, out, frame=collection.frame, fingerprint=collection.fingerprint(),
                                calibration_names=calibration, resume=checkpoint, device=device, quiet=quiet,
                                family=None if family_frame is None else family_frame.as_dict(),
                                info={"decision_seconds": decision_seconds} if decision_seconds else None, **options)
        except TrainingInputError:
            raise
        except ValueError as exc:
            raise TrainingInputError(f"{data}: {exc}") from None
    finally:
        collection.close()
        if initialised:
            import torch.distributed as dist

            dist.destroy_process_group()


def pose_scans(scans, pose="auto", seed=0, quiet=True):
    """``scans`` (a lazy sequence of training scans) moved into one common pose when their poses spread (parts placed
    by hand: :func:`autodecoder.latent.family.fit_pose`), with one printed line saying so unless ``quiet``. Returns
    (the scans to train on, the :class:`~autodecoder.latent.family.FamilyFrame` or None)."""
    with registration_ticks("pose: placed by hand?" if pose == "auto" else "common pose",
                            not quiet and pose is not False) as tick:
        frame, spread = fit_pose(scans, pose, seed=seed, tick=tick)
    if frame is None:
        return scans, None
    if not quiet:
        why = "" if spread is None else f" (registered onto each other, their residuals fall by a median " \
                                        f"{100 * (1 - 1 / spread):.0f} %)"
        print(f"note: the training scans' poses spread{why}: they are moved into one common pose before training, "
              f"and every scan inspected later is registered onto it", flush=True)
    return NormalisedScans(scans, frame), frame


def family_scans(scans, family="auto", seed=0, quiet=True):
    """``scans`` (a lazy sequence of training scans) brought to one size when they are a product family
    (:func:`autodecoder.latent.family.fit_family`), with one printed line saying so unless ``quiet``. Returns
    (the scans to train on, the :class:`~autodecoder.latent.family.FamilyFrame` or None)."""
    with registration_ticks("family of sizes?" if family == "auto" else "common size",
                            not quiet and family is not False) as tick:
        frame, spread = fit_family(scans, family, seed=seed, tick=tick)
    if frame is None:
        return scans, None
    if not quiet:
        why = "" if spread is None else f" (registered onto each other, their sizes spread by {100 * spread:.0f} %)"
        print(f"note: the training scans are a family of sizes{why}: each scan is registered onto one common size "
              f"before training, and so is every scan inspected later", flush=True)
    return NormalisedScans(scans, frame), frame
