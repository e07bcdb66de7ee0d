"""Single-cloud fits (``fit_cloud``): the grid default and the paper's SIRENs against open3d's screened Poisson, the
exact minimiser of the mean loss, the covariance loss's throughput, and real range scans.

Modes (``--mode``), a module each:

``grid`` (default, :mod:`benchmarks.suites.fit.grid`)
    ``fit_cloud``'s default representation on 20k points sampled on ``--mesh`` (fandisk), per ``--variants``
    entry: fit time, the mean surface's Chamfer distance (marched at ``--resolution``) next to open3d's depth-8
    screened Poisson of the same cloud, the variance's Spearman correlation with gpytoolbox's stochastic Poisson
    variance on its 20^3 grid. The sweep behind the grid's defaults.
``siren`` (:mod:`benchmarks.suites.fit.siren`)
    The paper's SIRENs on the same cloud: fit time, Chamfer next to open3d, where the error lies, the variance's
    Spearman correlation, ``slice.png`` in ``--out``.
``target-limit`` (:mod:`benchmarks.suites.fit.target_limit`)
    The exact minimiser of ``fit_cloud``'s mean loss on a grid per lengthscale and resolution, and SIRENs regressed
    onto it (``--regress-steps``).
``d-operator`` (:mod:`benchmarks.suites.fit.d_operator`)
    Covariance-loss throughput: the pair SIREN's D c by autograd and by its mixed jet, the feature covariance.
``real-scans`` (:mod:`benchmarks.suites.fit.real_scans`)
    The grid and the SIREN at their defaults on single real range scans.

The shared cloud, open3d's reconstruction and the comparisons are :mod:`benchmarks.suites.fit.cloud`'s. The Chamfer
distance is ``benchmarks.surface_metrics.mean_surface_distance`` throughout.
"""
from benchmarks.cache import CACHE
from benchmarks.suites.fit.cloud import OUT

DESCRIPTION = ("single-cloud fits: grid default and SIREN vs open3d's Poisson, the mean loss's exact minimiser, "
               "covariance-loss throughput, real range scans")
MODES = ("grid", "siren", "target-limit", "d-operator", "real-scans")


def _int_list(text):
    return [int(v) for v in text.split(",") if v.strip()]


def _float_list(text):
    return [float(v) for v in text.split(",") if v.strip()]


def add_arguments(parser):
    parser.add_argument("--mode", choices=MODES, default="grid", help="what to measure (default: %(default)s)")
    cloud = parser.add_argument_group("the sampled cloud (grid, siren, target-limit)")
    cloud.add_argument("--mesh", default="fandisk", help="fandisk, bunny, a built-in part or a mesh file")
    cloud.add_argument("--points", type=int, default=20_000)
    cloud.add_argument("--seed", type=int, default=0, help="draws the points and seeds the fits")
    cloud.add_argument("--resolution", type=int, default=192, help="marching-cubes grid of the mean surface")
    cloud.add_argument("--out", default=None, help=f"written files (default: {OUT})")
    cloud.add_argument("--cache", default=CACHE, help="gpytoolbox's variance solves (default: %(default)s)")
    grid = parser.add_argument_group("grid")
    grid.add_argument("--variants", default="", help="';'-separated variants (see benchmarks/suites/fit/grid.py)")
    grid.add_argument("--reference-field", default=None,
                      help="field whose variance the Spearman correlation uses when gpytoolbox is not installed")
    siren = parser.add_argument_group("siren")
    siren.add_argument("--steps", type=int, default=None, help="Adam steps (default: fit_cloud's)")
    siren.add_argument("--width", type=int, default=None, help="SIREN width (default: fit_cloud's)")
    siren.add_argument("--depth", type=_int_list, default=None,
                       help="SIREN hidden layers (siren; default: fit_cloud's), or a list of sine-layer counts "
                            "(d-operator; default 3, the paper's 5: --depth 3,5)")
    siren.add_argument("--h-factor", type=float, default=None,
                       help="kernel lengthscale / point spacing (default: fit_cloud's)")
    siren.add_argument("--omega0", type=float, default=None, help="SIREN first-layer frequency (default: fit_cloud's)")
    siren.add_argument("--covariance-every", type=int, default=None,
                       help="one covariance step every this many mean steps (default: fit_cloud's)")
    siren.add_argument("--no-gpytoolbox", action="store_true", help="skip the variance's comparison")
    siren.add_argument("--quiet", action="store_true", help="no progress bar")
    siren.add_argument("--field", default=None, help="load this fitted field instead of fitting (e.g. the field.pt "
                       "an earlier run wrote)")
    limit = parser.add_argument_group("target-limit")
    limit.add_argument("--h-factors", type=_float_list, default=[1.0, 1.5, 2.0],
                       help="kernel lengthscales / point spacing (default: 1,1.5,2)")
    limit.add_argument("--resolutions", type=_int_list, default=[128, 192], help="grid nodes per side")
    limit.add_argument("--screening-weight", type=float, default=None, help="lambda_S (default: the library's)")
    limit.add_argument("--regress-steps", type=_int_list, default=[],
                       help="comma-separated Adam step counts: fit the mean SIREN to the finest grid's minimiser")
    throughput = parser.add_argument_group("d-operator")
    throughput.add_argument("--batch", type=int, default=512, help="points (feature net) / pairs (pair net) per step")
    throughput.add_argument("--widths", type=_int_list, default=[128, 256, 512])
    throughput.add_argument("--latent", type=_int_list, default=[0, 128], help="latent code dimensions (0: none)")
    throughput.add_argument("--features", type=int, default=128, help="K of the feature covariance")
    throughput.add_argument("--seconds", type=float, default=3.0, help="wall time per measurement")
    real = parser.add_argument_group("real-scans")
    real.add_argument("--views", default="bun000,bun090", help="comma-separated file stems in --source")
    real.add_argument("--source", default=None, help="folder of the scans (default: ../shared/realscans/bunny)")


def run(args):
    """The mode's own ``run``: its table printed, its figures returned."""
    from benchmarks.suites.fit import d_operator, grid, real_scans, siren, target_limit

    return {"grid": grid, "siren": siren, "target-limit": target_limit, "d-operator": d_operator,
            "real-scans": real_scans}[args.mode].run(args)
