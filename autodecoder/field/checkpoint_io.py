"""Atomic writes and safe reads of torch files (fields, checkpoints)."""
from pathlib import Path

import torch

from datasets.atomic import atomic_path


def atomic_torch_save(obj, path):
    """``torch.save`` through :func:`datasets.atomic.atomic_path`: an interrupted write leaves any previous file at
    ``path`` untouched and no partial file behind."""
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def load_torch_file(path, what="file"):
    """``torch.load(path, weights_only=True)`` with one clear error for a missing, foreign or corrupt file.

    Parameters
    ----------
    path : str or Path
    what : str
        What the file should be, for the message ("model checkpoint", "stochastic field").
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such {what}")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many types for foreign bytes; all mean "not readable"
        raise ValueError(f"{path}: not a readable {what} ({type(exc).__name__}: {str(exc).splitlines()[0][:200]})") from None
