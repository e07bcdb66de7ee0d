"""Missing material: object AUROC of the point score alone against the point score combined with the ray score.

Run by hand from the repository root (not a test):

    .venv/bin/python benchmarks/missing_material.py [--work results/missing_material] [--parts fandisk,thinbox]

One run, two parts, each with its own synthetic collection and latent model (both cached in WORK by their
parameters):

* ``fandisk`` (``../shared/meshes/fandisk.obj``): ``missing`` defects are pits (a ball of material removed at the
  surface of a solid part);
* ``thinbox``: an open box built here (1.0 x 0.7 x 0.5, walls 0.03 = 3 % of its size), whose ``missing`` defects
  (balls of radius 4-6 % of the diagonal) punch holes through a wall or the floor. Through a hole the sensor sees
  the inside of the box, or nothing (a hole in the floor seen from above).

Defective scans are made here rather than by ``datasets.synth``: a hole in a thin wall has almost no points on its
own surface (the ball's lining is as thin as the wall), so a scan is kept when the hole is in view (at least 1.5 % of
a good scan's points from the same camera lie in the removed ball), and a point is labelled defective when it lies
on the defect's new surface or its ray passed through the removed material (the points seen through a hole).

For each part: train the latent model on the good training scans (``inspection.training.train_model``; 20 % held
back), calibrate on the held-back and validation scans, project and score every test scan once, and print object
AUROC for the NLL and the default ``distance`` point score, alone and combined with the ray score
(:class:`inspection.combine.Combination`'s default, gated rule, exactly what ``Inspector(rays=True)`` computes:
the standardized point score, plus the standardized ray score where it exceeds every calibration scan's by 2 sd),
the ray score alone, false-alarm and detection rates at ``--alpha``, point AUROC of the ray map and the
point maps against the labels above, and seconds per scan (projection + point scores, then the ray score).
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

SHARED = Path(__file__).resolve().parents[2] / "shared" / "meshes"
PARTS = ("fandisk", "thinbox")


def thin_box(size=(1.0, 0.7, 0.5), wall=0.03):
    """An open-topped box with walls and floor ``wall`` thick (watertight, manifold3d boolean). trimesh.Trimesh."""
    import trimesh
    from trimesh.creation import box

    outer = box(extents=size)
    outer.apply_translation((0.0, 0.0, size[2] / 2))
    inner = box(extents=(size[0] - 2 * wall, size[1] - 2 * wall, size[2]))
    inner.apply_translation((0.0, 0.0, size[2] / 2 + wall))
    part = trimesh.boolean.difference([outer, inner], engine="manifold")
    if not part.is_watertight:
        raise RuntimeError("thin_box: the boolean result is not watertight")
    return part


def _load_part(name):
    if name == "thinbox":
        return thin_box()
    from datasets.parts import load_part

    return load_part(SHARED / "fandisk.obj")


def _removed(mesh_scene, defect, x):
    """(k, 3) mesh-frame points -> (k,) bool: inside the removed ball and inside the original solid."""
    import open3d as o3d

    inside_ball = np.linalg.norm(x - defect.center, axis=1) < defect.radius
    out = np.zeros(len(x), dtype=bool)
    if inside_ball.any():
        occ = mesh_scene.compute_occupancy(o3d.core.Tensor(x[inside_ball].astype(np.float32))).numpy()
        out[inside_ball] = occ > 0.5
    return out


def _ray_labels(mesh_scene, defect, sensor, clean, samples=256):
    """Points whose ray from the sensor passed through the removed material: (n,) bool."""
    t = np.linspace(0.0, 1.0, samples)[1:-1]
    seg = sensor + t[None, :, None] * (clean - sensor)[:, None, :]  # (n, S, 3)
    near = np.linalg.norm(seg - defect.center, axis=2).min(1) < defect.radius
    out = np.zeros(len(clean), dtype=bool)
    for i in np.flatnonzero(near):
        out[i] = _removed(mesh_scene, defect, seg[i]).any()
    return out


def _defective_scans(mesh, n, n_points, noise, seed, min_fraction=0.015, max_attempts=12):
    """``n`` scans of ``mesh`` with a ``missing`` defect in view, labelled by surface and by ray (mesh units)."""
    import open3d as o3d

    from datasets.defects import defect_for_view
    from datasets.scanner import VirtualScanner

    scanner = VirtualScanner(mesh)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)))
    needed = int(np.ceil(min_fraction * n_points))
    out = []
    for i, child in enumerate(np.random.SeedSequence([seed, 1]).spawn(n)):
        rng = np.random.default_rng(child)
        for _ in range(max_attempts):
            view = scanner.random_view(seed=rng, radius_range=(1.5, 2.2))
            defect = defect_for_view(mesh, scanner, view, "missing", seed=rng)
            good = scanner.scan(view, n_points=n_points, noise=0.0, seed=rng)
            footprint = int((np.linalg.norm(good.to_mesh_frame(good.clean_points) - defect.center, axis=1)
                             < defect.radius).sum())
            if footprint >= needed:
                break
        else:
            raise RuntimeError(f"defective scan {i}: no view in {max_attempts} showed the hole")
        result = VirtualScanner(defect.mesh).scan(view, n_points=n_points, noise=noise * scanner.diagonal, seed=rng)
        clean = result.to_mesh_frame(result.clean_points)
        sensor = result.to_mesh_frame(result.sensor_origin[None])[0]
        labels = defect.region(clean, result.triangle_ids) | _ray_labels(scene, defect, sensor, clean)
        out.append((result, labels.astype(np.uint8), defect, footprint))
    return out


def _synth(part, args, work):
    """The part's collection (cached by its parameters): good train / validation / test scans from
    ``datasets.synth.synthesise``, defective test scans from :func:`_defective_scans`."""
    from datasets import Scan, ScanCollection
    from datasets.synth import synthesise

    params = dict(part=part, n_train=args.train, n_validation=args.validation, n_test_good=args.test_good,
                  n_defective=args.per_defect, n_points=args.points, noise=args.noise, seed=args.seed, version=1)
    key = hashlib.sha256(json.dumps(params, sort_keys=True).encode()).hexdigest()[:10]
    path = work / f"{part}_{key}.h5"
    if path.is_file():
        return path, key
    t0 = time.perf_counter()
    mesh = _load_part(part)
    scans, frame = synthesise(mesh, n_train=args.train, n_validation=args.validation, n_test_good=args.test_good,
                              n_test_defective=0, defects=(), n_points=args.points, noise=args.noise,
                              seed=args.seed, progress=False)
    footprints = []
    for i, (result, labels, defect, footprint) in enumerate(
            _defective_scans(mesh, args.per_defect, args.points, args.noise, args.seed)):
        footprints.append(footprint)
        scans.append(frame.apply(Scan(
            name=f"test/missing/{i:03d}", points=result.points, normals=result.normals, split="test",
            label="defective", defect="missing", part_id=part, point_labels=labels,
            sensor_origin=result.sensor_origin,
            extra={"defect_center": defect.center, "defect_radius": defect.radius})))
    ScanCollection.create(path, scans, frame=frame, provenance={"benchmark": "missing_material", **params})
    print(f"[{part}] synthesised {len(scans)} scans in {time.perf_counter() - t0:.0f} s -> {path} (hole "
          f"footprint in a good scan from the same view: median {np.median(footprints):.0f} points)")
    return path, key


def _train(part, data, key, args, work):
    model = work / f"{part}_model_{key}_e{args.epochs}.pt"
    if model.is_file():
        return model
    from inspection.training import train_model

    t0 = time.perf_counter()
    train_model(data, model, calibration_fraction=0.2, seed=args.seed, epochs=args.epochs, quiet=True)
    print(f"[{part}] trained {model} ({args.epochs} epochs) in {time.perf_counter() - t0:.0f} s")
    return model


def _rates(test, cal, y, alpha):
    from inspection.threshold import conformal_threshold

    t = conformal_threshold(cal, alpha)
    return float(np.mean(test[y == 0] > t)), float(np.mean(test[y == 1] > t))


def run_part(part, args, work):
    from sklearn.metrics import roc_auc_score

    from datasets import ScanCollection
    from inspection.combine import Combination
    from inspection.estimator import DEFAULT_PROJECTION, Inspector
    from inspection.model_io import load_model
    from inspection.ray_evidence import check_ray_options, ray_evidence
    from inspection.scores import aggregate, point_scores

    data, key = _synth(part, args, work)
    handle = load_model(_train(part, data, key, args, work))
    with ScanCollection(data) as c:
        held = set(handle.heldback_names)
        train = set(handle.train_names)
        cal_scans = c.read_many([i for i, n in enumerate(c.names) if n in held or n.startswith("validation/")])
        ref_scans = c.read_many([i for i, n in enumerate(c.names) if n in train])
        test_scans = c.read_many(c.select(split="test"))
    ray_options = check_ray_options({"n_rays": args.rays, "n_empty": args.empty})
    insp = Inspector(handle.model, alpha=args.alpha, point_score="distance", projection=DEFAULT_PROJECTION)
    t0 = time.perf_counter()
    insp.fit_reference(ref_scans)
    t_ref = time.perf_counter() - t0

    n_empty = [0, 0]  # scans with missing-return rays, scans

    def components(scans):
        """Per scan: the point scores' aggregates and the ray score (what Inspector(rays=True) combines), the maps,
        and the seconds of each half."""
        rows, point_maps, ray_maps, sec_points, sec_rays = [], [], [], [], []
        n_empty[:] = [0, len(scans)]
        for s in scans:
            t0 = time.perf_counter()
            res = insp.inspect_components(s)
            nll = point_scores(res.field, s.points, "nll")
            t1 = time.perf_counter()
            ev = ray_evidence(res.field, s.points, s.sensor_origin, **ray_options)
            t2 = time.perf_counter()
            rows.append({"distance": res.components["points"], "nll": aggregate(nll, insp.aggregate), "rays": ev.score})
            point_maps.append({"distance": res.point_scores, "nll": nll})
            ray_maps.append(ev.point_map)
            n_empty[0] += len(ev.empty_values) > 0
            sec_points.append(t1 - t0)
            sec_rays.append(t2 - t1)
        return rows, point_maps, ray_maps, np.mean(sec_points), np.mean(sec_rays)

    cal, _, _, _, _ = components(cal_scans)
    test, test_maps, test_ray_maps, sec_points, sec_rays = components(test_scans)
    y = np.array([s.label == "defective" for s in test_scans], dtype=int)
    pl = np.concatenate([s.point_labels for s in test_scans])
    results = []
    for name in ("nll", "distance"):
        alone_cal = np.array([r[name] for r in cal])
        alone = np.array([r[name] for r in test])
        comb = Combination({"points": alone_cal, "rays": [r["rays"] for r in cal]})
        both = comb.score({"points": alone, "rays": [r["rays"] for r in test]})
        point_auc = roc_auc_score(pl, np.concatenate([m[name] for m in test_maps]))
        results.append((f"{name} alone", roc_auc_score(y, alone), *_rates(alone, alone_cal, y, args.alpha),
                        point_auc))
        results.append((f"{name} + rays", roc_auc_score(y, both),
                        *_rates(both, comb.calibration_scores(), y, args.alpha), None))
    rays_cal = np.array([r["rays"] for r in cal])
    rays_test = np.array([r["rays"] for r in test])
    ray_point_auc = roc_auc_score(pl, np.concatenate(test_ray_maps))
    results.append(("rays alone", roc_auc_score(y, rays_test), *_rates(rays_test, rays_cal, y, args.alpha),
                    ray_point_auc))

    print(f"\n[{part}] {len(cal_scans)} calibration scans (held back + validation), {len(test_scans)} test scans "
          f"({int(y.sum())} missing), alpha {args.alpha} (smallest p-value {1 / (len(cal_scans) + 1):.3f}); "
          f"aggregate {insp.aggregate}, ray options {ray_options}")
    print(f"{'score':<16} {'AUROC':>6} {'FAR@a':>6} {'det@a':>6} {'pointAUC':>8}")
    for name, auc, far, det, pauc in results:
        print(f"{name:<16} {auc:6.3f} {far:6.3f} {det:6.3f} {'-' if pauc is None else f'{pauc:.3f}':>8}")
    good_rays = rays_test[y == 0]
    bad_rays = rays_test[y == 1]
    print(f"ray score ({ray_options['aggregate']} of -log P(free), nats): calibration median "
          f"{np.median(rays_cal):.2f} max {rays_cal.max():.2f}; good test median {np.median(good_rays):.2f}; missing "
          f"median {np.median(bad_rays):.2f}, {int((bad_rays > rays_cal.max()).sum())} of {len(bad_rays)} above "
          f"every calibration scan; missing-return rays tested in {n_empty[0]} of {n_empty[1]} test scans")
    print(f"seconds per scan: projection + point scores {sec_points:.3f}, ray score {sec_rays:.3f}, total "
          f"{sec_points + sec_rays:.3f} (per-location reference built once: {t_ref:.0f} s)")
    return results


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated, from {PARTS}")
    parser.add_argument("--train", type=int, default=24, help="good training scans (20 %% held back to calibrate)")
    parser.add_argument("--validation", type=int, default=12, help="good validation scans (calibration)")
    parser.add_argument("--test-good", type=int, default=12)
    parser.add_argument("--per-defect", type=int, default=12, help="test scans with a missing defect")
    parser.add_argument("--points", type=int, default=6000, help="points per scan (3000: the box's 3 %% walls are "
                        "thinner than the kernel lengthscale, and its model blurs them)")
    parser.add_argument("--noise", type=float, default=0.002, help="depth noise, relative to the diagonal")
    parser.add_argument("--epochs", type=int, default=300)
    parser.add_argument("--rays", type=int, default=384, help="returned rays tested per scan")
    parser.add_argument("--empty", type=int, default=128, help="most missing-return rays tested per scan")
    parser.add_argument("--alpha", type=float, default=0.1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    parser.add_argument("--work", default="results/missing_material")
    args = parser.parse_args(argv)
    parts = [p for p in args.parts.split(",") if p]
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        parser.error(f"unknown part(s) {unknown}; expected some of {PARTS}")
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    print(f"load average at start: {os.getloadavg()}; torch threads {torch.get_num_threads()}")
    print("settings: " + ", ".join(f"{k}={v}" for k, v in vars(args).items()))
    for part in parts:
        run_part(part, args, work)
    print(f"\nload average at end: {os.getloadavg()}; wall time {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
