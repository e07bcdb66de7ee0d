"""The next good scans to take: sensor positions whose good scans would cover the surface the good scans missed.

A model trained on few good scans leaves surface uncovered (:mod:`inspection.coverage`), and a scan whose evidence
lies there is told ``'uncertain'``. Which good scans would fix that is the paper's next-best-view question, given a
user's job: among candidate sensor positions on a sphere around the part (the good scans' own stand-off), choose
greedily the one that sees most of the still uncovered target surface, then the next, and so on (a greedy set
cover, within 1 - 1/e of the best choice of ``n`` views).

The target surface is what should be covered: the points of scans the user scores (``nsspr-inspect coverage --data``;
their uncovered points are what test views see and training did not), or, with no scans, the surface of the model's
mean shape (the zero level set of the field at the mean training code). A target point is seen from a position when
it faces it (incidence below ``MAX_INCIDENCE_DEG``, the scanner's grazing limit) and is not hidden behind other
surface (open3d's hidden point removal over the targets and the good scans' points).

Positions are in the model's frame (the collection frame of the training scans), each looking at the part's centre:
a fixtured part's sensor goes there; a part turned by hand is turned so that the sensor sees it from there.
"""
from dataclasses import dataclass

import numpy as np

from .coverage import covered_points

MAX_INCIDENCE_DEG = 75.0  # a surface seen more obliquely than this returns few, noisy points
CANDIDATES = 256  # candidate sensor positions on the sphere
MAX_TARGETS = 6000  # uncovered target points planned with (a seeded subsample beyond)
MAX_OCCLUDERS = 20000  # surface points that can hide targets (a seeded subsample beyond)
MESH_RESOLUTION = 64  # marching-cubes samples per side for the mean shape
MESH_TARGETS = 8000  # points sampled on the mean shape


@dataclass
class ProposedView:
    """One proposed good scan: the sensor at ``position`` looking at ``look_at`` (model frame, (3,) each); it would
    cover ``gain`` target points that no good scan nor earlier proposal covers, ``share`` of the uncovered ones."""

    position: np.ndarray
    look_at: np.ndarray
    gain: int
    share: float

    def as_dict(self):
        return {"position": [float(v) for v in self.position], "look_at": [float(v) for v in self.look_at],
                "gain": int(self.gain), "share": float(self.share)}


@dataclass
class CoveragePlan:
    """The coverage of a target surface and the views proposed to complete it.

    Attributes
    ----------
    points, normals : (m, 3) arrays
        The target surface's points and outward normals (model frame).
    covered : (m,) bool
        Covered by the good scans (:func:`inspection.coverage.covered_points`).
    views : list of ProposedView
        In the order chosen (from a seeded subsample of ``MAX_TARGETS`` uncovered points when there are more).
    first_view : (m,) int
        For each uncovered point, the index of the first proposed view that sees it; -1 otherwise.
    radius, standoff : float
        The coverage radius and the sensors' distance from ``center`` (model units).
    center : (3,) array
    source : str
        Where the target surface came from, in words.
    """

    points: np.ndarray
    normals: np.ndarray
    covered: np.ndarray
    views: list
    first_view: np.ndarray
    radius: float
    standoff: float
    center: np.ndarray
    source: str = ""

    @property
    def uncovered_share(self):
        return float(np.mean(~self.covered)) if len(self.covered) else 0.0

    @property
    def remaining_share(self):
        """The share of the uncovered points that no proposed view sees either."""
        todo = ~self.covered
        return float(np.mean(self.first_view[todo] < 0)) if todo.any() else 0.0

    def as_dict(self):
        return {"source": self.source, "points": int(len(self.points)), "uncovered_share": self.uncovered_share,
                "remaining_share_after_views": self.remaining_share, "radius": float(self.radius),
                "standoff": float(self.standoff), "center": [float(v) for v in self.center],
                "views": [v.as_dict() for v in self.views]}


def sphere_directions(n):
    """(n, 3) unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    if n < 1:
        raise ValueError(f"need at least one candidate direction, got {n}")
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    azimuth = np.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(np.clip(1 - z ** 2, 0, None))
    return np.c_[r * np.cos(azimuth), r * np.sin(azimuth), z]


def seen_from(position, points, normals, occluders, max_incidence_deg=MAX_INCIDENCE_DEG):
    """(m,) bool: the target ``points`` (with outward ``normals``) a sensor at ``position`` sees: facing it within
    ``max_incidence_deg`` and not hidden by the ``occluders`` (k, 3) or each other (open3d's hidden point removal,
    Katz et al. 2007, over both)."""
    import open3d as o3d

    position = np.asarray(position, dtype=np.float64)
    to_sensor = position - points
    distance = np.linalg.norm(to_sensor, axis=1)
    facing = np.einsum("mj,mj->m", normals, to_sensor) > np.cos(np.radians(max_incidence_deg)) * distance * \
        np.linalg.norm(normals, axis=1)
    if not facing.any():
        return facing
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.vstack([points, occluders])))
    extent = float(np.linalg.norm(np.ptp(np.vstack([points, occluders, position[None]]), axis=0)))
    _, visible = cloud.hidden_point_removal(position.tolist(), 100.0 * extent)
    visible = np.asarray(visible, dtype=np.int64)
    seen = np.zeros(len(points), dtype=bool)
    seen[visible[visible < len(points)]] = True
    return facing & seen


def plan_views(reference, points, normals, radius, n_views=4, center=None, standoff=None, candidates=CANDIDATES,
               max_incidence_deg=MAX_INCIDENCE_DEG, seed=0, source="", progress=False):
    """The coverage of a target surface by the good scans and ``n_views`` sensor positions that cover most of the rest.

    Parameters
    ----------
    reference : inspection.reference.LocalReference
        The good scans' surface (a calibrated inspector's ``reference_``).
    points, normals : (m, 3) arrays
        The target surface (model frame; outward normals).
    radius : float
        The coverage radius (:func:`inspection.coverage.coverage_radius`).
    n_views : int >= 1
    center : (3,) array, optional
        What the sensors look at (default: the centre of the bounding box of the good surface and the targets).
    standoff : float, optional
        The sensors' distance from ``center`` (default: 2 x that bounding box's diagonal, about where the virtual
        scanner stands; the coverage command passes the scans' own).
    candidates : int
        Candidate positions on the sphere.
    seed : int
        The subsamples of targets and occluders.

    Returns
    -------
    CoveragePlan
    """
    from tqdm import tqdm

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0 or normals.shape != points.shape or not np.isfinite(points).all():
        raise ValueError(f"plan_views needs finite target points with one normal each, got {points.shape} points "
                         f"and {normals.shape} normals")
    if int(n_views) != n_views or n_views < 1:
        raise ValueError(f"n_views must be a whole number >= 1, got {n_views!r}")
    index, _ = reference.distinct_surface()
    good = np.asarray(index.data, dtype=np.float64)
    lo, hi = np.minimum(good.min(0), points.min(0)), np.maximum(good.max(0), points.max(0))
    center = (lo + hi) / 2 if center is None else np.asarray(center, dtype=np.float64).reshape(3)
    standoff = 2.0 * float(np.linalg.norm(hi - lo)) if standoff is None else float(standoff)
    covered = covered_points(reference, points, normals, radius)
    rng = np.random.default_rng(seed)
    todo = np.flatnonzero(~covered)
    if len(todo) > MAX_TARGETS:
        todo = np.sort(rng.choice(todo, MAX_TARGETS, replace=False))
    occluders = good if len(good) <= MAX_OCCLUDERS else good[rng.choice(len(good), MAX_OCCLUDERS, replace=False)]
    positions = center + standoff * sphere_directions(candidates)
    first_view = np.full(len(points), -1, dtype=np.int64)
    views = []
    if len(todo):
        sees = np.stack([seen_from(p, points[todo], normals[todo], occluders, max_incidence_deg)
                         for p in tqdm(positions, desc="candidate views", unit="view", disable=not progress)])
        open_ = np.ones(len(todo), dtype=bool)
        for k in range(int(n_views)):
            gains = (sees & open_).sum(1)
            best = int(np.argmax(gains))
            if gains[best] == 0:
                break
            new = sees[best] & open_
            first_view[todo[new]] = k
            open_ &= ~new
            views.append(ProposedView(positions[best], center.copy(), int(gains[best]), float(gains[best] / len(todo))))
        # every uncovered point, not only the planned subsample: the first chosen view that sees it
        rest = np.flatnonzero(~covered)
        for k in reversed(range(len(views))):
            first_view[rest[seen_from(views[k].position, points[rest], normals[rest], occluders,
                                      max_incidence_deg)]] = k
    return CoveragePlan(points, normals, covered, views, first_view, float(radius), standoff, center, source)


def mean_shape_targets(model, count=MESH_TARGETS, resolution=MESH_RESOLUTION, seed=0):
    """(points, normals) sampled evenly on the model's mean shape: the zero level set of its field at the mean
    training code (model frame; outward normals). A ValueError when the model has no mean code or its field no
    surface."""
    import trimesh

    code = getattr(model, "code_mean", None)
    if code is None or not hasattr(model, "field"):
        raise ValueError("the model has no mean training code to take its mean shape from: give scans (--data)")
    mesh = model.field(code).mesh(resolution)  # in the coordinates the field reads: the model's frame
    points, faces = trimesh.sample.sample_surface_even(mesh, count, seed=seed)
    return np.asarray(points, dtype=np.float64), np.asarray(mesh.face_normals[faces], dtype=np.float64)
