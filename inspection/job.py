"""A model file's job, one scan at a time, shared by the command lines (``calibrate``, ``score``, ``watch``) and the
benchmarks: calibrate a model file on good scans, the calibrated inspector of a model file (an uncalibrated model
calibrating itself first, on its training collection's held-back scans), whether it registers the scans, one scan
inspected into its ``scores.csv`` row and anomaly map, the row of a scan that could not be scored.

A batch of scans into a results folder is :mod:`inspection.run`'s, a drop folder watched :mod:`inspection.watch`'s;
reading files is :mod:`inspection.loading`'s, the decisions are :class:`inspection.Inspector`'s; a user's mistake is
an :class:`inspection.errors.InspectionError`.
"""
import time
from pathlib import Path

import numpy as np

from .errors import InspectionError, about
from .loading import COLLECTION_SUFFIXES, load_scans, open_collection
from .results import write_scan_maps


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
    from .model_io import load_model_handle

    config = (config or InspectionConfig()).validated()
    handle = load_model_handle(model)
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

    insp = calibrated_inspector(handle, data, config.alpha, progress, echo)
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
    aligned += _member_note(insp)
    plain, stats = describe_decision(t.as_dict())  # the threshold in plain words first, the statistics after
    lines = [f"threshold {t.value:.4g} at alpha={t.alpha:g}: {plain}",
             f"calibrated on {info['n']} scans ({info['how']}): {what}", stats]
    if getattr(insp, "combination_", None) is not None:  # how much the rays count, as the good scans' rays say
        lines.append(insp.combination_.rays.describe())
    return lines + aligned


def _member_note(insp):
    """[] or, when the good scans' members differ in shape (:mod:`inspection.member_surface`), one note saying so and
    what the good points' term then compares."""
    spread = getattr(getattr(insp, "reference_", None), "member_spread", None)
    if spread is None or not spread.differs:
        return []
    return [f"note: the good scans differ in shape over {100 * spread.share:.0f} % of their surface, more than "
            f"partial views of one part do (members of a family): each scan's good points' term compares it with "
            f"the good surface carried to its own member"]


def _term_spread(insp):
    """'' or, for a point score that weighs its two terms (:func:`inspection.scores.fit_term_variances`), how much
    each spreads on the good calibration scans, the weight it gets being the inverse of its variance."""
    variances = insp.term_variances()
    if variances is None:
        return ""
    v_d, v_s = variances
    return (f" (its terms weighed by their spread on the good scans: the field's {v_d ** 0.5:.2f}, the good "
            f"points' {v_s ** 0.5:.2f} standard deviations)")


def calibrated_inspector(handle, data=None, alpha=None, progress=False, echo=None, align="auto"):
    """The :class:`inspection.Inspector` of a model file with its stored calibration; a model that is not calibrated
    yet calibrates itself first, when ``data`` is its training collection with held-back scans.

    Parameters
    ----------
    handle : inspection.model_io.ModelHandle
        The model file, as :func:`inspection.model_io.load_model_handle` reads it.
    data : str or Path, optional
        What is about to be scored. Only an uncalibrated model reads it: when it is the model's training collection
        (the fingerprint the model records) with held-back scans, the model is calibrated on those with the
        defaults (and ``align``; ``alpha`` too when given) and the calibration is stored in the model file, as
        :func:`calibrate` would; ``echo`` is told so, and told the calibration's lines (:func:`describe_calibration`).
    alpha : float, optional
        The false-alarm rate (None: the calibration's).
    progress : bool
        Progress bars while calibrating.
    echo : callable (str) -> None, optional
        Where the lines of a calibration made here go (None: nowhere).
    align : True, False or 'auto'
        The calibration's ``align`` when the model calibrates itself here (``score --align``: True); a calibrated
        model keeps its own.

    Returns
    -------
    Inspector
        Fitted: from the stored calibration (:meth:`Inspector.from_calibration`) or the one made here.

    Raises
    ------
    InspectionError
        An uncalibrated model and ``data`` not its training collection with held-back scans (naming the command
        that calibrates it), or a stored calibration that cannot be used (naming the file).
    """
    from .estimator import Inspector

    if handle.calibration is None:
        return _calibrate_for_scoring(handle, data, alpha, progress, echo or (lambda line: None), align)
    try:
        return Inspector.from_calibration(handle.model, handle.calibration, alpha, verbose=progress)
    except (KeyError, ValueError) as exc:
        raise InspectionError(f"{handle.path}: its calibration cannot be used ({exc}); calibrate it again with "
                              f"`python -m inspection calibrate`") from None


def _calibrate_for_scoring(handle, data, alpha, progress, echo, align="auto"):
    """An uncalibrated model scored on its own training collection: calibrate on the held-back good scans with the
    defaults (and ``align``; stored in the model file, as ``calibrate`` would) and say so; anything else is an
    InspectionError."""
    from .config import InspectionConfig

    data = None if data is None else Path(data)
    fingerprint = ""
    if data is not None and data.suffix.lower() in COLLECTION_SUFFIXES and data.is_file():
        with open_collection(data) as c:
            fingerprint = c.fingerprint()
    if not (handle.fingerprint and fingerprint == handle.fingerprint and handle.heldback_names):
        what = "no data was given" if data is None else f"{data} is not its training collection with held-back scans"
        raise InspectionError(f"{handle.path}: the model is not calibrated, and {what}; run `python -m inspection "
                              f"calibrate --model {handle.path} --data GOOD_SCANS` first")
    echo(f"{handle.path} is not calibrated: calibrating on its {len(handle.heldback_names)} held-back good scans "
         f"of {data} first (stored in the model file)")
    config = InspectionConfig(align=align, **({} if alpha is None else {"alpha": alpha}))
    insp, info = calibrate(handle.path, data, config, progress=progress)
    for line in describe_calibration(insp, info):
        echo(line)
    return insp


def calibrated_aligned(insp):
    """Whether the calibration of ``insp`` (of any of its part types) registers every scan before scoring it
    (``calibrate --align``, or ``align='auto'`` that found the training scans' poses spread)."""
    return any(one.settings_.align is True for one in (insp.parts_ or {"": insp}).values())


def common_frame(insp):
    """The model's own common frame, onto which every scan is registered before it is projected whatever the
    calibration's ``align`` (:meth:`autodecoder.latent.model.LatentModel.normalise`): ``'pose'`` (trained on scans
    moved into one common pose: parts placed by hand), ``'size'`` (a product family's common size) or None."""
    family = getattr(insp.model, "family", None)
    return None if family is None else family.kind


_REGISTERS_BY_ITSELF = {
    "pose": "it was trained on scans moved into one common pose, and registers every scan onto that pose before "
            "scoring it",
    "size": "it was trained on a family of sizes, and registers every scan onto the family's common size before "
            "scoring it"}


def check_align(insp, path):
    """What ``score --align`` (every scan registered before it is scored) says of the calibrated ``insp`` of the
    model file ``path``.

    Returns
    -------
    str
        '' when the calibration registers every scan (:func:`calibrated_aligned`); a one-line note when the model
        registers every scan by itself (:func:`common_frame`), which is what --align asks for.

    Raises
    ------
    InspectionError
        When nothing registers the scans: the threshold was drawn from scans scored where they lay (naming the
        command that calibrates the model with registration).
    """
    if calibrated_aligned(insp):
        return ""
    frame = common_frame(insp)
    if frame is not None:
        return f"note: --align is not needed for {path}: {_REGISTERS_BY_ITSELF[frame]}"
    raise InspectionError(f"{path}: --align, but the model was calibrated without it: its threshold was drawn from "
                          f"scans scored where they lay, not registered ones; calibrate it again with "
                          f"`python -m inspection calibrate --model {path} --data TRAINING_COLLECTION --align` "
                          f"(scoring then registers every scan by itself)")


def inspect_scan(insp, scan, i=0, maps="none", maps_dir=None, uncertain=True, tolerance=None, features=None):
    """One scan inspected by the calibrated ``insp`` (registered first as its calibration and its model say) into
    its ``scores.csv`` row, and its anomaly map written when ``maps`` asks for one.

    Parameters
    ----------
    insp : Inspector
        Fitted (:func:`calibrated_inspector`); of a model of several part types, the scan's part's is used.
    scan : datasets.Scan
    i : int
        The scan's place in its run: names a scan without a name, seeds its map's subsample (the same ``i``, the
        same row and map).
    maps : {'none', 'flagged', 'all'}
        Write the scan's coloured PLY into ``maps_dir`` never, when its verdict is not 'good', or always.
    maps_dir : Path, optional
        Where the maps go (needed unless ``maps`` is 'none').
    uncertain : bool
        The 'uncertain' verdict (False: good or defective only).
    tolerance : inspection.tolerance.Tolerance, optional
        Also judge the scan's defect regions against it (:func:`inspection.tolerance.judged`).
    features : dict of str -> (3,) array, optional
        Named places of the part (:func:`inspection.regions.read_features`): each region's nearest is its feature.

    Returns
    -------
    dict
        ``row``: the scores.csv columns (``name``, ``split``, ``label``, ``defect``, ``score``, ``p_value``,
        ``verdict``, ``reason``, ``flagged``, ``why``; with rays also ``score_points``, ``score_rays``, ``ray_nats``,
        ``rays_through``), or :func:`error_row`'s for a scan that cannot be scored (a ValueError: its first line is
        the reason), and nothing else then; the row also has ``regions`` (how many defect regions,
        :mod:`inspection.regions`; None when not looked for: a good verdict without maps 'all' or a tolerance),
        ``tolerance`` and ``decided_by`` (:func:`inspection.tolerance.judged`). For a scored scan also ``seconds``
        (the inspection's), ``defects`` (one ``defects.csv`` row per region), with
        ground-truth point labels ``point_labels``, ``point_map`` and ``ray_map`` (the map's values,
        :func:`inspection.maps.map_values`), and with a map written ``view`` (its 3D view for report.html).
    """
    from .html_report import scan_view
    from .maps import map_values
    from .regions import Units
    from .tolerance import judged

    if maps not in ("none", "flagged", "all") or (maps != "none" and maps_dir is None):
        raise ValueError(f"maps must be 'none', or 'flagged' or 'all' with a maps_dir, got {maps!r}")
    t0 = time.perf_counter()
    try:
        one = insp.for_scan(scan)  # the scan's part's inspector (a model of several part types), else insp
        res = one.inspect(scan, i)
    except ValueError as exc:
        return {"row": error_row(scan, _first_line(exc))}
    out = {"seconds": time.perf_counter() - t0}
    rays = one.settings_.rays
    flagged = bool(one.predict_from_scores([res.score])[0] == -1)
    (verdict,), (why,) = one.verdicts_from_results([res], [scan], uncertain=uncertain)
    row = {"name": scan.name, "split": scan.split, "label": scan.label, "defect": scan.defect,
           "score": res.score, "p_value": float(one.p_values_from_scores([res.score])[0]), "verdict": verdict,
           "reason": one.size_note(scan), "flagged": flagged, "why": why,
           "uncovered": None if res.coverage is None else res.coverage.uncovered_share,
           "beyond_family": None if res.family is None else res.family.share}
    if rays:
        through = res.rays.through_observed
        row.update(score_points=res.components["points"], score_rays=res.components["rays"],
                   ray_nats=res.components.get("ray_nats"),
                   rays_through=float(np.mean(through)) if through is not None and len(through) else 0.0)
    out["row"] = row
    regions, region_ids = [], None
    if verdict != "good" or maps == "all" or tolerance is not None:
        regions, region_ids = one.regions_of_result(scan, res, features, defective=verdict == "defective")
        row["regions"] = len(regions) if region_ids is not None else None
    row.update(judged(verdict, why, regions, tolerance))
    verdict = row["verdict"]
    out["defects"] = [{"name": scan.name, **r.row()} for r in regions]
    if scan.point_labels is not None:
        out["region_ids"] = region_ids
    if res.sample is not None:  # a scan denser than the training scans: scored at their density
        row.update(points_scored=len(res.sample.kept),
                   spacing=res.sample.spacing / Units.of(one.model).length_scale)
        region_ids = res.full(region_ids)
        if scan.point_labels is not None:
            out["region_ids"] = region_ids
    mapped = maps == "all" or (maps == "flagged" and verdict != "good")
    if scan.point_labels is not None or mapped:  # every point's: each scored point's carried to those nearest it
        values, ray_values = (res.full(v) for v in map_values(one.settings_, res.scored(scan), res))
    if scan.point_labels is not None:  # the point metrics are those of the map a user sees
        out.update(point_labels=scan.point_labels, point_map=values, ray_map=ray_values)
    if mapped:
        write_scan_maps(scan, values, ray_values, maps_dir,
                        None if res.coverage is None else res.full(res.coverage.covered), region_ids)
        out["view"] = scan_view(scan.name, scan.points, values, ray_values, seed=i,
                                regions=region_ids)  # report.html's 3D view
    return out


def error_row(scan_or_name, reason):
    """The scores.csv row of a scan that could not be read or scored: verdict ``'error'``, no score, ``reason``.

    Parameters
    ----------
    scan_or_name : datasets.Scan or str
        The scan (its name, split, label and defect go into the row) or only its name.
    reason : str
        One line: what went wrong, naming the file where there is one.

    Returns
    -------
    dict
        The row: ``name``, ``split``, ``label``, ``defect``, ``score`` (None), ``p_value`` (None), ``verdict``
        ('error'), ``reason``.
    """
    scan = None if isinstance(scan_or_name, (str, Path)) else scan_or_name  # a name has no split (str.split!)
    name = scan_or_name if scan is None else scan.name
    return {"name": str(name), "split": getattr(scan, "split", ""), "label": getattr(scan, "label", "unknown"),
            "defect": getattr(scan, "defect", ""), "score": None, "p_value": None, "verdict": "error",
            "reason": str(reason)}


def _first_line(exc):
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__
