"""A training run's checkpoints: the dict that saves a run's state, restoring a run from it, and the checkpoint a
collection run continues.

The format itself (its keys, the check, reading and writing a file) is :mod:`autodecoder.latent.model`'s; this module
fills it from a run (gathering the codes from every rank) and reads a run back from it, bit-identically.
"""
import math
import tempfile
from pathlib import Path

import torch

from autodecoder.latent.distributed import all_gather
from autodecoder.latent.model import LATENT_FORMAT, LATENT_VERSION, code_statistics, read_checkpoint
from autodecoder.latent.options import TrainingInputError
from datasets.frame import Frame


def gather_checkpoint(state, scope):
    """The full checkpoint dict of ``state`` (codes, optimiser moments and per-rank random states gathered from
    all ranks; a collective call: every rank makes it)."""
    codes = state.codes
    code_state = state.opt_codes.state_dict()
    st = code_state["state"].get(0)
    latent_dim = codes.shape[1]
    if st is None:
        st = {"step": torch.tensor(0.0), "exp_avg": torch.zeros_like(codes), "exp_avg_sq": torch.zeros_like(codes)}
    # noise: RMS of the mean at this rank's scans' points
    total, count = 0.0, 0
    with torch.no_grad():
        for p, pts in enumerate(scope.local_points):
            total += float(state.nets.mean_net(pts, codes[p]).double().square().sum())
            count += len(pts)
    mine = {"local": scope.local, "codes": codes.detach().cpu(), "exp_avg": st["exp_avg"].detach().cpu(),
            "exp_avg_sq": st["exp_avg_sq"].detach().cpu(), "rng": state.rng.bit_generator.state, "sq": total,
            "n": count}
    gathered = all_gather(mine, scope.world)
    n = len(scope.names)
    full = {k: torch.zeros(n, latent_dim) for k in ("codes", "exp_avg", "exp_avg_sq")}
    for g in gathered:
        for k in full:
            full[k][g["local"]] = g[k]
    sq, cnt = sum(g["sq"] for g in gathered), sum(g["n"] for g in gathered)
    noise = math.sqrt(sq / cnt) if cnt else 0.0
    mean, std = code_statistics(full["codes"])
    step = st["step"].detach().cpu() if torch.is_tensor(st["step"]) else torch.tensor(float(st["step"]))
    return {
        "format": LATENT_FORMAT,
        "version": LATENT_VERSION,
        "config": dict(state.config),
        "mean_state": {k: v.detach().cpu() for k, v in state.nets.mean_net.state_dict().items()},
        "cov_state": {k: v.detach().cpu() for k, v in state.nets.cov_net.state_dict().items()},
        "codes": full["codes"],
        "code_mean": mean,
        "code_std": std,
        "train_names": list(scope.names),
        "train_part_ids": list(scope.part_ids),
        "calibration_names": list(scope.calibration_names),
        "frame": dict(scope.frame),
        **({} if scope.family is None else {"family": dict(scope.family)}),
        "noise": float(noise),
        "fingerprint": scope.fingerprint,
        "epoch": int(state.epoch),
        "resume": {
            "opt_nets": _to_cpu(state.opt_nets.state_dict()),
            "opt_codes": {"step": step, "exp_avg": full["exp_avg"], "exp_avg_sq": full["exp_avg_sq"],
                          "param_groups": code_state["param_groups"]},
            "numpy_rng": [g["rng"] for g in gathered],
            "torch_rng": torch.get_rng_state(),
        },
        "info": {**state.info, "history": list(state.history)},
    }


def _to_cpu(obj):
    """``obj`` (a state dict: tensors in dicts and lists) with every tensor detached and on the CPU."""
    if torch.is_tensor(obj):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_to_cpu(v) for v in obj]
    return obj


def restore_state(state, checkpoint, local, rank, device):
    """Continue from ``checkpoint``: weights, this rank's codes and their optimiser moments, random states, epoch,
    history and provenance."""
    state.nets.mean_net.load_state_dict(checkpoint["mean_state"])
    state.nets.cov_net.load_state_dict(checkpoint["cov_state"])
    r = checkpoint["resume"]
    state.opt_nets.load_state_dict(r["opt_nets"])
    with torch.no_grad():
        state.codes.copy_(checkpoint["codes"][local].to(device))
    code_state = r["opt_codes"]
    state.opt_codes.load_state_dict({"state": {0: {"step": code_state["step"], "exp_avg": code_state["exp_avg"][local],
                                                   "exp_avg_sq": code_state["exp_avg_sq"][local]}},
                                     "param_groups": code_state["param_groups"]})
    state.rng.bit_generator.state = r["numpy_rng"][rank]
    torch.set_rng_state(r["torch_rng"])
    state.epoch = int(checkpoint["epoch"])
    state.history = list(checkpoint.get("info", {}).get("history", []))
    state.info = dict(checkpoint.get("info", {}))
    state.info.setdefault("train_seconds", 0.0)


def check_output(out):
    """Raise one :class:`TrainingInputError` naming ``out`` unless a checkpoint can be written there: ``out`` is not
    a folder, and the nearest of its folders that exists (the missing ones are created when the file is written) is
    a folder a file can be created in (tried with a nameless temporary file, so permissions, read-only file systems
    and the like all count)."""
    out = Path(out)
    if out.is_dir():
        raise TrainingInputError(f"{out}: is a folder; name the checkpoint file to write (e.g. {out / 'model.pt'})")
    folder = out.parent
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir():
        raise TrainingInputError(f"{out}: cannot be written, {folder} is a file, not a folder")
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise TrainingInputError(f"{out}: cannot be written, no file can be created in folder {folder} "
                                 f"({exc.strerror})") from None


def checkpoint_to_resume(out, collection, data, resume, overwrite):
    """The checkpoint at ``out`` to continue (``resume``), None to start afresh; refuses to replace ``out`` unless
    ``overwrite``, and to resume a checkpoint of other data."""
    if not out.exists():
        return None
    if not resume:
        if overwrite:
            return None
        raise TrainingInputError(f"{out}: already exists (pass --resume to continue it or --overwrite to replace it)")
    try:
        checkpoint = read_checkpoint(out)
    except (ValueError, FileNotFoundError) as exc:
        raise TrainingInputError(str(exc)) from None
    if checkpoint.get("fingerprint", "") != collection.fingerprint():
        raise TrainingInputError(f"{out}: this checkpoint was trained on another collection than {data} "
                                 f"(fingerprints differ); use a new --out or the original data")
    return checkpoint


def frame_dict(frame):
    """The training frame as the checkpoint stores it (:meth:`datasets.frame.Frame.as_dict`); None is the identity."""
    if frame is None:
        frame = Frame.identity()
    elif isinstance(frame, dict):
        frame = Frame.from_dict(frame)
    return frame.as_dict()
