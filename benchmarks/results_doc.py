"""``python -m benchmarks table``: docs/results.md's tables, each suite's current figures rendered from its newest run
record.

docs/results.md holds one marked block per suite::

    <!-- table: SUITE -->
    ... the figures as markdown tables, then the command, commit, date and record ...
    <!-- /table -->

:func:`main` finds the newest record of each suite in the records' folder (:mod:`benchmarks.record`: ``suite``,
``command``, ``commit``, ``dirty``, ``date``, ``seconds``, ``load``, ``figures``), renders its figures with the suite's
renderer (:data:`RENDERERS`: suite name -> function(figures, record) -> markdown lines; :func:`generic` for a suite
without one, or whose figures its renderer does not know) and rewrites that suite's block; every other block stays
byte for byte as it is. The document is written whole or not at all (:func:`datasets.atomic.atomic_path`).
"""
import argparse
import json
import math
import pkgutil
import re
import shlex
import sys
from pathlib import Path

from benchmarks.record import RECORDS, ROOT

DOC = "docs/results.md"
BLOCK = re.compile(r"^<!-- table: (?P<suite>[\w-]+) -->\n(?P<body>.*?)^<!-- /table -->$", re.M | re.S)
RECORD_KEYS = ("suite", "command", "commit", "date", "figures")
LINE_LIMIT = 400  # docs/results.md's length at most (tests/test_results_doc.py): the tables summarise, records hold all
MAX_ROWS = 20  # rows of one rendered table at most


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
def cell(value, fmt=None):
    """A table cell: with ``fmt`` (a format spec, '' for text) :func:`benchmarks.table.cell`'s text, else by the
    value's type; '-' for None and NaN."""
    from benchmarks.table import cell as text_cell

    if fmt:
        try:
            return text_cell(value, fmt)
        except (TypeError, ValueError):  # a figure of another type than the renderer expects: as it is
            return str(value)
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.3f}" if abs(value) < 100 else f"{value:.0f}"
    if isinstance(value, (list, tuple)):
        return ", ".join(cell(v) for v in value) if len(value) <= 6 else f"{len(value)} values"
    if isinstance(value, dict):
        return ", ".join(f"{k} {cell(v)}" for k, v in value.items()) if len(value) <= 6 else f"{len(value)} values"
    return str(value).replace("|", "\\|").replace("\n", " ")


def markdown_table(rows, columns, limit=MAX_ROWS):
    """Rows of dicts as a markdown table: ``columns`` a list of (key, header, fmt) (``fmt`` as :func:`cell`'s;
    a callable key is given the row); at most ``limit`` rows, then a line saying how many more the record holds."""
    def value(row, key):
        return key(row) if callable(key) else row.get(key)

    lines = ["| " + " | ".join(h for _, h, _ in columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(cell(value(r, k), f) for k, _, f in columns) + " |" for r in rows[:limit]]
    if len(rows) > limit:
        lines += ["", f"({len(rows) - limit} more rows in the record.)"]
    return lines


def pivot(rows, row_key, column_key, text, first="", limit=MAX_ROWS):
    """Rows of dicts as a markdown table with one line per value of ``row_key`` and one column per value of
    ``column_key`` (both in order of appearance), each cell ``text(row)`` ('' where no row has the pair)."""
    keys = list(dict.fromkeys(r[row_key] for r in rows))
    columns = list(dict.fromkeys(r[column_key] for r in rows))
    cells = {(r[row_key], r[column_key]): text(r) for r in rows}
    table = [{"": k, **{str(c): cells.get((k, c), "") for c in columns}} for k in keys]
    return markdown_table(table, [("", first, "")] + [(str(c), str(c), "") for c in columns], limit)


def _listed(label, items):
    """'label: none' or 'label: N (a; b; ...)'."""
    return f"{label}: {len(items)}" + (f" ({'; '.join(map(str, items))})" if items else "")


def _rate(predicted, interval):
    """A predicted false-alarm rate with its interval as the suites print it ('2% (0.086-7%)'); '-' without one."""
    if predicted is None:
        return "-"
    from inspection.threshold import format_rate

    text = format_rate(predicted)
    if interval:
        text += f" ({format_rate(interval[0])}-{format_rate(interval[1])})"
    return text.replace(" %", "%")


def _of(count, total):
    return "-" if count is None or total is None else f"{count} of {total}"


def _kinds(aurocs):
    """The defect types of AUROC dicts ({'overall', type: value}), sorted."""
    return sorted({k for a in aurocs if isinstance(a, dict) for k in a if k != "overall"})


# ------------------------------------------------------------------------------------------------ generic
MAX_TABLES, MAX_COLUMNS = 3, 10  # the generic renderer's tables and columns at most


def generic(figures, record=None):
    """Any suite's figures: the top level's scalars as one line, then up to :data:`MAX_TABLES` of the lists of dicts
    (or dicts of dicts) among them, to two levels down, each as a table of up to :data:`MAX_COLUMNS` scalar fields."""
    lines, scalars = [], [f"{key} {cell(value)}" for key, value in figures.items() if _is_scalar(value)]
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


# ------------------------------------------------------------------------------------------------ the suites
RENDERERS = {}


def renderer(suite):
    """Register ``function(figures, record) -> markdown lines`` as ``suite``'s renderer."""
    def register(function):
        RENDERERS[suite] = function
        return function

    return register


def _verdict_row(part, method, one):
    """A row of :func:`_verdict_lines` from :func:`benchmarks.inspect_api.summary_figures`-like figures."""
    flagged, threshold = one.get("flagged") or {}, one.get("threshold") or {}
    n_good = flagged.get("n_good")
    good = flagged.get("good")
    return {"part": part, "method": method, "auroc": one.get("auroc") or {}, "point_auroc": one.get("point_auroc"),
            "defective": flagged.get("defective"),
            "good_text": _of(round(good * n_good), n_good) if good is not None and n_good else "-",
            "oracle": one.get("oracle"), "far": _rate(threshold.get("predicted_far"), threshold.get("far_interval")),
            "sec": one.get("seconds_per_scan")}


def _verdict_lines(rows):
    kinds = _kinds(r["auroc"] for r in rows)
    return markdown_table(rows, [("part", "part", ""), ("method", "method", ""),
                                 (lambda r: r["auroc"].get("overall"), "AUROC", ".3f"),
                                 *[((lambda r, k=k: r["auroc"].get(k)), k, ".3f") for k in kinds],
                                 ("point_auroc", "point AUROC", ".3f"), ("defective", "defective flagged", ".3f"),
                                 ("good_text", "good flagged", ""), ("oracle", "oracle", ".3f"),
                                 ("far", "predicted false alarms (90 % interval)", ""), ("sec", "s/scan", ".2f")])


@renderer("inspection")
def inspection_lines(figures, record=None):
    """Per part: the toolkit's rows (with and without fold models, each point score alone) and the baseline's; in the
    template regime also object and point AUROC per type; with ``--multi-part`` the one model's rows."""
    rows, per_type = [], []
    for part, one in figures["parts"].items():
        for key, method in (("toolkit_nofolds", None), ("toolkit", None), ("toolkit_summary_nofolds", None),
                            ("toolkit_summary", None)):
            if one.get(key):
                rows.append(_verdict_row(part, one[key].get("method") or method or key, one[key]))
        for spec, alone in (one.get("point_scores") or {}).items():
            rows.append(_verdict_row(part, f"{spec} alone", alone))
        nn = one.get("nn") or {}
        if "flagged" in nn:
            rows.append(_verdict_row(part, nn.get("method") or "nearest-neighbour", nn))
        if "toolkit_summary" in one or "toolkit_summary_nofolds" in one:
            for name in ("toolkit", "nn"):
                if isinstance(one.get(name), dict) and "point_auroc" in one[name]:
                    per_type += [{"part": part, "method": name, "defect": k, "object": v,
                                  "point": one[name]["point_auroc"].get(k)} for k, v in one[name]["auroc"].items()]
    lines = _verdict_lines(rows)
    if per_type:
        lines += ["", "Object and point AUROC per defect type (the template regime):", ""]
        lines += markdown_table(per_type, [("part", "part", ""), ("method", "method", ""), ("defect", "defect", ""),
                                           ("object", "object AUROC", ".3f"), ("point", "point AUROC", ".3f")])
    multi = figures.get("multi_part")
    if multi:
        rows = [_verdict_row(part, f"{kind.replace('_', '-')} model", two[kind])
                for part, two in multi["parts"].items() for kind in ("multi_part", "single_part")]
        lines += ["", f"One model on all the parts (trained in {cell(multi.get('train_seconds'), '.0f')} s):", ""]
        lines += _verdict_lines(rows)
    return lines


@renderer("verdicts")
def verdicts_lines(figures, record=None):
    """Per tree (lines) and seed (columns): AUROC / defective flagged / good flagged; then the issue's targets."""
    runs = figures["runs"]
    lines = ["AUROC / defective flagged / good flagged (of them told `defective`), per tree and seed:", ""]
    lines += pivot(runs, "tree", "seed", lambda r: f"{cell(r['auroc'], '.3f')} / {cell(r['defective'], '.3f')} / "
                   f"{r['good_text']}" + (f" ({r['rejected_text'].split(' of ')[0]})"
                                          if r.get("rejected_text", "-") != "-" else ""), first="tree")
    t = figures.get("targets") or {}
    if t:
        lines += ["", f"Over {len(runs)} runs: mean AUROC {_mean(runs, 'auroc', '.4f')}, mean share of defective scans "
                      f"flagged {_mean(runs, 'defective', '.3f')}; realised false-alarm rate {t['mean_far']:.4f} "
                      f"(target <= 2 alpha = {2 * t['alpha']:.3f}: {'met' if t['far_ok'] else 'NOT met'}); "
                  + _listed("runs above 1 of 16 good scans", t["over_one_in_16"])
                  + f" (a threshold at exactly alpha: {t['expected_over']:.1f} on average, none with probability "
                    f"{t['p_none_over']:.2f}); "
                  + _listed("runs short of the detection target where a threshold at exactly alpha meets it",
                            t["detection_misses"]) + "; "
                  + _listed("where it misses it too", t["beyond_alpha"]) + "."]
    return lines


def _mean(rows, key, fmt):
    values = [r[key] for r in rows if isinstance(r.get(key), (int, float)) and not math.isnan(r[key])]
    return format(sum(values) / len(values), fmt) if values else "-"


@renderer("rays")
def rays_lines(figures, record=None):
    """Per tree (lines) and seed (columns): the default's AUROC / the point score alone's / defective flagged / good
    flagged, then per tree missing material and the good scans' largest ray score; then the issue's targets."""
    runs = figures["runs"]

    def good(r):
        return r.get("good_text") or _of(round(r["good"] * r["n_good"]), r["n_good"])

    lines = ["Default AUROC / points alone / defective flagged / good flagged; the good scans' largest ray score "
             "(nats) and missing material's AUROC, per tree and seed:", ""]
    lines += pivot(runs, "tree", "seed", lambda r: f"{cell(r['auroc'], '.3f')} / {cell(r['points_alone'], '.3f')} / "
                   f"{cell(r['defective'], '.3f')} / {good(r)}; {cell(r.get('good_rays_max'), '.1f')}, "
                   f"{cell(r.get('missing'), '.3f')}", first="tree")
    t = figures.get("targets") or {}
    if t:
        lines += ["", f"Targets over {len(runs)} runs, misses: "
                  + "; ".join(_listed(label, t.get(key, [])) for key, label in (
                      ("ranking", "default below the points alone"),
                      ("detection", "detection short of the points-alone oracle"),
                      ("calibration", "of them the threshold's calibration"),
                      ("false_alarms", "above 1 of 16 good scans"),
                      ("missing", "missing material below the target on thin walls"))) + "."]
    return lines


@renderer("sensors")
def sensors_lines(figures, record=None):
    """One line per sensor: over its runs mean AUROC and defective flagged, good scans flagged and told 'defective',
    mean gap (held-back) and shift against 'same', warnings fired; then each run (a column per tree and seed): AUROC /
    defective flagged / good flagged (told defective), a fired warning marked; the issue's targets. '<sensor>+site'
    runs: the level set by that sensor's own good scans (``--site-scans``, 8 by default)."""
    runs = [dict(r, _column=f"{r['tree']} s{r['seed']}") for r in figures["runs"]]
    columns = list(dict.fromkeys(r["_column"] for r in runs))
    cells = {(r["sensor"], r["_column"]): (
        f"{cell(r['auroc'], '.3f')} / {cell(r['defective'], '.3f')} / {_of(r.get('good_flagged'), r.get('n_good'))}"
        f" ({r.get('good_told_defective', '-')})" + (" warning" if r.get("warning") else "")) for r in runs}
    summary = figures.get("per_sensor") or [{"sensor": s} for s in dict.fromkeys(r["sensor"] for r in runs)]
    table = [{**one, **{c: cells.get((one["sensor"], c), "") for c in columns}} for one in summary]
    lines = ["Per sensor over its runs, then each run: AUROC / defective flagged / good flagged (told defective); "
             "alpha, the predicted false-alarm rate and the gaps of each run: the record.", ""]
    lines += markdown_table(table, [
        ("sensor", "sensor", ""), ("auroc", "mean AUROC", ".3f"), ("defective", "mean defective flagged", ".3f"),
        ("good_text", "good flagged", ""), ("told_text", "told defective", ""), ("gap", "mean gap held-back", "+.3f"),
        ("shift", "mean shift vs same", "+.3f"), ("fired", "warnings", ""), *[(c, c, "") for c in columns]])
    site = [r for r in runs if str(r.get("sensor", "")).endswith("+site")]
    if site:
        command = shlex.split((record or {}).get("command", ""))
        n = command[command.index("--site-scans") + 1] if "--site-scans" in command[:-1] else "8"
        lines += ["", f"'SENSOR+site': the same test scans scored by a copy of the calibrated model whose level "
                      f"{n} good scans of that sensor set (`calibrate --data FOLDER`)."]
    t = figures.get("targets") or {}
    if t:
        base = [r for r in runs if not str(r.get("sensor", "")).endswith("+site")]
        lines += ["", f"Targets over {len(base)} template-calibrated runs, misses: "
                  + "; ".join(_listed(label, t.get(key, [])) for key, label in (
                      ("false_alarms", "above 1 of 16 good scans (without the warning excusing them)"),
                      ("detection", "defective flagged short where AUROC is high and no warning"),
                      ("site", "'+site' runs above 1 of 16 good or short of detection"))) + "."]
    return lines


@renderer("ablation")
def ablation_lines(figures, record=None):
    """``--trees``: per tree and seed (lines) and method (columns) object AUROC (the maps' point AUROC), then issue
    28's targets; else per part and setting the verdicts table's row."""
    if "rows" in figures:
        rows = [dict(r, _line=f"{r['tree']} s{r['seed']}") for r in figures["rows"]]
        lines = ["Object AUROC (the maps' point AUROC) per tree, seed and method:", ""]
        lines += pivot(rows, "_line", "method", lambda r: f"{cell(r['auroc'].get('overall'), '.3f')}"
                       + (f" ({cell(r['point_auroc'], '.3f')})" if r.get("point_auroc") is not None else ""),
                       first="tree")
        misses = (figures.get("targets") or {}).get("misses")
        if misses is not None:
            lines += ["", _listed("Issue 28's targets missed", misses) + "."]
        return lines
    return _verdict_lines([_verdict_row(part, spec, one) for part, settings in figures["parts"].items()
                           for spec, one in settings.items()])


@renderer("real")
def real_lines(figures, record=None):
    """Object AUROC overall and per type of the baseline, the defaults and each term alone; flagged; seconds."""
    rows = [{"method": "nearest-neighbour", **figures["nn"]}, {"method": "toolkit (defaults)", **figures["toolkit"]}]
    rows += [{"method": f"toolkit, {name}", **one} for name, one in (figures.get("terms") or {}).items()]
    kinds = _kinds(rows)
    lines = markdown_table(rows, [("method", "method", ""), ("overall", "AUROC", ".3f"),
                                  *[(k, k, ".3f") for k in kinds if k != "method"]])
    f = figures.get("flagged") or {}
    lines += ["", f"Flagged at the calibrated default: defective {cell(f.get('defective'), '.3f')}, good "
                  f"{cell(f.get('good'), '.3f')}; {cell(figures.get('seconds_per_scan'), '.2f')} s a scan "
                  f"(baseline {cell(figures.get('nn_seconds_per_scan'), '.3f')}); training "
                  f"{cell(figures.get('train_seconds'), '.0f')} s."]
    return lines


@renderer("maps")
def maps_lines(figures, record=None):
    """Point AUROC of the anomaly map per run at each patch size, and per defect type at k = 1 and the default."""
    sizes, default = figures["neighbours"], figures["default"]
    lines = markdown_table(figures["runs"], [("run", "run", ""), ("points", "points", "d"),
                                             ("defect", "defect points", ""),
                                             *[(f"k{k}", f"k={k}" + (" (default)" if k == default else ""), ".3f")
                                               for k in sizes], ("patch", f"k={default}, no rays", ".3f")])
    per = [p for p in figures.get("per_type") or [] if p.get("patch") == default]
    if per:
        kinds = sorted({k for p in per for k in p} - {"run", "patch", "overall"})
        lines += ["", f"Per defect type at k = {default} (k = 1: the record):", ""]
        lines += markdown_table(per, [("run", "run", ""), *[(k, k, ".3f") for k in kinds]])
    return lines


@renderer("latency")
def latency_lines(figures, record=None):
    """Seconds per scan and per stage at each scan size, the baseline's, peak memory; the throughput of `score`."""
    sizes = figures["sizes"]
    stages = list(dict.fromkeys(k for one in sizes.values() for k in one.get("stages", {})))
    rows = [{"points": f"{one['points']:,.0f}", "scans": one["scans"], "s": one["seconds_per_scan"],
             "max": one.get("seconds_max"), **one.get("stages", {}), "other": one.get("other"),
             "nn": one.get("nn_seconds_per_scan"), "mb": one.get("peak_rss_mb")} for one in sizes.values()]
    lines = [f"{figures.get('part')}, calibrated in {cell(figures.get('calibrate_seconds'), '.1f')} s, "
             f"{figures.get('threads')} torch thread(s); seconds per scan:", ""]
    lines += markdown_table(rows, [("points", "points", ""), ("scans", "scans", "d"), ("s", "s/scan", ".3f"),
                                   ("max", "max", ".3f"), *[(k, k, ".3f") for k in stages], ("other", "other", ".3f"),
                                   ("nn", "nearest-neighbour s/scan", ".4f"), ("mb", "peak MB", ".0f")])
    throughput = figures.get("throughput")
    if throughput:
        lines += ["", f"Throughput, `score --maps none` over {throughput.get('scans')} test scans "
                      f"(the same scores with every `--jobs`: {cell(throughput.get('same_scores'))}):", ""]
        lines += markdown_table([{"jobs": n, **one} for n, one in throughput["jobs"].items()],
                                [("jobs", "--jobs", ""), ("seconds", "seconds", ".1f"),
                                 ("scans_per_second", "scans/s", ".2f")])
    return lines
