"""Command line of the model package: ``python -m autodecoder next-view --field field.pt --n 5 --out views.json``."""
import json
import sys
from pathlib import Path

from datasets.cli import OneLineParser


def _parser():
    parser = OneLineParser(prog="python -m autodecoder", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    nv = sub.add_parser("next-view", help="rank camera placements by the field's variance at their expected hits")
    nv.add_argument("--field", required=True, type=Path, help="stochastic field file (StochasticField.save)")
    nv.add_argument("--n", type=int, default=5, help="views to return (default 5)")
    nv.add_argument("--out", type=Path, help="JSON file to write (default: print to stdout)")
    nv.add_argument("--starts", type=int, default=16, help="random starts of the optimiser (default 16)")
    nv.add_argument("--steps", type=int, default=60, help="Adam steps (default 60)")
    nv.add_argument("--standoff", type=float, nargs=2, default=(1.5, 2.5), metavar=("MIN", "MAX"),
                    help="camera distance from the part's centre in bounding-sphere radii (default 1.5 2.5)")
    nv.add_argument("--fov", type=float, default=30.0, help="field of view in degrees (default 30)")
    nv.add_argument("--rays", type=int, default=3, help="rays per image side (default 3)")
    nv.add_argument("--samples", type=int, default=24, help="samples per ray (default 24)")
    nv.add_argument("--seed", type=int, default=0)
    return parser


def main(argv=None):
    """Run the command line; returns the exit status (0 success, 2 bad input)."""
    args = _parser().parse_args(argv)
    from autodecoder.field.stochastic_field import StochasticField
    from autodecoder.scanning.views import next_best_views

    if args.n < 1 or args.starts < 1 or args.steps < 0:
        print("error: --n and --starts must be >= 1 and --steps >= 0", file=sys.stderr)
        return 2
    try:
        field = StochasticField.load(args.field)
    except (FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        views = next_best_views(field, n_views=args.n, starts=max(args.starts, args.n), steps=args.steps,
                                standoff=tuple(args.standoff), fov_deg=args.fov, n_side=args.rays,
                                n_samples=args.samples, seed=args.seed)
    except ValueError as exc:
        print(f"error: {args.field}: {exc}", file=sys.stderr)
        return 2
    text = json.dumps({"field": str(args.field), "views": [v.as_dict() for v in views]}, indent=2)
    if args.out is None:
        print(text)
    else:
        try:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(text + "\n")
        except OSError as exc:
            print(f"error: cannot write {args.out}: {exc}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
