"""Watching a scanner's drop folder: score each scan file once it has landed, exactly once, into a verdict journal.

The results folder ``OUT`` holds:

* ``verdicts.jsonl``, the journal: one JSON object per line and per scored file (``name``, ``file``, ``size``,
  ``mtime_ns``, the columns of ``scores.csv``, ``why``: the verdict in words, ``time``, ``seconds``, ``map``). A
  line is appended whole with one ``write`` and made durable (``fsync``) before the next file is read. The journal
  is also the record of what was done: on start it is read back, a torn last line (a crash mid-write) is cut off,
  and every file it records by name, size and modification time is skipped, so a watcher killed at any moment
  (kill -9) and restarted scores each file exactly once. A file that changes afterwards (same name, new size or
  time: a rescan) is scored again.
* ``verdicts.csv``: the same verdicts as a table, rewritten atomically from the journal after each line (never torn).
* ``defects.csv``: the defect regions of the files not told good (:mod:`inspection.regions`), rewritten with it.
* ``maps/<name>.ply``: each scan's anomaly map (``--maps``), written atomically before its journal line.
* ``report.html``: the page ``score`` writes (:mod:`inspection.html_report`: the decision, the verdict table of every
  file in the journal, the score histogram, the 3D maps of the ``REPORT_VIEWS`` most anomalous scans scored since the
  watcher started), rewritten atomically every ``report_every`` scans or ``report_seconds`` seconds, whichever comes
  first, and when the watcher stops. A page that lags the journal by a few scans is the price of not rewriting a
  page of megabytes for every scan; the journal and ``verdicts.csv`` are always up to date.

A file is read once it has *landed*: a visible cloud file (:func:`datasets.cloud_io.is_cloud_file`: a suffix of
:data:`datasets.cloud_io.CLOUD_SUFFIXES`, not starting with a dot) whose size and modification time have not changed
for ``settle`` seconds (and the same for its ``<stem>.json`` sensor-origin sidecar, when there is one). Scanners
that write under a temporary name (a leading dot, or another suffix such as ``.part``) and rename when done need no
settling at all. Other files are ignored (the rule of every command that reads a folder of scans); one line at the
start names those already there.
A file that cannot be read or scored gets one ``error`` line with its reason, and the watcher goes on.
"""
import fcntl
import json
import math
import os
import time
from datetime import datetime, timezone
from pathlib import Path

from .batch_check import DEFAULT_MAX_DEFECTIVE_SHARE, check_max_defective_share
from .errors import InspectionError

JOURNAL = "verdicts.jsonl"
TABLE = "verdicts.csv"
DEFECTS = "defects.csv"  # the defect regions of the files not told good (inspection.regions), one row each
REPORT = "report.html"
LOCK = ".watch.lock"
_SIDECAR = ".json"
REPORT_EVERY = 10  # scans between two rewrites of report.html ...
REPORT_SECONDS = 60.0  # ... or seconds, whichever comes first
DEFAULT_WINDOW = 50  # the batch check's window: the last 50 scans (at the default share a batch of 50 good scans of
# another sensor can fire it, one of 16 cannot: inspection.batch_check)
REPORT_VIEWS = 50  # the most anomalous scans whose 3D maps the page holds (each up to VIEW_POINTS points)


def read_journal(path, repair=True):
    """The entries of a journal (list of dict), in order. A last line without its newline (torn by a crash) is
    cut off the file when ``repair``, else ignored; a complete line that does not parse is an InspectionError
    naming the file and line (the journal is not this watcher's)."""
    path = Path(path)
    if not path.exists():
        return []
    data = path.read_bytes()
    end = data.rfind(b"\n") + 1
    if end < len(data) and repair:  # a torn last line: the file it was about is scored again
        with open(path, "r+b") as fh:
            fh.truncate(end)
            os.fsync(fh.fileno())
    entries = []
    for k, line in enumerate(data[:end].splitlines(), 1):
        try:
            entry = json.loads(line)
            entry["file"], entry["size"], entry["mtime_ns"]  # noqa: B018 - the keys the watcher needs
        except (ValueError, TypeError, KeyError):
            raise InspectionError(f"{path}: line {k} is not a verdict of `watch`; move the file away or choose "
                                  f"another --out") from None
        entries.append(entry)
    return entries


def _key(entry):
    return entry["file"], int(entry["size"]), int(entry["mtime_ns"])


def _json_safe(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if hasattr(value, "item"):  # numpy scalars
        return _json_safe(value.item())
    return value


def landed_files(folder, settle, now=None):
    """The files of ``folder`` ready to be read, sorted by name, as (path, os.stat_result), and how many candidates
    are still settling: visible cloud files whose (and whose sidecar's) modification time is at least ``settle``
    seconds old."""
    from datasets.cloud_io import is_cloud_file

    now = time.time() if now is None else now
    ready, settling = [], 0
    for p in sorted(Path(folder).iterdir()):
        if not is_cloud_file(p):
            continue
        try:
            st = p.stat()
            if not p.is_file():
                continue
            side = p.with_suffix(_SIDECAR)
            newest = max(st.st_mtime, side.stat().st_mtime if side.exists() else 0.0)
        except FileNotFoundError:  # gone between the listing and the look
            continue
        if now - newest >= settle:
            ready.append((p, st))
        else:
            settling += 1
    return ready, settling


class Watcher:
    """Scores the scan files landing in ``folder`` into the results folder ``out`` (module docstring).

    Parameters
    ----------
    model : str or Path
        A calibrated model file.
    folder : str or Path
        The folder the scanner drops files into (its own files only; not searched recursively).
    out : str or Path
        The results folder (created; held by one watcher at a time).
    settle : float
        Seconds a file must stay unchanged before it is read.
    maps : {'all', 'flagged', 'none'}
    alpha : float, optional
        False-alarm rate (None: the calibration's).
    uncertain : bool
        The 'uncertain' verdict (False: good or defective only).
    echo : callable
        Where the one line per scan goes (None: nowhere).
    report_every : int
        Rewrite report.html after this many scans (0: only every ``report_seconds`` and when the watcher stops).
    report_seconds : float
        ... or once this many seconds have passed since it was last written and a scan was scored since (checked
        at each verdict and each look, :meth:`poll`).
    max_defective_share, window : float, int
        The batch check (:mod:`inspection.batch_check`) of the last ``window`` scored scans, this one included, at
        most ``max_defective_share`` of them defective: when it fires, the scan is told 'uncertain' rather than
        'defective' unless its score lies beyond the window's shift, and a warning says so once (and once when
        the scans look like the calibration's again). A model of several part types is not checked.
    """

    def __init__(self, model, folder, out, settle=1.0, maps="all", alpha=None, uncertain=True, echo=print,
                 report_every=REPORT_EVERY, report_seconds=REPORT_SECONDS,
                 max_defective_share=DEFAULT_MAX_DEFECTIVE_SHARE, window=DEFAULT_WINDOW):
        self.model, self.folder, self.out = Path(model), Path(folder), Path(out)
        self.max_defective_share = check_max_defective_share(max_defective_share)
        if not (isinstance(window, int) and window >= 1):
            raise InspectionError(f"--window must be a whole number of scans >= 1, got {window!r}")
        self.window, self.batch = window, None  # batch: the last check of the window (a BatchCheck)
        self.settle, self.maps, self.alpha, self.uncertain = float(settle), maps, alpha, uncertain
        self.report_every, self.report_seconds = report_every, report_seconds
        self.echo = echo or (lambda line: None)
        self.counts = {}  # verdict -> scans scored by this watcher
        self.views = {}  # file name -> (score, its 3D view for report.html): the REPORT_VIEWS most anomalous
        self._unreported, self._reported_at = 0, time.monotonic()
        self._lock = self._journal = None

    # ------------------------------------------------------------------------------------------------ set up
    def open(self):
        """Check the options and folders, take the results folder's lock, read the journal back and load the model.
        Returns self."""
        from datasets.atomic import check_writable
        from datasets.importer import cloud_files, skipped_line

        from .job import calibrated_inspector
        from .model_io import load_model_handle
        from .report import CSV_COLUMNS, RAY_CSV_COLUMNS

        if self.maps not in ("flagged", "all", "none"):
            raise InspectionError(f"--maps must be flagged, all or none, got {self.maps!r}")
        if not (self.settle >= 0 and math.isfinite(self.settle)):
            raise InspectionError(f"--settle must be a number of seconds >= 0, got {self.settle!r}")
        if not (isinstance(self.report_every, int) and self.report_every >= 0):
            raise InspectionError(f"--report-every must be a whole number of scans >= 0, got {self.report_every!r}")
        if not (self.report_seconds > 0 and math.isfinite(self.report_seconds)):
            raise InspectionError(f"--report-seconds must be a number of seconds > 0, got {self.report_seconds!r}")
        if not self.folder.is_dir():
            raise InspectionError(f"{self.folder}: no such folder" if not self.folder.exists() else
                                  f"{self.folder}: not a folder (watch needs the folder the scanner writes into)")
        if self.out.exists() and not self.out.is_dir():
            raise InspectionError(f"{self.out}: exists and is not a folder")
        self.out.mkdir(parents=True, exist_ok=True)
        check_writable(self.out / JOURNAL)
        self._lock = open(self.out / LOCK, "a")
        try:
            fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)  # released by the kernel however we end
        except BlockingIOError:
            self.close()
            raise InspectionError(f"{self.out}: another watcher is writing this results folder") from None
        try:
            self.entries = read_journal(self.out / JOURNAL)
            self.done = {_key(e) for e in self.entries}
            handle = load_model_handle(self.model)
            if handle.frame is None:
                raise InspectionError(f"{self.model}: scanner files need the model's frame, and this model records "
                                      f"none")
            self.frame, self.handle = handle.frame, handle
            self.insp = calibrated_inspector(handle, self.folder, self.alpha, False, self.echo)
            self.columns = (RAY_CSV_COLUMNS if self.insp.settings_.rays else CSV_COLUMNS) + ("file", "time")
            self._journal = os.open(self.out / JOURNAL, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
            if self.entries:
                self._write_table()
                self._unreported += not (self.out / REPORT).exists()  # a journal from before the page was kept
            skipped = skipped_line(cloud_files(self.folder)[1], self.folder)
            if skipped:
                self.echo(skipped)
        except BaseException:
            self.close()
            raise
        return self

    def close(self):
        if self._journal is not None:
            os.close(self._journal)
            self._journal = None
        if self._lock is not None:
            self._lock.close()  # releases the lock
            self._lock = None

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------------------------------------ work
    def poll(self):
        """Score every landed file not in the journal yet. Returns (scored now, files still settling)."""
        ready, settling = landed_files(self.folder, self.settle)
        n = 0
        for path, st in ready:
            key = (path.name, st.st_size, st.st_mtime_ns)
            if key in self.done:
                continue
            entry = self._score_file(path, st)
            if entry is None:  # it changed or went away while it was read: looked at again later
                settling += 1
                continue
            self._append(entry)
            n += 1
        if self._report_overdue():  # verdicts came, and then none for a while: the page catches up
            self.write_report()
        return n, settling

    def _report_overdue(self):
        return bool(self._unreported) and time.monotonic() - self._reported_at >= self.report_seconds

    def run(self, once=False, interval=1.0):
        """Poll until interrupted (KeyboardInterrupt propagates), or with ``once`` until every file present has
        landed and been scored."""
        while True:
            _, settling = self.poll()
            if once and not settling:
                return
            time.sleep(max(0.05, min(interval, self.settle)) if once else interval)

    def _score_file(self, path, st):
        """Read and score one file; its journal entry, or None when the file changed while it was read."""
        from datasets.importer import ScanSource

        from .job import error_row, inspect_scan
        from .loading import read_file

        t0 = time.perf_counter()
        src = ScanSource(path, path.stem, "test", "unknown", "")
        one = None
        try:
            scan = read_file(src, self.frame, getattr(self.insp, "reading_", None))  # as score reads it (issue 47)
        except Exception as exc:  # noqa: BLE001 - a bad file is an error line, never the end of the watcher
            reason = " ".join(str(exc).split()) or type(exc).__name__
            row = error_row(src.name, reason if str(path) in reason else f"{path}: {reason}")
        else:
            try:
                one = inspect_scan(self.insp, scan, 0, self.maps, self.out / "maps", self.uncertain)
                row = one["row"]
                self._check_window(row)
            except Exception as exc:  # noqa: BLE001 - as above, for what scoring raises beyond a ValueError
                row = error_row(scan, f"{path}: cannot be scored ({type(exc).__name__}: {exc})")
        try:
            now = path.stat()
        except FileNotFoundError:
            return None
        if (now.st_size, now.st_mtime_ns) != (st.st_size, st.st_mtime_ns):
            return None
        entry = {k: _json_safe(v) for k, v in row.items()}
        entry.update(name=src.name, split="test", label=row.get("label", "unknown"), file=path.name,
                     size=st.st_size, mtime_ns=st.st_mtime_ns,
                     time=datetime.now(timezone.utc).isoformat(timespec="seconds"),
                     seconds=round(time.perf_counter() - t0, 3))
        if one is not None and one.get("defects"):  # its defect regions, named by the file like its row
            entry["defects"] = [{k: _json_safe(v) for k, v in {**d, "name": path.name}.items()}
                                for d in one["defects"]]
        if one is not None and "view" in one:
            from .maps import safe_name

            entry["map"] = f"maps/{safe_name(src.name)}.ply"
            self._keep_view({**one["view"], "name": path.name}, entry["score"])
        return entry

    def _check_window(self, row):
        """The batch check of the last ``window`` scored scans with ``row`` (a scored scan's row, retold in place
        when the check fires); a warning line when the check's state changes."""
        if self.insp.parts_ or row.get("verdict") == "error":
            return
        from .batch_check import check_rows, retell

        recent = [e for e in self.entries if e.get("verdict") != "error" and e.get("score") is not None]
        check = check_rows(self.insp, recent[-(self.window - 1):] + [row] if self.window > 1 else [row],
                           self.max_defective_share)
        was = self.batch is not None and self.batch.fired
        self.batch = check
        if check.fired and self.uncertain:
            retell(row, check)
        if check.fired != was:
            self.echo(f"warning: the last {check.n} scans: {check.message}" if check.fired else
                      f"the last {check.n} scans look like the calibration's good scans again")

    def _keep_view(self, view, score):
        """Hold a scored file's 3D view for report.html, keeping the ``REPORT_VIEWS`` most anomalous."""
        self.views[view["name"]] = (-math.inf if score is None else score, view)
        if len(self.views) > REPORT_VIEWS:
            del self.views[min(self.views, key=lambda k: self.views[k][0])]

    def _append(self, entry):
        """Append ``entry`` to the journal as one whole line, durable before anything else happens."""
        data = (json.dumps(entry, allow_nan=False) + "\n").encode()
        while data:
            data = data[os.write(self._journal, data):]
        os.fsync(self._journal)
        self.entries.append(entry)
        self.done.add(_key(entry))
        self.counts[entry["verdict"]] = self.counts.get(entry["verdict"], 0) + 1
        self._write_table()
        score = "" if entry.get("score") is None else f" score {entry['score']:.4g}"
        self.echo(f"{entry['file']}: {entry['verdict']}{score}"
                  + (f" ({entry['reason']})" if entry["verdict"] == "error" else ""))
        self._unreported += 1
        if (self.report_every and self._unreported >= self.report_every) or self._report_overdue():
            self.write_report()

    def _write_table(self):
        from .report import write_defects_csv, write_scores_csv

        write_scores_csv(self.out / TABLE, self.entries, self.columns)
        write_defects_csv(self.out / DEFECTS, [d for e in self.entries for d in e.get("defects", [])])

    def write_report(self, force=False):
        """Rewrite ``OUT/report.html`` (atomically) from the journal when a verdict came since it was last written
        (or ``force``): the page ``score`` writes, one row per file of the journal (named by its file name), with
        the 3D maps this watcher holds (:meth:`_keep_view`). Returns whether it was written."""
        if not (self._unreported or force) or not self.entries:
            return False
        from .html_report import write_html_report
        from .job import calibrated_aligned
        from .results import summarize_run
        from .run import run_warnings

        rows = [{**e, "name": e["file"]} for e in self.entries]
        scored = [e for e in self.entries if e["verdict"] != "error"]
        results = {"rows": rows, "point_labels": [], "point_maps": [], "ray_maps": [],
                   "seconds": [e["seconds"] for e in scored], "maps": sum("map" in e for e in scored)}
        summary = summarize_run(self.handle, self.insp, self.folder, None, calibrated_aligned(self.insp), results)
        batch = None if self.batch is None else {**self.batch.as_dict(), "window": self.window}
        summary.update(batch_check=batch, warnings=run_warnings(self.insp, batch))
        write_html_report(self.out / REPORT, rows, summary, [v for _, v in self.views.values()],
                          title=f"Watch: {self.folder}", defects=[d for e in self.entries for d in e.get("defects", [])])
        self._unreported, self._reported_at = 0, time.monotonic()
        return True

    def summary(self):
        """The one line said when the watcher stops: this run's files by verdict (an 'uncertain' never counted as
        flagged), and where the journal and the page are."""
        from .report import format_verdict_counts

        n = sum(self.counts.values())
        parts = format_verdict_counts(self.counts) if n else ""
        page = f", the page in {self.out / REPORT}" if (self.out / REPORT).exists() else ""
        return (f"watch: {n} file(s) scored this time" + (f" ({parts})" if parts else "")
                + f"; {len(self.entries)} verdict(s) in {self.out / JOURNAL}{page}")


def watch(model, folder, out, once=False, settle=1.0, interval=1.0, maps="all", alpha=None, uncertain=True,
          echo=print, quiet=False, report_every=REPORT_EVERY, report_seconds=REPORT_SECONDS,
          max_defective_share=DEFAULT_MAX_DEFECTIVE_SHARE, window=DEFAULT_WINDOW):
    """Score the scan files landing in ``folder`` into ``out`` (module docstring) until interrupted, or with
    ``once`` those present (waiting for any still being written to land). ``echo`` says one line per file (not
    when ``quiet``) and the summary line when it stops, however it stops; report.html is brought up to date then
    too (``report_every``, ``report_seconds``: :class:`Watcher`). Returns the :class:`Watcher` (its ``counts`` say
    what this run scored)."""
    if not (interval > 0 and math.isfinite(interval)):
        raise InspectionError(f"--interval must be a number of seconds > 0, got {interval!r}")
    echo = echo or (lambda line: None)
    watcher = Watcher(model, folder, out, settle, maps, alpha, uncertain, None if quiet else echo, report_every,
                      report_seconds, max_defective_share, window)
    with watcher:
        try:
            watcher.run(once=once, interval=interval)
        finally:
            watcher.write_report()
            echo(watcher.summary())
    return watcher
