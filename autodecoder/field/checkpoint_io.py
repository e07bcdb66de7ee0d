"""Atomic writes and safe reads of torch files (fields, checkpoints)."""
import os
import tempfile
from pathlib import Path

import torch


def atomic_torch_save(obj, path):
    """``torch.save`` to a temporary file beside ``path``, then rename it into place.

    An interrupted write leaves any previous file at ``path`` untouched and no partial file behind.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            torch.save(obj, fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


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
