"""Reading what inspection scores: collections, folders of scanner files and cloud files, in the model's frame.

One reading of a file (issue 47): a scanner file is read by the rules its model's training collection was imported
with (:class:`datasets.reading.Reading`, carried by the calibration as ``Inspector.reading_``), and a scan without a
sensor origin whose normal signs the reading leaves to the good surface has them decided, when it is scored, by the
good scans' surface the calibration holds (:func:`signed_for_scoring`), whether it comes from a collection or a file.
"""
import weakref
from dataclasses import replace
from pathlib import Path

import numpy as np

from .errors import InspectionError, about

COLLECTION_SUFFIXES = (".h5", ".hdf5")


def load_scans(data, frame=None, split=None, label=None, model_fingerprint="", errors="raise", reading=None):
    """Scans to inspect, in the model's frame.

    Parameters
    ----------
    data : str or Path
        A collection file (.h5), a folder of scanner files (tree or flat, see datasets.importer) or one cloud file.
    frame : datasets.Frame, optional
        The model's frame: a collection must have been stored in it; scanner files are moved into it.
    reading : datasets.reading.Reading or dict, optional
        How scanner files are read (:func:`read_file`): the model's training collection's reading, as the
        calibration carries it (``Inspector.reading_``); None: the default reading. A collection's scans were read
        by its own import, recorded in its provenance; those without a sensor origin whose signs that reading leaves
        to the good surface are marked so (:func:`datasets.reading.mark_signs`).
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
    from datasets.importer import ScanSource, find_sources
    from datasets.reading import Reading, mark_signs

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
            try:
                imported = Reading.from_provenance(coll.provenance)
            except ValueError as exc:
                raise InspectionError(f"{data}: {exc}") from None
            scans = [mark_signs(s, imported) for s in scans]
    elif data.is_dir() or data.suffix.lower() in CLOUD_SUFFIXES:
        if data.is_dir():
            sources = find_sources(data)
        else:
            sources = [ScanSource(data, data.stem, "test", "unknown", "")]
        if frame is None:
            raise InspectionError(f"{data}: scanner files need the model's frame, and this model records none")
        reading = checked_reading(reading)
        scans = []
        for src in sources:
            if (split is not None and src.split != split) or (label is not None and src.label != label):
                continue
            try:
                scans.append(read_file(src, frame, reading))
            except InspectionError as exc:
                if errors == "raise":
                    raise
                info["failed"].append((src.name, str(exc)))
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


def checked_reading(reading):
    """``reading`` (a :class:`datasets.reading.Reading`, its dict, or None: the default) as a Reading; an
    InspectionError when a stored record cannot be read."""
    from datasets.reading import Reading

    try:
        return Reading.from_dict(reading)
    except (TypeError, ValueError) as exc:
        raise InspectionError(f"the calibration's reading of scanner files: {exc}") from None


def read_file(src, frame, reading=None):
    """One scanner file read as the model's training collection read its files, moved into the model's frame.

    Parameters
    ----------
    src : datasets.importer.ScanSource
    frame : datasets.Frame
        The model's frame.
    reading : datasets.reading.Reading, dict or None
        The training collection's reading (:func:`datasets.importer.read_scan`); None: the default.

    Returns
    -------
    Scan
        In the model's frame; marked when its normal signs are left to the good surface.

    Raises
    ------
    InspectionError
        Naming the file: it cannot be read as a scan.
    """
    from datasets.importer import read_scan

    try:
        scan, _ = read_scan(src, checked_reading(reading))
    except (OSError, ValueError) as exc:
        raise about(src.path, exc) from None
    return frame.apply(scan)


def reading_of(data):
    """The reading (a dict, :meth:`datasets.reading.Reading.as_dict`) a collection's import applied to its files,
    from its provenance; None for anything else (scans given as a list). What ``Inspector.fit`` records as
    ``reading_``, so that the files scored later are read the same."""
    from datasets.reading import Reading

    provenance = getattr(data, "provenance", None)
    if not isinstance(provenance, dict):
        return None
    return Reading.from_provenance(provenance).as_dict()


# the good surface of each reference, built once: reference -> (index, normals, spacing) or None
_SURFACES = weakref.WeakKeyDictionary()


def reference_surface(reference):
    """The good scans' surface a per-location reference holds, as :func:`datasets.layouts.orient_by_surface`
    takes it: (nearest-neighbour index over its distinct points, their unit outward normals (M, 3), their median
    nearest-neighbour distance over all of them), in the model's frame; None without a reference or without surface
    normals. Built once per reference, the same for a fitted inspector and one restored from its calibration."""
    if reference is None:
        return None
    try:
        return _SURFACES[reference]
    except (KeyError, TypeError):
        pass
    oriented = reference.oriented_surface() if hasattr(reference, "oriented_surface") else None
    surface = None
    if oriented is not None and oriented[0].n >= 2:
        index, normals = oriented
        d = index.query(index.data, 2)[0][:, 1]  # every point (a sample would depend on the points' order)
        d = d[d > 0]
        if len(d):
            surface = (index, np.asarray(normals, dtype=np.float64), float(np.median(d)))
    try:
        _SURFACES[reference] = surface
    except TypeError:  # not weakly referenceable: built again next time
        pass
    return surface


def signed_for_scoring(scan, reference):
    """``scan`` with its normal signs decided by the good surface, when it is marked so; as it is otherwise.

    A scan without a sensor origin whose normals were estimated, read by a reading that leaves their signs to the
    good surface (``scan.extra[datasets.reading.SIGNS_KEY]``), gets them from :func:`datasets.layouts.orient_by_surface`
    over the good scans' surface of ``reference`` (:func:`reference_surface`; without one, the estimator's
    consistent orientation). The result depends on the scan's points and its normals' lines only, so an imported scan
    (signed by the templates at import) and the same file read from a folder score the same. The scan must be in
    the reference's frame (after any registration).

    A point counts as lying on the surface within 3 spacings of the coarser of the two samplings, the surface's or
    the scan's own (:func:`datasets.layouts.cloud_spacing`): the surface is the union of many overlapping good scans
    (views of 4 templates, say), whose spacing is finer than one scan's, where the import measured the templates'
    spacing one template at a time.

    Parameters
    ----------
    scan : Scan or anything the Inspector scores
        Only a :class:`datasets.Scan`-like with ``extra`` can be marked; anything else is returned as it is.
    reference : inspection.reference.LocalReference or None

    Returns
    -------
    Scan
        A new scan when its normals were signed (``scan`` itself is not modified).
    """
    from datasets.layouts import cloud_spacing, orient_by_surface
    from datasets.reading import SIGNS_FROM_SURFACE, SIGNS_KEY

    extra = getattr(scan, "extra", None)
    if not (isinstance(extra, dict) and extra.get(SIGNS_KEY) == SIGNS_FROM_SURFACE):
        return scan
    surface = reference_surface(reference)
    if surface is not None:
        surface = (surface[0], surface[1], max(surface[2], cloud_spacing(scan.points)))
    normals, _ = orient_by_surface(scan.points, scan.normals, surface)
    return replace(scan, normals=normals, extra=dict(extra))
