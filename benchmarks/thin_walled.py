"""Thin-walled and open parts never seen: every defect type, with and without the sensor's rays, next to a
nearest-neighbour baseline, in one run per part.

Run by hand from the repository root (not a test):

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/thin_walled.py [--parts enclosure,cup,fandisk] [--figures]

Parts: ``datasets.parts.sheet_enclosure`` (a 1.5 mm sheet-metal cover, open at the bottom, with openings),
``datasets.parts.open_cup`` (a 1.5 mm cup on a hemispherical bottom, open at the top) and fandisk
(``../shared/meshes/fandisk.obj``, a solid, for comparison). For each part: ``datasets.synth.synthesise`` scans it
(32 good training scans of which 20 % are held back to calibrate, validation scans that calibrate too, good test
scans and test scans per defect type: dent, bump, missing, foreign; on the sheets a dent or bump moves the whole
sheet and a ``missing`` ball punches a hole through it, whose points seen through the hole count as defective), the
latent model is trained with the trainer's defaults (``inspection.training.train_model``), and every calibration and
test scan is projected once. Collections, models and projected latent codes are cached in ``--work``, so the scoring
side can be changed and rerun in seconds.

Printed per part, object AUROC per defect type and overall, and the false-alarm / detection rates at ``--alpha``:

* ``points``: the toolkit without sensor origins, the ``distance`` point score (what ``python -m inspection``
  picks) aggregated as ``Inspector`` does;
* ``rays``: the ray score alone (:mod:`inspection.ray_evidence`);
* ``points+rays (max)``: :class:`inspection.combine.Combination` with ``rule='max'`` (the rule before issue 18);
* ``points+rays (gated)``: :class:`inspection.combine.Combination` with rule ``'gated'`` (what
  ``Inspector(rays=True)`` computed before issue 18's ``'gated-log'``; the toolkit's defaults, surface band and
  ``gated-log`` included, are measured by benchmarks/verdicts.py);
* ``NN baseline``: each point's distance to the nearest point of all good training scans, scan score = mean of the
  top 5 % (as in benchmarks/inspect_fandisk.py).

``--figures`` writes the diagnosis pictures to ``--work``: the field's mean and standard deviation on a plane
across a sheet through a hole, with the sensor's rays through it and the tested samples; and profiles of the mean
and sd along rays through the hole and across a good stretch of the sheet.
"""
import argparse
import hashlib
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: spinning OpenMP threads crawl on a shared CPU
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

from baselines import nn_baseline
from datasets.atomic import atomic_path

SHARED = Path(__file__).resolve().parents[2] / "shared" / "meshes"
PARTS = ("enclosure", "cup", "fandisk")
KINDS = ("dent", "bump", "missing", "foreign")


def _load_part(name):
    from datasets.parts import load_part

    return load_part(SHARED / "fandisk.obj" if name == "fandisk" else name)


def _synth(part, args, work):
    """The part's collection, cached by its parameters."""
    from datasets import ScanCollection
    from datasets.synth import synthesise

    params = dict(part=part, n_train=args.train, n_validation=args.validation, n_test_good=args.test_good,
                  n_defective=args.per_defect, n_points=args.points, noise=args.noise, seed=args.seed, version=1)
    key = hashlib.sha256(json.dumps(params, sort_keys=True).encode()).hexdigest()[:10]
    path = work / f"{part}_{key}.h5"
    if path.is_file():
        return path, key
    t0 = time.perf_counter()
    scans, frame = synthesise(_load_part(part), n_train=args.train, n_validation=args.validation,
                              n_test_good=args.test_good, n_test_defective=args.per_defect, defects=KINDS,
                              n_points=args.points, noise=args.noise, seed=args.seed, part_id=part, progress=False)
    ScanCollection.create(path, scans, frame=frame, provenance={"benchmark": "thin_walled", **params})
    _save_sites(path, scans, frame)
    print(f"[{part}] synthesised {len(scans)} scans in {time.perf_counter() - t0:.0f} s -> {path}", flush=True)
    return path, key


def _sites_path(path):
    return path.with_suffix(".sites.json")


def _save_sites(path, scans, frame):
    """Where each defect is (the collection does not store ``Scan.extra``): name -> centre (3,) and radius,
    collection frame, in a JSON file beside the collection."""
    sites = {s.name: {"center": frame.to_collection(s.extra["defect_center"]).tolist(),
                      "radius": float(s.extra["defect_radius"]) * frame.scale}
             for s in scans if "defect_center" in s.extra}
    with atomic_path(_sites_path(path)) as tmp:
        tmp.write_text(json.dumps(sites))


def _sites(part, path, args):
    """The defect sites of a cached collection (synthesised again, deterministically, when the file is missing)."""
    from datasets.synth import synthesise

    if not _sites_path(path).is_file():
        scans, frame = synthesise(_load_part(part), n_train=args.train, n_validation=args.validation,
                                  n_test_good=args.test_good, n_test_defective=args.per_defect, defects=KINDS,
                                  n_points=args.points, noise=args.noise, seed=args.seed, part_id=part,
                                  progress=False)
        _save_sites(path, scans, frame)
    return json.loads(_sites_path(path).read_text())


def _train(part, data, key, args, work):
    tag = f"_e{args.epochs}" if args.epochs else ""
    model = work / f"{part}_model_{key}{tag}.pt"
    if model.is_file():
        return model
    from inspection.training import train_model

    t0 = time.perf_counter()
    train_model(data, model, calibration_fraction=0.2, seed=args.seed, epochs=args.epochs, quiet=True)
    print(f"[{part}] trained {model} in {time.perf_counter() - t0:.0f} s (load {os.getloadavg()})", flush=True)
    return model


class CachedProjections:
    """A latent model whose ``project`` remembers each scan's code (keyed by a hash of its points) in a file, so a
    rerun of the scoring side does not project again. Same contract as the model's ``project``."""

    def __init__(self, model, path):
        import torch

        self.model, self.path = model, Path(path)
        self.codes = torch.load(self.path) if self.path.is_file() else {}
        self.dirty = False

    def project(self, points, normals=None, **options):
        from types import SimpleNamespace

        key = hashlib.sha256(np.ascontiguousarray(points, dtype=np.float32).tobytes()).hexdigest()[:16]
        key += hashlib.sha256(json.dumps(options, sort_keys=True).encode()).hexdigest()[:6]
        if key not in self.codes:
            self.codes[key] = self.model.project(points, normals, **options).code.detach().clone()
            self.dirty = True
        return SimpleNamespace(field=self.model.field(self.codes[key]), code=self.codes[key])

    def save(self):
        import torch

        if self.dirty:
            with atomic_path(self.path) as tmp:
                torch.save(self.codes, tmp)
            self.dirty = False


def _metrics(scores, cal, y, defects, alpha):
    from sklearn.metrics import roc_auc_score

    from inspection.calibration import conformal_threshold

    res = {"overall": roc_auc_score(y, scores)}
    for d in KINDS:
        sel = (y == 0) | (defects == d)
        if (defects == d).any():
            res[d] = roc_auc_score(y[sel], scores[sel])
    t = conformal_threshold(cal, alpha, warn=False)
    res["far"] = float(np.mean(scores[y == 0] > t))
    res["det"] = float(np.mean(scores[y == 1] > t))
    return res


def _components(insp, scans, ray_options, point_cache):
    """Per scan: the point score's aggregate ('points'), the ray score ('rays'); the fields and ray evidences.
    ``point_cache`` (dict scan name -> points score) saves the point scores of a rerun."""
    from inspection.ray_evidence import ray_evidence

    rows, extras = [], []
    t_points = t_rays = 0.0
    for s in scans:
        t0 = time.perf_counter()
        field = insp.model.project(s.points, s.normals, **insp.projection).field
        if s.name not in point_cache:
            point_cache[s.name] = float(insp.inspect_components(s).components["points"])
        t1 = time.perf_counter()
        ev = ray_evidence(field, s.points, s.sensor_origin, **ray_options)
        t2 = time.perf_counter()
        rows.append({"points": point_cache[s.name], "rays": ev.score})
        extras.append((field, ev))
        t_points += t1 - t0
        t_rays += t2 - t1
    return rows, extras, t_points / len(scans), t_rays / len(scans)


def run_part(part, args, work):
    data, key = _synth(part, args, work)
    model_path = _train(part, data, key, args, work)
    if args.train_only:
        return None
    from datasets import ScanCollection
    from inspection.combine import Combination
    from inspection.estimator import DEFAULT_PROJECTION, Inspector
    from inspection.model_io import load_model
    from inspection.ray_evidence import check_ray_options

    handle = load_model(model_path)
    cached = CachedProjections(handle.model, model_path.with_suffix(".codes.pt"))
    with ScanCollection(data) as c:
        held, train = set(handle.heldback_names), set(handle.train_names)
        cal_scans = c.read_many([i for i, n in enumerate(c.names) if n in held or n.startswith("validation/")])
        ref_scans = c.read_many([i for i, n in enumerate(c.names) if n in train])
        test_scans = c.read_many(c.select(split="test"))
    own_depth = {"auto": "auto", "none": None}.get(args.own_depth, None)
    own_depth = float(args.own_depth) if args.own_depth not in ("auto", "none") else own_depth
    ray_options = check_ray_options({"n_rays": args.rays, "n_empty": args.empty, "own_depth": own_depth,
                                     "clearance": args.clearance})
    insp = Inspector(cached, alpha=args.alpha, point_score="distance", projection=DEFAULT_PROJECTION)
    points_path = model_path.with_suffix(".points.json")
    point_cache = json.loads(points_path.read_text()) if points_path.is_file() else {}
    if len(point_cache) < len(cal_scans) + len(test_scans):
        insp.fit_reference(ref_scans)
    if args.reference_radius > 0:
        from inspection.ray_evidence import RayReference

        t0 = time.perf_counter()
        fields = ((s.points, s.sensor_origin, insp.model.project(s.points, s.normals, **insp.projection).field)
                  for s in ref_scans)
        reference = RayReference.build(fields, args.reference_radius, **dict(ray_options, n_rays=args.reference_rays))
        ray_options = dict(ray_options, reference=reference)
        print(f"[{part}] ray reference: {len(reference.entries)} entry points of good rays from {len(ref_scans)} "
              f"training scans, radius {reference.radius:.4f}, {time.perf_counter() - t0:.0f} s")
    cal, _, _, _ = _components(insp, cal_scans, ray_options, point_cache)
    test, test_extra, sec_points, sec_rays = _components(insp, test_scans, ray_options, point_cache)
    cached.save()
    points_path.write_text(json.dumps(point_cache))
    y = np.array([s.label == "defective" for s in test_scans], dtype=int)
    defects = np.array([s.defect for s in test_scans])
    cal_m = {k: np.array([r[k] for r in cal]) for k in ("points", "rays")}
    test_m = {k: np.array([r[k] for r in test]) for k in ("points", "rays")}
    rows = [("points (no origins)", test_m["points"], cal_m["points"]),
            ("rays alone", test_m["rays"], cal_m["rays"])]
    comb = Combination(cal_m, rule="max")
    rows.append(("points+rays (max)", comb.score(test_m), comb.calibration_scores()))
    comb = Combination(cal_m)
    both_test = comb.score(test_m)
    rows.append(("points+rays (gated)", both_test, comb.calibration_scores()))
    train_points = np.concatenate([s.points for s in ref_scans])
    nn_test, nn_cal = nn_baseline(train_points, test_scans), nn_baseline(train_points, cal_scans)
    rows.append(("NN baseline top5%", nn_test, nn_cal))
    # every scan's components, to try other combinations without scoring again
    dump = [{"name": s.name, "set": which, "label": s.label, "defect": s.defect, "points": r["points"],
             "rays": r["rays"], "nn": float(nn)}
            for which, scans_, comps, nns in (("cal", cal_scans, cal, nn_cal), ("test", test_scans, test, nn_test))
            for s, r, nn in zip(scans_, comps, nns)]
    saved = {k: v for k, v in ray_options.items() if k != "reference"}
    saved["reference_radius"] = args.reference_radius
    saved["reference_rays"] = args.reference_rays
    tag = hashlib.sha256(json.dumps(saved, sort_keys=True).encode()).hexdigest()[:6]
    (work / f"{part}_components_{tag}.json").write_text(json.dumps({"ray_options": saved, "scans": dump}))

    print(f"\n[{part}] {len(ref_scans)} training scans, {len(cal_scans)} calibration (held back + validation), "
          f"{len(test_scans)} test ({int(y.sum())} defective), {args.points} points, alpha {args.alpha}; "
          f"ray options {saved}")
    print(f"{'score':<24} {'overall':>7} " + " ".join(f"{k:>7}" for k in KINDS) + f" {'FAR@a':>6} {'det@a':>6}")
    results = {}
    for name, scores, cal_scores in rows:
        m = _metrics(scores, cal_scores, y, defects, args.alpha)
        results[name] = m
        print(f"{name:<24} {m['overall']:7.3f} " + " ".join(f"{m.get(k, np.nan):7.3f}" for k in KINDS)
              + f" {m['far']:6.3f} {m['det']:6.3f}")
    print(f"seconds per scan: projection + point score {sec_points:.3f} (cached: none of it), ray score "
          f"{sec_rays:.3f}", flush=True)
    if args.figures:
        with ScanCollection(data) as c:
            frame = c.frame
        mesh = _load_part(part)
        sites = _sites(part, data, args)
        missing = [i for i, s in enumerate(test_scans) if s.defect == "missing"]
        # the two holes the default combined score ranks lowest (the ones to understand) and the highest
        order = sorted(missing, key=lambda i: both_test[i])
        for i in order[:2] + order[-1:]:
            _figure(work / f"{part}_{test_scans[i].name.replace('/', '_')}.png", test_scans[i], *test_extra[i],
                    sites[test_scans[i].name], frame, mesh)
    return results


def _ray_profile(field, origin, point, observed, clearance, n=400):
    """Samples along the ray from ``origin`` to ``point``: t (n,), mean, sd, P(f <= 0), kept (not within
    ``clearance`` of an observed point), as the ray score samples them (collection frame)."""
    from scipy.spatial import cKDTree

    t = np.linspace(0.0, 1.0, n)[:-1] * np.linalg.norm(point - origin)
    d = (point - origin) / np.linalg.norm(point - origin)
    x = origin + t[:, None] * d
    mean, sd = field.mean(x), np.sqrt(np.maximum(field.variance(x), 1e-20))
    from scipy.special import ndtr

    kept = ~np.isfinite(cKDTree(observed).query(x, k=1, distance_upper_bound=clearance)[0])
    return t, mean, sd, ndtr(-mean / sd), kept


def _figure(path, scan, field, evidence, site, frame, mesh):
    """The diagnosis picture of one scan with a hole: the field across the sheet and the sensor's rays through it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import trimesh
    from scipy.special import ndtr

    center, radius = np.asarray(site["center"]), float(site["radius"])
    center_file = frame.to_file(center)
    _, _, face = trimesh.proximity.closest_point(mesh, center_file[None])
    normal = np.asarray(mesh.face_normals[face[0]], dtype=np.float64)
    origin = np.asarray(scan.sensor_origin, dtype=np.float64)
    h = field.lengthscale
    # the plane through the hole's centre spanned by the sheet's normal and the direction to the sensor
    towards = origin - center
    e2 = towards - (towards @ normal) * normal
    e2 = e2 / np.linalg.norm(e2) if np.linalg.norm(e2) > 1e-9 else np.cross(normal, [1.0, 0, 0])
    e2 /= np.linalg.norm(e2)
    half = 4.0 * radius
    u = np.linspace(-half, half, 161)
    uu, vv = np.meshgrid(u, u, indexing="xy")  # uu along e2 (the sheet), vv along the normal
    grid = center + uu.reshape(-1, 1) * e2 + vv.reshape(-1, 1) * normal
    mean = field.mean(grid).reshape(uu.shape)
    sd = np.sqrt(np.maximum(field.variance(grid), 1e-20)).reshape(uu.shape)
    q = ndtr(-mean / sd)
    pts = np.asarray(scan.points, dtype=np.float64)
    rel = pts - center
    near_plane = np.abs(rel @ np.cross(normal, e2)) < 0.5 * h
    labels = scan.point_labels.astype(bool)
    # the part's true cross-section in the plane (undamaged part: where the hole's material was)
    section = mesh.section(plane_origin=center_file, plane_normal=np.cross(normal, e2))
    fig, axes = plt.subplots(2, 3, figsize=(18, 11))
    for ax, img, title, cmap, lim in ((axes[0, 0], mean, "E f (world units)", "RdBu", None),
                                      (axes[0, 1], sd, "sd f", "viridis", None),
                                      (axes[0, 2], q, "P(f <= 0)", "magma", (0, 1))):
        if lim is None and cmap == "RdBu":
            m = np.quantile(np.abs(img), 0.98)
            lim = (-m, m)
        im = ax.imshow(img, origin="lower", extent=(-half, half, -half, half), cmap=cmap,
                       vmin=None if lim is None else lim[0], vmax=None if lim is None else lim[1])
        ax.contour(uu, vv, mean, levels=[0.0], colors="k", linewidths=0.8)
        fig.colorbar(im, ax=ax, shrink=0.8)
        if section is not None:
            for line in section.discrete:
                local = frame.to_collection(line) - center
                ax.plot(local @ e2, local @ normal, color="lime", lw=0.8)
        ax.add_patch(plt.Circle((0, 0), radius, fill=False, ls="--", color="orange"))
        rp = rel[near_plane]
        ax.scatter(rp @ e2, rp @ normal, s=4, c=np.where(labels[near_plane], "red", "white"), edgecolors="k",
                   linewidths=0.2)
        # the sensor's rays to the defective points near the plane
        od = origin - center
        for p in rel[near_plane & labels][:12]:
            ax.plot([od @ e2, p @ e2], [od @ normal, p @ normal], color="red", lw=0.4, alpha=0.6)
        ax.set_xlim(-half, half)
        ax.set_ylim(-half, half)
        ax.set_title(f"{title}; black: E f = 0; green: the part; orange: the hole's ball")
        ax.set_xlabel("along the sheet (collection units)")
        ax.set_ylabel("along the sheet's normal")
    # profiles along the rays to points seen through the hole (the labelled points off the sheet)
    through = np.flatnonzero(labels & (np.abs(rel @ normal) > 2 * h))
    ax = axes[1, 0]
    ax2 = axes[1, 1]
    for k, i in enumerate(through[:: max(1, len(through) // 4)][:4]):
        t, m, s_, q_, kept = _ray_profile(field, origin, pts[i], pts, h)
        crossing = float((center - origin) @ (pts[i] - origin) / np.linalg.norm(pts[i] - origin))
        ax.plot(t - crossing, m / s_, label=f"ray {k}: E f / sd")
        ax2.plot(t - crossing, q_, label=f"ray {k}: P(f<=0)")
        ax2.plot((t - crossing)[~kept], q_[~kept], "k.", ms=2)
    for a in (ax, ax2):
        a.axvspan(-0.5 * 1.5 * frame.scale, 0.5 * 1.5 * frame.scale, color="grey", alpha=0.3)
        a.set_xlim(-4 * radius, 4 * radius)
        a.set_xlabel("distance along the ray from where it crosses the sheet's plane (grey: the sheet)")
        a.legend(fontsize=7)
    ax.axhline(0, color="k", lw=0.5)
    ax.axhline(-2, color="k", lw=0.5, ls=":")
    ax.set_title("rays through the hole: E f / sd")
    ax2.set_title("rays through the hole: P(f <= 0); black dots: left out (within a lengthscale of a point)")
    # across the sheet where it is intact: 2.5 radii from the hole along the sheet
    ax = axes[1, 2]
    for side in (-2.5, 2.5):
        base = center + side * radius * e2
        offs = np.linspace(-4 * h, 4 * h, 201)
        x = base + offs[:, None] * normal
        m, s_ = field.mean(x), np.sqrt(np.maximum(field.variance(x), 1e-20))
        ax.plot(offs, m, label=f"E f at {side:+.1f} radii")
        ax.fill_between(offs, m - 2 * s_, m + 2 * s_, alpha=0.2)
    ax.axvspan(-1.5 * frame.scale, 0, color="grey", alpha=0.3)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel(f"offset along the outward normal (grey: the sheet, {1.5 * frame.scale:.3f}; lengthscale "
                  f"{h:.3f})")
    ax.set_title("across the intact sheet: E f +- 2 sd")
    ax.legend(fontsize=7)
    n_lab = int(labels.sum())
    fig.suptitle(f"{scan.name}: ray score {evidence.score:.2f} nats; {n_lab} defective points; tested rays to "
                 f"them {int(labels[evidence.ray_index].sum())}, their P(blocked) max "
                 f"{evidence.ray_values[labels[evidence.ray_index]].max(initial=0):.2f}; hole radius {radius:.3f}")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    print(f"figure {path}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated, from {PARTS}")
    parser.add_argument("--train", type=int, default=32, help="good training scans (20 %% held back to calibrate)")
    parser.add_argument("--validation", type=int, default=8, help="good validation scans (calibration)")
    parser.add_argument("--test-good", type=int, default=16)
    parser.add_argument("--per-defect", type=int, default=12, help="test scans per defect type")
    parser.add_argument("--points", type=int, default=4000, help="points per scan")
    parser.add_argument("--noise", type=float, default=0.002, help="depth noise, relative to the diagonal")
    parser.add_argument("--epochs", type=int, default=None, help="training epochs (default: the trainer's)")
    parser.add_argument("--rays", type=int, default=384, help="returned rays tested per scan")
    parser.add_argument("--empty", type=int, default=128, help="most missing-return rays tested per scan")
    parser.add_argument("--own-depth", default="auto", help="ray option own_depth: auto, none or world units")
    parser.add_argument("--clearance", type=float, default=None, help="ray option clearance (world units)")
    parser.add_argument("--reference-radius", type=float, default=1.0, help="ray reference radius in kernel "
                        "lengthscales (0: no reference)")
    parser.add_argument("--reference-rays", type=int, default=1536, help="returned rays per training scan that "
                        "build the ray reference")
    parser.add_argument("--alpha", type=float, default=0.2, help="false-alarm rate of the FAR/det columns (8 "
                        "calibration scans: p-values start at 1/9)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--train-only", action="store_true", help="synthesise and train (cache), score nothing")
    parser.add_argument("--figures", action="store_true", help="write the diagnosis pictures to --work")
    parser.add_argument("--work", default="results/thin_walled")
    args = parser.parse_args(argv)
    parts = [p for p in args.parts.split(",") if p]
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        parser.error(f"unknown part(s) {unknown}; expected some of {PARTS}")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    print(f"load average at start: {os.getloadavg()}")
    print("settings: " + ", ".join(f"{k}={v}" for k, v in vars(args).items()), flush=True)
    for part in parts:
        run_part(part, args, work)
    print(f"\nload average at end: {os.getloadavg()}; wall time {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
