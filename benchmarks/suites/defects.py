"""Defects as a quality engineer reports them: each defect region found, typed and measured, against the synthesis'
truth (issue 49).

Per part and seed: the collection and model of a new user's first run (the ``inspection`` suite's: 32 good training
scans, 16 good and 16 per defect type test scans; ``--parts real``: the ``real`` suite's bunny tree, its defects made
in real points), calibrated the README's way, every test scan's anomaly map and defect regions
(:func:`benchmarks.inspect_api.scan_regions`). Printed per run:

- **AU-PRO** at 0.3 false-positive rate (:func:`benchmarks.metrics.au_pro`, as MVTec 3D-AD scores the maps);
- **found**: the share of true defects overlapped by a region with IoU >= 0.3 (:func:`benchmarks.metrics.region_overlap`);
- **type**: the share of found defects whose region has the defect's type;
- **depth err / area err**: median relative error of a found region's deviation and area against the truth: the
  largest |true deviation| of the defect's points (``Scan.point_deviation``, recorded by the synthesis) and the area
  of its points that moved by at least ``FOOTPRINT_FRACTION`` of it, each point's area as the regions measure it
  (the same definition of a footprint as the regions', applied to the truth). Defects whose points did not move
  (seen through a hole onto good surface behind) have no depth and are left out of both;
- **below**: the share of true defects found only by the strongest region of a scan called defective that passes
  the region level nowhere (``DefectRegion.above_level`` False);
- **false / good scan**: regions above the region level on good test scans per good scan, looked for on every scan
  (``false/good``: the level's own rate), and the regions the toolkit shows on the good scans it does not call
  good, a defective one's strongest region below the level included (``shown``);
- per type: found, typed right.
"""
from pathlib import Path

import numpy as np

from benchmarks import cache, inspect_api, metrics
from benchmarks.table import format_table

DESCRIPTION = ("defect regions (issue 49): AU-PRO, the share of defects found (IoU >= 0.3), type accuracy, depth and "
               "area errors against the synthesis' truth, false regions per good scan")
WORK = "results/defects"
KINDS = ("bump", "dent", "missing", "foreign")
FOOTPRINT_FRACTION = 0.1  # inspection.regions' (a test checks they agree)


def add_arguments(p):
    p.add_argument("--parts", default="fandisk,cup,real", help="comma-separated: synthetic parts (fandisk, cup, "
                                                                 "bunny, builtin, enclosure, a mesh file) and 'real' "
                                                                 "(the real bunny tree) (default: %(default)s)")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default: %(default)s)")
    p.add_argument("--cache", default=cache.CACHE, help="collections and models (default: %(default)s)")
    p.add_argument("--work", default=WORK, help="calibrated models and maps (default: %(default)s)")
    p.add_argument("--progress", action="store_true", help="progress bars")


def run(args):
    rows = []
    for part in [p.strip() for p in args.parts.split(",") if p.strip()]:
        for seed in [int(s) for s in args.seeds.split(",")]:
            data, model = _tree(part, seed, args)
            runs = inspect_api.scan_regions(model, data, Path(args.work) / f"{part}_s{seed}", progress=args.progress)
            rows.append({"part": part, "seed": seed, **region_figures(runs)})
            print(format_table([_flat(rows[-1])], _COLUMNS), flush=True)
    print(format_table([_flat(r) for r in rows], _COLUMNS))
    rules = type_rules(rows)
    print("type accuracy of the found defects under other rules (the regions' own: fill + aspect >= 1.2):")
    print(format_table(rules, [("rule", "rule", "")] + [(p, p, ".3f") for p in rules[0] if p != "rule"]))
    return {"runs": rows, "type_rules": rules}


def _tree(part, seed, args):
    """(collection, model) of ``part`` at ``seed``: the inspection suite's synthetic tree, or the real suite's."""
    if part == "real":  # the real suite's tree (built by it: suites do not import each other)
        try:
            tree = cache.real_tree(seed, args.cache)
        except FileNotFoundError as exc:
            raise SystemExit(f"defects: {exc}") from None
        return tree, cache.trained_model(tree, root=args.cache, seed=0)
    data = cache.synth_collection(part, seed, root=args.cache, progress=args.progress, **cache.COLLECTION_DEFAULTS)
    return data, cache.trained_model(data, root=args.cache, seed=seed)


# other ways to tell a smooth displacement from a part with walls, on a found region's fill and aspect (depth over
# its footprint's radius): what the regions' rule (inspection.regions.region_type) was chosen against
_RULES = {"fill >= 0.6": lambda fill, aspect: fill >= 0.6, "aspect >= 0.7": lambda fill, aspect: aspect >= 0.7,
          **{f"fill + aspect >= {t}": (lambda t: lambda fill, aspect: fill + aspect >= t)(t)
             for t in (1.1, 1.15, 1.2, 1.25, 1.3)}}


def type_rules(rows):
    """Per rule of ``_RULES`` and part: the share of found defects typed right (the rays' share decides 'missing'
    first, as the regions' rule does)."""
    out = []
    for name, sharp in _RULES.items():
        line = {"rule": name}
        for part in dict.fromkeys(r["part"] for r in rows):
            found = [m for r in rows if r["part"] == part for m in r["matched"]]
            right = [_typed(m, sharp) == m["defect"] for m in found]
            line[part] = float(np.mean(right)) if right else float("nan")
        out.append(line)
    return out


def _typed(match, sharp):
    if match["ray_share"] >= 0.5:
        return "missing"
    aspect = abs(match["deviation"]) / np.sqrt(match["area"] / np.pi) if match["area"] > 0 else 0.0
    walls = match["fill"] is not None and sharp(match["fill"], aspect)
    return ("foreign" if walls else "bump") if match["deviation"] >= 0 else ("missing" if walls else "dent")


def truth_size(deviation, labels, areas):
    """(depth, area) of a defect's truth: the largest |deviation| of its labelled points and the area of those that
    moved by at least ``FOOTPRINT_FRACTION`` of it (None, None when none moved)."""
    moved = np.abs(np.asarray(deviation, dtype=np.float64))[labels]
    depth = float(moved.max()) if len(moved) else 0.0
    if depth <= 0:
        return None, None
    return depth, float(np.asarray(areas)[labels][moved >= FOOTPRINT_FRACTION * depth].sum())


def region_figures(runs):
    """The figures of one run (module docstring) from :func:`benchmarks.inspect_api.scan_regions`' scans."""
    scored = [r for r in runs if r["map"] is not None and r["region_ids"] is not None]
    points = [r["points"] for r in scored]
    labels = [np.asarray(r["point_labels"], dtype=bool) for r in scored]
    ids = [np.asarray(r["region_ids"]) for r in scored]
    au_pro = metrics.au_pro(points, [l.astype(int) for l in labels], [r["map"] for r in scored], max_fpr=0.3)
    defective = [i for i, r in enumerate(scored) if r["label"] == "defective" and labels[i].any()]
    # one true region per defective scan: the synthesis makes one defect a scan (a foreign object's points stand
    # apart from the surface around it, and would otherwise count as several)
    overlap = metrics.region_overlap([points[i] for i in defective], [labels[i].astype(int) for i in defective],
                                     [ids[i] for i in defective], min_iou=0.3, link=np.inf)
    per_kind = {k: {"defects": 0, "found": 0, "typed": 0} for k in KINDS}
    depth_err, area_err, matched = [], [], []
    for match in overlap["matches"]:
        scan = scored[defective[match["scan"]]]
        kind = per_kind.setdefault(scan["defect"], {"defects": 0, "found": 0, "typed": 0})
        kind["defects"] += 1
        if not match["detected"]:
            continue
        kind["found"] += 1
        region = next(g for g in scan["regions"] if g["region"] == match["predicted"])
        kind["typed"] += region["type"] == scan["defect"]
        depth = area = None
        if scan["point_deviation"] is not None:
            truth = np.zeros(len(scan["points"]), dtype=bool)
            truth[match["points"]] = True
            depth, area = truth_size(scan["point_deviation"], truth, scan["areas"])
            if depth:
                depth_err.append(abs(abs(region["deviation"]) - depth) / depth)
                area_err.append(abs(region["area"] - area) / area if area > 0 else np.nan)
        matched.append({"defect": scan["defect"], "truth_depth": depth, "truth_area": area, "iou": match["iou"],
                        **{k: region[k] for k in ("type", "deviation", "area", "fill", "ray_share", "peak",
                                                  "above_level")}})
    good = [i for i, r in enumerate(scored) if r["label"] == "good"]
    told = [i for i in good if scored[i]["verdict"] != "good"]  # the good scans whose regions a user is shown
    found = sum(k["found"] for k in per_kind.values())
    return {"au_pro": au_pro, "found": overlap["detected"], "typed": sum(k["typed"] for k in per_kind.values()) /
            found if found else float("nan"),
            "depth_error": float(np.nanmedian(depth_err)) if depth_err else float("nan"),
            "area_error": float(np.nanmedian(area_err)) if area_err else float("nan"), "measured": len(depth_err),
            "below": sum(m["above_level"] is False for m in matched) / len(overlap["matches"])
            if overlap["matches"] else float("nan"),
            "false_per_good": metrics.false_regions_per_scan([_above_level(scored[i], ids[i]) for i in good],
                                                             [labels[i] for i in good]) if good else float("nan"),
            "false_shown": sum(int(np.max(ids[i], initial=-1)) + 1 for i in told) / len(good) if good else float("nan"),
            "good_scans": len(good), "per_kind": per_kind, "matched": matched}


def _above_level(scan, ids):
    """A scan's region ids (m,) with its regions below the region level (a defective scan's strongest) set to -1."""
    below = [g["region"] for g in scan["regions"] if g.get("above_level") is False]
    return np.where(np.isin(ids, below), -1, ids)


_COLUMNS = [("part", "part", ""), ("seed", "seed", ">"), ("au_pro", "AU-PRO", ".3f"), ("found", "found", ".3f"),
            ("below", "below", ".3f"),
            ("typed", "type", ".3f"), ("depth_error", "depth err", ".3f"), ("area_error", "area err", ".3f"),
            ("false_per_good", "false/good", ".3f"), ("false_shown", "shown", ".3f")] + [(k, k, "") for k in KINDS]


def _flat(row):
    return {**{k: v for k, v in row.items() if k not in ("per_kind", "matched")},
            **{k: f"{v['found']}/{v['defects']} found, {v['typed']} typed" for k, v in row["per_kind"].items()
               if k in KINDS}}

