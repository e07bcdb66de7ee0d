"""The README's first hour on a folder of real scans, walked as a user walks it (issue 53).

A folder as a scanner leaves it (``../shared/realscans/bunny``: ten Cyberware range views as PLY files without
normals, the repository's README and its alignment ``bun.conf``) is copied into a temporary folder, and the command
lines the README names are run there one after the other, as a user types them (subprocesses of the console entry
points beside this Python, the working folder the temporary one): the whole folder imported and trained on as it is
(the error says how to make it training data), the good views sorted into ``good/`` and the others into ``new/``
(each with the README and the .conf beside the clouds), ``nsspr-data import good --split train --label good``,
``nsspr-data info``, ``nsspr-train``, ``nsspr-inspect calibrate``, ``nsspr-inspect score --data new``,
``nsspr-inspect watch --once`` on ``new/``, and the README's Python example for one scanner file, copied out of the
README into ``example.py`` and run on one of the new views. The transcript is printed (each command, then what it
printed, progress bars at their last state); the figures are each command's exit status and seconds, the verdicts,
and whether each promise of the issue shows in the transcript: the skipped files named, the error that says how to
get good scans into split 'train', the few-scan note before the training's work, the whole run's time, the verdicts
counted by kind, no precision or recall without labels, the API's verdict equal to ``score``'s, ``watch``'s page.

Training with the trainer's defaults takes a few minutes on 2 shared cores (``--epochs`` fewer for a quick look).
"""
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks import cache

DESCRIPTION = ("the README walked as a user walks it on a folder of real scans (the bunny's range views, README and "
               ".conf beside them): import, train, calibrate, score, watch, the API; prints the transcript")
TRAIN_VIEWS = "bun000,bun045,bun090,bun180,bun270,bun315,chin"  # the good views trained on; the others are new


def add_arguments(p):
    p.add_argument("--scans", default=str(cache.REAL_SCANS / "bunny"),
                   help="the scanner's folder, copied as it is (default: %(default)s)")
    p.add_argument("--train", default=TRAIN_VIEWS,
                   help="comma-separated stems of the views that are the good training scans; the others are the "
                        "new scans scored (default: %(default)s)")
    p.add_argument("--epochs", type=int, default=None, help="nsspr-train --epochs (default: the trainer's)")
    p.add_argument("--keep", metavar="DIR", default=None,
                   help="walk in DIR (created; must not exist) and keep it, instead of a temporary folder")
    p.add_argument("--fresh-clone", action="store_true",
                   help="begin as a new user begins: git clone the repository's committed HEAD into the walk's "
                        "folder, set it up with the README's own command (make setup: a virtual environment of its "
                        "own, a few minutes) and walk with that environment's commands instead of this one's")


def _readme_example():
    """The README's Python example for one scanner file (the block that calls ``load_scans``), as a user copies it."""
    text = (cache.ROOT / "README.md").read_text()
    blocks = [b for b in re.findall(r"```python\n(.*?)```", text, flags=re.S) if "load_scans(" in b]
    if len(blocks) != 1:
        raise RuntimeError(f"README.md: {len(blocks)} Python examples read a scanner file (load_scans), expected one")
    return blocks[0]


def _readme_says(*fragments):
    """Whether the README holds every fragment (the walk types nothing the README does not show)."""
    text = (cache.ROOT / "README.md").read_text()
    return all(f in text for f in fragments)


def _last_states(text):
    """A command's output as a terminal leaves it: of each line rewritten with carriage returns (a progress bar) only
    its last state."""
    lines = []
    for line in text.split("\n"):  # (str.splitlines would split at each carriage return too)
        states = [s for s in line.split("\r") if s.strip()]
        if states:
            lines.append(states[-1].rstrip())
    return lines


class _Walk:
    """Runs commands in ``folder`` as a user types them, printing and keeping the transcript."""

    def __init__(self, folder, bin_dir=None):
        self.folder = Path(folder)
        # the environment's console entry points (nsspr-data, ...) and its python: this one's unless told
        self.bin_dir = Path(bin_dir) if bin_dir is not None else Path(sys.executable).parent
        self.python = self.bin_dir / "python"
        self.env = {**os.environ, "PATH": str(self.bin_dir) + os.pathsep + os.environ.get("PATH", "")}
        self.env.pop("VIRTUAL_ENV", None)
        self.steps, self.transcript = [], []

    def __call__(self, *argv, expect=0):
        """Run ``argv``; returns its output lines (stdout and stderr as a terminal shows them)."""
        shown = "$ " + " ".join(str(a) for a in argv)
        print(shown, flush=True)
        t0 = time.perf_counter()
        done = subprocess.run([str(a) for a in argv], cwd=self.folder, env=self.env, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT)  # bytes: text mode would turn a bar's '\r' into lines
        seconds = time.perf_counter() - t0
        lines = _last_states(done.stdout.decode("utf-8", errors="replace"))
        for line in lines:
            print(f"  {line}", flush=True)
        print(f"  [exit {done.returncode}, {seconds:.1f} s]", flush=True)
        self.transcript += [shown, *lines]
        self.steps.append({"command": shown[2:], "status": done.returncode, "expected": expect,
                           "seconds": round(seconds, 1)})
        return lines


def run(args):
    scans = Path(args.scans)
    if not scans.is_dir():
        raise FileNotFoundError(f"{scans}: no such folder (the shared real scans, beside the checkout)")
    train = [s for s in args.train.split(",") if s]
    stems = sorted(p.stem for p in scans.glob("*.ply"))
    missing = [s for s in train if s not in stems]
    if missing or not train:
        raise ValueError(f"--train: {missing or 'none'} not among the views of {scans} ({', '.join(stems)})")
    new = [s for s in stems if s not in train]
    folder = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="nsspr-walk-"))
    if args.keep:
        folder.mkdir(parents=True)
    print(f"walking in {folder}", flush=True)
    try:
        if args.fresh_clone:
            walk = _fresh_clone(folder)
        else:
            walk = _Walk(folder)
        return _walk(walk, scans, train, new, args.epochs)
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)


def _fresh_clone(folder):
    """Clone the repository's committed HEAD into ``folder/nsspr-inspect`` and set it up with the README's command;
    returns a walk in ``folder`` whose commands are the new environment's. Uncommitted changes are not walked."""
    setup = _Walk(folder)
    setup("git", "clone", "--quiet", cache.ROOT, "nsspr-inspect")
    clone = folder / "nsspr-inspect"
    if not _readme_says("make test", "make demo"):
        raise RuntimeError("README.md no longer names `make` as its setup; the fresh-clone walk follows it")
    setup("make", "-C", "nsspr-inspect", "setup")
    if any(s["status"] != 0 for s in setup.steps):
        raise RuntimeError(f"the fresh clone in {clone} could not be set up (the transcript above says why)")
    walk = _Walk(folder, bin_dir=clone / ".venv" / "bin")
    walk.steps, walk.transcript = setup.steps, setup.transcript
    return walk


def _walk(walk, scans, train, new, epochs):
    others = sorted(p.name for p in scans.iterdir() if p.is_file() and p.suffix.lower() != ".ply")  # README, .conf
    walk("cp", "-r", scans, "scans")
    # 1. the folder as it is
    imported_all = walk("nsspr-data", "import", "scans", "--out", "all.h5")
    refused = walk("nsspr-train", "--data", "all.h5", "--out", "model.pt", expect=2)
    # 2. the good views made training data, the others kept apart as new scans
    walk("mkdir", "good", "new")
    walk("cp", *[f"scans/{s}.ply" for s in train], *[f"scans/{o}" for o in others], "good/")
    walk("cp", *[f"scans/{s}.ply" for s in new], *[f"scans/{o}" for o in others], "new/")
    imported = walk("nsspr-data", "import", "good", "--split", "train", "--label", "good", "--out", "good.h5")
    walk("nsspr-data", "info", "good.h5")
    trained = walk("nsspr-train", "--data", "good.h5", "--out", "model.pt",
                   *([] if epochs is None else ["--epochs", epochs]))
    walk("nsspr-inspect", "calibrate", "--model", "model.pt", "--data", "good.h5")
    scored = walk("nsspr-inspect", "score", "--model", "model.pt", "--data", "new", "--out", "results")
    watched = walk("nsspr-inspect", "watch", "--model", "model.pt", "--data", "new", "--out", "line", "--once")
    # 3. the README's Python example, copied out of it, on one new scanner file
    (walk.folder / "example.py").write_text(_readme_example())
    walk("cp", f"new/{new[0]}.ply", "scan.ply")
    api = walk(walk.python, "example.py")

    rows = _scores(walk.folder / "results" / "scores.csv")
    summary = json.loads((walk.folder / "results" / "summary.json").read_text())
    row = rows.get(new[0], {})
    journal = _journal(walk.folder / "line" / "verdicts.jsonl")  # watch's: each verdict in words too ('why')
    said = "\n".join(walk.transcript)
    skipped = f"skipped {len(others)} file{'s' if len(others) != 1 else ''} that"
    checks = {
        "the README shows every command walked": _readme_says("nsspr-data import", "--split train --label good",
                                                              "nsspr-data info", "nsspr-train --data",
                                                              "nsspr-inspect calibrate", "nsspr-inspect score",
                                                              "nsspr-inspect watch", "load_scans("),
        "every command ended as expected": all(s["status"] == s["expected"] for s in walk.steps),
        "import names the files it skipped": any(line.startswith(skipped) for line in imported_all + imported),
        "a folder left in split 'test' is told how to train on it": "--split train --label good" in
        "\n".join(imported_all),
        "nsspr-train's error says how to get good scans into 'train'": any(
            "no good scans in split 'train'" in line and "--split train --label good" in line for line in refused),
        "the few-scan note comes before the training's work": _before(
            trained, "note: few good scans", ("family of sizes?", "pose:", "reading scans", "GP targets", "training:")),
        "the training reports the whole run's time": any(" s in all (the training epochs" in line for line in trained),
        "score names the files it skipped": any(line.startswith(skipped) for line in scored),
        "score counts the scans by verdict": any(re.match(r"\d+ scans: \d+ defective \(flagged\), \d+ uncertain "
                                                          r"\(rescan\), \d+ good", line) for line in scored),
        "no precision or recall without labels": "precision" not in "\n".join(scored),
        "the threshold in plain words first, its statistics after": _before(scored, "threshold ", "statistics: "),
        "watch names the files it skipped": any(line.startswith(skipped) for line in watched),
        "watch keeps the report page": (walk.folder / "line" / "report.html").is_file(),
        "the README's example says what score and watch say": bool(row) and api[-1:] == [
            f"{row['verdict']} - {journal.get(f'{new[0]}.ply', {}).get('why')}"],
    }
    print("\nwhat the issue asks, as the transcript shows it:")
    for what, ok in checks.items():
        print(f"  {'yes' if ok else 'NO '}  {what}")
    return {"steps": walk.steps, "verdicts": summary.get("verdict_counts"), "threshold": summary.get("threshold"),
            "decision": summary.get("decision"), "checks": checks, "transcript": said.splitlines(),
            "seconds": round(sum(s["seconds"] for s in walk.steps), 1)}


def _before(lines, first, then):
    """Whether a line starting with ``first`` comes before the first line starting with ``then`` (a str or a tuple of
    them)."""
    a = next((i for i, line in enumerate(lines) if line.startswith(first)), None)
    b = next((i for i, line in enumerate(lines) if line.startswith(then)), len(lines))
    return a is not None and a < b


def _journal(path):
    """{file name: entry} of a ``watch`` journal ({} when there is none)."""
    if not path.is_file():
        return {}
    return {e["file"]: e for e in map(json.loads, path.read_text().splitlines())}


def _scores(path):
    import csv

    if not path.is_file():
        return {}
    with open(path, newline="") as f:
        return {r["name"]: r for r in csv.DictReader(f)}
