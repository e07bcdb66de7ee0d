"""Reading what inspection scores: collections, folders of scanner files and cloud files, in the model's frame."""
from pathlib import Path

from .errors import InspectionError, about

COLLECTION_SUFFIXES = (".h5", ".hdf5")


def load_scans(data, frame=None, split=None, label=None, model_fingerprint="", errors="raise"):
    """Scans to inspect, in the model's frame.

    Parameters
    ----------
    data : str or Path
        A collection file (.h5), a folder of scanner files (tree or flat, see datasets.importer) or one cloud file.
    frame : datasets.Frame, optional
        The model's frame: a collection must have been stored in it; scanner files are moved into it.
    split : str, optional
        Keep only this split ('train', 'validation', 'test') when the data has splits; None keeps all.
    label : str, optional
        Keep only this label.
    errors : {'raise', 'collect'}
        A scan that cannot be read (damaged, NaN points, content that does not match its stored hash, an unreadable
        scanner file): an :class:`InspectionError` naming it, or collected.

    Returns
    -------
    scans : list of Scan
    info : dict
        ``source``, ``kind`` ('collection' / 'files'), ``fingerprint`` (collections), ``same_as_training``,
        ``frame``, and ``failed``: a list of (scan name, reason) of the scans that could not be read (``'collect'``).
    """
    from datasets import ScanReadError
    from datasets.cloud_io import CLOUD_SUFFIXES
    from datasets.importer import ScanSource, find_sources, load_source

    data = Path(data)
    if not data.exists():
        raise InspectionError(f"{data}: no such file or folder")
    info = {"source": str(data), "failed": []}
    if data.is_file() and data.suffix.lower() in COLLECTION_SUFFIXES:
        with open_collection(data, frame) as coll:
            idx = coll.select(split=split, label=label)
            fp = coll.fingerprint()
            info.update(kind="collection", fingerprint=fp, same_as_training=bool(model_fingerprint)
                        and fp == model_fingerprint, frame=coll.frame)
            try:
                scans, failed = coll.read_many(idx, errors="collect")
            except ScanReadError as exc:  # pragma: no cover - 'collect' returns them
                raise InspectionError(str(exc)) from None
            if failed and errors == "raise":
                raise InspectionError(str(failed[0]))
            info["failed"] = [(e.scan_name, str(e)) for e in failed]
    elif data.is_dir() or data.suffix.lower() in CLOUD_SUFFIXES:
        if data.is_dir():
            sources = find_sources(data)
        else:
            sources = [ScanSource(data, data.stem, "test", "unknown", "")]
        if frame is None:
            raise InspectionError(f"{data}: scanner files need the model's frame, and this model records none")
        scans = []
        for src in sources:
            if (split is not None and src.split != split) or (label is not None and src.label != label):
                continue
            try:
                scan, _ = load_source(src)
            except (OSError, ValueError) as exc:
                reason = str(about(src.path, exc))
                if errors == "raise":
                    raise InspectionError(reason) from None
                info["failed"].append((src.name, reason))
                continue
            scans.append(frame.apply(scan))
        info.update(kind="files", fingerprint="", same_as_training=False, frame=frame)
    else:
        raise InspectionError(f"{data}: unknown data file type {data.suffix!r} (expected a collection "
                              f"{'/'.join(COLLECTION_SUFFIXES)}, a folder of scans, or a cloud file "
                              f"{'/'.join(CLOUD_SUFFIXES)})")
    for s in scans:
        if len(s.points) == 0:
            raise InspectionError(f"{data}: scan {s.name!r} has no points")
    return scans, info


def open_collection(data, frame=None):
    """A :class:`datasets.ScanCollection` opened on ``data`` (use it as a context manager), checked to be stored in
    the model's ``frame``; InspectionError naming the file otherwise."""
    from datasets import ScanCollection

    try:
        coll = ScanCollection(data)
    except (OSError, ValueError) as exc:
        raise about(data, exc) from None
    if frame is not None and coll.frame != frame:
        coll.close()
        raise InspectionError(f"{data}: collection frame {coll.frame} differs from the model's {frame}; the model was "
                              f"trained on other data (re-import the scans with the model's frame, or pass the "
                              f"scanner files)")
    return coll
