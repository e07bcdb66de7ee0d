"""The inspection jobs behind the command line: calibrate a model on good scans, score scans and write the results.

Reading files is :mod:`inspection.loading`'s, the decisions are :class:`inspection.Inspector`'s, the results folder
is :mod:`inspection.results`'; a user's mistake is an :class:`inspection.errors.InspectionError`.
"""
import time
from pathlib import Path

import numpy as np

from .batch_check import DEFAULT_MAX_DEFECTIVE_SHARE, check_run
from .errors import InspectionError, about
from .loading import COLLECTION_SUFFIXES, load_scans, open_collection
from .results import prepare_out, summarize_run, write_results, write_scan_maps


def calibrate(model, data, config=None, split=None, progress=True, write=True, echo=None):
    """Calibrate ``model`` on the good scans of ``data`` and store the calibration in the model file:
    ``Inspector.from_config(model, config).fit(good scans of data, split=split)``, the Python API's one pipeline
    (:mod:`inspection.selection` chooses the calibration and reference scans). Returns (Inspector, info).

    Parameters
    ----------
    model : str or Path
        The model file (rewritten atomically with the calibration when ``write``).
    data : str or Path
        A collection (the model's training collection gives the held-back scans and the training scans' reference),
        a folder of scanner files or one cloud file. A model that is calibrated already, given good scans none of
        which it trained on (real good scans of the inspection's own sensor, say 4-16 of a first shift; a flat
        folder's unlabelled scans are taken for good), keeps its calibration and lets those scans set the
        threshold's level (:meth:`Inspector.fit_level`; ``config``'s alpha applies, its other settings are the
        stored calibration's).
    config : InspectionConfig, optional
        The settings (None: the defaults); validated before any file is read.
    split : str, optional
        Calibrate on this split's good scans.
    echo : callable, optional
        Told, before the work, which files of a folder ``data`` were skipped as not point clouds (one line).
    """
    from .calibration import write_calibration
    from .config import InspectionConfig
    from .model_io import load_model

    config = (config or InspectionConfig()).validated()
    handle = load_model(model)
    data = Path(data)
    if handle.calibration is not None and not _holds_training_scans(handle, data, split):
        insp = _site_level(handle, data, config, split, progress, echo)
    else:
        insp = _full_calibration(handle, data, config, split, progress, echo)
    if write:
        write_calibration(handle.path, insp.calibration())
    info = {"n": insp.n_calibration_, "how": insp.calibration_source_}
    if insp.parts_:
        info["parts"] = insp.summary()
    else:
        info.update(threshold=insp.threshold_, decision=insp.decision_threshold_)
    return insp, info


def _full_calibration(handle, data, config, split, progress, echo):
    """``Inspector.fit`` on the good scans of ``data`` (:func:`calibrate`)."""
    from .estimator import Inspector

    insp = Inspector.from_config(handle.model, config, verbose=progress)
    if data.is_file() and data.suffix.lower() in COLLECTION_SUFFIXES:
        with open_collection(data, handle.frame) as coll:
            try:
                insp.fit(coll, split=split)
            except ValueError as exc:
                raise about(data, exc) from None
        return insp
    scans = _given_good_scans(data, handle, split, echo)
    try:
        insp.fit(scans, split=split)
    except ValueError as exc:
        raise about(data, exc) from None
    return insp


def _holds_training_scans(handle, data, split):
    """Whether ``data`` holds any of the model's training scans (its training collection does): a full calibration
    then, else the calibrated model's level is set by the given scans (:func:`_site_level`)."""
    trained = set(str(n) for n in (getattr(handle.model, "train_names", None) or []))
    if not trained:
        return True
    if data.is_file() and data.suffix.lower() in COLLECTION_SUFFIXES:
        with open_collection(data, handle.frame) as coll:
            if handle.fingerprint and coll.fingerprint() == handle.fingerprint:
                return True
            return any(m["name"] in trained for m in coll.metadata())
    return False  # scanner files: not the model's collection (a file named like a training scan is refused later)


def _given_good_scans(data, handle, split, echo):
    """The good scans of ``data`` that ``calibrate`` was given: a collection's or a labelled tree's good ones; the
    scans of a folder without labels (a flat folder of scanner files) are taken for good, as calibrate is given good
    scans, and ``echo`` says so."""
    if data.is_file() and data.suffix.lower() in COLLECTION_SUFFIXES:
        scans, _ = load_scans(data, handle.frame, split=split, label="good")
        return scans
    reading = None if handle.calibration is None else (handle.calibration.extra or {}).get("reading")
    scans, _ = load_scans(data, handle.frame, split=split, reading=reading)  # files read as the model's were
    skipped = skipped_files_line(data)
    if echo is not None and skipped:
        echo(skipped)
    unlabelled = [s for s in scans if s.label == "unknown"]
    if unlabelled and echo is not None:
        echo(f"taking the {len(unlabelled)} unlabelled scan{'s' if len(unlabelled) != 1 else ''} of {data} for good "
             f"ones (calibrate is given good scans; a tree's good/ and defective folders label them)")
    return [s for s in scans if s.label in ("good", "unknown")]


def _site_level(handle, data, config, split, progress, echo):
    """A calibrated model given good scans it never trained on (not its training collection): they set the
    threshold's level, the stored calibration its spread and everything else (:meth:`Inspector.fit_level`)."""
    from .estimator import Inspector

    insp = _calibrated_inspector(handle, data, config.alpha, progress, echo)
    scans = _given_good_scans(data, handle, split, echo)
    if not scans:
        raise InspectionError(f"{data}: no good scans to set the threshold's level with")
    if echo is not None:
        echo(f"{handle.path} is calibrated: the {len(scans)} good scan{'s' if len(scans) != 1 else ''} of {data} set "
             f"its threshold's level (the scans of the inspection's own sensor), its calibration scans the spread; "
             f"calibrating on the training collection again starts afresh")
    try:
        insp.fit_level(scans, source=str(data))
    except ValueError as exc:
        raise about(data, exc) from None
    return insp


def skipped_files_line(data):
    """The one line naming the files of a folder ``data`` skipped as not point clouds
    (:func:`datasets.importer.list_folder`); '' for a collection, a cloud file or a folder without such files."""
    from datasets.importer import list_folder, skipped_line

    data = Path(data)
    if not data.is_dir():
        return ""
    try:
        return skipped_line(list_folder(data).skipped, data)
    except (OSError, ValueError):  # reading the folder says what is wrong with it
        return ""


def describe_calibration(insp, info):
    """The lines the command line prints after calibrating: the threshold in plain words first (its false-alarm
    rate, that rate's interval, what set it: :func:`inspection.threshold.describe_decision`), then what was done and
    the threshold's statistics, then how the rays are weighed and how scans are registered (a model of several part
    types: a threshold line and its note per part)."""
    from .threshold import describe_decision

    settings = insp.settings_
    what = f"aggregate {settings.aggregate}, point score {settings.point_score}{' + ray score' if settings.rays else ''}"
    if insp.parts_:
        lines = [f"calibrated on {info['n']} scans ({info['how']}): {what}"]
        for part, one in sorted(insp.parts_.items()):
            t = one.decision_threshold_
            lines.append(f"part {part}: threshold {t.value:.4g} at alpha={t.alpha:g} ({t.basis}) on "
                         f"{one.n_calibration_} scans{_term_spread(one)}")
            if getattr(one, "combination_", None) is not None:
                lines.append(f"part {part}: {one.combination_.rays.describe()}")
            if t.note:
                lines.append(f"note: part {part}: {t.note}")
            if getattr(one, "alignment_note_", ""):
                lines.append(f"note: part {part}: {one.alignment_note_}")
        return lines
    t = insp.decision_threshold_
    what += _term_spread(insp)
    aligned = [f"note: {insp.alignment_note_}"] if getattr(insp, "alignment_note_", "") else []
    frame = getattr(insp.model, "family", None)
    if frame is not None and frame.kind == "size":
        aligned.append("note: the model was trained on a family of sizes: every scan is registered onto its common "
                       "size before it is scored (a part of another size in the family's range is not a defect)")
    elif frame is not None:
        aligned.append("note: the model was trained on scans moved into one common pose (their poses spread): every "
                       "scan is registered onto it before it is scored")
    plain, stats = describe_decision(t.as_dict())  # the threshold in plain words first, the statistics after
    lines = [f"threshold {t.value:.4g} at alpha={t.alpha:g}: {plain}",
             f"calibrated on {info['n']} scans ({info['how']}): {what}", stats]
    if getattr(insp, "combination_", None) is not None:  # how much the rays count, as the good scans' rays say
        lines.append(insp.combination_.rays.describe())
    return lines + aligned


def _term_spread(insp):
    """'' or, for a point score that weighs its two terms (:func:`inspection.scores.fit_term_variances`), how much
    each spreads on the good calibration scans, the weight it gets being the inverse of its variance."""
    variances = insp.term_variances()
    if variances is None:
        return ""
    v_d, v_s = variances
    return (f" (its terms weighed by their spread on the good scans: the field's {v_d ** 0.5:.2f}, the good "
            f"points' {v_s ** 0.5:.2f} standard deviations)")


def _calibrate_for_scoring(handle, data, alpha, progress, echo, align="auto"):
    """An uncalibrated model scored on its own training collection: calibrate on the held-back good scans with the
    defaults (and ``align``; stored in the model file, as ``calibrate`` would) and say so; anything else is an
    InspectionError."""
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
    config = InspectionConfig(align=align, **({} if alpha is None else {"alpha": alpha}))
    insp, info = calibrate(handle.path, data, config, progress=progress)
    for line in describe_calibration(insp, info):
        echo(line)
    return insp


def score(model, data, out, split="test", alpha=None, maps="flagged", align=False, progress=True, overwrite=False,
          echo=print, uncertain=True, jobs=1, max_defective_share=None):
    """Score scans against a calibrated model and write report.html, scores.csv, summary.json, roc.png, scores.png,
    maps/.

    A model that is not calibrated yet is calibrated first on its held-back good scans when ``data`` is its training
    collection (and says so); otherwise that is an error naming the command to run. A scan that cannot be read or
    scored (damaged, no sensor origin where the calibration uses rays, an unknown part) gets verdict ``'error'``
    with its reason; the others are scored (``summary['n_errors']`` counts them). A scan whose score lies within
    the threshold's own uncertainty gets verdict ``'uncertain'`` (rescan it; ``summary['n_uncertain']``) unless
    ``uncertain`` is False (two classes). ``jobs`` > 1 scores the scans in that many processes, with the same
    results, in the same order, as one (:func:`_inspect_scans`).

    The scored scans are checked as a batch against the calibration (:mod:`inspection.batch_check`, at most
    ``max_defective_share`` of them defective; None: its default): when they do not look like the calibration's good
    scans (another sensor, other units) the summary says so (``summary['batch_check']``, ``summary['warnings']``)
    and a scan above the threshold but within the batch's shift is told 'uncertain', not 'defective'.

    ``align``: every scan is registered onto the good training scans before it is scored. It is a setting of the
    calibration (``calibrate --align``), which registers the calibration scans the same way: an uncalibrated model
    is calibrated with it (without it: ``align='auto'``, registered when the training scans' poses spread); a model
    calibrated with it aligns whether or not ``align`` is given; asking for it of a model calibrated without it is an
    InspectionError (its threshold was drawn from scans scored unmoved).

    Returns
    -------
    summary : dict
    """
    from .html_report import write_html_report
    from .model_io import load_model
    from .report import format_table

    if maps not in ("flagged", "all", "none"):
        raise InspectionError(f"--maps must be flagged, all or none, got {maps!r}")
    if not isinstance(jobs, int) or jobs < 1:
        raise InspectionError(f"--jobs must be a whole number >= 1, got {jobs!r}")
    handle = load_model(model)
    insp = _calibrated_inspector(handle, data, alpha, progress, echo, True if align else "auto")
    aligned = calibrated_aligned(insp)
    if align and not aligned:
        raise InspectionError(f"{handle.path}: --align, but the model was calibrated without it: its threshold was "
                              f"drawn from scans scored where they lay, not registered ones; calibrate it again with "
                              f"`python -m inspection calibrate --model {handle.path} --data TRAINING_COLLECTION "
                              f"--align` (scoring then registers every scan by itself)")
    scans, info = load_scans(data, handle.frame, split=split, model_fingerprint=handle.fingerprint, errors="collect",
                             reading=getattr(insp, "reading_", None))  # files read as the model's were (issue 47)
    skipped = skipped_files_line(data)
    if skipped:
        echo(skipped)
    if not scans:  # nothing to score: one line, the first scan's reason when there was one
        raise InspectionError(info["failed"][0][1] if info["failed"] else
                              f"{data}: no scans" + (f" in split {split!r}" if split else ""))
    out = prepare_out(out, overwrite=overwrite)
    calibration = insp.calibration() if handle.calibration is None else handle.calibration
    spec = (handle.path, calibration, alpha)  # what a worker process builds its inspector from
    results = _inspect_scans(insp, scans, maps, out / "maps", progress, uncertain, jobs, spec)
    batch = check_run(insp, scans, results["rows"], DEFAULT_MAX_DEFECTIVE_SHARE if max_defective_share is None
                      else max_defective_share, uncertain)  # before the counts: it can retell verdicts
    results["rows"] += [_error_row(name, reason) for name, reason in info["failed"]]
    summary = summarize_run(handle, insp, data, split, aligned, results)
    summary["batch_check"] = batch
    summary["warnings"] = run_warnings(insp, batch)
    write_results(out, insp, results, summary)
    write_html_report(out / "report.html", results["rows"], summary, results["views"])  # the page of it all
    echo(format_table(results["rows"], summary))
    for line in summary["warnings"]:
        echo(f"warning: {line}")
    echo(f"results in {out}/: report.html, scores.csv, summary.json, roc.png, scores.png"
         + (f", maps/ ({results['maps']} coloured PLY + legend.png)" if results["maps"] else ""))
    return summary


def run_warnings(insp, batch):
    """What a run's user must read before its verdicts (summary.json's ``warnings``, the report page, the terminal):
    the batch check's message when it fired (per part), and that the threshold's level rests on views rendered from
    templates only."""
    lines = []
    checks = {None: batch} if batch is None or "fired" in batch else batch
    for part, check in checks.items():
        if check and check.get("fired"):
            lines.append((f"part {part}: " if part else "") + check["message"])
    if any(getattr(one, "level_rendered_", False) for one in (insp.parts_ or {"": insp}).values()):
        from .estimator import LEVEL_RENDERED_NOTE

        lines.append(LEVEL_RENDERED_NOTE)
    return lines


def calibrated_aligned(insp):
    """Whether the calibration of ``insp`` (of any of its part types) registers every scan before scoring it."""
    return any(one.settings_.align is True for one in (insp.parts_ or {"": insp}).values())


def _calibrated_inspector(handle, data, alpha, progress, echo, align="auto"):
    """The Inspector of ``handle`` with its stored calibration (``alpha`` None: the calibration's), calibrating
    first (with ``align``) when the model has none (:func:`_calibrate_for_scoring`)."""
    from .estimator import Inspector

    if handle.calibration is None:
        return _calibrate_for_scoring(handle, data, alpha, progress, echo, align)
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


def _inspect_scans(insp, scans, maps, maps_dir, progress, uncertain=True, jobs=1, worker_spec=None):
    """Inspect every scan (registered first when the calibration aligns) and write the anomaly maps ``maps`` asks for. A scan that
    cannot be scored (a ValueError naming it) gets an ``'error'`` row and the others go on.

    With ``jobs`` > 1 the scans are scored by that many processes: this one and ``jobs - 1`` workers (a 'spawn'
    context, one torch thread each), each of which builds its inspector once from ``worker_spec`` = (model path,
    calibration, alpha) (:func:`_inspect_in_workers`). A scan's scoring is deterministic (its projection is seeded), so the rows
    are those of one process, in the input order whatever the order the workers finish in.

    Returns a dict: ``rows`` (one per scan, the CSV columns), ``point_labels``, ``point_maps`` (the anomaly maps'
    values, :func:`inspection.maps.map_values`) and ``ray_maps``
    (per scan with ground-truth point labels), ``seconds`` (per scored scan), ``maps`` (maps written) and ``views``
    (their 3D views for report.html)."""
    from tqdm import tqdm

    results = {"rows": [], "point_labels": [], "point_maps": [], "ray_maps": [], "seconds": [], "maps": 0,
               "views": []}  # views: report.html's 3D views (inspection.html_report.scan_view), one per map
    jobs = min(int(jobs), len(scans))
    if jobs <= 1:
        outs = (_inspect_one(insp, scan, i, maps, maps_dir, uncertain)
                for i, scan in enumerate(tqdm(scans, desc="inspect", unit="scan", disable=not progress)))
    else:
        outs = _inspect_in_workers(worker_spec, scans, maps, maps_dir, progress, uncertain, jobs, insp)
    for one in outs:
        results["rows"].append(one["row"])
        if "seconds" not in one:  # an error row
            continue
        results["seconds"].append(one["seconds"])
        if "point_labels" in one:
            results["point_labels"].append(one["point_labels"])
            results["point_maps"].append(one["point_map"])
            if one["ray_map"] is not None:
                results["ray_maps"].append(one["ray_map"])
        if "view" in one:
            results["maps"] += 1
            results["views"].append(one["view"])
    return results


def _first_line(exc):
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


def _inspect_one(insp, scan, i, maps, maps_dir, uncertain=True):
    """Inspect one scan (the ``i``-th of the run: names a scan without a name, seeds its map's subsample) and write
    its map when ``maps`` asks for one. Returns a dict: ``row``; for a scored scan also ``seconds``, ``point_labels``,
    ``point_map`` and ``ray_map`` (scans with ground-truth point labels) and ``view`` (with a map)."""
    from .html_report import scan_view
    from .maps import map_values

    t0 = time.perf_counter()
    try:
        one = insp.for_scan(scan)  # the scan's part's inspector (a model of several part types), else insp
        res = one.inspect(scan, i)
    except ValueError as exc:
        return {"row": _error_row(scan, _first_line(exc))}
    out = {"seconds": time.perf_counter() - t0}
    rays = one.settings_.rays
    flagged = bool(one.predict_from_scores([res.score])[0] == -1)
    verdict = str(one.verdicts_from_scores([res.score], uncertain=uncertain)[0])
    row = {"name": scan.name, "split": scan.split, "label": scan.label, "defect": scan.defect,
           "score": res.score, "p_value": float(one.p_values_from_scores([res.score])[0]), "verdict": verdict,
           "reason": one.size_note(scan), "flagged": flagged,
           "why": one.reasons_from_scores([res.score], [scan], uncertain=uncertain)[0]}
    if rays:
        through = res.rays.through_observed
        row.update(score_points=res.components["points"], score_rays=res.components["rays"],
                   ray_nats=res.components.get("ray_nats"),
                   rays_through=float(np.mean(through)) if through is not None and len(through) else 0.0)
    out["row"] = row
    mapped = maps == "all" or (maps == "flagged" and verdict != "good")
    if scan.point_labels is not None or mapped:
        values, ray_values = map_values(one.settings_, scan, res)
    if scan.point_labels is not None:  # the point metrics are those of the map a user sees
        out.update(point_labels=scan.point_labels, point_map=values, ray_map=ray_values)
    if mapped:
        write_scan_maps(scan, values, ray_values, maps_dir)
        out["view"] = scan_view(scan.name, scan.points, values, ray_values, seed=i)  # report.html's 3D view
    return out


_WORKER = {}  # a worker process's inspector, built once by _start_worker


def _start_worker(spec):
    """A worker process's initializer: one thread (torch, BLAS), Ctrl-C left to the parent, the inspector built once
    from ``spec`` = pickle bytes of (model path, calibration, alpha)."""
    import pickle
    import signal

    import torch

    from .estimator import Inspector
    from .model_io import load_model

    from threadpoolctl import threadpool_limits  # scikit-learn's dependency

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops the pool; no traceback per worker
    torch.set_num_threads(1)  # N processes, a core each: no thread oversubscription, in torch or in BLAS
    threadpool_limits(1)
    path, calibration, alpha = pickle.loads(spec)
    handle = load_model(path)
    _WORKER["insp"] = Inspector.from_calibration(handle.model, calibration, alpha)


def _worker_inspect(scan, i, maps, maps_dir, uncertain):
    return _inspect_one(_WORKER["insp"], scan, i, maps, maps_dir, uncertain)


def _inspect_in_workers(spec, scans, maps, maps_dir, progress, uncertain, jobs, insp):
    """:func:`_inspect_one` of every scan in ``jobs`` processes; returns their outputs in the input order.

    The parent, with its own inspector ``insp``, is one of the ``jobs``: it starts ``jobs - 1`` workers and scores
    scans from the end of the list, on one thread, while the workers start (a worker spends seconds loading torch,
    the model and the calibration) and take scans from the front; each scan is scored once, by whoever takes it
    first (a scan already handed to a worker cannot be taken back)."""
    import multiprocessing
    import pickle
    from concurrent.futures import ProcessPoolExecutor

    import torch
    from tqdm import tqdm

    from threadpoolctl import threadpool_limits  # scikit-learn's dependency

    outs = [None] * len(scans)
    # the spec goes as plain pickle bytes: multiprocessing's own pickler would move the calibration's torch tensors
    # into shared memory, under the numpy arrays of this process's inspector that view them (which then read freed
    # memory: this process scores scans too)
    pool = ProcessPoolExecutor(jobs - 1, mp_context=multiprocessing.get_context("spawn"), initializer=_start_worker,
                               initargs=(pickle.dumps(spec),))
    bar = tqdm(total=len(scans), desc=f"inspect ({jobs} processes)", unit="scan", disable=not progress)
    try:
        futures = [pool.submit(_worker_inspect, scan, i, maps, maps_dir, uncertain) for i, scan in enumerate(scans)]
        for fut in futures:
            fut.add_done_callback(lambda f: None if f.cancelled() else bar.update())
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # a core of its own, as each worker has (torch, and BLAS below)
        try:
            with threadpool_limits(1):
                for i in reversed(range(len(scans))):
                    if not futures[i].cancel():  # the workers have reached this scan: the rest is theirs
                        break
                    outs[i] = _inspect_one(insp, scans[i], i, maps, maps_dir, uncertain)
                    bar.update()
        finally:
            torch.set_num_threads(threads)
        for i, fut in enumerate(futures):
            if outs[i] is None:
                outs[i] = fut.result()
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    finally:
        bar.close()
    pool.shutdown()
    return outs
