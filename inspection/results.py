"""Writing an inspection run's results folder: scores.csv, summary.json, roc.png, scores.png and the coloured maps."""
from pathlib import Path

import numpy as np

from .errors import InspectionError

RESULT_FILES = ("scores.csv", "summary.json", "roc.png", "scores.png")


def prepare_out(out, overwrite=False):
    """Create the results folder. An existing folder is reused only when empty or holding an earlier inspection
    run (its result files are replaced and its old maps removed); anything else needs ``overwrite``."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InspectionError(f"{out}: exists and is not a folder")
    if out.is_dir():
        entries = [p for p in out.iterdir() if not p.name.startswith(".")]
        ours = (out / "summary.json").is_file() or (out / "scores.csv").is_file()
        if entries and not ours and not overwrite:
            raise InspectionError(f"{out}: folder exists and does not hold inspection results; choose another --out "
                                  f"or pass --overwrite")
        maps = out / "maps"
        if maps.is_dir():
            for p in [*maps.glob("*.ply"), *maps.glob("rays/*.ply")]:
                p.unlink()
    out.mkdir(parents=True, exist_ok=True)
    return out


def write_scan_maps(scan, values, rays, maps_dir, covered=None, regions=None):
    """One scan's anomaly map (``values``, (m,) patch residuals) and, with rays, its ray map (``rays``, (m,) or
    None), as coloured PLY files; both from :func:`inspection.maps.map_values`. With ``covered`` ((m,) bool,
    :mod:`inspection.coverage`) and any point uncovered, also ``coverage/<scan>.ply``: grey where good scans covered
    the surface, magenta where none saw it (the score leaves those points out). ``regions`` ((m,) int or None):
    each point's defect region id (-1: none), a vertex property ``region`` of the anomaly map."""
    from datasets import write_cloud

    from .maps import RAY_MAP_RANGE, safe_name, write_map

    write_map(maps_dir / f"{safe_name(scan.name)}.ply", scan.points, scan.normals, values, regions=regions)
    if rays is not None:
        write_map(maps_dir / "rays" / f"{safe_name(scan.name)}.ply", scan.points, scan.normals, rays,
                  vrange=RAY_MAP_RANGE)
    if covered is not None and not np.all(covered):
        colours = np.where(np.asarray(covered, dtype=bool)[:, None], np.uint8(180), np.array([230, 0, 200], np.uint8))
        write_cloud(maps_dir / "coverage" / f"{safe_name(scan.name)}.ply", np.asarray(scan.points, np.float32),
                    None if scan.normals is None else np.asarray(scan.normals, np.float32), colours.astype(np.uint8))


def summarize_run(handle, insp, data, split, align, results):
    """summary.json's content: the verdict metrics (:func:`inspection.report.summarize`) and how they were made."""
    from .combine import RULE
    from .report import summarize

    settings = insp.settings_
    parted = bool(insp.parts_)
    extra = {"model": str(handle.path), "model_kind": handle.kind, "data": str(data), "split": split,
             "settings": settings.as_dict(), "aggregate": settings.aggregate, "point_score": settings.point_score,
             "noise": settings.noise, "projection": settings.projection, "n_calibration": insp.n_calibration_,
             "calibration_source": insp.calibration_source_,
             "decision": None if parted else insp.decision_threshold_.as_dict(), "aligned": bool(align),
             # the frame every scan was registered onto before projection: the model's training scans' common
             # 'pose' (parts placed by hand) or a family's 'size'; None for a part in a fixture
             "common_frame": getattr(getattr(insp.model, "family", None), "kind", None),
             "seconds_per_scan": float(np.mean(results["seconds"])) if results["seconds"] else None,
             "maps": results["maps"], "higher_score_means": "more anomalous",
             "rays": None if not settings.rays else {
                 "options": settings.ray_options,
                 "score": "sqrt(point score^2 + 2 x the rays' evidence in nats, weighed per ray, per place and as a "
                          "whole by the good calibration scans' rays) (inspection.combine, rule " + RULE + ")",
                 "weighing": None if parted else insp.combination_.rays.describe()}}
    # the joint score's two terms' variances on the good calibration scans (field, good points), what weighs them
    extra["term_variances"] = None if parted else insp.term_variances()
    extra["regions"] = _regions_summary(insp, results.get("defects", []))
    if parted:  # thresholds per part: summary['parts']; scores compare within a part only
        extra["parts"] = insp.summary()
    summary = summarize(results["rows"], None if parted else insp.threshold_, insp.alpha, results["point_labels"],
                        results["point_maps"], extra)
    if results["ray_maps"]:
        from sklearn.metrics import roc_auc_score

        yl = np.concatenate(results["point_labels"]).astype(int)
        if 0 < yl.sum() < len(yl):
            summary["metrics"]["ray_point_auroc"] = float(roc_auc_score(yl, np.concatenate(results["ray_maps"])))
    return summary


def _regions_summary(insp, defects):
    """summary.json's ``regions``: the region level (per part for a model of several; None: a calibration that
    does not measure its good scans' maps), the number of regions in defects.csv and per type."""
    from collections import Counter

    parts = insp.parts_ or {"": insp}
    levels = {p: one.region_level() for p, one in sorted(parts.items())}
    return {"level": levels[""] if not insp.parts_ else levels, "n_regions": len(defects),
            "by_type": dict(sorted(Counter(d["type"] for d in defects).items())),
            "units": "the scans' own (lengths, areas and volumes as in the scan files)"}


def write_results(out, insp, results, summary):
    """scores.csv, defects.csv, summary.json, roc.png (scans with known labels), scores.png and the maps'
    legends."""
    from .maps import RAY_MAP_LABEL, RAY_MAP_RANGE, write_legend
    from .plots import plot_roc, plot_score_histograms
    from .report import CSV_COLUMNS, RAY_CSV_COLUMNS, write_defects_csv, write_json, write_scores_csv

    rays = insp.settings_.rays
    rows = results["rows"]
    write_scores_csv(out / "scores.csv", rows, RAY_CSV_COLUMNS if rays else CSV_COLUMNS)
    write_defects_csv(out / "defects.csv", results.get("defects", []))
    write_json(out / "summary.json", summary)
    scored = [r for r in rows if r["verdict"] != "error"]
    labels = np.array([r["label"] for r in scored])
    sc = np.array([r["score"] for r in scored], dtype=np.float64)
    known = labels != "unknown"
    plot_roc(out / "roc.png", (labels[known] == "defective").astype(int), sc[known],
             np.array([r["defect"] for r in scored])[known])
    plot_score_histograms(out / "scores.png", sc, labels, None if insp.parts_ else insp.decision_threshold_,
                          insp.calibration_scores_)
    if results["maps"]:
        write_legend(out / "maps" / "legend.png")
        if rays:
            write_legend(out / "maps" / "rays" / "legend.png", RAY_MAP_RANGE, RAY_MAP_LABEL)
