"""The suites' renderers of docs/results.md's tables (:mod:`benchmarks.results_doc`): one function per suite,
``function(figures, record) -> markdown lines``, registered in :data:`RENDERERS` by :func:`renderer`; a suite without
one is rendered by :func:`benchmarks.results_doc.generic`."""
import math
import shlex

from benchmarks.table import defect_kinds, listed, markdown_cell, markdown_table, of_text, pivot, rate_text

RENDERERS = {}


def renderer(suite):
    """Register ``function(figures, record) -> markdown lines`` as ``suite``'s renderer."""
    def register(function):
        RENDERERS[suite] = function
        return function

    return register


def _verdict_row(part, method, one):
    """A row of :func:`_verdict_lines` from :func:`benchmarks.inspect_api.summary_figures`-like figures."""
    flagged, threshold = one.get("flagged") or {}, one.get("threshold") or {}
    n_good = flagged.get("n_good")
    good = flagged.get("good")
    return {"part": part, "method": method, "auroc": one.get("auroc") or {}, "point_auroc": one.get("point_auroc"),
            "defective": flagged.get("defective"),
            "good_text": of_text(round(good * n_good), n_good) if good is not None and n_good else "-",
            "oracle": one.get("oracle"), "far": rate_text(threshold.get("predicted_far"), threshold.get("far_interval")),
            "sec": one.get("seconds_per_scan")}


def _verdict_lines(rows):
    kinds = defect_kinds(r["auroc"] for r in rows)
    return markdown_table(rows, [("part", "part", ""), ("method", "method", ""),
                                 (lambda r: r["auroc"].get("overall"), "AUROC", ".3f"),
                                 *[((lambda r, k=k: r["auroc"].get(k)), k, ".3f") for k in kinds],
                                 ("point_auroc", "point AUROC", ".3f"), ("defective", "defective flagged", ".3f"),
                                 ("good_text", "good flagged", ""), ("oracle", "oracle", ".3f"),
                                 ("far", "predicted false alarms (90 % interval)", ""), ("sec", "s/scan", ".2f")])


@renderer("inspection")
def inspection_lines(figures, record=None):
    """Per part: the toolkit's rows (with and without fold models, each point score alone) and the baseline's; in the
    template regime also object and point AUROC per type; with ``--multi-part`` the one model's rows."""
    rows, per_type = [], []
    for part, one in figures["parts"].items():
        for key, method in (("toolkit_nofolds", None), ("toolkit", None), ("toolkit_summary_nofolds", None),
                            ("toolkit_summary", None)):
            if one.get(key):
                rows.append(_verdict_row(part, one[key].get("method") or method or key, one[key]))
        for spec, alone in (one.get("point_scores") or {}).items():
            rows.append(_verdict_row(part, f"{spec} alone", alone))
        nn = one.get("nn") or {}
        if "flagged" in nn:
            rows.append(_verdict_row(part, nn.get("method") or "nearest-neighbour", nn))
        if "toolkit_summary" in one or "toolkit_summary_nofolds" in one:
            for name in ("toolkit", "nn"):
                if isinstance(one.get(name), dict) and "point_auroc" in one[name]:
                    per_type += [{"part": part, "method": name, "defect": k, "object": v,
                                  "point": one[name]["point_auroc"].get(k)} for k, v in one[name]["auroc"].items()]
    lines = _verdict_lines(rows)
    if per_type:
        lines += ["", "Object and point AUROC per defect type (the template regime):", ""]
        lines += markdown_table(per_type, [("part", "part", ""), ("method", "method", ""), ("defect", "defect", ""),
                                           ("object", "object AUROC", ".3f"), ("point", "point AUROC", ".3f")])
    multi = figures.get("multi_part")
    if multi:
        rows = [_verdict_row(part, f"{kind.replace('_', '-')} model", two[kind])
                for part, two in multi["parts"].items() for kind in ("multi_part", "single_part")]
        lines += ["", f"One model on all the parts (trained in {markdown_cell(multi.get('train_seconds'), '.0f')} s):", ""]
        lines += _verdict_lines(rows)
    return lines


@renderer("verdicts")
def verdicts_lines(figures, record=None):
    """Per tree (lines) and seed (columns): AUROC / defective flagged / good flagged; then the issue's targets."""
    runs = figures["runs"]
    lines = ["AUROC / defective flagged / good flagged (of them told `defective`), per tree and seed:", ""]
    lines += pivot(runs, "tree", "seed", lambda r: f"{markdown_cell(r['auroc'], '.3f')} / {markdown_cell(r['defective'], '.3f')} / "
                   f"{r['good_text']}" + (f" ({r['rejected_text'].split(' of ')[0]})"
                                          if r.get("rejected_text", "-") != "-" else ""), first="tree")
    t = figures.get("targets") or {}
    if t:
        lines += ["", f"Over {len(runs)} runs: mean AUROC {_mean(runs, 'auroc', '.4f')}, mean share of defective scans "
                      f"flagged {_mean(runs, 'defective', '.3f')}; realised false-alarm rate {t['mean_far']:.4f} "
                      f"(target <= 2 alpha = {2 * t['alpha']:.3f}: {'met' if t['far_ok'] else 'NOT met'}); "
                  + listed("runs above 1 of 16 good scans", t["over_one_in_16"])
                  + f" (a threshold at exactly alpha: {t['expected_over']:.1f} on average, none with probability "
                    f"{t['p_none_over']:.2f}); "
                  + listed("runs short of the detection target where a threshold at exactly alpha meets it",
                            t["detection_misses"]) + "; "
                  + listed("where it misses it too", t["beyond_alpha"]) + "."]
    return lines


def _mean(rows, key, fmt):
    values = [r[key] for r in rows if isinstance(r.get(key), (int, float)) and not math.isnan(r[key])]
    return format(sum(values) / len(values), fmt) if values else "-"


@renderer("rays")
def rays_lines(figures, record=None):
    """Per tree (lines) and seed (columns): the default's AUROC / the point score alone's / defective flagged / good
    flagged, then per tree missing material and the good scans' largest ray score; then the issue's targets."""
    runs = figures["runs"]

    def good(r):
        return r.get("good_text") or of_text(round(r["good"] * r["n_good"]), r["n_good"])

    lines = ["Default AUROC / points alone / defective flagged / good flagged; the good scans' largest ray score "
             "(nats) and missing material's AUROC, per tree and seed:", ""]
    lines += pivot(runs, "tree", "seed", lambda r: f"{markdown_cell(r['auroc'], '.3f')} / {markdown_cell(r['points_alone'], '.3f')} / "
                   f"{markdown_cell(r['defective'], '.3f')} / {good(r)}; {markdown_cell(r.get('good_rays_max'), '.1f')}, "
                   f"{markdown_cell(r.get('missing'), '.3f')}", first="tree")
    t = figures.get("targets") or {}
    if t:
        lines += ["", f"Targets over {len(runs)} runs, misses: "
                  + "; ".join(listed(label, t.get(key, [])) for key, label in (
                      ("ranking", "default below the points alone"),
                      ("detection", "detection short of the points-alone oracle"),
                      ("calibration", "of them the threshold's calibration"),
                      ("false_alarms", "above 1 of 16 good scans"),
                      ("missing", "missing material below the target on thin walls"))) + "."]
    return lines


@renderer("sensors")
def sensors_lines(figures, record=None):
    """One line per sensor: over its runs mean AUROC and defective flagged, good scans flagged and told 'defective',
    mean gap (held-back) and shift against 'same', warnings fired; then each run (a column per tree and seed): AUROC /
    defective flagged / good flagged (told defective), a fired warning marked; the issue's targets. '<sensor>+site'
    runs: the level set by that sensor's own good scans (``--site-scans``, 8 by default)."""
    runs = [dict(r, _column=f"{r['tree']} s{r['seed']}") for r in figures["runs"]]
    columns = list(dict.fromkeys(r["_column"] for r in runs))
    cells = {(r["sensor"], r["_column"]): (
        f"{markdown_cell(r['auroc'], '.3f')} / {markdown_cell(r['defective'], '.3f')} / {of_text(r.get('good_flagged'), r.get('n_good'))}"
        f" ({r.get('good_told_defective', '-')})" + (" warning" if r.get("warning") else "")) for r in runs}
    summary = figures.get("per_sensor") or [{"sensor": s} for s in dict.fromkeys(r["sensor"] for r in runs)]
    table = [{**one, **{c: cells.get((one["sensor"], c), "") for c in columns}} for one in summary]
    lines = ["Per sensor over its runs, then each run: AUROC / defective flagged / good flagged (told defective); "
             "alpha, the predicted false-alarm rate and the gaps of each run: the record.", ""]
    lines += markdown_table(table, [
        ("sensor", "sensor", ""), ("auroc", "mean AUROC", ".3f"), ("defective", "mean defective flagged", ".3f"),
        ("good_text", "good flagged", ""), ("told_text", "told defective", ""), ("gap", "mean gap held-back", "+.3f"),
        ("shift", "mean shift vs same", "+.3f"), ("fired", "warnings", ""), *[(c, c, "") for c in columns]])
    site = [r for r in runs if str(r.get("sensor", "")).endswith("+site")]
    if site:
        command = shlex.split((record or {}).get("command", ""))
        n = command[command.index("--site-scans") + 1] if "--site-scans" in command[:-1] else "8"
        lines += ["", f"'SENSOR+site': the same test scans scored by a copy of the calibrated model whose level "
                      f"{n} good scans of that sensor set (`calibrate --data FOLDER`)."]
    t = figures.get("targets") or {}
    if t:
        base = [r for r in runs if not str(r.get("sensor", "")).endswith("+site")]
        lines += ["", f"Targets over {len(base)} template-calibrated runs, misses: "
                  + "; ".join(listed(label, t.get(key, [])) for key, label in (
                      ("false_alarms", "above 1 of 16 good scans (without the warning excusing them)"),
                      ("detection", "defective flagged short where AUROC is high and no warning"),
                      ("site", "'+site' runs above 1 of 16 good or short of detection"))) + "."]
    return lines


@renderer("ablation")
def ablation_lines(figures, record=None):
    """``--trees``: per tree and seed (lines) and method (columns) object AUROC (the maps' point AUROC), then issue
    28's targets; else per part and setting the verdicts table's row."""
    if "rows" in figures:
        rows = [dict(r, _line=f"{r['tree']} s{r['seed']}") for r in figures["rows"]]
        lines = ["Object AUROC (the maps' point AUROC) per tree, seed and method:", ""]
        lines += pivot(rows, "_line", "method", lambda r: f"{markdown_cell(r['auroc'].get('overall'), '.3f')}"
                       + (f" ({markdown_cell(r['point_auroc'], '.3f')})" if r.get("point_auroc") is not None else ""),
                       first="tree")
        misses = (figures.get("targets") or {}).get("misses")
        if misses is not None:
            lines += ["", listed("Issue 28's targets missed", misses) + "."]
        return lines
    return _verdict_lines([_verdict_row(part, spec, one) for part, settings in figures["parts"].items()
                           for spec, one in settings.items()])


@renderer("real")
def real_lines(figures, record=None):
    """Object AUROC overall and per type of the baseline, the defaults and each term alone; flagged; seconds."""
    rows = [{"method": "nearest-neighbour", **figures["nn"]}, {"method": "toolkit (defaults)", **figures["toolkit"]}]
    rows += [{"method": f"toolkit, {name}", **one} for name, one in (figures.get("terms") or {}).items()]
    kinds = defect_kinds(rows)
    lines = markdown_table(rows, [("method", "method", ""), ("overall", "AUROC", ".3f"),
                                  *[(k, k, ".3f") for k in kinds if k != "method"]])
    f = figures.get("flagged") or {}
    lines += ["", f"Flagged at the calibrated default: defective {markdown_cell(f.get('defective'), '.3f')}, good "
                  f"{markdown_cell(f.get('good'), '.3f')}; {markdown_cell(figures.get('seconds_per_scan'), '.2f')} s a scan "
                  f"(baseline {markdown_cell(figures.get('nn_seconds_per_scan'), '.3f')}); training "
                  f"{markdown_cell(figures.get('train_seconds'), '.0f')} s."]
    return lines


@renderer("maps")
def maps_lines(figures, record=None):
    """Point AUROC of the anomaly map per run at each patch size, and per defect type at k = 1 and the default."""
    sizes, default = figures["neighbours"], figures["default"]
    lines = markdown_table(figures["runs"], [("run", "run", ""), ("points", "points", "d"),
                                             ("defect", "defect points", ""),
                                             *[(f"k{k}", f"k={k}" + (" (default)" if k == default else ""), ".3f")
                                               for k in sizes], ("patch", f"k={default}, no rays", ".3f")])
    per = [p for p in figures.get("per_type") or [] if p.get("patch") == default]
    if per:
        kinds = sorted({k for p in per for k in p} - {"run", "patch", "overall"})
        lines += ["", f"Per defect type at k = {default} (k = 1: the record):", ""]
        lines += markdown_table(per, [("run", "run", ""), *[(k, k, ".3f") for k in kinds]])
    return lines


@renderer("latency")
def latency_lines(figures, record=None):
    """Seconds per scan and per stage at each scan size, the baseline's, peak memory; the throughput of `score`."""
    sizes = figures["sizes"]
    stages = list(dict.fromkeys(k for one in sizes.values() for k in one.get("stages", {})))
    rows = [{"points": f"{one['points']:,.0f}", "scored": markdown_cell(one.get("points_scored"), ",.0f"),
             "as": one.get("scored_as", "every point"),
             "scans": one["scans"], "s": one["seconds_per_scan"],
             "max": one.get("seconds_max"), **one.get("stages", {}), "other": one.get("other"),
             "map": one.get("map_seconds"), "nn": one.get("nn_seconds_per_scan"), "mb": one.get("peak_rss_mb")}
            for one in sizes.values()]
    lines = [f"{figures.get('part')}, calibrated in {markdown_cell(figures.get('calibrate_seconds'), '.1f')} s, "
             f"{figures.get('threads')} torch thread(s); seconds per scan:", ""]
    lines += markdown_table(rows, [("points", "points", ""), ("scored", "points scored", ""), ("as", "scored as", ""),
                                   ("scans", "scans", "d"),
                                   ("s", "s/scan", ".3f"), ("max", "max", ".3f"), *[(k, k, ".3f") for k in stages],
                                   ("other", "other", ".3f"), ("map", "map of every point s", ".3f"),
                                   ("nn", "nearest-neighbour s/scan", ".4f"), ("mb", "peak MB", ".0f")])
    throughput = figures.get("throughput")
    if throughput:
        lines += ["", f"Throughput, `score --maps none` over {throughput.get('scans')} test scans "
                      f"(the same scores with every `--jobs`: {markdown_cell(throughput.get('same_scores'))}):", ""]
        lines += markdown_table([{"jobs": n, **one} for n, one in throughput["jobs"].items()],
                                [("jobs", "--jobs", ""), ("seconds", "seconds", ".1f"),
                                 ("scans_per_second", "scans/s", ".2f")])
    return lines


@renderer("training")
def training_lines(figures, record=None):
    """Per part and epoch budget: a training's wall time and its stages (seconds), its final loss."""
    stages = ("family", "pose", "read", "targets", "epochs")
    rows = [{"part": one["part"], "budget": f"{one['epochs']} ({one.get('epochs_run', '-')})",
             "scans": one.get("scans"), "total": one["seconds"], **one.get("stages", {}), "other": one.get("other"),
             "loss": one.get("loss")} for one in figures.get("runs", [])]
    lines = [f"Seed {figures.get('seed')}; seconds per stage of one training, one torch thread:", ""]
    return lines + markdown_table(rows, [("part", "part", ""), ("budget", "epochs (run)", ""),
                                         ("scans", "scans", "d"), ("total", "total s", ".1f"),
                                         *[(k, k, ".1f") for k in stages], ("other", "other", ".1f"),
                                         ("loss", "final loss", ".4g")])


@renderer("fewscans")
def fewscans_lines(figures, record=None):
    """Per part and number of training scans, over the seeds: AUROC, the baseline's, defective scans flagged and told
    uncertain, good scans told defective / uncertain, the defects on covered surface flagged, the unflagged defective
    scans told uncertain; with the closed loop, per strategy of 4 added good scans the same, over parts and seeds."""
    def summed(rows, key):
        return sum(r[key] for r in rows if r.get(key) is not None)

    def mean(rows, key):
        values = [r[key] for r in rows if isinstance(r.get(key), (int, float)) and not math.isnan(r[key])]
        return sum(values) / len(values) if values else None

    def grouped(rows, key):
        groups = {}
        for r in rows:
            groups.setdefault((r["part"], r[key]), []).append(r)
        return [{"part": part, "what": what, "seeds": len(g), "auroc": mean(g, "auroc"), "nn": mean(g, "nn_auroc"),
                 "flagged": mean(g, "flagged"),
                 "uncertain": of_text(summed(g, "uncertain"), summed(g, "n_defective")),
                 "good": f"{summed(g, 'good_defective')} / {summed(g, 'good_uncertain')} of {summed(g, 'n_good')}",
                 "covered": f"{mean(g, 'covered_flagged') or 0:.3f} of {summed(g, 'on_covered')}",
                 "missed": of_text(summed(g, "missed_uncertain"), summed(g, "missed"))}
                for (part, what), g in groups.items()]

    columns = [("part", "part", ""), ("what", "training scans", ""), ("seeds", "seeds", ""),
               ("auroc", "AUROC", ".3f"), ("nn", "nearest-neighbour", ".3f"), ("flagged", "defective flagged", ".3f"),
               ("uncertain", "defective told uncertain", ""), ("good", "good told defective / uncertain", ""),
               ("covered", "defects on covered surface flagged", ""), ("missed", "unflagged told uncertain", "")]
    lines = []
    if figures.get("runs"):
        lines += markdown_table(grouped(figures["runs"], "scans"), columns) + [""]
    if figures.get("loop"):  # over the parts and seeds (each part's rows: the record)
        overall = [dict(r, part="all", what=r["strategy"]) for r in figures["loop"]]
        lines += ["Closed loop, 4 good scans added to 8 and the model trained again (base: the 8 alone), over the "
                  "parts and seeds:", ""]
        lines += markdown_table(grouped(overall, "what"),
                                [(k, "added views" if k == "what" else h, f) for k, h, f in columns]) + [""]
    return lines[:-1] if lines else None


@renderer("defects")
def defects_lines(figures, record=None):
    """Per part, over its seeds: mean AU-PRO, defects found (IoU >= 0.3), type accuracy, median depth and area
    errors, false regions per good scan (looked for on every scan / shown), and per true type found and typed right."""
    runs = figures.get("runs") or []
    if not runs:
        return None

    def mean(rows, key):
        values = [r[key] for r in rows if isinstance(r.get(key), (int, float)) and not math.isnan(r[key])]
        return sum(values) / len(values) if values else None

    parts = {}
    for run in runs:
        parts.setdefault(run["part"], []).append(run)
    rows = []
    for part, group in parts.items():
        kinds = {}
        for run in group:
            for kind, counts in run["per_kind"].items():
                total = kinds.setdefault(kind, {"defects": 0, "found": 0, "typed": 0})
                for key in total:
                    total[key] += counts[key]
        rows.append({"part": part, "seeds": ", ".join(str(r["seed"]) for r in sorted(group, key=lambda r: r["seed"])),
                     **{k: mean(group, k) for k in ("au_pro", "found", "below", "typed", "depth_error",
                                                     "area_error", "false_per_good", "false_shown")},
                     "kinds": ", ".join(f"{k} {c['typed']}/{c['found']}/{c['defects']}" for k, c in sorted(kinds.items()))})
    columns = [("part", "part", ""), ("seeds", "seeds", ""), ("au_pro", "AU-PRO (0.3 FPR)", ".3f"),
               ("found", "found (IoU >= 0.3)", ".3f"), ("below", "of them below the level", ".3f"),
               ("typed", "type right", ".3f"),
               ("depth_error", "depth error (median)", ".3f"), ("area_error", "area error (median)", ".3f"),
               ("false_per_good", "false regions / good scan (above the level / shown)", ".3f"),
               ("false_shown", "", ".3f"),
               ("kinds", "per type: typed right / found / defects", "")]
    lines = markdown_table(rows, columns)
    lines[0] = lines[0].replace("| false regions / good scan (above the level / shown) |  |",
                                "| false regions / good scan, above the level | shown |")
    return lines
