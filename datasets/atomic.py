"""Atomic writes: a file (or folder) appears whole at its path, or not at all.

Every file this toolkit writes (collections, checkpoints, fields, clouds, reports, figures) goes through
:func:`atomic_path`: the writer fills a temporary file in the destination's folder (same file system), which is then
flushed to disk and renamed over the destination. An interruption at any point (an exception, Ctrl-C, kill -9)
leaves the previous file, if any, untouched; a leftover temporary file is hidden (leading dot) and never mistaken
for a result. The final file gets the permissions a plain ``open()`` would give (0o666 minus the umask; folders 0o777
minus the umask), not the 0o600 of ``tempfile.mkstemp``: exported files are meant to be read by others.
"""
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path


def _umask():
    umask = os.umask(0)  # the only portable way to read the umask is to set it; restore it at once
    os.umask(umask)
    return umask


def _temporary_file(path, suffix):
    """An empty hidden temporary file beside ``path`` (Path); an OSError that names ``path`` when none can be made."""
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    except OSError as e:  # name the destination asked for, not a temporary file nobody has heard of
        raise OSError(e.errno, f"cannot write a file in {path.parent} ({e.strerror})", str(path)) from None
    os.close(fd)
    return Path(tmp)


def check_writable(path):
    """Raise now the OSError that writing ``path`` with :func:`atomic_path` or :func:`atomic_directory` would raise
    at the end (folder missing or read-only), so a long job fails before its work, not after.

    Creates and removes one hidden temporary file in ``path``'s folder; creates no folder.
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path.parent}: output folder does not exist")
    _temporary_file(path, ".tmp").unlink()


@contextmanager
def atomic_path(path, suffix=".tmp"):
    """A temporary path to write instead of ``path``; moved onto ``path`` when the block ends without error.

    Parameters
    ----------
    path : str or Path
        The destination; its parent folders are created.
    suffix : str
        Suffix of the temporary file (writers that choose a format by suffix, e.g. matplotlib, need the real one).

    Yields
    ------
    Path
        An existing, empty temporary file beside ``path``; the block writes it (by name, or reopening it).

    Examples
    --------
    >>> with atomic_path("out/model.pt") as tmp:  # doctest: +SKIP
    ...     torch.save(state, tmp)
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary_file(path, suffix)
    try:
        yield tmp
        with open(tmp, "rb") as fh:  # on disk before it takes the destination's name (power loss, not just kill)
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_directory(path):
    """A temporary folder to fill instead of ``path``; swapped in for ``path`` (replacing it) on success.

    The old folder is moved aside before the new one is renamed into place and deleted after, so ``path`` is at
    every moment either the complete old folder, absent for the instant between two renames, or the complete new
    one. On error the temporary folder is removed and ``path`` is left as it was.

    Yields
    ------
    Path
        An empty folder beside ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp's 0o700 would make the folder private
        old = None
        if path.exists():
            old = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".old"))
            os.replace(path, old / path.name)
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
