"""The HDF5 scan collection: many scans in one versioned, chunked, compressed file (schema: docs/collection_format.md).

Layout in one paragraph: all scans' points are concatenated into ``/points`` (P, 3) (likewise ``/normals``,
``/point_labels`` and ``/point_deviation``), and scan ``i`` owns rows ``offsets[i]:offsets[i + 1]``; per-scan
metadata lives in ``/scans/*`` arrays of length S; the collection's frame and provenance are root attributes. Reading
one scan reads one slice.

The per-point deviations (``Scan.point_deviation``: ground truth of how far each point lies off the good surface)
are optional datasets of format version 1 (``/point_deviation``, ``/scans/has_deviation``): a file written before
them reads with ``point_deviation=None``, and appending to it adds them (zeros, flag 0 for the scans it holds). They
are in neither the content hashes nor the fingerprint: an annotation beside the data, like a sidecar, that must not
change the key of the models cached for the data (docs/collection_format.md).
"""
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .frame import Frame
from .scan import LABELS, SPLITS, Scan
from .validation import ScanReadError, _points_problem

FORMAT_NAME = "nsspr-scan-collection"
FORMAT_VERSION = 1

# 4096 rows * 3 * 4 B = 48 KiB per points chunk: a 20k-point scan touches 5-6 chunks, so a random read decompresses
# little beyond its own rows (larger chunks cost more CPU per read for the same file size). gzip level 1 + shuffle:
# the size of higher levels at less write time, and unlike lzf every HDF5 build can read it (lzf is h5py-only).
# Measurements (python -m benchmarks data --mode io): docs/collection_format.md. Per-scan arrays: 4096 rows.
POINT_CHUNK_ROWS = 4096
SCAN_CHUNK_ROWS = 4096
DEFAULT_COMPRESSION = ("gzip", 1)
# points buffered before a write, so chunks are written whole instead of re-compressed once per scan
_WRITE_BATCH_POINTS = 1 << 20

_STRING_FIELDS = ("name", "split", "label", "defect", "part_id")


def _toolkit_version():
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("nsspr-inspect")
    except PackageNotFoundError:
        return "0+unknown"


def _content_hash(points, normals, point_labels):
    """sha256 hex over one scan's arrays exactly as stored (little-endian float32 / uint8)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(points, dtype="<f4"))  # hashlib reads the array's buffer: no copy
    h.update(np.ascontiguousarray(normals, dtype="<f4"))
    if point_labels is not None:
        h.update(np.ascontiguousarray(point_labels, dtype="u1"))
    return h.hexdigest()


def _check_scan(scan, where):
    if not isinstance(scan, Scan):
        raise TypeError(f"{where}: expected a Scan, got {type(scan).__name__}")
    if not isinstance(scan.name, str) or not scan.name:
        raise ValueError(f"{where}: scan name must be a non-empty string, got {scan.name!r}")
    if not np.all(np.isfinite(scan.points)) or not np.all(np.isfinite(scan.normals)):
        raise ValueError(f"{where}: scan {scan.name!r} has non-finite points or normals; drop them before storing")
    if scan.split not in SPLITS or scan.label not in LABELS:  # Scan checks this too, unless fields were reassigned
        raise ValueError(f"{where}: scan {scan.name!r} has split {scan.split!r} / label {scan.label!r}")
    deviation = scan.point_deviation
    if deviation is not None and (np.shape(deviation) != (len(scan),) or not np.all(np.isfinite(deviation))):
        raise ValueError(f"{where}: scan {scan.name!r} has point deviations of shape {np.shape(deviation)} for "
                         f"{len(scan)} points, or NaN / Inf ones")


def _add_deviation_datasets(h5, big, small):
    """Create ``/point_deviation`` (P,) and ``/scans/has_deviation`` (S,), zeros, in a file that lacks them (a new
    one, or one written before they existed: its scans then have no deviations)."""
    n_points, n_scans = h5["points"].shape[0], h5["scans/n_points"].shape[0]
    h5.create_dataset("point_deviation", data=np.zeros(n_points, "<f4"), maxshape=(None,),
                      chunks=(POINT_CHUNK_ROWS,), **big)
    h5["scans"].create_dataset("has_deviation", data=np.zeros(n_scans, "u1"), maxshape=(None,),
                               chunks=(SCAN_CHUNK_ROWS,), **small)


def _filters(ds):
    """The creation options (filters, no times) of dataset ``ds``, for a dataset added beside it."""
    return dict(compression=ds.compression, compression_opts=ds.compression_opts, shuffle=ds.shuffle,
                track_times=False)


def _new_file_layout(h5, frame, provenance, compression):
    """Create the empty datasets and root attributes of a version-1 collection in the open h5py file ``h5``."""
    import h5py

    comp, level = compression if isinstance(compression, tuple) else (compression, None)
    # track_times=False everywhere: HDF5 otherwise stamps each dataset with its creation time, and the same inputs
    # must give a byte-identical file.
    big = dict(compression=comp, compression_opts=level, shuffle=comp is not None, track_times=False)
    small = dict(compression="gzip" if comp else None, shuffle=False, track_times=False)
    h5.create_dataset("points", shape=(0, 3), maxshape=(None, 3), dtype="<f4", chunks=(POINT_CHUNK_ROWS, 3), **big)
    h5.create_dataset("normals", shape=(0, 3), maxshape=(None, 3), dtype="<f4", chunks=(POINT_CHUNK_ROWS, 3), **big)
    h5.create_dataset("point_labels", shape=(0,), maxshape=(None,), dtype="u1", chunks=(POINT_CHUNK_ROWS,), **big)
    g = h5.create_group("scans")
    for key in _STRING_FIELDS:
        g.create_dataset(key, shape=(0,), maxshape=(None,), dtype=h5py.string_dtype("utf-8"),
                         chunks=(SCAN_CHUNK_ROWS,), **small)
    g.create_dataset("n_points", shape=(0,), maxshape=(None,), dtype="<i8", chunks=(SCAN_CHUNK_ROWS,), **small)
    g.create_dataset("offsets", data=np.zeros(1, "<i8"), maxshape=(None,), chunks=(SCAN_CHUNK_ROWS,), **small)
    g.create_dataset("has_labels", shape=(0,), maxshape=(None,), dtype="u1", chunks=(SCAN_CHUNK_ROWS,), **small)
    g.create_dataset("sensor_origin", shape=(0, 3), maxshape=(None, 3), dtype="<f4", chunks=(SCAN_CHUNK_ROWS, 3),
                     **small)
    g.create_dataset("content_sha256", shape=(0,), maxshape=(None,), dtype="S64", chunks=(SCAN_CHUNK_ROWS,), **small)
    _add_deviation_datasets(h5, big, small)
    h5.attrs["format"] = FORMAT_NAME
    h5.attrs["format_version"] = np.int64(FORMAT_VERSION)
    h5.attrs["frame_center"] = np.asarray(frame.center, dtype="<f8")
    h5.attrs["frame_scale"] = np.float64(frame.scale)
    h5.attrs["provenance"] = json.dumps(provenance or {}, sort_keys=True)
    h5.attrs["toolkit_version"] = _toolkit_version()


class _Appender:
    """Appends scans to an open collection file, buffering ~1M points so each chunk is compressed once."""

    def __init__(self, h5, where):
        self.h5, self.where = h5, where
        if "point_deviation" not in h5:  # a file written before the deviations: its scans have none
            _add_deviation_datasets(h5, _filters(h5["point_labels"]), _filters(h5["scans/has_labels"]))
        self.names = set(h5["scans/name"].asstr()[()].tolist())
        self.buf = []
        self.buf_points = 0

    def add(self, scan):
        _check_scan(scan, self.where)
        if scan.name in self.names:
            raise ValueError(f"{self.where}: duplicate scan name {scan.name!r}")
        self.names.add(scan.name)
        self.buf.append(scan)
        self.buf_points += len(scan)
        if self.buf_points >= _WRITE_BATCH_POINTS:
            self.flush()

    def flush(self):
        if not self.buf:
            return
        h5, scans = self.h5, self.buf
        g = h5["scans"]
        p0, s0 = h5["points"].shape[0], g["n_points"].shape[0]
        counts = np.array([len(s) for s in scans], dtype="<i8")
        p1, s1 = p0 + int(counts.sum()), s0 + len(scans)

        def grow(ds, n):
            ds.resize(n, axis=0)

        for key in ("points", "normals", "point_labels", "point_deviation"):
            grow(h5[key], p1)
        h5["points"][p0:p1] = np.concatenate([s.points for s in scans])
        h5["normals"][p0:p1] = np.concatenate([s.normals for s in scans])
        h5["point_labels"][p0:p1] = np.concatenate(
            [s.point_labels if s.point_labels is not None else np.zeros(len(s), "u1") for s in scans])
        h5["point_deviation"][p0:p1] = np.concatenate(
            [s.point_deviation if s.point_deviation is not None else np.zeros(len(s), "<f4") for s in scans])
        for key in (*_STRING_FIELDS, "n_points", "has_labels", "has_deviation", "sensor_origin", "content_sha256"):
            grow(g[key], s1)
        for key in _STRING_FIELDS:
            g[key][s0:s1] = np.array([getattr(s, key) for s in scans], dtype=object)
        g["n_points"][s0:s1] = counts
        g["has_labels"][s0:s1] = np.array([s.point_labels is not None for s in scans], dtype="u1")
        g["has_deviation"][s0:s1] = np.array([s.point_deviation is not None for s in scans], dtype="u1")
        g["sensor_origin"][s0:s1] = np.array(
            [s.sensor_origin if s.sensor_origin is not None else np.full(3, np.nan) for s in scans], dtype="<f4")
        g["content_sha256"][s0:s1] = np.array(
            [_content_hash(s.points, s.normals, s.point_labels).encode() for s in scans], dtype="S64")
        offsets = g["offsets"]
        grow(offsets, s1 + 1)
        offsets[s0 + 1:s1 + 1] = p0 + np.cumsum(counts)
        self.buf, self.buf_points = [], 0


def _atomic_write(path, fill, copy_from=None):
    """Write ``path`` through :func:`datasets.atomic.atomic_path`: ``fill(h5)`` fills the open temporary file (a
    copy of ``copy_from`` when given). Any exception leaves ``path`` as it was and removes the temporary file."""
    import h5py

    with atomic_path(path) as tmp:
        if copy_from is not None:
            shutil.copyfile(copy_from, tmp)
        with h5py.File(tmp, "r+" if copy_from is not None else "w") as h5:
            fill(h5)


def _open_h5(path):
    """Open ``path`` read-only as a version-1 collection, or raise one ValueError that names it and the problem."""
    import h5py

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such scan collection")
    if path.is_dir():
        raise ValueError(f"{path}: is a folder, not a scan collection file")
    try:
        h5 = h5py.File(path, "r")
    except OSError as e:
        msg = str(e)
        if "signature" in msg:
            why = "not an HDF5 file"
        elif "truncated" in msg:
            why = "truncated HDF5 file (was a write interrupted?)"
        else:
            why = f"cannot be read as HDF5 ({msg})"
        raise ValueError(f"{path}: {why}") from None
    try:
        fmt = h5.attrs.get("format")
        fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
        if fmt != FORMAT_NAME:
            raise ValueError(f"{path}: an HDF5 file but not a scan collection (attribute 'format' is {fmt!r}, "
                             f"expected {FORMAT_NAME!r})")
        version = h5.attrs.get("format_version")
        if not (isinstance(version, (int, np.integer)) and version == FORMAT_VERSION):
            raise ValueError(f"{path}: scan collection format version {version} is not supported "
                             f"(this toolkit reads version {FORMAT_VERSION})")
        required = ["points", "normals", "point_labels"] + [f"scans/{k}" for k in (
            *_STRING_FIELDS, "n_points", "offsets", "has_labels", "sensor_origin", "content_sha256")]
        missing = [k for k in required if k not in h5]
        if missing:
            raise ValueError(f"{path}: damaged scan collection, missing datasets {missing}")
    except ValueError:
        h5.close()
        raise
    except (OSError, TypeError) as e:
        h5.close()
        raise ValueError(f"{path}: damaged scan collection ({e})") from None
    return h5


def _scan_index(h5):
    """The per-scan arrays of an open collection: (string fields {key: list}, n_points, offsets, has_labels,
    has_deviation, sensor_origin, content hashes). ValueError unless they have S rows each and the offsets match the
    counts and the point arrays."""
    g = h5["scans"]
    meta = {k: g[k].asstr()[()].tolist() for k in _STRING_FIELDS}
    n_points, offsets = g["n_points"][()].astype(np.int64), g["offsets"][()].astype(np.int64)
    has_labels, has_deviation = g["has_labels"][()].astype(bool), _deviation_flags(h5, len(n_points))
    origin, hashes = g["sensor_origin"][()].astype(np.float32), g["content_sha256"][()]
    s = len(n_points)
    lengths = [len(offsets) - 1, len(has_labels), len(has_deviation), len(origin), len(hashes),
               *map(len, meta.values())]
    if not (all(n == s for n in lengths) and origin.shape[1:] == (3,) and offsets[0] == 0
            and offsets[-1] == h5["points"].shape[0] and (n_points >= 0).all()
            and np.array_equal(np.diff(offsets), n_points)):
        raise ValueError("offsets, counts and per-scan arrays disagree")
    return meta, n_points, offsets, has_labels, has_deviation, origin, hashes


def _deviation_flags(h5, n_scans):
    """(S,) bool: which scans have per-point deviations. A file written before they existed has neither dataset (all
    False); a file with one of the two, or with ``/point_deviation`` shorter than ``/points``, is damaged."""
    have = ("point_deviation" in h5, "scans/has_deviation" in h5)
    if not any(have):
        return np.zeros(n_scans, dtype=bool)
    if not all(have) or h5["point_deviation"].shape != (h5["points"].shape[0],):
        raise ValueError("/point_deviation and /scans/has_deviation disagree with each other or with /points")
    return h5["scans/has_deviation"][()].astype(bool)


def _data_fingerprint(frame, meta, offsets, has_labels, sensor_origin, hashes):
    """sha256 hex of a collection's data (:meth:`ScanCollection.fingerprint`): the format, the frame, the per-scan
    string fields, the offsets, which scans have labels, the sensor origins (NaN: none) and the content hashes."""
    h = hashlib.sha256()
    h.update(f"{FORMAT_NAME}/{FORMAT_VERSION}\n".encode())
    h.update(json.dumps(frame.as_dict(), sort_keys=True).encode())
    h.update(json.dumps([meta[k] for k in _STRING_FIELDS], ensure_ascii=False).encode())
    h.update(offsets.astype("<i8").tobytes())
    h.update(has_labels.astype("u1").tobytes())
    h.update(np.nan_to_num(sensor_origin, nan=np.inf).astype("<f4").tobytes())  # one NaN bit pattern
    h.update(b"".join(hashes.tolist()))
    return h.hexdigest()


class ScanCollection:
    """A read-only view of a collection file; reads one scan's slice at a time.

    Use as a context manager or call :meth:`close`. Per-scan metadata (S strings and numbers) is read once at open;
    points are read on demand, so iterating holds one scan in memory at a time whatever the number of scans.

    Every scan read is checked: its arrays must have matching shapes and finite values and must match the scan's
    stored ``content_sha256``; otherwise reading it raises :class:`datasets.validation.ScanReadError` (a ValueError
    carrying the file, the scan's stored name and its index). :meth:`read_many` with ``errors="collect"`` reads the
    readable scans and returns the errors of the others.

    Parameters
    ----------
    path : str or Path
        A file written by :meth:`create` / :meth:`append`.

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ValueError
        The file is not HDF5, not a collection, another format version, truncated or damaged (message names it).
    """

    def __init__(self, path):
        self.path = Path(path)
        self._h5 = _open_h5(self.path)
        try:
            (self._meta, self._n_points, self._offsets, self._has_labels, self._has_deviation, self._sensor_origin,
             self._hashes) = _scan_index(self._h5)
            self._frame = Frame(np.asarray(self._h5.attrs["frame_center"]), float(self._h5.attrs["frame_scale"]))
            self._provenance = json.loads(self._h5.attrs.get("provenance", "{}"))
            self.toolkit_version = str(self._h5.attrs.get("toolkit_version", ""))
        except (OSError, KeyError, TypeError, ValueError) as e:  # JSONDecodeError is a ValueError
            self._h5.close()
            raise ValueError(f"{self.path}: damaged scan collection ({e})") from None
        self._index = {n: i for i, n in enumerate(self._meta["name"])}

    # ---- writing -------------------------------------------------------------------------------------------------
    @classmethod
    def create(cls, path, scans, frame=None, provenance=None, overwrite=False, compression=DEFAULT_COMPRESSION):
        """Write a new collection file atomically (:func:`datasets.atomic.atomic_path`).

        Parameters
        ----------
        path : str or Path
        scans : iterable of Scan
            Already in the collection frame; may be a generator (scans are written in ~1M-point batches).
        frame : Frame, optional
            The file -> collection transform the scans were moved by; identity by default.
        provenance : dict, optional
            JSON-serialisable description of where the data came from (stored, not part of the fingerprint).
        overwrite : bool
            Replace an existing file; otherwise FileExistsError.
        compression : (str, int or None) or str or None
            HDF5 filter for the point arrays: ("gzip", level), "lzf" or None.

        Returns
        -------
        Path
            ``path``.
        """
        path = Path(path)
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path}: already exists (pass overwrite=True to replace it)")
        if not path.parent.is_dir():
            raise FileNotFoundError(f"{path.parent}: folder does not exist")
        frame = Frame.identity() if frame is None else frame
        json.dumps(provenance or {})  # fail before touching the disk if provenance is not JSON-serialisable

        def fill(h5):
            _new_file_layout(h5, frame, provenance, compression)
            app = _Appender(h5, str(path))
            for scan in scans:
                app.add(scan)
            app.flush()

        _atomic_write(path, fill)
        return path

    @classmethod
    def append(cls, path, scans):
        """Add scans to an existing collection atomically: copy to a temporary file, append, rename into place.

        The copy costs one read and write of the file, which is fine at our sizes (a few GB) and means a failure
        mid-append leaves the original untouched. Scans must already be in the collection's frame. A file written
        before the per-point deviations existed gets their datasets (zeros: its scans have none).

        Parameters
        ----------
        path : str or Path
        scans : iterable of Scan
            Names must not repeat each other or the names already stored (ValueError).
        """
        path = Path(path)
        cls(path).close()  # validates the file first, with the usual clear errors

        def fill(h5):
            app = _Appender(h5, str(path))
            for scan in scans:
                app.add(scan)
            app.flush()

        _atomic_write(path, fill, copy_from=path)
        return path

    # ---- reading -------------------------------------------------------------------------------------------------
    def close(self):
        """Close the HDF5 handle (idempotent)."""
        if self._h5 is not None:
            self._h5.close()
            self._h5 = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown: h5py may already be gone
            pass

    def __len__(self):
        return len(self._n_points)

    def __repr__(self):
        return f"ScanCollection({str(self.path)!r}, {len(self)} scans)"

    def _live(self):
        if self._h5 is None:
            raise ValueError(f"{self.path}: collection is closed")
        return self._h5

    def _norm_index(self, i):
        n = len(self)
        i = int(i)
        if not -n <= i < n:
            raise IndexError(f"{self.path}: scan index {i} out of range for {n} scans")
        return i % n

    def __getitem__(self, i):
        """Scan ``i`` (negative indices count from the end); reads only that scan's rows.

        Raises
        ------
        IndexError
            ``i`` is out of range.
        ScanReadError
            The scan's rows cannot be read, have the wrong shapes, hold NaN or Inf, or do not match its stored
            ``content_sha256``; the message names the file, the scan's stored name and its index.
        """
        if isinstance(i, slice):
            return self.read_many(range(*i.indices(len(self))))
        i = self._norm_index(i)
        h5 = self._live()
        name = self._meta["name"][i]
        a, b = int(self._offsets[i]), int(self._offsets[i + 1])
        try:
            points = h5["points"][a:b]
            normals = h5["normals"][a:b]
            labels = h5["point_labels"][a:b] if self._has_labels[i] else None
            deviation = h5["point_deviation"][a:b] if self._has_deviation[i] else None
        except OSError as e:
            raise ScanReadError(f"cannot be read, the file is damaged ({e})", self.path, name, i) from None
        for key, arr in (("points", points), ("normals", normals)):
            problem = _points_problem(arr, min_points=0)
            if problem:
                raise ScanReadError(f"{key} {problem}", self.path, name, i)
        origin = self._sensor_origin[i]
        try:  # checks the shapes against each other, and the split and label
            scan = Scan(name=name, points=points, normals=normals, split=self._meta["split"][i],
                        label=self._meta["label"][i], defect=self._meta["defect"][i],
                        part_id=self._meta["part_id"][i], point_labels=labels, point_deviation=deviation,
                        sensor_origin=None if np.isnan(origin).any() else origin.copy())
        except ValueError as e:
            raise ScanReadError(str(e).removeprefix(f"scan {name!r}: "), self.path, name, i) from None
        # ~0.1 ms for 4,000 points, against ~1 ms to read and decompress them (docs/collection_format.md)
        if _content_hash(scan.points, scan.normals, scan.point_labels).encode() != self._hashes[i]:
            raise ScanReadError("content does not match its stored content_sha256: the file was modified or "
                                "damaged", self.path, name, i)
        return scan

    def read_many(self, indices, errors="raise"):
        """Scans at ``indices``, in the order given.

        Parameters
        ----------
        indices : iterable of int
        errors : {'raise', 'collect'}
            What an unreadable scan (:class:`datasets.validation.ScanReadError`: NaN or Inf, wrong shapes, content
            that does not match its stored hash) does: ``'raise'`` (default) raises its error; ``'collect'`` skips
            it and goes on with the others.

        Returns
        -------
        list of Scan
            With ``errors='raise'``.
        (scans, failed) : (list of Scan, list of ScanReadError)
            With ``errors='collect'``: the readable scans in the order given, and one error per unreadable scan, in
            the order given; each carries ``.path``, ``.scan_name`` and ``.index``.
        """
        if errors not in ("raise", "collect"):
            raise ValueError(f"errors must be 'raise' or 'collect', got {errors!r}")
        if errors == "raise":
            return [self[i] for i in indices]
        scans, failed = [], []
        for i in indices:
            try:
                scans.append(self[i])
            except ScanReadError as e:
                failed.append(e)
        return scans, failed

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    @property
    def names(self):
        """Scan names in storage order (list of str)."""
        return list(self._meta["name"])

    @property
    def frame(self):
        """The file -> collection :class:`Frame` the scans were stored in."""
        return self._frame

    @property
    def provenance(self):
        """Where the data came from (dict, as given to :meth:`create`)."""
        return json.loads(json.dumps(self._provenance))

    @property
    def n_points(self):
        """(S,) int64 array: points per scan."""
        return self._n_points.copy()

    def metadata(self):
        """One dict per scan, without arrays: index, name, split, label, defect, part_id, n_points, has_labels,
        has_deviation, sensor_origin ([x, y, z] in the collection frame, or None)."""
        out = []
        for i in range(len(self)):
            o = self._sensor_origin[i]
            out.append({"index": i, **{k: self._meta[k][i] for k in _STRING_FIELDS},
                        "n_points": int(self._n_points[i]), "has_labels": bool(self._has_labels[i]),
                        "has_deviation": bool(self._has_deviation[i]),
                        "sensor_origin": None if np.isnan(o).any() else [float(x) for x in o]})
        return out

    def select(self, split=None, label=None, defect=None, part_id=None):
        """Indices (sorted list of int) of the scans matching every given filter.

        Each filter is None (any), one string, or a collection of accepted strings.
        """
        keep = np.ones(len(self), dtype=bool)
        for key, want in (("split", split), ("label", label), ("defect", defect), ("part_id", part_id)):
            if want is None:
                continue
            want = {want} if isinstance(want, str) else set(want)
            keep &= np.array([v in want for v in self._meta[key]], dtype=bool)
        return np.flatnonzero(keep).tolist()

    def index_of(self, name):
        """Index of the scan called ``name``; KeyError naming the file if absent."""
        try:
            return self._index[name]
        except KeyError:
            raise KeyError(f"{self.path}: no scan named {name!r}") from None

    def fingerprint(self):
        """sha256 hex identifying the data: frame, per-scan metadata, offsets and each scan's stored content hash.

        Cheap (reads no points: the per-scan hashes are computed at write time; :meth:`verify` re-checks them).
        Provenance and toolkit version are not part of it: the same data imported twice has the same fingerprint.
        Nor are the per-point deviations (module docstring): a ground-truth annotation, which leaves the models
        cached under the fingerprint valid.
        """
        return _data_fingerprint(self._frame, self._meta, self._offsets, self._has_labels, self._sensor_origin,
                                 self._hashes)

    def verify(self):
        """Read every scan, which recomputes its content hash from its arrays; :class:`ScanReadError` naming the
        first scan that is damaged or differs from its stored hash."""
        for _ in self:
            pass
