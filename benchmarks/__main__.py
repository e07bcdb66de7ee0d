"""``python -m benchmarks SUITE [options]``: run one benchmark suite and write the record of the run.

The suites are the modules of ``benchmarks/suites/`` (found with pkgutil). Each exposes ``DESCRIPTION`` (one line),
``add_arguments(parser)`` and ``run(args) -> dict`` (the figures; the suite prints its own table). After the run the
record (command, commit, date, load, figures: :mod:`benchmarks.record`) is written and its path printed.

``python -m benchmarks table [--records DIR] [--doc FILE] [--suites A,B] [--check]`` runs no suite: it rewrites
docs/results.md's table of every suite from its newest record (:mod:`benchmarks.results_doc`).
"""
import argparse
import importlib
import os
import pkgutil
import sys
import traceback

# before torch is imported anywhere: OpenMP threads spinning while they wait crawl on a shared CPU
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def discover():
    """{suite name: module or the ImportError text} of every module of :mod:`benchmarks.suites`, by name."""
    from benchmarks import suites

    found = {}
    for info in sorted(pkgutil.iter_modules(suites.__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        try:
            found[info.name] = importlib.import_module(f"benchmarks.suites.{info.name}")
        except Exception as exc:  # one broken suite must not hide the others
            found[info.name] = f"cannot be imported: {type(exc).__name__}: {exc}"
    return found


def build_parser(found=None):
    """The argparse parser: one sub-command per suite, with the suite's own options."""
    from benchmarks.record import RECORDS

    found = discover() if found is None else found
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks", description="Run one benchmark suite and write the record of the run "
        "(command, commit, date, load, figures) as JSON.",
        epilog="Each suite's options: python -m benchmarks SUITE --help. Map of the suites: benchmarks/README.md. "
        "docs/results.md's tables from the newest records: python -m benchmarks table [--check] (no suite is run).")
    parser.add_argument("--records", default=RECORDS, metavar="DIR",
                        help="folder of the run records (default: %(default)s)")
    parser.add_argument("--no-record", action="store_true", help="do not write the run's record")
    sub = parser.add_subparsers(dest="suite", metavar="SUITE", required=True)
    for name, module in found.items():
        if isinstance(module, str):
            sub.add_parser(name, help=f"({module})")
            continue
        p = sub.add_parser(name, help=module.DESCRIPTION, description=module.DESCRIPTION)
        module.add_arguments(p)
    return parser


def main(argv=None):
    """Parse, run the suite, write its record. Returns the exit status."""
    from benchmarks.record import Moment, write_record

    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["table"]:  # not a suite: docs/results.md's tables from the records
        from benchmarks.results_doc import main as table

        return table(argv[1:])
    found = discover()
    args = build_parser(found).parse_args(argv)
    module = found[args.suite]
    if isinstance(module, str):
        print(f"python -m benchmarks: suite {args.suite!r} {module}", file=sys.stderr)
        return 2
    started = Moment.now()
    print(f"{args.suite}: load average at start {started.load[0]:.2f} {started.load[1]:.2f} {started.load[2]:.2f} "
          f"({os.cpu_count()} CPUs)", flush=True)
    try:
        figures = module.run(args)
    except KeyboardInterrupt:
        print(f"{args.suite}: interrupted; no record written", file=sys.stderr)
        return 130
    except Exception:
        traceback.print_exc()
        print(f"{args.suite}: failed; no record written", file=sys.stderr)
        return 1
    finished = Moment.now()
    print(f"{args.suite}: load average at end {finished.load[0]:.2f} {finished.load[1]:.2f} {finished.load[2]:.2f}; "
          f"{finished.time - started.time:.0f} s")
    if not args.no_record:
        path = write_record(args.suite, argv, figures or {}, started, finished, out_dir=args.records)
        print(f"record: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
