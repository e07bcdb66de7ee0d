"""The inspection jobs behind the command line: calibrate a model on good scans, score scans and write the results."""
import logging
import time
from pathlib import Path

import numpy as np


log = logging.getLogger(__name__)

COLLECTION_SUFFIXES = (".h5", ".hdf5")
RESULT_FILES = ("scores.csv", "summary.json", "roc.png", "scores.png")


class InspectionError(Exception):
    """A user-facing problem (bad input); the command line prints its message as one line and exits 2."""


# ------------------------------------------------------------------------------------------------------ inputs
def load_scans(data, frame=None, split=None, label=None, model_fingerprint="", errors="raise"):
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
    errors : {'raise', 'collect'}
        A scan that cannot be read (damaged, NaN points, content that does not match its stored hash, an unreadable
        scanner file): an :class:`InspectionError` naming it, or collected.

    Returns
    -------
    scans : list of Scan
    info : dict
        ``source``, ``kind`` ('collection' / 'files'), ``fingerprint`` (collections), ``same_as_training``,
        ``frame``, and ``failed``: a list of (scan name, reason) of the scans that could not be read (``'collect'``).
    """
    from datasets import ScanReadError
    from datasets.cloud_io import CLOUD_SUFFIXES
    from datasets.importer import ScanSource, find_sources, load_source

    data = Path(data)
    if not data.exists():
        raise InspectionError(f"{data}: no such file or folder")
    info = {"source": str(data), "failed": []}
    if data.is_file() and data.suffix.lower() in COLLECTION_SUFFIXES:
        with open_collection(data, frame) as coll:
            idx = coll.select(split=split, label=label)
            fp = coll.fingerprint()
            info.update(kind="collection", fingerprint=fp, same_as_training=bool(model_fingerprint)
                        and fp == model_fingerprint, frame=coll.frame)
            try:
                scans, failed = coll.read_many(idx, errors="collect")
            except ScanReadError as exc:  # pragma: no cover - 'collect' returns them
                raise InspectionError(str(exc)) from None
            if failed and errors == "raise":
                raise InspectionError(str(failed[0]))
            info["failed"] = [(e.scan_name, str(e)) for e in failed]
    elif data.is_dir() or data.suffix.lower() in CLOUD_SUFFIXES:
        if data.is_dir():
            sources = find_sources(data)
        else:
            sources = [ScanSource(data, data.stem, "test", "unknown", "")]
        if frame is None:
            raise InspectionError(f"{data}: scanner files need the model's frame, and this model records none")
        scans = []
        for src in sources:
            if (split is not None and src.split != split) or (label is not None and src.label != label):
                continue
            try:
                scan, _ = load_source(src)
            except (OSError, ValueError) as exc:
                reason = str(exc) if str(src.path) in str(exc) else f"{src.path}: {exc}"
                if errors == "raise":
                    raise InspectionError(reason) from None
                info["failed"].append((src.name, reason))
                continue
            scans.append(frame.apply(scan))
        info.update(kind="files", fingerprint="", same_as_training=False, frame=frame)
    else:
        raise InspectionError(f"{data}: unknown data file type {data.suffix!r} (expected a collection "
                              f"{'/'.join(COLLECTION_SUFFIXES)}, a folder of scans, or a cloud file "
                              f"{'/'.join(CLOUD_SUFFIXES)})")
    for s in scans:
        if len(s.points) == 0:
            raise InspectionError(f"{data}: scan {s.name!r} has no points")
    return scans, info


def open_collection(data, frame=None):
    """A :class:`datasets.ScanCollection` opened on ``data`` (use it as a context manager), checked to be stored in
    the model's ``frame``; InspectionError naming the file otherwise."""
    from datasets import ScanCollection

    try:
        coll = ScanCollection(data)
    except (OSError, ValueError) as exc:
        raise InspectionError(str(exc) if str(data) in str(exc) else f"{data}: {exc}") from None
    if frame is not None and coll.frame != frame:
        coll.close()
        raise InspectionError(f"{data}: collection frame {coll.frame} differs from the model's {frame}; the model was "
                              f"trained on other data (re-import the scans with the model's frame, or pass the "
                              f"scanner files)")
    return coll


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
def calibrate(model, data, config=None, split=None, progress=True, write=True):
    """Calibrate ``model`` on the good scans of ``data`` and store the calibration in the model file:
    ``Inspector.from_config(model, config).fit(good scans of data, split=split)``, the Python API's one pipeline
    (:mod:`inspection.selection` chooses the calibration and reference scans). Returns (Inspector, info).

    Parameters
    ----------
    model : str or Path
        The model file (rewritten atomically with the calibration when ``write``).
    data : str or Path
        A collection (the model's training collection gives the held-back scans and the training scans' reference),
        a folder of scanner files or one cloud file.
    config : InspectionConfig, optional
        The settings (None: the defaults); validated before any file is read.
    split : str, optional
        Calibrate on this split's good scans.
    """
    from .calibration import write_calibration
    from .config import InspectionConfig
    from .estimator import Inspector
    from .model_io import load_model

    config = (config or InspectionConfig()).validated()
    handle = load_model(model)
    insp = Inspector.from_config(handle.model, config, verbose=progress)
    data = Path(data)
    if data.is_file() and data.suffix.lower() in COLLECTION_SUFFIXES:
        with open_collection(data, handle.frame) as coll:
            try:
                insp.fit(coll, split=split)
            except ValueError as exc:
                raise InspectionError(f"{data}: {exc}") from None
    else:
        scans, info = load_scans(data, handle.frame, split=split, label="good")
        try:
            insp.fit(scans, split=split)
        except ValueError as exc:
            raise InspectionError(f"{data}: {exc}") from None
    if write:
        write_calibration(handle.path, insp.calibration())
    info = {"n": insp.n_calibration_, "how": insp.calibration_source_}
    if insp.parts_:
        info["parts"] = insp.summary()
    else:
        info.update(threshold=insp.threshold_, decision=insp.decision_threshold_)
    return insp, info


def describe_calibration(insp, info):
    """The lines the command line prints after calibrating: what it did and, when the threshold is extrapolated or
    coarser than asked, the one line that says so."""
    settings = insp.settings_
    what = f"aggregate {settings.aggregate}, point score {settings.point_score}{' + ray score' if settings.rays else ''}"
    if insp.parts_:
        lines = [f"calibrated on {info['n']} scans ({info['how']}): {what}"]
        for part, one in sorted(insp.parts_.items()):
            t = one.decision_threshold_
            lines.append(f"part {part}: threshold {t.value:.4g} at alpha={t.alpha:g} ({t.basis}) on "
                         f"{one.n_calibration_} scans")
            if t.note:
                lines.append(f"note: part {part}: {t.note}")
        return lines
    t = insp.decision_threshold_
    lines = [f"calibrated on {info['n']} scans ({info['how']}): {what}; threshold {t.value:.4g} at alpha={t.alpha:g} "
             f"({t.basis})"]
    if t.note:
        lines.append(f"note: {t.note}")
    return lines


def _calibrate_for_scoring(handle, data, alpha, progress, echo):
    """An uncalibrated model scored on its own training collection: calibrate on the held-back good scans with the
    defaults (stored in the model file, as ``calibrate`` would) and say so; anything else is an InspectionError."""
    from .config import InspectionConfig

    data = Path(data)
    fingerprint = ""
    if data.suffix.lower() in COLLECTION_SUFFIXES and data.is_file():
        with open_collection(data) as c:
            fingerprint = c.fingerprint()
    if not (handle.fingerprint and fingerprint == handle.fingerprint and handle.heldback_names):
        raise InspectionError(f"{handle.path}: the model is not calibrated, and {data} is not its training collection "
                              f"with held-back scans; run `python -m inspection calibrate --model {handle.path} "
                              f"--data GOOD_SCANS` first")
    echo(f"{handle.path} is not calibrated: calibrating on its {len(handle.heldback_names)} held-back good scans "
         f"of {data} first (stored in the model file)")
    config = InspectionConfig() if alpha is None else InspectionConfig(alpha=alpha)
    insp, info = calibrate(handle.path, data, config, progress=progress)
    for line in describe_calibration(insp, info):
        echo(line)
    return insp


def score(model, data, out, split="test", alpha=None, maps="flagged", align=False, reference=None, progress=True,
          overwrite=False, echo=print):
    """Score scans against a calibrated model and write scores.csv, summary.json, roc.png, scores.png, maps/.

    A model that is not calibrated yet is calibrated first on its held-back good scans when ``data`` is its training
    collection (and says so); otherwise that is an error naming the command to run. A scan that cannot be read or
    scored (damaged, no sensor origin where the calibration uses rays, an unknown part) gets verdict ``'error'``
    with its reason; the others are scored (``summary['n_errors']`` counts them).

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
    scans, info = load_scans(data, handle.frame, split=split, model_fingerprint=handle.fingerprint, errors="collect")
    if not scans:  # nothing to score: one line, the first scan's reason when there was one
        raise InspectionError(info["failed"][0][1] if info["failed"] else
                              f"{data}: no scans" + (f" in split {split!r}" if split else ""))
    out = prepare_out(out, overwrite=overwrite)
    aligner = make_aligner(handle, info, reference) if align else None
    results = _inspect_scans(insp, scans, aligner, maps, out / "maps", progress)
    results["rows"] += [_error_row(name, reason) for name, reason in info["failed"]]
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
    try:
        return Inspector.from_calibration(handle.model, handle.calibration, alpha, verbose=progress)
    except (KeyError, ValueError) as exc:
        raise InspectionError(f"{handle.path}: its calibration cannot be used ({exc}); calibrate it again with "
                              f"`python -m inspection calibrate`") from None


def _error_row(scan_or_name, reason):
    """The scores.csv row of a scan that could not be scored."""
    name = getattr(scan_or_name, "name", scan_or_name)
    return {"name": str(name), "split": getattr(scan_or_name, "split", ""), "label": getattr(scan_or_name, "label",
            "unknown"), "defect": getattr(scan_or_name, "defect", ""), "score": None, "p_value": None,
            "verdict": "error", "reason": str(reason)}


def _inspect_scans(insp, scans, aligner, maps, maps_dir, progress):
    """Inspect every scan (aligned first when ``aligner``) and write the anomaly maps ``maps`` asks for. A scan that
    cannot be scored (a ValueError naming it) gets an ``'error'`` row and the others go on.

    Returns a dict: ``rows`` (one per scan, the CSV columns), ``point_labels``, ``point_scores`` and ``ray_maps``
    (per scan with ground-truth point labels), ``seconds`` (per scored scan) and ``maps`` (maps written)."""
    from tqdm import tqdm

    rays = insp.settings_.rays
    results = {"rows": [], "point_labels": [], "point_scores": [], "ray_maps": [], "seconds": [], "maps": 0}
    for i, scan in enumerate(tqdm(scans, desc="inspect", unit="scan", disable=not progress)):
        t0 = time.perf_counter()
        try:
            if aligner is not None:
                scan = aligner.align_scan(scan)
            one = insp.for_scan(scan)  # the scan's part's inspector (a model of several part types), else insp
            res = one.inspect(scan, i)
        except ValueError as exc:
            results["rows"].append(_error_row(scan, str(exc).strip().splitlines()[0]))
            continue
        results["seconds"].append(time.perf_counter() - t0)
        verdict = "defective" if one.predict_from_scores([res.score])[0] == -1 else "good"
        row = {"name": scan.name, "split": scan.split, "label": scan.label, "defect": scan.defect,
               "score": res.score, "p_value": float(one.p_values_from_scores([res.score])[0]), "verdict": verdict,
               "reason": ""}
        if rays:
            row.update(score_points=res.components["points"], score_rays=res.components["rays"])
        results["rows"].append(row)
        if scan.point_labels is not None:
            results["point_labels"].append(scan.point_labels)
            results["point_scores"].append(res.point_scores)
            if rays:
                results["ray_maps"].append(res.rays.point_map)
        if maps == "all" or (maps == "flagged" and verdict == "defective"):
            _write_scan_maps(one.settings_, scan, res, maps_dir)
            results["maps"] += 1
    return results


def _write_scan_maps(settings, scan, res, maps_dir):
    """One scan's anomaly map (its point scores when they are standardized residuals, else the standardized
    residual) and, with rays, its ray map."""
    from .maps import RAY_MAP_RANGE, safe_name, write_map
    from .scores import POINT_SCORES, point_scores

    resid = res.point_scores if POINT_SCORES[settings.point_score].in_deviations else \
        point_scores(res.field, scan.points, "residual", settings.noise)
    write_map(maps_dir / f"{safe_name(scan.name)}.ply", scan.points, scan.normals, resid)
    if settings.rays:
        write_map(maps_dir / "rays" / f"{safe_name(scan.name)}.ply", scan.points, scan.normals, res.rays.point_map,
                  vrange=RAY_MAP_RANGE)


def _summarize(handle, insp, data, split, align, results):
    """summary.json's content: the verdict metrics (:func:`inspection.report.summarize`) and how they were made."""
    from .estimator import COMBINATION_RULE
    from .report import summarize

    settings = insp.settings_
    parted = bool(insp.parts_)
    extra = {"model": str(handle.path), "model_kind": handle.kind, "data": str(data), "split": split,
             "settings": settings.as_dict(), "aggregate": settings.aggregate, "point_score": settings.point_score,
             "noise": settings.noise, "projection": settings.projection, "n_calibration": insp.n_calibration_,
             "calibration_source": insp.calibration_source_,
             "decision": None if parted else insp.decision_threshold_.as_dict(), "aligned": bool(align),
             "seconds_per_scan": float(np.mean(results["seconds"])) if results["seconds"] else None,
             "maps": results["maps"], "higher_score_means": "more anomalous",
             "rays": None if not settings.rays else {
                 "options": settings.ray_options,
                 "score": "the point score plus what the ray score shows beyond the good calibration scans' "
                          "(inspection.combine, rule " + COMBINATION_RULE + ")"}}
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

    rays = insp.settings_.rays
    rows = results["rows"]
    write_scores_csv(out / "scores.csv", rows, RAY_CSV_COLUMNS if rays else CSV_COLUMNS)
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
