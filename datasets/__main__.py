"""Command line of the datasets package: import / export / info of scan collections, and synth (virtual scanner)."""
import json
import logging
import sys

from .cli import OneLineParser, one_line


def _cmd_import(args):
    from .importer import import_tree, skipped_line

    # options of the public layouts (datasets.layouts), passed only when given: a 'tree' import refuses them
    public = {k: v for k, v in (("views", args.views), ("validation_views", args.validation_views),
                                ("keep_plane", args.keep_plane or None), ("max_points", args.max_points))
              if v is not None}
    s = import_tree(args.root, args.out, voxel=args.voxel, n_points=args.points, seed=args.seed,
                    overwrite=args.overwrite, drop_strays=args.drop_strays, layout=args.layout, split=args.split,
                    label=args.label, **public)
    if s.get("skipped"):
        print(skipped_line(s["skipped"], args.root))
    print(f"wrote {s['out']}: {s['n_scans']} scans, points per scan min {s['points_min']} / median "
          f"{s['points_median']:g} / max {s['points_max']}, {s.get('n_dropped', 0)} non-finite points dropped, "
          f"{s['n_stray']} stray points {'removed' if s['strays_dropped'] else 'found (kept; see info)'}")
    if "layout" in s:
        how = "from the training clouds' spacing" if s["voxel_auto"] else "given"
        print(f"  layout {s['layout']} ({s['units']}); voxel "
              + (f"{s['voxel']:.4g} {s['units']} ({how})" if s["voxel"] else "none (no downsampling)"))
        if s["n_without_origin"]:
            print(f"  normals of {s['oriented_by_templates']} of the {s['n_without_origin']} test scans without a "
                  f"sensor origin oriented like the templates (the others lie off them: another pose)")
    for (split, label, defect), n in s["groups"].items():
        print(f"  {split:<11}{label:<11}{defect or '-':<16}{n:>6}")
    print(f"  frame: {json.dumps(s['frame'])}")
    if not any(split == "train" and label in ("good", "unknown") for split, label, _ in s["groups"]):
        print(f"  no good scans in split 'train' to train a model on: a folder of good scans is imported for that "
              f"with `--split train --label good` (or laid out as train/good/*.ply beside test/<defect>/)")
    return 0


def _cmd_export(args):
    from .importer import export_collection

    n = export_collection(args.collection, args.dir, file_frame=args.file_frame, overwrite=args.overwrite)
    print(f"wrote {n} PLY files under {args.dir}")
    return 0


def _cmd_info(args):
    from .importer import collection_info

    print(collection_info(args.collection))
    return 0


def build_parser():
    """The argparse parser (only argparse is imported: ``--help`` must stay fast)."""
    parser = OneLineParser(prog="python -m datasets", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log per-file details (dropped points, ...)")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("import", help="scanner files (tree or flat folder) -> HDF5 scan collection",
                       description="Import a train/validation/test tree (MVTec-3D-AD / Real3D-AD style) or a flat "
                                   "folder of PLY/PCD/XYZ/PTS/TXT/NPY/NPZ clouds into a scan collection.")
    p.add_argument("root", help="folder to import (files that are not point clouds, e.g. a README or a scanner's "
                                "alignment .conf, are skipped and named in one line)")
    p.add_argument("--out", required=True, help="collection file to write (.h5)")
    p.add_argument("--split", choices=("train", "validation", "test"), default=None,
                   help="a flat folder's scans go to this split (default test): `--split train --label good` makes "
                        "a folder of good scans a collection to train on; a tree's folders say it themselves")
    p.add_argument("--label", choices=("good", "defective", "unknown"), default=None,
                   help="a flat folder's scans get this label (default: unknown in test, good in train and "
                        "validation)")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--voxel", type=float, metavar="SIZE", help="voxel downsampling, side in file units")
    size.add_argument("--points", type=int, metavar="N", help="keep a seeded random subset of N points per scan")
    p.add_argument("--seed", type=int, default=0, help="seed of the random subsets (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--drop-strays", action="store_true",
                   help="remove stray points (isolated returns off the surface) from the scans; by default they are "
                        "kept, counted (see info) and only left out of the frame's fit")
    p.add_argument("--layout", default="auto",
                   choices=("auto", "tree", "real3d-ad", "anomaly-shapenet", "mvtec3d"),
                   help="folder layout: a public benchmark's class folder (docs/public_layouts.md), 'tree' for "
                        "this toolkit's own, or 'auto' to detect it (default)")
    p.add_argument("--views", type=int, metavar="N",
                   help="real3d-ad / anomaly-shapenet: partial training views rendered per template (default 16)")
    p.add_argument("--validation-views", type=int, metavar="N",
                   help="real3d-ad / anomaly-shapenet: held-back views per template for calibration (default 4)")
    p.add_argument("--keep-plane", action="store_true", help="mvtec3d: keep the table plane (default: removed)")
    p.add_argument("--max-points", type=int, metavar="N",
                   help="public layouts without --voxel/--points: voxel size from the data's spacing so a scan keeps "
                        "about N points (default 20000; 0: no downsampling)")
    p.set_defaults(func=_cmd_import)

    p = sub.add_parser("export", help="collection -> PLY files in the same tree layout")
    p.add_argument("collection")
    p.add_argument("dir")
    p.add_argument("--file-frame", action="store_true", help="write in the original file units")
    p.add_argument("--overwrite", action="store_true", help="write into a non-empty folder")
    p.set_defaults(func=_cmd_export)

    p = sub.add_parser("info", help="summary of a collection")
    p.add_argument("collection")
    p.set_defaults(func=_cmd_info)

    try:  # the virtual scanner lives in a colleague's module; the other commands must work without it
        from .synth_cli import register
    except ModuleNotFoundError as e:
        if e.name != f"{__package__}.synth_cli":  # synth_cli exists but is broken: say so, don't hide it
            raise
        register = None
    if register is not None:
        register(sub)
    return parser


def main(argv=None):
    """Run the command line; returns the exit code (0 ok, 2 bad input or usage).

    Every user mistake (a bad option value, a missing or corrupt input, an existing or unwritable output) prints one
    line ``error: ...`` naming the file or option on stderr and returns 2; no traceback.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help (0) or a usage error (2, already printed as one line)
        return e.code if isinstance(e.code, int) else 2
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except (ValueError, OSError) as e:  # bad input or an unwritable output: one line naming the file, no traceback
        print(f"error: {one_line(e)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
