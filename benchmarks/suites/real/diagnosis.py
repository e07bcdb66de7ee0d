"""The real suite's ``--diagnose``: what the worst points of the good test scans are (border, grazing, sparse,
stray, rarely covered by training), with pictures in the run's ``diagnosis/``."""
from pathlib import Path

import numpy as np

from benchmarks import inspect_api, metrics
from benchmarks.suites.real.tree import KINDS


def point_features(scan, train_tree, train_owner, n_train):
    """Per-point descriptors of a scan (collection frame): grazing cosine, border offset, local sparsity, stray flag,
    distance to the nearest training point and how many training scans cover the point, both in local spacings."""
    from scipy.spatial import cKDTree

    from datasets.outliers import stray_points

    p, n = np.asarray(scan.points, np.float64), np.asarray(scan.normals, np.float64)
    ray = scan.sensor_origin - p
    cos = np.abs(np.einsum("ij,ij->i", n, ray / np.linalg.norm(ray, axis=1, keepdims=True)))
    d, idx = cKDTree(p).query(p, 17)
    radius = d[:, -1]
    off = p[idx[:, 1:]].mean(1) - p
    off -= np.einsum("ij,ij->i", off, n)[:, None] * n
    border = np.linalg.norm(off, axis=1) / radius  # ~0 inside, ~0.4 or more at the scan's edge
    spacing = d[:, 1]
    sparse = d[:, 8] / np.median(d[:, 8])
    near, _ = train_tree.query(p, 1)
    owners = train_tree.query_ball_point(p, 2.0 * np.median(d[:, 8]))
    cover = np.array([len(set(train_owner[o])) for o in owners]) / n_train
    return dict(cos=cos, border=border, sparse=sparse, stray=stray_points(p).astype(float),
                nearest=near / np.median(spacing), cover=cover)


CATEGORIES = (("border", lambda f: f["border"] > 0.35), ("grazing", lambda f: f["cos"] < 0.3),
              ("sparse", lambda f: f["sparse"] > 2.0), ("stray", lambda f: f["stray"] > 0),
              ("rarely covered", lambda f: f["cover"] < 0.1), ("far from training", lambda f: f["nearest"] > 3.0))


def view_picture(path, scan, values, title, labels=None, vmax=None):
    """The scan seen from its sensor (orthographic), coloured by per-point score; defect points circled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = np.asarray(scan.points, np.float64)
    c = p.mean(0)
    z = scan.sensor_origin - c
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    q = (p - c) @ np.stack([x, np.cross(z, x), z]).T
    order = np.argsort(q[:, 2])  # far points first, near ones on top
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5), gridspec_kw={"width_ratios": [1.4, 1]})
    vmax = vmax or max(np.quantile(values, 0.995), 1e-9)
    sc = axes[0].scatter(q[order, 0], q[order, 1], c=values[order], s=4, cmap="turbo", vmin=0, vmax=vmax)
    if labels is not None and labels.any():
        axes[0].scatter(q[labels > 0, 0], q[labels > 0, 1], s=14, facecolors="none", edgecolors="k", lw=0.3)
    top = np.argsort(values)[-max(1, len(values) // 100):]
    axes[0].scatter(q[top, 0], q[top, 1], s=40, marker="x", c="m", lw=0.8, label="top 1 % (the scan's score)")
    axes[0].legend(loc="lower right", fontsize=8)
    axes[0].set_aspect("equal")
    fig.colorbar(sc, ax=axes[0], fraction=0.04)
    bins = np.linspace(0, max(float(values.max()), vmax), 60)
    lab = np.zeros(len(values), bool) if labels is None else labels > 0
    axes[1].hist([values[~lab], values[lab]], bins=bins, label=["good points", "defect points"], log=True)
    axes[1].legend()
    axes[1].set_xlabel("point score (all values; the map's colours stop at the left panel's bar)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def diagnose(data, run_dir):
    """Per-point scores of the run's test scans (the calibrated model through the inspection API, as ``score``
    computes them), what the worst points of the good scans are, and pictures of the worst good and the missed
    defective scans."""
    from scipy.spatial import cKDTree
    from scipy.stats import spearmanr

    from datasets import ScanCollection

    model = Path(run_dir) / "model.pt"
    pics = Path(run_dir) / "diagnosis"
    pics.mkdir(exist_ok=True)
    info = inspect_api.model_info(model)
    held = set(info["heldback_names"])
    with ScanCollection(data) as c:
        train = [c[i] for i in c.select(split="train") if c.names[i] not in held]
    test, results = inspect_api.point_maps(model, data, fields=True)
    vals = [r["point_scores"] for r in results]
    score = np.array([r["score"] for r in results])
    owner = np.concatenate([np.full(len(s), k) for k, s in enumerate(train)])
    tree = cKDTree(np.concatenate([s.points for s in train]))
    good = np.array([s.label == metrics.GOOD for s in test])
    feats = [point_features(s, tree, owner, len(train)) for s in test]
    settings = inspect_api.calibration_settings(model)
    print(f"point score {settings['point_score']}, aggregate {settings['aggregate']}, noise floor "
          f"{settings['noise']:.4g} (model frame), kernel lengthscale {settings['lengthscale']:.4g}, median point "
          f"spacing of the test scans "
          f"{np.median([np.median(cKDTree(s.points).query(s.points, 2)[0][:, 1]) for s in test]):.4g}")
    print("\ngood test scans: the worst 1 % of each scan's points against all its points")
    print(f"{'scan':<26}{'score':>7}" + "".join(f"{k[:14]:>16}" for k, _ in CATEGORIES))
    for i in np.flatnonzero(good)[np.argsort(-score[good])]:
        v, f = vals[i], feats[i]
        top = np.argsort(v)[-max(1, len(v) // 100):]
        cells = [f"{rule(f)[top].mean():6.2f} / {rule(f).mean():5.2f}" for _, rule in CATEGORIES]
        print(f"{test[i].name[-24:]:<26}{score[i]:7.2f}" + "".join(f"{c:>16}" for c in cells))
    allv = np.concatenate([vals[i] for i in np.flatnonzero(good)])
    print("\nall good test points: median / 99th percentile of the point score, inside and outside each category")
    for k, rule in CATEGORIES:
        m = np.concatenate([rule(feats[i]) for i in np.flatnonzero(good)])
        if m.any():
            print(f"  {k:<18} in: {np.median(allv[m]):6.2f} / {np.quantile(allv[m], 0.99):6.2f}   out: "
                  f"{np.median(allv[~m]):6.2f} / {np.quantile(allv[~m], 0.99):6.2f}   ({m.mean():.3f} of the points)")
    print("  Spearman rank correlation of the point score with: " + ", ".join(
        f"{k} {spearmanr(allv, np.concatenate([feats[i][k] for i in np.flatnonzero(good)]))[0]:+.2f}"
        for k in ("cos", "border", "sparse", "nearest", "cover")))
    thr = score[good].max()
    print(f"\ndefective test scans below the worst good scan's score ({thr:.2f}):")
    for kind in KINDS:
        idx = [i for i, s in enumerate(test) if s.defect == kind]
        missed = [i for i in idx if score[i] <= thr]
        dp = np.concatenate([vals[i][test[i].point_labels > 0] for i in idx])
        print(f"  {kind:<8} {len(missed)}/{len(idx)} missed; defect points: median {np.median(dp):.2f}, "
              f"90th pct {np.quantile(dp, 0.9):.2f}; their scans' good points: 99th pct "
              f"{np.quantile(np.concatenate([vals[i][test[i].point_labels == 0] for i in idx]), 0.99):.2f}")
    vmax = float(np.quantile(allv, 0.999))
    for i in np.flatnonzero(good)[np.argsort(-score[good])][:3]:
        view_picture(pics / f"good_{test[i].name.split('/')[-1]}.png", test[i], vals[i],
                     f"{test[i].name}: worst good scans, score {score[i]:.2f} (threshold region)", vmax=vmax)
    for kind in KINDS:
        idx = [i for i, s in enumerate(test) if s.defect == kind]
        for i in sorted(idx, key=lambda i: score[i])[:2]:
            view_picture(pics / f"missed_{kind}_{test[i].name.split('/')[-1]}.png", test[i], vals[i],
                         f"{test[i].name}: lowest-scoring {kind}, score {score[i]:.2f} (worst good {thr:.2f})",
                         labels=test[i].point_labels, vmax=vmax)
    for i in [*np.flatnonzero(good)[np.argsort(-score[good])][:2],
              min((i for i, s in enumerate(test) if s.defect == "bump"), key=lambda i: score[i])]:
        section_picture(pics / f"section_{test[i].name.split('/')[-1]}.png", test[i], vals[i], results[i]["field"],
                        f"{test[i].name}: the projected mean surface (E f = 0) through the worst non-stray point (x), "
                        f"real points within 1 spacing of the section")
    print(f"pictures in {pics}")


def section_picture(path, scan, values, field, title):
    """A cross-section through the scan's worst point, in the plane holding the ray to the sensor: the projected
    mean surface (the zero level of E f) and the real points near the plane, coloured by score."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.spatial import cKDTree

    from datasets.outliers import stray_points

    p = np.asarray(scan.points, np.float64)
    worst = int(np.argmax(np.where(stray_points(p), -np.inf, values)))  # the worst point on the surface
    w = p[worst]
    z = scan.sensor_origin - w
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(scan.normals[worst], np.float64))
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # the plane spanned by z (toward the sensor) and y; x is its normal
    half = 0.15
    u = np.linspace(-half, half, 160)
    gu, gv = np.meshgrid(u, u)
    grid = w + gu.reshape(-1, 1) * y + gv.reshape(-1, 1) * z
    mean = np.asarray(field.mean(grid)).reshape(gu.shape)
    spacing = float(np.median(cKDTree(p).query(p, 2)[0][:, 1]))
    near = np.abs((p - w) @ x) < spacing
    q = (p[near] - w) @ np.stack([y, z]).T
    fig, ax = plt.subplots(figsize=(7, 7))
    lim = float(np.quantile(np.abs(mean), 0.95))
    ax.contourf(gu, gv, mean, levels=21, cmap="RdBu_r", vmin=-lim, vmax=lim, alpha=0.5)
    ax.contour(gu, gv, mean, levels=[0.0], colors="k", linewidths=1.2)
    sc = ax.scatter(q[:, 0], q[:, 1], c=values[near], s=14, cmap="turbo", vmin=0,
                    vmax=max(float(np.quantile(values, 0.995)), 1e-9), edgecolors="none")
    ax.scatter([0], [0], marker="x", c="m", s=60)
    ax.annotate("to the sensor", xy=(-0.13, 0.14), xytext=(-0.13, 0.09), arrowprops=dict(arrowstyle="->"))
    ax.set_xlim(-half, half)
    ax.set_ylim(-half, half)
    ax.set_aspect("equal")
    fig.colorbar(sc, ax=ax, fraction=0.04, label="point score")
    ax.set_title(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
