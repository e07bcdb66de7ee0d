"""``python -m benchmarks table``: docs/results.md's tables, each suite's current figures rendered from its newest run
record.

docs/results.md holds one marked block per suite::

    <!-- table: SUITE -->
    ... the figures as markdown tables, then the command, commit, date and record ...
    <!-- /table -->

:func:`main` finds the newest record of each suite in the records' folder (:mod:`benchmarks.record`: ``suite``,
``command``, ``commit``, ``dirty``, ``date``, ``seconds``, ``load``, ``figures``), renders its figures with the suite's
renderer (:data:`benchmarks.renderers.RENDERERS`: suite name -> function(figures, record) -> markdown lines; :func:`generic` for a suite
without one, or whose figures its renderer does not know) and rewrites that suite's block; every other block stays
byte for byte as it is. The document is written whole or not at all (:func:`datasets.atomic.atomic_path`).
"""
import argparse
import json
import pkgutil
import re
import sys
from pathlib import Path

from benchmarks.record import RECORDS, ROOT
from benchmarks.table import MAX_ROWS, markdown_cell, markdown_table  # noqa: F401 (MAX_ROWS: the tests')

DOC = "docs/results.md"
BLOCK = re.compile(r"^<!-- table: (?P<suite>[\w-]+) -->\n(?P<body>.*?)^<!-- /table -->$", re.M | re.S)
RECORD_KEYS = ("suite", "command", "commit", "date", "figures")
LINE_LIMIT = 400  # docs/results.md's length at most (tests/test_results_doc.py): the tables summarise, records hold all


class RecordError(ValueError):
    """A file of the records' folder that is not a readable run record (the message names the file)."""


class DocError(ValueError):
    """docs/results.md's blocks cannot be told apart (the message names the file and the line)."""


def suite_names():
    """The suites' names: the modules of :mod:`benchmarks.suites` (not imported)."""
    from benchmarks import suites

    return sorted(i.name for i in pkgutil.iter_modules(suites.__path__) if not i.name.startswith("_"))


# ------------------------------------------------------------------------------------------------ records
def read_record(path, known=None):
    """The run record at ``path`` (a dict with at least :data:`RECORD_KEYS`); RecordError naming the file when it is
    not JSON, not a record, or (``known``: the suites' names) of a suite that does not exist."""
    try:
        record = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RecordError(f"{path}: not a readable run record ({type(exc).__name__}: {exc})") from None
    missing = [k for k in RECORD_KEYS if not isinstance(record, dict) or k not in record]
    if missing:
        raise RecordError(f"{path}: not a run record of python -m benchmarks (no {', '.join(missing)})")
    if not isinstance(record["figures"], dict) or not isinstance(record["suite"], str):
        raise RecordError(f"{path}: not a run record of python -m benchmarks ('suite' must be text and 'figures' "
                          f"an object)")
    if known is not None and record["suite"] not in known:
        raise RecordError(f"{path}: record of an unknown suite {record['suite']!r} (suites: {', '.join(known)})")
    return record


def newest_records(folder, known=None):
    """{suite: (path, record)} of the newest record of each suite in ``folder`` (by the record's date, then file
    name); {} when the folder does not exist. Every ``*.json`` file there must be a record (:func:`read_record`)."""
    newest = {}
    folder = Path(folder)
    for path in sorted(folder.glob("*.json")) if folder.is_dir() else ():
        record = read_record(path, known)
        key = (str(record["date"]), path.name)
        if record["suite"] not in newest or key > newest[record["suite"]][0]:
            newest[record["suite"]] = (key, path, record)
    return {suite: (path, record) for suite, (_, path, record) in newest.items()}


# ------------------------------------------------------------------------------------------------ the document
def blocks(text, name=DOC):
    """{suite: (start, end)} of the marked blocks' bodies in ``text`` (character offsets: the lines between the two
    markers, each a line of its own); DocError on a suite marked twice or a marker without its partner."""
    found = {}
    for m in BLOCK.finditer(text):
        if m.group("suite") in found:
            raise DocError(f"{name}: two blocks of {m.group('suite')!r}")
        if re.search(r"^<!-- table:", m.group("body"), re.M):
            line = text.count("\n", 0, m.start()) + 1
            raise DocError(f"{name}:{line}: the block of {m.group('suite')!r} has no '<!-- /table -->' before the "
                           f"next block")
        found[m.group("suite")] = (m.start("body"), m.end("body"))
    opened, closed = len(re.findall(r"^<!-- table:", text, re.M)), len(re.findall(r"^<!-- /table -->", text, re.M))
    if opened != len(found) or closed != len(found):
        raise DocError(f"{name}: {opened} '<!-- table: SUITE -->' and {closed} '<!-- /table -->' markers, "
                       f"{len(found)} whole blocks")
    return found


def render_block(suite, record, path=None):
    """The body of ``suite``'s block from ``record``: the figures' tables, then the command, commit, date, seconds,
    load and the record's file. Returns (text ending in a newline, the renderer's name)."""
    from benchmarks.renderers import RENDERERS

    renderer, used = RENDERERS.get(suite), suite
    try:
        lines = renderer(record["figures"], record) if renderer else None
    except (KeyError, TypeError, ValueError, AttributeError, IndexError):
        lines = None
    if lines is None:  # no renderer, or figures it does not know (another mode of the suite)
        lines, used = generic(record["figures"]), "generic"
    return "\n".join([*lines, "", provenance(record, path)]) + "\n", used


def provenance(record, path=None):
    """'Command: `...`; commit `abc1234`; date; seconds, load; record `...`.' of a record."""
    commit = record.get("commit")
    commit = f"commit `{commit[:7]}`" if commit else "commit unknown"
    if record.get("dirty"):
        commit += " with uncommitted changes"
    parts = [f"Command: `OMP_NUM_THREADS=1 .venv/bin/{record['command']}`", commit, str(record["date"])]
    seconds, load = record.get("seconds"), record.get("load") or {}
    if seconds is not None:
        text = f"{seconds:.0f} s"
        if load.get("start") and load.get("end"):
            text += f", load {load['start'][0]:.1f} at start and {load['end'][0]:.1f} at end"
            text += f" on {load['cpus']} CPUs" if load.get("cpus") else ""
        parts.append(text)
    if path is not None:
        parts.append(f"record `{_shown_path(path)}`")
    return "; ".join(parts) + "."


def _shown_path(path):
    path = Path(path).resolve()
    try:
        return str(path.relative_to(ROOT))
    except ValueError:
        return str(path)


def update(text, records, suites=None, name=DOC):
    """``text`` with the block of every suite in ``records`` ({suite: (path, record)}; only ``suites`` when given)
    rendered again. Returns (new text, regenerated: {suite: (path, renderer)}, kept: {suite: why})."""
    spans = blocks(text, name)
    regenerated, kept = {}, {}
    pieces, at = [], 0
    for suite, (start, end) in sorted(spans.items(), key=lambda item: item[1]):
        if suite not in records:
            kept[suite] = "no record"
            continue
        if suites is not None and suite not in suites:
            kept[suite] = "not asked for (--suites)"
            continue
        path, record = records[suite]
        try:
            body, used = render_block(suite, record, path)
        except (TypeError, ValueError, AttributeError, KeyError) as exc:  # a record whose entries are not what
            # its suite writes (hand-edited, another version): one line naming the file
            raise RecordError(f"{path}: its entries are not what a {suite} record holds ({type(exc).__name__}: "
                              f"{exc})") from None
        pieces += [text[at:start], body]
        at = end
        regenerated[suite] = (path, used)
    for suite in sorted(set(records) - set(spans)):
        kept[suite] = f"a record but no block in {name}: add '<!-- table: {suite} -->' and '<!-- /table -->'"
    return "".join(pieces) + text[at:], regenerated, kept


def write_text(path, text):
    """Write ``text`` at ``path`` whole or not at all."""
    from datasets.atomic import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(text)


def main(argv=None):
    """``python -m benchmarks table``: rewrite docs/results.md's blocks from the newest records. Returns the exit
    status (0; 1 with ``--check`` when a block is not what its newest record gives; 2 on a bad record or document)."""
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks table",
        description="Rewrite the marked block of every suite in docs/results.md whose newest run record is in the "
                    "records' folder, from that record's figures, command and commit; the other blocks stay as they "
                    "are.")
    parser.add_argument("--records", default=RECORDS, metavar="DIR", help="the records' folder (default: %(default)s)")
    parser.add_argument("--doc", default=DOC, metavar="FILE", help="the document (default: %(default)s)")
    parser.add_argument("--suites", default=None, metavar="A,B",
                        help="only these suites' blocks (default: every suite with a record)")
    parser.add_argument("--check", action="store_true",
                        help="write nothing; exit 1 when a block differs from what its newest record gives")
    args = parser.parse_args(argv)
    doc = Path(args.doc)
    known = suite_names()
    suites = None if args.suites is None else {s.strip() for s in args.suites.split(",") if s.strip()}
    try:
        if suites is not None and suites - set(known):
            raise RecordError(f"--suites: unknown suite(s) {sorted(suites - set(known))} (suites: {', '.join(known)})")
        text = doc.read_text()
        records = newest_records(args.records, known)
        new, regenerated, kept = update(text, records, suites, name=str(doc))
    except (RecordError, DocError, OSError) as exc:
        print(f"python -m benchmarks table: {exc}; {doc} left as it was", file=sys.stderr)
        return 2
    changed = blocks(new, str(doc))
    before = blocks(text, str(doc))
    differs = [s for s in regenerated if new[slice(*changed[s])] != text[slice(*before[s])]]
    for suite, (path, used) in regenerated.items():
        how = "" if used == suite else f" (with the {used} renderer: the suite's own does not know these figures)"
        state = "regenerated" if suite in differs else "regenerated, unchanged"
        print(f"{suite}: {state} from {_shown_path(path)}{how}")
    for suite, why in kept.items():
        print(f"{suite}: kept ({why})")
    if new.count("\n") > LINE_LIMIT:
        print(f"{doc}: {new.count(chr(10))} lines, more than {LINE_LIMIT}: shorten a renderer's tables "
              f"(tests/test_results_doc.py fails past it)")
    if args.check:
        if differs:
            print(f"{doc}: {len(differs)} block(s) differ from their newest record: {', '.join(differs)}")
            return 1
        return 0
    if new != text:
        try:
            write_text(doc, new)
        except OSError as exc:
            print(f"python -m benchmarks table: cannot write {doc} ({exc}); it was left as it was", file=sys.stderr)
            return 2
        print(f"{doc}: written ({len(differs)} block(s) changed)")
    else:
        print(f"{doc}: unchanged")
    return 0


# ------------------------------------------------------------------------------------------------ markdown
# ------------------------------------------------------------------------------------------------ generic
MAX_TABLES, MAX_COLUMNS = 3, 10  # the generic renderer's tables and columns at most


def generic(figures, record=None):
    """Any suite's figures: the top level's scalars as one line, then up to :data:`MAX_TABLES` of the lists of dicts
    (or dicts of dicts) among them, to two levels down, each as a table of up to :data:`MAX_COLUMNS` scalar fields."""
    lines, scalars = [], [f"{key} {markdown_cell(value)}" for key, value in figures.items() if _is_scalar(value)]
    if scalars:
        lines += ["Figures: " + ", ".join(scalars) + ".", ""]
    tables = [(title, rows) for title, rows in _tables(figures) if _columns(rows)]
    for title, rows in tables[:MAX_TABLES]:
        lines += [f"{title}:", ""] + markdown_table(rows, [(k, k, None) for k in _columns(rows)]) + [""]
    if len(tables) > MAX_TABLES:
        lines += [f"({len(tables) - MAX_TABLES} more tables in the record: "
                  f"{', '.join(t for t, _ in tables[MAX_TABLES:])}.)", ""]
    if not lines:
        lines = ["(the record's figures hold no table: see the record)", ""]
    return lines[:-1]


def _columns(rows):
    """The scalar (or short flat) fields of ``rows``, in order of first appearance, at most :data:`MAX_COLUMNS`."""
    columns = []
    for r in rows:
        for k, v in r.items():
            if k not in columns and k not in ("log", "run") and (_is_scalar(v) or _is_flat(v)):
                columns.append(k)
    return columns[:MAX_COLUMNS]


def _is_scalar(value):
    return value is None or isinstance(value, (str, int, float, bool))


def _is_flat(value):
    return isinstance(value, (list, tuple, dict)) and len(value) <= 6 and all(
        _is_scalar(v) for v in (value.values() if isinstance(value, dict) else value))


def _tables(figures, prefix="", depth=0):
    """(title, rows) of the lists of dicts and dicts of dicts in ``figures``, to two levels down."""
    out = []
    for key, value in figures.items():
        title = f"{prefix}{key}"
        if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            out.append((title, value))
        elif isinstance(value, dict) and value and all(isinstance(v, dict) for v in value.values()) and any(
                any(_is_scalar(x) for x in v.values()) for v in value.values()):
            out.append((title, [{"": k, **v} for k, v in value.items()]))
        elif isinstance(value, dict) and depth < 1:
            out += _tables(value, f"{title}.", depth + 1)
    return out
