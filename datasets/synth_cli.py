"""The ``synth`` command: virtual scans of a CAD part (with synthetic defects) -> a scan collection or a PLY tree."""
import json
from pathlib import Path

FORMATS = ("h5", "tree")


def register(subparsers):
    """Add the ``synth`` subcommand to an argparse subparsers object (only argparse is touched: --help stays fast)."""
    p = subparsers.add_parser(
        "synth", help="virtual scans of a CAD mesh, good and with synthetic defects -> collection",
        description="Scan a part (OBJ/STL/PLY/OFF mesh, or 'builtin' for the built-in bracket) with a virtual depth "
                    "camera from random views and write good train/validation/test scans and defective test scans "
                    "(dent, bump, missing material, foreign object) with per-point ground truth, in the unit-cube "
                    "frame of the part's bounding box.")
    p.add_argument("--mesh", required=True, metavar="PART", help="mesh file, or 'builtin'")
    p.add_argument("--out", required=True, help="collection file (.h5) or, with --format tree, a folder")
    p.add_argument("--train", type=int, default=32, help="good training scans (default 32)")
    p.add_argument("--validation", type=int, default=0, help="good validation scans (default 0)")
    p.add_argument("--test-good", type=int, default=16, help="good test scans (default 16)")
    p.add_argument("--test-defective", type=int, default=16, help="defective test scans PER defect kind (default 16)")
    p.add_argument("--defects", default="dent,bump,missing,foreign", help="comma-separated defect kinds")
    p.add_argument("--points", type=int, default=4000, help="points per scan (default 4000)")
    p.add_argument("--noise", type=float, default=0.002,
                   help="depth-noise std relative to the part's bounding-box diagonal (default 0.002)")
    p.add_argument("--grazing-dropout", type=float, default=0.0, metavar="K",
                   help="returns lost at grazing incidence: a hit at incidence angle theta kept with probability "
                        "cos(theta)^K (1: Lambertian; default 0: every hit kept)")
    p.add_argument("--ragged", type=float, default=0.0, metavar="F",
                   help="ragged borders: silhouettes and occluding edges eaten back by up to F x the bounding-box "
                        "diagonal, by a depth that varies along them (default 0: clean borders)")
    p.add_argument("--jitter", type=float, default=0.0, metavar="DEG",
                   help="random rotation of the part per scan, up to DEG degrees (default 0: a fixture)")
    p.add_argument("--seed", type=int, default=0, help="seed of everything random (default 0)")
    p.add_argument("--part-id", default=None, help="part id stored in the scans (default: the mesh file's stem)")
    p.add_argument("--format", choices=FORMATS, default="h5", help="h5 collection (default) or a tree of PLY files")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_synth)
    return p


# synthesise's parameter -> the option that sets it (its errors name the option)
_OPTION_OF = {"n_train": "--train", "n_validation": "--validation", "n_test_good": "--test-good",
              "n_test_defective": "--test-defective", "n_points": "--points", "noise": "--noise",
              "jitter_deg": "--jitter", "grazing_dropout": "--grazing-dropout", "ragged": "--ragged"}


def run_synth(args):
    """Run ``synth`` from parsed arguments (an argparse Namespace from `register`'s parser); returns 0.

    Raises
    ------
    ValueError
        Unreadable mesh, unknown defect kind or format, a defect no view could show (the message names the file).
    FileExistsError
        ``--out`` exists and ``--overwrite`` was not given.
    OSError
        ``--out``'s folder does not exist or cannot be written (checked before scanning).
    """
    from .atomic import check_writable
    from .defects import DEFECT_KINDS

    out = Path(args.out)
    if args.format not in FORMATS:
        raise ValueError(f"--format must be one of {FORMATS}, got {args.format!r}")
    # Check everything cheap before the minutes of scanning.
    if out.exists() and not args.overwrite:
        raise FileExistsError(f"{out}: already exists (pass --overwrite to replace it)")
    check_writable(out)
    defects = tuple(d.strip() for d in args.defects.split(",") if d.strip())
    unknown = [d for d in defects if d not in DEFECT_KINDS]
    if unknown:
        raise ValueError(f"--defects: unknown defect kind(s) {', '.join(map(repr, unknown))}; "
                         f"expected some of {', '.join(DEFECT_KINDS)}")

    from .parts import load_part
    from .synth import synthesise

    mesh = load_part(args.mesh)
    part_id = args.part_id if args.part_id is not None else ("builtin" if args.mesh == "builtin"
                                                              else Path(args.mesh).stem)
    parameters = dict(n_train=args.train, n_validation=args.validation, n_test_good=args.test_good,
                      n_test_defective=args.test_defective, defects=list(defects), n_points=args.points,
                      noise=args.noise, jitter_deg=args.jitter, seed=args.seed, part_id=part_id)
    # the sensor's losses only when asked for: a collection written at the defaults keeps its bytes
    parameters.update({k: v for k, v in (("grazing_dropout", getattr(args, "grazing_dropout", 0.0)),
                                         ("ragged", getattr(args, "ragged", 0.0))) if v})
    try:
        scans, frame = synthesise(mesh, progress=not getattr(args, "quiet", False), **parameters)
    except ValueError as exc:  # the library names its parameters; the user typed the options
        message = str(exc)
        for name, option in _OPTION_OF.items():
            if message.startswith(f"{name} "):
                message = option + message[len(name):]
                break
        raise ValueError(message) from None
    provenance = {"generator": "datasets.synth", "mesh": str(args.mesh), **parameters}
    if args.format == "h5":
        from .collection import ScanCollection

        ScanCollection.create(out, scans, frame=frame, provenance=provenance, overwrite=args.overwrite)
    else:
        _write_tree(out, scans, frame, provenance)
    n_defective = sum(s.label == "defective" for s in scans)
    print(f"wrote {out}: {len(scans)} scans ({n_defective} defective) of {args.points} points, part {part_id!r}")
    return 0


def _write_tree(out, scans, frame, provenance):
    """MVTec-style tree: <split>/<good|defect>/<NNN>.ply, ground_truth/<defect>/<NNN>.txt (0/1 per point) and
    <NNN>.deviation.txt (each point's deviation, in the clouds' units: :data:`datasets.importer.DEVIATION_SUFFIX`).

    Written into a temporary folder beside ``out`` and renamed into place, so a reader never sees half a tree.
    """
    from .atomic import atomic_directory
    from .cloud_io import write_cloud

    with atomic_directory(out) as tmp:
        for scan in scans:
            write_cloud(tmp / f"{scan.name}.ply", scan.points, scan.normals)
            if scan.label == "defective":
                truth = tmp / "ground_truth" / scan.defect / f"{Path(scan.name).name}.txt"
                truth.parent.mkdir(parents=True, exist_ok=True)
                truth.write_text("".join(f"{v}\n" for v in scan.point_labels.tolist()))
                truth.with_name(f"{truth.stem}.deviation.txt").write_text(
                    "".join(f"{v:.9g}\n" for v in scan.point_deviation.tolist()))
        # The frame maps the part's file units to the cloud coordinates: keep it with the clouds.
        meta = {"frame": frame.as_dict(), "provenance": provenance,
                "sensor_origins": {s.name: [float(v) for v in s.sensor_origin] for s in scans}}
        (tmp / "synth.json").write_text(json.dumps(meta, indent=1) + "\n")
