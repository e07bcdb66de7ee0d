"""The anomaly map's patch size: point AUROC of the map at each number of points per patch, on scored runs.

Each run folder under ``--work`` that holds a calibrated ``model.pt`` and the ``results/summary.json`` of its scoring
(the verdicts and real suites write these: ``<work>/runs/<suite>/<collection>/<run>/``) is scored again through the
Python API with the model's stored calibration (:func:`benchmarks.inspect_api.point_maps`), and its test scans' maps
are made at each patch size of ``--neighbours`` (:func:`inspection.maps.map_values`; 1 = the points' own
residuals). Printed per run: the collection, its points per scan, the labelled defect points per defective scan
(min / median / max: the defects' own size in points), and the point AUROC of every point of the test scans (good
scans' points count as good) at each patch size, with the rays' evidence where the run scores rays (as the maps
show it), and at the default patch size without it; then the same per defect type at the default patch size and
at 1.
The default patch size is ``inspection.maps.MAP_NEIGHBOURS`` (:func:`benchmarks.inspect_api.map_neighbours`).
"""
import json
from pathlib import Path

import numpy as np

from benchmarks import inspect_api, metrics
from benchmarks.trees import run_folders
from benchmarks.table import format_table

DESCRIPTION = "point AUROC of the anomaly map at each patch size (points per patch), on the scored runs of a folder"


def add_arguments(p):
    p.add_argument("--work", required=True,
                   help="a suite's work folder (e.g. results/verdicts): every run folder below it with model.pt and "
                        "results/summary.json is measured")
    p.add_argument("--neighbours", default="1,8,16,24,32,48,64",
                   help="comma-separated points per patch (default: %(default)s)")
    p.add_argument("--match", default="",
                   help="comma-separated texts: only runs whose path contains one of them (default: all)")
    p.add_argument("--root", default=".",
                   help="the folder the runs were made from: a relative collection path in a run's summary is read "
                        "from here (default: the current folder)")


def run(args):
    default = inspect_api.map_neighbours()
    sizes = sorted({int(v) for v in args.neighbours.split(",")} | {1, default})
    folders = run_folders(args.work, args.match)
    if not folders:
        raise SystemExit(f"no run folder with model.pt and results/summary.json under {args.work}")
    rows, per_type = [], []
    for folder in folders:
        data = Path(args.root) / json.loads((folder / "results" / "summary.json").read_text())["data"]
        scans, results = inspect_api.point_maps(folder / "model.pt", data, neighbours=sizes)
        labels = [s.point_labels for s in scans]
        defect_points = [int(np.sum(s.point_labels)) for s in scans if s.label != metrics.GOOD and
                         s.point_labels is not None]
        name = f"{Path(data).parent.name}/{folder.name}"
        row = {"run": name, "points": int(np.median([len(s.points) for s in scans])),
               "defect": "/".join(str(int(v)) for v in (np.min(defect_points), np.median(defect_points),
                                                         np.max(defect_points))) if defect_points else "-"}
        for k in sizes:
            row[f"k{k}"] = metrics.point_auroc(labels, [r["maps"][k] for r in results])
        row["patch"] = metrics.point_auroc(labels, [r["patch_maps"][default] for r in results])
        rows.append(row)
        kinds = [s.label for s in scans], [s.defect for s in scans]
        for k in (1, default):
            per = metrics.point_auroc_per_defect(labels, [r["maps"][k] for r in results], *kinds)
            per_type.append({"run": name, "patch": k, **per})
        print(f"{name}: " + " ".join(f"k={k} {row[f'k{k}']:.3f}" for k in sizes)
              + f" (k={default} without the rays {row['patch']:.3f})", flush=True)
    print(f"\npoint AUROC of the anomaly map by points per patch (k; the default is {default}, k=1 the "
          f"points' own residuals), with the rays' evidence where the run scores rays, and at k={default} without "
          f"it; 'defect': labelled points per defective scan, min/median/max")
    print(format_table(rows, [("run", "run", ""), ("points", "points", "d"), ("defect", "defect", "")]
                       + [(f"k{k}", f"k={k}", ".3f") for k in sizes] + [("patch", f"k={default}, no rays", ".3f")]))
    kinds = sorted({k for p in per_type for k in p} - {"run", "patch"}, key=lambda k: (k != "overall", k))
    print("\nper defect type, at k=1 and the default")
    print(format_table(per_type, [("run", "run", ""), ("patch", "k", "d")] + [(k, k, ".3f") for k in kinds]))
    return {"neighbours": sizes, "default": default, "runs": rows, "per_type": per_type}
