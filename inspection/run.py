"""Scoring a batch of scans into a results folder (``python -m inspection score``): each scan through the per-scan
job of :mod:`inspection.job` (in this process or in several), the batch checked against the calibration, the results
written (:mod:`inspection.results`, the report page).

Calibrating a model file, its calibrated inspector and one scan's row are :mod:`inspection.job`'s; reading files is
:mod:`inspection.loading`'s, the decisions are :class:`inspection.Inspector`'s; a user's mistake is an
:class:`inspection.errors.InspectionError`.
"""
from .batch_check import DEFAULT_MAX_DEFECTIVE_SHARE, check_run
from .errors import InspectionError
from .job import calibrated_aligned, calibrated_inspector, check_align, error_row, inspect_scan, skipped_files_line
from .loading import load_scans
from .results import prepare_out, summarize_run, write_results


def score(model, data, out, split="test", alpha=None, maps="flagged", align=False, progress=True, overwrite=False,
          echo=print, uncertain=True, jobs=1, max_defective_share=None, tolerance=None, features=None):
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

    ``align``: every scan is registered before it is scored (:func:`inspection.job.check_align`). It is a setting of
    the calibration (``calibrate --align``), which registers the calibration scans the same way: an uncalibrated
    model is calibrated with it (without it: ``align='auto'``, registered when the training scans' poses spread); a
    model calibrated with it aligns whether or not ``align`` is given; a model that registers every scan by itself
    onto its common frame (trained in one common pose, or a family's size) accepts it, and one line says it is not
    needed; asking for it of a model whose calibration registers nothing is an InspectionError (its threshold was
    drawn from scans scored unmoved).

    Returns
    -------
    summary : dict
    """
    from .html_report import write_html_report
    from .model_io import load_model_handle
    from .report import format_table

    if maps not in ("flagged", "all", "none"):
        raise InspectionError(f"--maps must be flagged, all or none, got {maps!r}")
    if not isinstance(jobs, int) or jobs < 1:
        raise InspectionError(f"--jobs must be a whole number >= 1, got {jobs!r}")
    if isinstance(tolerance, str):
        from .tolerance import Tolerance

        try:
            tolerance = Tolerance.parse(tolerance)
        except ValueError as exc:
            raise InspectionError(str(exc)) from None
    if features is not None and not isinstance(features, dict):
        from .regions import read_features

        try:
            features = read_features(features)
        except ValueError as exc:
            raise InspectionError(str(exc)) from None
    handle = load_model_handle(model)
    insp = calibrated_inspector(handle, data, alpha, progress, echo, True if align else "auto")
    aligned = calibrated_aligned(insp)
    note = check_align(insp, handle.path) if align else ""  # refused where nothing registers the scans
    if note:
        echo(note)
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
    results = _inspect_scans(insp, scans, maps, out / "maps", progress, uncertain, jobs, spec, (tolerance, features))
    batch = check_run(insp, scans, results["rows"], DEFAULT_MAX_DEFECTIVE_SHARE if max_defective_share is None
                      else max_defective_share, uncertain)  # before the counts: it can retell verdicts
    results["rows"] += [error_row(name, reason) for name, reason in info["failed"]]
    summary = summarize_run(handle, insp, data, split, aligned, results)
    summary["batch_check"] = batch
    summary["warnings"] = run_warnings(insp, batch)
    write_results(out, insp, results, summary)
    write_html_report(out / "report.html", results["rows"], summary, results["views"],
                      defects=results["defects"])  # the page of it all
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
        from .verdicts import LEVEL_RENDERED_NOTE

        lines.append(LEVEL_RENDERED_NOTE)
    return lines


def _inspect_scans(insp, scans, maps, maps_dir, progress, uncertain=True, jobs=1, worker_spec=None,
                   regions=(None, None)):
    """Inspect every scan (registered first when the calibration aligns) and write the anomaly maps ``maps`` asks for. A scan that
    cannot be scored (a ValueError naming it) gets an ``'error'`` row and the others go on.

    With ``jobs`` > 1 the scans are scored by that many processes: this one and ``jobs - 1`` workers (a 'spawn'
    context, one torch thread each), each of which builds its inspector once from ``worker_spec`` = (model path,
    calibration, alpha) (:func:`_inspect_in_workers`). A scan's scoring is deterministic (its projection is seeded), so the rows
    are those of one process, in the input order whatever the order the workers finish in.

    ``regions``: (tolerance, features) for :func:`inspection.job.inspect_scan`.

    Returns a dict: ``rows`` (one per scan, the CSV columns), ``point_labels``, ``point_maps`` (the anomaly maps'
    values, :func:`inspection.maps.map_values`) and ``ray_maps``
    (per scan with ground-truth point labels), ``seconds`` (per scored scan), ``maps`` (maps written) and ``views``
    (their 3D views for report.html)."""
    from tqdm import tqdm

    results = {"rows": [], "point_labels": [], "point_maps": [], "ray_maps": [], "seconds": [], "maps": 0,
               "views": [], "defects": [], "region_ids": []}  # views: report.html's 3D views (inspection.html_report.scan_view), one per map
    jobs = min(int(jobs), len(scans))
    if jobs <= 1:
        outs = (inspect_scan(insp, scan, i, maps, maps_dir, uncertain, *regions)
                for i, scan in enumerate(tqdm(scans, desc="inspect", unit="scan", disable=not progress)))
    else:
        outs = _inspect_in_workers(worker_spec, scans, maps, maps_dir, progress, uncertain, jobs, insp, regions)
    for one in outs:
        results["rows"].append(one["row"])
        if "seconds" not in one:  # an error row
            continue
        results["seconds"].append(one["seconds"])
        results["defects"] += one.get("defects", [])
        if "point_labels" in one:
            results["region_ids"].append(one.get("region_ids"))
            results["point_labels"].append(one["point_labels"])
            results["point_maps"].append(one["point_map"])
            if one["ray_map"] is not None:
                results["ray_maps"].append(one["ray_map"])
        if "view" in one:
            results["maps"] += 1
            results["views"].append(one["view"])
    return results


_WORKER = {}  # a worker process's inspector, built once by _start_worker


def _start_worker(spec):
    """A worker process's initializer: one thread (torch, BLAS), Ctrl-C left to the parent, the inspector built once
    from ``spec`` = pickle bytes of (model path, calibration, alpha)."""
    import pickle
    import signal

    import torch

    from .estimator import Inspector
    from .model_io import load_model_handle

    from threadpoolctl import threadpool_limits  # scikit-learn's dependency

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops the pool; no traceback per worker
    torch.set_num_threads(1)  # N processes, a core each: no thread oversubscription, in torch or in BLAS
    threadpool_limits(1)
    path, calibration, alpha = pickle.loads(spec)
    handle = load_model_handle(path)
    _WORKER["insp"] = Inspector.from_calibration(handle.model, calibration, alpha)


def _worker_inspect(scan, i, maps, maps_dir, uncertain, regions=(None, None)):
    return inspect_scan(_WORKER["insp"], scan, i, maps, maps_dir, uncertain, *regions)


def _inspect_in_workers(spec, scans, maps, maps_dir, progress, uncertain, jobs, insp, regions=(None, None)):
    """:func:`inspection.job.inspect_scan` of every scan in ``jobs`` processes; returns their outputs in the input
    order.

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
        futures = [pool.submit(_worker_inspect, scan, i, maps, maps_dir, uncertain, regions)
                   for i, scan in enumerate(scans)]
        for fut in futures:
            fut.add_done_callback(lambda f: None if f.cancelled() else bar.update())
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # a core of its own, as each worker has (torch, and BLAS below)
        try:
            with threadpool_limits(1):
                for i in reversed(range(len(scans))):
                    if not futures[i].cancel():  # the workers have reached this scan: the rest is theirs
                        break
                    outs[i] = inspect_scan(insp, scans[i], i, maps, maps_dir, uncertain, *regions)
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
