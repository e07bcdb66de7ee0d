"""Scanning a part view by view: next-best-view against simple strategies with fine-tuning after each scan, and the
next-best-view score's ranking of cameras on a one-scan field.

Both modes start from the same first view (a random camera on the sphere of 1.8 diagonals around ``--mesh``, drawn
with ``--seed``) and the same one-scan field: the SIREN (the grid's solve has no boundary term) with every fit and
fine-tune using ``FitOptions.outside_weight`` ``--outside-weight`` (default 100: the box's boundary is outside,
which closes a partial scan; 0: the paper's loss), the kernel at ``--h-factor`` 2 point spacings (with which the
recorded figures were measured; ``fit_cloud``'s own default is 1.5) and small nets (``--width`` 64 x 3, ``--features``
64).

Modes (``--mode``):

``next-view`` (default)
    Each next view is (a) ``next_best_views`` (variance at the expected correlated first hits, weighted by their
    novelty against the points measured so far), (b) a random view, (c) the camera on a sphere furthest from all
    previous cameras; after each scan the field is fine-tuned (``update_field``) on old + new points. Prints the
    Chamfer distance of the mean surface to the true mesh after each view and its mean per strategy, writes
    ``chamfer.png`` in ``--out``; with all three strategies it then refits from scratch on the last union cloud of
    (a) and compares at equal error: the field before (a)'s last view fine-tuned on the last scan for 10, 25, 50, ...
    steps until its error is within two standard errors of the refit's (the sampled Chamfer has its own noise) and
    at or below it; then refits with a quarter and half the budget, and for each fine-tune the cheapest refit as
    good. NBV results move a lot with the seed: compare strategies over several ``--seed`` values.
``view-score``
    The score alone, in ~2 minutes a seed: ``--cameras`` cameras spread evenly over the scanning sphere, aimed at the
    part's centre, are scored on the one-scan field and also scanned; a camera's oracle gain is the fraction of its
    points farther than one kernel support (2 h) from the points already measured. Prints the oracle gain by angle
    from the first view, then per score variant the Spearman correlation of score and gain, the angle and gain of
    its best camera and the mean gain of its top 10 against the best 10 possible. Variants: the library's scores
    (expected point or first-hit distribution, with or without novelty) and three that replace the learned Var f at
    the expected hit: 1 (P(hit) x novelty alone), the learned variance of grad f, and with ``--spsr`` gpytoolbox's
    stochastic Poisson variance of the same scan on a 20^3 grid (minutes): does the learned variance or the score
    itself limit the ranking?

The Chamfer distance is ``benchmarks.surface_metrics.mean_surface_distance``.
"""
import time
from pathlib import Path

from benchmarks.surface_metrics import SPSR_GRID

DESCRIPTION = "scanning: next-best-view vs random and furthest-point views with fine-tuning; the view score's ranking"
MODES = ("next-view", "view-score")


def add_arguments(parser):
    parser.add_argument("--mode", choices=MODES, default="next-view", help="what to measure (default: %(default)s)")
    field = parser.add_argument_group("the first view and its field (both modes)")
    field.add_argument("--mesh", default="fandisk", help="fandisk, bunny, a built-in part or a mesh file")
    field.add_argument("--seed", type=int, default=0)
    field.add_argument("--points", type=int, default=3000, help="points per scan")
    field.add_argument("--fit-steps", type=int, default=400)
    field.add_argument("--width", type=int, default=64)
    field.add_argument("--features", type=int, default=64, help="rank of the feature covariance")
    field.add_argument("--covariance", choices=("feature", "pair"), default="feature")
    field.add_argument("--cov-screening", type=float, default=None,
                       help="lambda_S of the covariance's screening term (default: the paper's, as the mean's)")
    field.add_argument("--outside-weight", type=float, default=100.0,
                       help="FitOptions.outside_weight of every fit and fine-tune (default 100: the box's boundary is "
                            "outside, which closes partial scans; 0: the paper's loss)")
    field.add_argument("--h-factor", type=float, default=2.0,
                       help="kernel lengthscale / point spacing of every fit (2: the recorded figures were measured "
                            "with it; fit_cloud's own default is 1.5)")
    views = parser.add_argument_group("next-view")
    views.add_argument("--views", type=int, default=6, help="scans in total, the first included")
    views.add_argument("--noise", type=float, default=0.0, help="depth noise, multiples of the mesh diagonal")
    views.add_argument("--update-steps", type=int, default=150)
    views.add_argument("--starts", type=int, default=12)
    views.add_argument("--candidates", type=int, default=None,
                       help="scored random cameras the starts are chosen from (default: starts, i.e. random starts)")
    views.add_argument("--nbv-steps", type=int, default=30)
    views.add_argument("--n-side", type=int, default=3, help="rays per image side of the NBV camera model")
    views.add_argument("--novelty", choices=("auto", "off"), default="auto",
                       help="NBV novelty weighting against the measured points ('off': the variance alone, the "
                            "paper's)")
    views.add_argument("--hit-summary", choices=("expected-point", "distribution"), default="expected-point",
                       help="camera score: variance at the expected hit point, or expected over the hit distribution")
    views.add_argument("--score-variance", choices=("learned", "none"), default="learned",
                       help="'none' scores cameras by P(hit) x novelty alone (the variance replaced by 1 where the "
                            "score reads it): not the paper's score, an experiment")
    views.add_argument("--strategies", default="nbv,random,furthest", help="comma-separated subset to run")
    views.add_argument("--mesh-res", type=int, default=64, help="marching-cubes grid of the Chamfer distance")
    views.add_argument("--out", type=Path, default=Path("results/next_view"))
    score = parser.add_argument_group("view-score")
    score.add_argument("--cameras", type=int, default=200)
    score.add_argument("--spsr", action="store_true",
                       help=f"also score with gpytoolbox's SPSR variance of the first scan ({SPSR_GRID}^3 grid, "
                            "minutes)")


def run(args):
    return {"next-view": _next_view, "view-score": _view_score}[args.mode](args)


# --- the first view and its field ------------------------------------------------------------------------------

def fibonacci_sphere(n):
    """(n, 3) unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    import numpy as np

    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)


def _fit_options(args):
    """fit_cloud's keyword arguments of every fit (the lengthscale aside): small SIRENs, big batches."""
    return dict(representation="siren", quiet=True, width=args.width, depth=3, features=args.features,
                covariance=args.covariance, mean_batch=2048, screen_batch=1024, pair_clusters=64, covariance_every=1,
                pool_passes=4, average_decay=0.0, covariance_screening_weight=args.cov_screening,
                outside_weight=args.outside_weight)


def _fit(points, normals, args, steps):
    from autodecoder import fit_cloud
    from autodecoder.field.targets import point_spacing

    return fit_cloud(points, normals, seed=args.seed, steps=steps,
                     lengthscale=args.h_factor * point_spacing(points), **_fit_options(args))


class _Setup:
    """The part, its virtual scanner, the first view, its scan and the one-scan field both modes start from."""

    def __init__(self, args):
        import torch

        from benchmarks.cache import part_mesh
        from datasets.scanner import VirtualScanner

        torch.set_num_threads(1)
        self.args = args
        self.mesh = part_mesh(args.mesh)
        self.scanner = VirtualScanner(self.mesh)
        self.radius = 1.8 * self.scanner.diagonal
        self.first = self.scanner.random_view(radius_range=(1.8, 1.8), seed=args.seed)
        self.p0, self.n0 = self.scan(self.first.camera_position, self.scanner.center, 0)
        t0 = time.perf_counter()
        self.field = _fit(self.p0, self.n0, args, args.fit_steps)
        self.field.training_points = torch.tensor(self.p0).float()  # what update_field adds the next scans to
        self.field.training_normals = torch.tensor(self.n0).float()
        self.fit_seconds = time.perf_counter() - t0

    def scan(self, position, look_at, seed, n_points=None):
        import numpy as np

        s = self.scanner.scan(position, look_at, n_points=n_points or self.args.points,
                              noise=self.args.noise * self.scanner.diagonal, seed=seed)
        return s.points.astype(np.float64), s.normals.astype(np.float64)


class WithoutVariance:
    """A field whose variance reads 1 where the score reads it (``torch_variance``); everything else, the rays'
    correlated Gaussian included, is the field's own. Scores cameras by P(hit) x novelty alone."""

    def __init__(self, field):
        self._field = field

    def __getattr__(self, name):
        return getattr(self._field, name)

    def torch_variance(self, x):
        import torch

        return torch.ones_like(x[:, 0])


class GradientVariance(WithoutVariance):
    """The field with Var f replaced by the variance of its gradient, tr D c(x, x) / 3 (unitless): the quantity the
    covariance loss fits directly (D c ~ Sigma I), free of the part of c that the mixed derivatives leave open."""

    def torch_variance(self, x):
        import torch

        f = self._field
        model_x = f._model_x(x)
        dc = f.cov_net.d_operator(model_x, model_x, f._code_for(x))
        return torch.diagonal(dc, dim1=1, dim2=2).mean(1)


class SpsrVariance(WithoutVariance):
    """The field with Var f replaced by gpytoolbox's stochastic Poisson (SPSR) variance of the same scan on a
    ``grid``^3 grid over the field's box (``benchmarks.surface_metrics.spsr``), trilinearly interpolated (no
    gradient: for scoring only)."""

    def __init__(self, field, points, normals, grid=SPSR_GRID):
        import numpy as np
        from scipy.interpolate import RegularGridInterpolator

        from benchmarks.surface_metrics import spsr, spsr_grid

        super().__init__(field)
        lo, hi = field.bounds
        gs, _, axes, self.grid_points = spsr_grid(lo, hi, grid)
        _, self.grid_var = spsr(points, normals, lo, hi, grid)
        self.interp = RegularGridInterpolator(axes, np.reshape(self.grid_var, tuple(gs), order="F"),
                                              bounds_error=False, fill_value=None)

    def torch_variance(self, x):
        import torch

        return torch.as_tensor(self.interp(x.detach().double().numpy()), dtype=x.dtype)


def _chamfer(field, mesh, res):
    from benchmarks.surface_metrics import mean_surface_distance

    try:
        return mean_surface_distance(field.mesh(res), mesh)
    except ValueError:  # no zero level set in the box
        return float("nan")


# --- next-view -------------------------------------------------------------------------------------------------

def _next_view(args):
    import numpy as np

    from autodecoder import update_field
    from autodecoder.scanning.views import next_best_views
    from benchmarks.table import format_table

    setup = _Setup(args)
    scanner, mesh = setup.scanner, setup.mesh
    err0 = _chamfer(setup.field, mesh, args.mesh_res)
    print(f"first fit {setup.fit_seconds:.1f}s, chamfer {err0:.5f}")
    candidates = scanner.center + setup.radius * fibonacci_sphere(200)
    rng = np.random.default_rng(args.seed + 1)
    results, last_step = {}, None
    strategies = [s for s in args.strategies.split(",") if s]
    for strategy in strategies:
        field, cams, previous = setup.field, [setup.first.camera_position], setup.field
        errors, times = [err0], []
        for k in range(1, args.views):
            t_select = time.perf_counter()
            if strategy == "nbv":
                scored = field if args.score_variance == "learned" else WithoutVariance(field)
                v = next_best_views(scored, n_views=1, starts=args.starts, steps=args.nbv_steps, standoff=(1.6, 2.4),
                                    candidates=args.candidates, n_side=args.n_side, seed=args.seed + k,
                                    observed="auto" if args.novelty == "auto" else None,
                                    hit_summary=args.hit_summary)[0]
                pos, look = v.position, v.look_at
            elif strategy == "random":
                view = scanner.random_view(radius_range=(1.8, 1.8), seed=int(rng.integers(1 << 31)))
                pos, look = view.camera_position, scanner.center
            else:
                d = np.min(np.linalg.norm(candidates[:, None] - np.array(cams)[None], axis=2), axis=1)
                pos, look = candidates[np.argmax(d)], scanner.center
            t_select = time.perf_counter() - t_select
            cams.append(np.asarray(pos))
            try:
                p, n = setup.scan(pos, look, k)
            except ValueError as exc:  # the part is not in view: aim at the part's centre from the same place
                print(f"  {strategy} view {k + 1}: {exc}; aiming at the part's centre instead")
                p, n = setup.scan(pos, scanner.center, k)
            t = time.perf_counter()
            previous = field
            field = update_field(field, p, n, steps=args.update_steps, seed=k)
            times.append(time.perf_counter() - t)
            errors.append(_chamfer(field, mesh, args.mesh_res))
            print(f"  {strategy} view {k + 1}: chamfer {errors[-1]:.5f} (select {t_select:.1f}s, update "
                  f"{times[-1]:.1f}s)", flush=True)
        results[strategy] = {"chamfer": errors, "update_seconds": times,
                             "mean_chamfer": float(np.mean(errors[1:])) if len(errors) > 1 else float("nan"),
                             "cameras": [list(map(float, c)) for c in cams]}
        if strategy == "nbv":
            last_step = (previous, p, n, field)  # the field before the last view, the last scan, the final field
    print(f"Chamfer after each view (1..{args.views}) and its mean over views 2..{args.views}:")
    print(format_table([{"strategy": s, "mean": r["mean_chamfer"], **{str(i + 1): e for i, e in
                                                                       enumerate(r["chamfer"])}}
                        for s, r in results.items()],
                       [("strategy", "strategy", ""), ("mean", "mean", ".5f")]
                       + [(str(i), f"view {i}", ".5f") for i in range(1, args.views + 1)]))
    _chamfer_png(results, args.views, args.out / "chamfer.png")
    if set(strategies) != {"nbv", "random", "furthest"} or args.views < 2:  # exploratory: no comparison, no refit
        return {"strategies": results}
    below = all(a < b for a, b in zip(results["nbv"]["chamfer"][1:], results["random"]["chamfer"][1:]))
    print(f"nbv below random at every step: {below}")
    return {"strategies": results, "nbv_below_random": below, "refit": _refit_comparison(args, setup, *last_step)}


def _refit_comparison(args, setup, before_last, p_last, n_last, final):
    """Fine-tuning against refitting from scratch on the final nbv union, at equal error, both ways."""
    from autodecoder import update_field
    from benchmarks.surface_metrics import mean_surface_distance_difference, surface_distance_samples

    def samples_and_error(field):
        samples = surface_distance_samples(field.mesh(args.mesh_res), setup.mesh)
        return samples, 0.5 * float(samples[0].mean() + samples[1].mean())

    pts, nrm = final.training_points.numpy(), final.training_normals.numpy()
    t = time.perf_counter()
    refit = _fit(pts, nrm, args, args.fit_steps)
    t_refit = time.perf_counter() - t
    refit_samples, err_refit = samples_and_error(refit)
    print(f"refit from scratch on the final nbv union ({len(pts)} points): {t_refit:.1f}s, chamfer {err_refit:.5f}")
    equal = {"within_2se": None, "at_or_below": None}
    tunes = []
    for steps in (10, 25, 50, 100, 150, 300):
        t = time.perf_counter()
        tuned = update_field(before_last, p_last, n_last, steps=steps, seed=args.views)
        t_tune = time.perf_counter() - t
        tuned_samples, err = samples_and_error(tuned)
        diff, se = mean_surface_distance_difference(tuned_samples, refit_samples)
        print(f"  fine-tune of the last view, {steps} steps: {t_tune:.1f}s, chamfer {err:.5f} "
              f"(minus the refit's: {diff:+.5f} +- {se:.5f})")
        record = {"steps": steps, "seconds": t_tune, "chamfer": err, "difference": diff, "standard_error": se}
        tunes.append(record)
        if equal["within_2se"] is None and diff <= 2 * se:
            equal["within_2se"] = record
        if err <= err_refit:
            equal["at_or_below"] = record
            break
    refits = [(args.fit_steps, t_refit, err_refit)]
    for budget in (args.fit_steps // 4, args.fit_steps // 2):  # each its own cosine schedule
        t = time.perf_counter()
        short = _fit(pts, nrm, args, budget)
        refits.append((budget, time.perf_counter() - t, _chamfer(short, setup.mesh, args.mesh_res)))
    refits.sort()
    print("refits from scratch: " + ", ".join(f"{b} steps {t_:.1f}s chamfer {e:.5f}" for b, t_, e in refits))
    for record in tunes:
        match = next(((b, t_) for b, t_, e in refits if e <= record["chamfer"]), None)
        record.update(refit_steps=match and match[0], refit_seconds=match and match[1])
        print(f"  fine-tune {record['steps']:3d} steps {record['seconds']:5.1f}s chamfer {record['chamfer']:.5f}: " + (
            f"cheapest refit as good: {match[0]} steps {match[1]:.1f}s, {match[1] / record['seconds']:.1f}x the time"
            if match else "no refit above is as good"))
    for kind, label in (("within_2se", "within two standard errors of"), ("at_or_below", "at or below")):
        if equal[kind]:
            print(f"error {label} the refit's: fine-tuning {equal[kind]['seconds']:.1f}s ({equal[kind]['steps']} "
                  f"steps) vs refit {t_refit:.1f}s: {t_refit / equal[kind]['seconds']:.1f}x faster")
        else:
            print(f"fine-tuning did not reach an error {label} the refit's within 300 steps")
    return {"seconds": t_refit, "chamfer": err_refit, "equal_error_finetune": equal,
            "refit_budgets": [{"steps": b, "seconds": t_, "chamfer": e} for b, t_, e in refits],
            "finetune_vs_cheapest_refit": tunes}


def _chamfer_png(results, views, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    for strategy, r in results.items():
        ax.plot(range(1, views + 1), r["chamfer"], marker="o", label=strategy)
    ax.set_xlabel("views"), ax.set_ylabel("Chamfer to the true mesh"), ax.legend(), fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    print(f"wrote {path}")


# --- view-score ------------------------------------------------------------------------------------------------

def _view_score(args):
    import numpy as np
    import torch
    from scipy.spatial import cKDTree
    from scipy.stats import spearmanr

    from autodecoder.scanning.views import camera_score, part_sphere
    from benchmarks.table import format_table

    setup = _Setup(args)
    field, scanner = setup.field, setup.scanner
    s = 2.0 * float(field.config["lengthscale"]) / float(field.frame.scale)
    seen = torch.tensor(setup.p0, dtype=torch.float32)
    dirs = fibonacci_sphere(args.cameras)
    u0 = setup.first.camera_position - scanner.center
    angle = np.degrees(np.arccos(np.clip(dirs @ (u0 / np.linalg.norm(u0)), -1, 1)))
    tree = cKDTree(setup.p0)
    gain = np.zeros(len(dirs))
    for k, d in enumerate(dirs):
        try:
            new = scanner.scan(scanner.center + setup.radius * d, scanner.center, n_points=1000, noise=0.0, seed=k)
            gain[k] = np.mean(tree.query(new.points)[0] > s)
        except ValueError:  # nothing in view: no gain
            pass
    bands = {f"{a}-{a + 45}": float(gain[(angle >= a) & (angle < a + 45)].mean()) for a in (0, 45, 90, 135)}
    print(f"seed {args.seed}: oracle gain by angle from the first view: "
          + ", ".join(f"{a} deg {g:.2f}" for a, g in bands.items()))

    center, rad = part_sphere(field)
    pos = torch.tensor(center + dirs * 2.0 * rad, dtype=torch.float32)  # mid stand-off of next_best_views
    look = torch.tensor(center, dtype=torch.float32) - pos
    novelty = dict(observed=seen, observed_scale=s)
    variants = {
        "expected-point + novelty (default)": (field, novelty),
        "expected-point, no novelty": (field, {}),
        "distribution + novelty": (field, dict(novelty, hit_summary="distribution")),
        "P(hit) x novelty, no variance": (WithoutVariance(field), novelty),
        "gradient variance + novelty": (GradientVariance(field), novelty),
        "gradient variance, no novelty": (GradientVariance(field), {}),
    }
    figures = {"gain_by_angle": bands}
    if args.spsr:
        spsr = SpsrVariance(field, setup.p0, setup.n0)
        figures["spearman_variance_spsr"] = float(spearmanr(field.variance(spsr.grid_points), spsr.grid_var).statistic)
        print(f"Spearman of the learned variance with SPSR's on its grid: {figures['spearman_variance_spsr']:+.2f}")
        variants["SPSR variance + novelty"] = (spsr, novelty)
        variants["SPSR variance, no novelty"] = (spsr, {})
    best10 = float(np.sort(gain)[-10:].mean())
    rows = []
    for name, (scored, kw) in variants.items():
        with torch.no_grad():
            score = torch.cat([camera_score(scored, pos[i:i + 50], look[i:i + 50], center, rad, **kw)
                               for i in range(0, len(pos), 50)]).double().numpy()
        top = np.argsort(-score)[:10]
        rows.append({"variant": name, "spearman": float(spearmanr(score, gain).statistic),
                     "best_angle": float(angle[top[0]]), "best_gain": float(gain[top[0]]),
                     "top10_gain": float(gain[top].mean())})
    print(f"score variants (best 10 cameras' mean gain: {best10:.2f}):")
    print(format_table(rows, [("variant", "variant", ""), ("spearman", "Spearman(score, gain)", "+.2f"),
                              ("best_angle", "best camera deg", ".0f"), ("best_gain", "its gain", ".2f"),
                              ("top10_gain", "top-10 mean gain", ".2f")]))
    return {**figures, "best10_gain": best10, "variants": rows}
