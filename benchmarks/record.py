"""The record of one benchmark run: a JSON file with the command as typed, the commit, the date, the machine's load
and the figures."""
import json
import math
import os
import shlex
import subprocess
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import NamedTuple

ROOT = Path(__file__).resolve().parents[1]
RECORDS = "results/records"


class Moment(NamedTuple):
    """When something happened: wall time (seconds since the epoch) and the 1/5/15-minute load averages then."""

    time: float
    load: tuple

    @classmethod
    def now(cls):
        return cls(time.time(), tuple(os.getloadavg()))


def git_state(root=ROOT):
    """(commit hex or None, dirty: bool or None) of the working tree at ``root``; None where git cannot tell."""
    def git(*args):
        out = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=30)
        return out.stdout.strip() if out.returncode == 0 else None

    try:
        commit = git("rev-parse", "HEAD")
        status = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None, None
    return commit or None, None if status is None else bool(status)


def jsonable(value):
    """``value`` with numpy scalars and arrays, tuples and paths made plain JSON (non-finite floats become None)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "tolist"):  # numpy scalars and arrays
        return jsonable(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def command_line(argv):
    """The command as typed: ``python -m benchmarks`` followed by ``argv`` (the arguments after it)."""
    return shlex.join(["python", "-m", "benchmarks", *map(str, argv)])


def write_record(suite, argv, figures, started, finished, out_dir=RECORDS):
    """Write the record of one run and return its path.

    Parameters
    ----------
    suite : str
    argv : sequence of str
        The arguments after ``python -m benchmarks`` (the suite's name first).
    figures : dict
        What the suite measured (JSON-serialisable after :func:`jsonable`).
    started, finished : Moment
        :meth:`Moment.now` at the start and at the end of the run.
    out_dir : str or Path
        The records' folder; the file is ``<suite>_<UTC date and time>.json`` there.

    Returns
    -------
    Path
    """
    from datasets.atomic import atomic_path

    commit, dirty = git_state()
    date = datetime.fromtimestamp(started.time, timezone.utc)
    record = {
        "suite": suite,
        "command": command_line(argv),
        "commit": commit,
        "dirty": dirty,
        "date": date.isoformat(timespec="seconds"),
        "seconds": round(finished.time - started.time, 3),
        "load": {"start": list(started.load), "end": list(finished.load), "cpus": os.cpu_count()},
        "figures": jsonable(figures),
    }
    out_dir = Path(out_dir)
    stem = f"{suite}_{date.strftime('%Y%m%dT%H%M%SZ')}"
    path, n = out_dir / f"{stem}.json", 1
    while path.exists():  # two runs started in the same second
        n += 1
        path = out_dir / f"{stem}_{n}.json"
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(record, indent=1, allow_nan=False) + "\n")
    return path
