"""The inspection jobs behind the command line: calibrate a model on good scans, score scans and write the results."""
import logging
import shutil
import time
from pathlib import Path

import numpy as np

from .parts import PartInspector, model_parts
from .threshold import DEFAULT_ALPHA

log = logging.getLogger(__name__)

COLLECTION_SUFFIXES = (".h5", ".hdf5")
RESULT_FILES = ("scores.csv", "summary.json", "roc.png", "scores.png")


class InspectionError(Exception):
    """A user-facing problem (bad input); the command line prints its message as one line and exits 2."""


# ------------------------------------------------------------------------------------------------------ inputs
def load_scans(data, frame=None, split=None, label=None, model_fingerprint=""):
    """Scans to inspect, in the model's frame.

    Parameters
    ----------
    data : str or Path
        A collection file (.h5), a folder of scanner files (tree or flat, see datasets.importer) or one cloud file.
    frame : datasets.Frame, optional
        The model's frame: a collection must have been stored in it; scanner files are moved into it.
    split : str, optional
        Keep only this split ('train', 'validation', 'test') when the data has splits; None keeps all.
    label : str, optional
        Keep only this label.

    Returns
    -------
    scans : list of Scan
    info : dict
        ``source``, ``kind`` ('collection' / 'files'), ``fingerprint`` (collections), ``same_as_training``.
    """
    from datasets import ScanCollection
    from datasets.cloud_io import CLOUD_SUFFIXES
    from datasets.importer import ScanSource, find_sources, load_source

    data = Path(data)
    if not data.exists():
        raise InspectionError(f"{data}: no such file or folder")
    info = {"source": str(data)}
    if data.is_file() and data.suffix.lower() in COLLECTION_SUFFIXES:
        try:
            coll = ScanCollection(data)
        except (OSError, ValueError) as exc:
            raise InspectionError(str(exc) if str(data) in str(exc) else f"{data}: {exc}") from None
        with coll:
            if frame is not None and coll.frame != frame:
                raise InspectionError(f"{data}: collection frame {coll.frame} differs from the model's {frame}; "
                                      f"the model was trained on other data (re-import the scans with the model's "
                                      f"frame, or pass the scanner files)")
            idx = coll.select(split=split, label=label)
            fp = coll.fingerprint()
            info.update(kind="collection", fingerprint=fp, same_as_training=bool(model_fingerprint)
                        and fp == model_fingerprint, frame=coll.frame)
            scans = coll.read_many(idx)
    elif data.is_dir() or data.suffix.lower() in CLOUD_SUFFIXES:
        if data.is_dir():
            sources = find_sources(data)
        else:
            sources = [ScanSource(data, data.stem, "test", "unknown", "")]
        if frame is None:
            raise InspectionError(f"{data}: scanner files need the model's frame, and this model records none")
        scans = []
        for src in sources:
            scan, _ = load_source(src)
            scans.append(frame.apply(scan))
        scans = [s for s in scans if (split is None or s.split == split) and (label is None or s.label == label)]
        info.update(kind="files", fingerprint="", same_as_training=False, frame=frame)
    else:
        raise InspectionError(f"{data}: unknown data file type {data.suffix!r} (expected a collection "
                              f"{'/'.join(COLLECTION_SUFFIXES)}, a folder of scans, or a cloud file "
                              f"{'/'.join(CLOUD_SUFFIXES)})")
    for s in scans:
        if len(s.points) == 0:
            raise InspectionError(f"{data}: scan {s.name!r} has no points")
    return scans, info


def make_aligner(handle, data_info, reference=None, seed=0):
    """An :class:`inspection.align.Aligner` onto: ``reference`` (a collection: its good training scans; a cloud file),
    else the good training scans of the data's collection, else the model's mean surface."""
    from .align import Aligner

    def from_collection(path, names=None):
        from datasets import ScanCollection

        with ScanCollection(path) as c:
            idx = c.select(split="train", label="good")
            if not idx:
                idx = c.select(label="good")
            rng = np.random.default_rng(seed)
            idx = sorted(rng.choice(idx, min(8, len(idx)), replace=False).tolist()) if idx else []
            scans = c.read_many(idx)
        if not scans:
            raise InspectionError(f"{path}: no good scans to align against")
        return (np.concatenate([s.points for s in scans]), np.concatenate([s.normals for s in scans]))

    if reference is not None:
        ref = Path(reference)
        if ref.suffix.lower() in COLLECTION_SUFFIXES:
            pts, nrm = from_collection(ref)
        else:
            from datasets import read_cloud

            pts, nrm = read_cloud(ref)
        return Aligner(pts, nrm, seed=seed)
    if data_info.get("kind") == "collection":
        from datasets import ScanCollection

        with ScanCollection(data_info["source"]) as c:
            has_train = bool(c.select(split="train", label="good"))
        if has_train:
            return Aligner(*from_collection(data_info["source"]), seed=seed)
    return Aligner(*handle.reference_points(seed=seed), seed=seed)


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


# ------------------------------------------------------------------------------------------------------ jobs
def calibration_scans(handle, data, split=None, frame_check=True):
    """The good scans of ``data`` that the model did not train on. Returns (scans, info, how).

    On the model's own training collection (same fingerprint) these are the scans the trainer held back: the
    checkpoint records them, chosen by the trainer's one rule (:func:`autodecoder.latent.train.split_training_scans`:
    the validation split's good scans, else a seeded fraction of the training scans). A model that records none is
    calibrated on the good scans outside the training split; with ``split``, on that split's good scans, training
    scans only when held back. On any other data: its good scans (of ``split``) the model did not train on.
    """
    scans, info = load_scans(data, handle.frame if frame_check else None, split=split, label="good",
                             model_fingerprint=handle.fingerprint)
    how = f"good scans of {data}" + (f" (split {split})" if split else "")
    train, held = set(handle.train_names), set(handle.heldback_names)
    if info.get("same_as_training"):
        if split is None and held:
            scans = [s for s in scans if s.name in held]
            how = f"the model's {len(held)} held-back good scans"
        else:
            scans = [s for s in scans if s.split != "train" or s.name in held]
            if split is None:
                how = "good scans outside the training split (the model records no held-back scans)"
    scans = [s for s in scans if s.name not in train or s.name in held]
    if not scans:
        raise InspectionError(f"{data}: no good scans the model did not train on (give a collection of good parts, "
                              f"a validation split, or a model with held-back calibration scans)")
    return scans, info, how


def reference_scans(handle, data, info, max_scans=32, part=None):
    """Up to ``max_scans`` (None: all) of the model's training scans (evenly spread; of part ``part`` only when
    given), read from ``data`` when it is the model's training collection; None otherwise."""
    if not info.get("same_as_training") or not handle.train_names:
        return None
    from datasets import ScanCollection

    part_ids = list(getattr(handle.model, "train_part_ids", None) or [""] * len(handle.train_names))
    with ScanCollection(data) as c:
        names = set(c.names)
        present = [n for n, p in zip(handle.train_names, part_ids) if n in names and (part is None or p == part)]
        if not present:
            return None
        n = len(present) if max_scans is None else min(max_scans, len(present))
        pick = np.unique(np.linspace(0, len(present) - 1, n).round().astype(int))
        return c.read_many([c.index_of(present[i]) for i in pick])


def check_sensor_origins(scans, data):
    """An InspectionError naming the data and a scan when any scan lacks the sensor origin the ray score needs."""
    missing = [s.name for s in scans if s.sensor_origin is None]
    if missing:
        raise InspectionError(f"{data}: {len(missing)} of {len(scans)} scans have no sensor origin (e.g. "
                              f"{missing[0]!r}); the ray score (--rays) needs where the sensor was (scanner files: a "
                              f"<stem>.json sidecar {{\"sensor_origin\": [x, y, z]}}); calibrate without --rays")


def _every_scan_has_an_origin(data):
    """Whether every scan of a collection records a sensor origin (True for anything else). A public layout's
    collection has rendered template views with origins and test scans without: rays calibrated on the views could
    not score its test scans (``score`` refuses a scan without an origin), so ``rays='auto'`` stays off there."""
    data = Path(data)
    if data.suffix.lower() not in COLLECTION_SUFFIXES or not data.is_file():
        return True
    from datasets import ScanCollection

    with ScanCollection(data) as c:
        return all(m["sensor_origin"] is not None for m in c.metadata())


def calibrate(model, data, alpha=DEFAULT_ALPHA, aggregate=None, point_score=None, noise=None, split=None, progress=True,
              write=True, projection="default", rays="auto", ray_options=None):
    """Calibrate ``model`` on good scans and store the calibration in the model file. Returns (Inspector, info).

    ``rays=True`` adds the ray score (:mod:`inspection.ray_evidence`, settings ``ray_options``; with the point
    score ``'joint'`` or ``'distance'`` it is tested only where the training scans have a surface) and calibrates
    its combination with the point score; every calibration scan then needs a sensor origin. ``rays='auto'`` (the
    default): on when ``data`` is the model's training collection (its training scans give that band) and every scan
    in it has a sensor origin (not a public layout's, whose test scans have none) (benchmarks/verdicts.py's parts
    and benchmarks/real_bunny.py: docs/results.md#thin-walled-and-open-parts-issue-18)."""
    from tqdm import tqdm

    from .calibration import write_calibration
    from .estimator import DEFAULT_AGGREGATE, DEFAULT_POINT_SCORE, DEFAULT_PROJECTION, Inspector
    from .model_io import load_model
    from .scores import REFERENCE_QUANTITY

    if rays not in (True, False, "auto"):
        raise InspectionError(f"rays must be True, False or 'auto', got {rays!r}")
    handle = load_model(model)
    scans, info, how = calibration_scans(handle, data, split=split)
    if rays is True:
        check_sensor_origins(scans, data)
    reference = None
    if point_score is None or point_score in REFERENCE_QUANTITY:
        reference = reference_scans(handle, data, info)
        if reference is None and point_score is not None:
            raise InspectionError(f"{data}: point score {point_score!r} needs the model's training scans, and this "
                                  f"is not its training collection (or the model records no training scan names)")
    if rays == "auto":  # the configuration measured: the band of the training scans' surfaces needs them
        rays = reference is not None and all(s.sensor_origin is not None for s in [*scans, *reference]) \
            and _every_scan_has_an_origin(data)
    if point_score is None:
        point_score = "joint" if reference else DEFAULT_POINT_SCORE

    def make():
        return Inspector(handle.model, alpha=alpha, aggregate=aggregate or DEFAULT_AGGREGATE,
                         point_score=point_score, noise=noise,
                         projection=(DEFAULT_PROJECTION if projection == "default" else projection)
                         if handle.kind == "latent" else None, rays=bool(rays), ray_options=ray_options)

    def fit(insp, scans, reference, desc="", part=None):
        insp._check_params()  # bad ray options fail before any work
        if point_score in REFERENCE_QUANTITY:
            # the good scans' own surface from every training scan: the reference's subset of them can miss a
            # region few views saw (docs/results.md#training-from-4-complete-templates-benchmarksfour_templatespy)
            insp.fit_reference(tqdm(reference, desc=f"reference{desc}", unit="scan", disable=not progress),
                               surface_scans=reference_scans(handle, data, info, max_scans=None, part=part))
        insp.fit(tqdm(scans, desc=f"calibrate{desc}", unit="scan", disable=not progress),
                 names=[s.name for s in scans])
        return insp

    parts = model_parts(handle.model) if handle.kind == "latent" else []
    if parts:  # several part types: each part calibrated on its own good scans (inspection.parts)
        by_part = {p: [s for s in scans if s.part_id == p] for p in parts}
        empty = [p for p, v in by_part.items() if not v]
        if empty:
            raise InspectionError(f"{data}: no good calibration scans of part(s) {empty} (the model was trained on "
                                  f"parts {parts} and calibrates each on its own scans)")
        insp = PartInspector({p: fit(make(), by_part[p], reference_scans(handle, data, info, part=p)
                                     if point_score in REFERENCE_QUANTITY else None, f" {p}", p) for p in parts})
        roles = [r for p in parts for r in insp.inspectors[p].calibration_roles_]
        how += f", per part ({', '.join(parts)})"
    else:
        insp = fit(make(), scans, reference)
        roles = insp.calibration_roles_
    crossed = roles.count("cross-fitted")
    if crossed:
        how += f" and {crossed} training scans cross-fitted"
    if write:
        write_calibration(handle.path, insp.calibration(source=f"{how}", fingerprint=info.get("fingerprint", "")))
    if parts:
        return insp, {"n": insp.n_calibration_, "how": how, "parts": insp.summary()}
    return insp, {"n": insp.n_calibration_, "how": how, "threshold": insp.threshold_,
                  "decision": insp.decision_threshold_}


def describe_calibration(insp, info):
    """The lines the command line prints after calibrating: what it did and, when the threshold is extrapolated or
    coarser than asked, the one line that says so."""
    if "parts" in info:
        lines = [f"calibrated on {info['n']} scans ({info['how']}): aggregate {insp.aggregate}, point score "
                 f"{insp.point_score}{' + ray score' if insp.rays else ''}"]
        for part, one in sorted(insp.inspectors.items()):
            t = one.decision_threshold_
            lines.append(f"part {part}: threshold {t.value:.4g} at alpha={t.alpha:g} ({t.basis}) on "
                         f"{one.n_calibration_} scans")
            if t.note:
                lines.append(f"note: part {part}: {t.note}")
        return lines
    t = insp.decision_threshold_
    lines = [f"calibrated on {info['n']} scans ({info['how']}): aggregate {insp.aggregate}, point score "
             f"{insp.point_score}{' + ray score' if insp.rays else ''}; threshold {t.value:.4g} at alpha={t.alpha:g} "
             f"({t.basis})"]
    if t.note:
        lines.append(f"note: {t.note}")
    return lines


def _calibrate_for_scoring(handle, data, alpha, progress, echo):
    """An uncalibrated model scored on its own training collection: calibrate on the held-back good scans with the
    defaults (stored in the model file, as ``calibrate`` would) and say so; anything else is an InspectionError."""
    from .model_io import load_model

    data = Path(data)
    fingerprint = ""
    if data.suffix.lower() in COLLECTION_SUFFIXES and data.is_file():
        from datasets import ScanCollection

        with ScanCollection(data) as c:
            fingerprint = c.fingerprint()
    if not (handle.fingerprint and fingerprint == handle.fingerprint and handle.heldback_names):
        raise InspectionError(f"{handle.path}: the model is not calibrated, and {data} is not its training collection "
                              f"with held-back scans; run `python -m inspection calibrate --model {handle.path} "
                              f"--data GOOD_SCANS` first")
    echo(f"{handle.path} is not calibrated: calibrating on its {len(handle.heldback_names)} held-back good scans "
         f"of {data} first (stored in the model file)")
    insp, info = calibrate(handle.path, data, alpha=DEFAULT_ALPHA if alpha is None else alpha, progress=progress)
    for line in describe_calibration(insp, info):
        echo(line)
    handle.calibration = load_model(handle.path).calibration
    return insp


def score(model, data, out, split="test", alpha=None, maps="flagged", align=False, reference=None, progress=True,
          overwrite=False, echo=print):
    """Score scans against a calibrated model and write scores.csv, summary.json, roc.png, scores.png, maps/.

    A model that is not calibrated yet is calibrated first on its held-back good scans when ``data`` is its training
    collection (and says so); otherwise that is an error naming the command to run.

    Returns
    -------
    summary : dict
    """
    from .model_io import load_model
    from .report import format_table

    if maps not in ("flagged", "all", "none"):
        raise InspectionError(f"--maps must be flagged, all or none, got {maps!r}")
    handle = load_model(model)
    insp = _calibrated_inspector(handle, data, alpha, progress, echo)
    scans, info = load_scans(data, handle.frame, split=split, model_fingerprint=handle.fingerprint)
    if not scans:
        raise InspectionError(f"{data}: no scans" + (f" in split {split!r}" if split else ""))
    if insp.rays:
        check_sensor_origins(scans, data)
    out = prepare_out(out, overwrite=overwrite)
    aligner = make_aligner(handle, info, reference) if align else None
    results = _inspect_scans(insp, scans, aligner, maps, out / "maps", progress)
    summary = _summarize(handle, insp, data, split, align, results)
    _write_results(out, insp, results, summary)
    echo(format_table(results["rows"], summary))
    echo(f"results in {out}/: scores.csv, summary.json, roc.png, scores.png"
         + (f", maps/ ({results['maps']} coloured PLY + legend.png)" if results["maps"] else ""))
    return summary


def _calibrated_inspector(handle, data, alpha, progress, echo):
    """The Inspector of ``handle`` with its stored calibration (``alpha`` None: the calibration's), calibrating
    first when the model has none (:func:`_calibrate_for_scoring`)."""
    from .estimator import Inspector

    if handle.calibration is None:
        return _calibrate_for_scoring(handle, data, alpha, progress, echo)
    if (handle.calibration.extra or {}).get("parts"):
        return PartInspector.from_calibration(handle.model, handle.calibration, alpha)
    insp = Inspector(handle.model, alpha=handle.calibration.alpha if alpha is None else alpha)
    insp.set_calibration(handle.calibration)
    return insp


def _inspect_scans(insp, scans, aligner, maps, maps_dir, progress):
    """Inspect every scan (aligned first when ``aligner``) and write the anomaly maps ``maps`` asks for.

    Returns a dict: ``rows`` (one per scan, the CSV columns), ``point_labels``, ``point_scores`` and ``ray_maps``
    (per scan with ground-truth point labels), ``seconds`` (per scan) and ``maps`` (maps written)."""
    from tqdm import tqdm

    results = {"rows": [], "point_labels": [], "point_scores": [], "ray_maps": [], "seconds": [], "maps": 0}
    for scan in tqdm(scans, desc="inspect", unit="scan", disable=not progress):
        t0 = time.perf_counter()
        if aligner is not None:
            scan = aligner.align_scan(scan)
        try:
            one = insp.for_scan(scan)  # the scan's part's inspector (a model of several part types), else insp
        except ValueError as exc:
            raise InspectionError(str(exc)) from None
        res = one.inspect(scan)
        results["seconds"].append(time.perf_counter() - t0)
        verdict = "defective" if one.predict_from_scores([res.score])[0] == -1 else "good"
        row = {"name": scan.name, "split": scan.split, "label": scan.label, "defect": scan.defect,
               "score": res.score, "p_value": float(one.p_values_from_scores([res.score])[0]), "verdict": verdict}
        if insp.rays:
            row.update(score_points=res.components["points"], score_rays=res.components["rays"])
        results["rows"].append(row)
        if scan.point_labels is not None:
            results["point_labels"].append(scan.point_labels)
            results["point_scores"].append(res.point_scores)
            if insp.rays:
                results["ray_maps"].append(res.rays.point_map)
        if maps == "all" or (maps == "flagged" and verdict == "defective"):
            _write_scan_maps(insp, scan, res, maps_dir)
            results["maps"] += 1
    return results


def _write_scan_maps(insp, scan, res, maps_dir):
    """One scan's anomaly map (the standardized residual, or the point score when it is one of the residual kind)
    and, with rays, its ray map."""
    from .maps import RAY_MAP_RANGE, safe_name, write_map
    from .scores import point_scores

    resid = res.point_scores if insp.point_score in ("residual", "local", "distance", "joint") else \
        point_scores(res.field, scan.points, "residual", insp.noise)
    write_map(maps_dir / f"{safe_name(scan.name)}.ply", scan.points, scan.normals, resid)
    if insp.rays:
        write_map(maps_dir / "rays" / f"{safe_name(scan.name)}.ply", scan.points, scan.normals, res.rays.point_map,
                  vrange=RAY_MAP_RANGE)


def _summarize(handle, insp, data, split, align, results):
    """summary.json's content: the verdict metrics (:func:`inspection.report.summarize`) and how they were made."""
    from .report import summarize

    cal = handle.calibration
    parted = isinstance(insp, PartInspector)
    rays_of = next(iter(insp.inspectors.values())) if parted else insp  # the parts share their ray settings and rule
    extra = {"model": str(handle.path), "model_kind": handle.kind, "data": str(data), "split": split,
             "aggregate": insp.aggregate, "point_score": insp.point_score, "noise": insp.noise,
             "projection": insp.projection, "n_calibration": insp.n_calibration_,
             "calibration_source": cal.source if cal is not None else "held-back scans, calibrated by score",
             "decision": None if parted else insp.decision_threshold_.as_dict(), "aligned": bool(align),
             "seconds_per_scan": float(np.mean(results["seconds"])), "maps": results["maps"],
             "higher_score_means": "more anomalous",
             "rays": None if not insp.rays else {
                 "options": rays_of._ray_record()["options"],
                 "score": "the point score plus what the ray score shows beyond the good calibration scans' "
                          "(inspection.combine, rule " + rays_of._combination().rule + ")"}}
    if parted:  # thresholds per part: summary['parts']; scores compare within a part only
        extra["parts"] = insp.summary()
    summary = summarize(results["rows"], None if parted else insp.threshold_, insp.alpha, results["point_labels"],
                        results["point_scores"], extra)
    if results["ray_maps"]:
        from sklearn.metrics import roc_auc_score

        yl = np.concatenate(results["point_labels"]).astype(int)
        if 0 < yl.sum() < len(yl):
            summary["metrics"]["ray_point_auroc"] = float(roc_auc_score(yl, np.concatenate(results["ray_maps"])))
    return summary


def _write_results(out, insp, results, summary):
    """scores.csv, summary.json, roc.png (scans with known labels), scores.png and the maps' legends."""
    from .maps import RAY_MAP_LABEL, RAY_MAP_RANGE, write_legend
    from .plots import plot_roc, plot_score_histograms
    from .report import CSV_COLUMNS, RAY_CSV_COLUMNS, write_json, write_scores_csv

    rows = results["rows"]
    write_scores_csv(out / "scores.csv", rows, RAY_CSV_COLUMNS if insp.rays else CSV_COLUMNS)
    write_json(out / "summary.json", summary)
    labels = np.array([r["label"] for r in rows])
    sc = np.array([r["score"] for r in rows])
    known = labels != "unknown"
    plot_roc(out / "roc.png", (labels[known] == "defective").astype(int), sc[known],
             np.array([r["defect"] for r in rows])[known])
    plot_score_histograms(out / "scores.png", sc, labels, getattr(insp, "decision_threshold_", None),
                          insp.calibration_scores_)
    if results["maps"]:
        write_legend(out / "maps" / "legend.png")
        if insp.rays:
            write_legend(out / "maps" / "rays" / "legend.png", RAY_MAP_RANGE, RAY_MAP_LABEL)
