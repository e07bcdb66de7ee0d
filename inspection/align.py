"""Registering a scan into the model's frame: coarse-to-fine point-to-plane ICP from the scan's own pose, with a
prior on how far a part placed by hand lies from its place.

For parts not held in a fixture (a few degrees of pose error): the scan (source) is moved onto a reference cloud
(target) that covers the part better than one view does, e.g. the union of training scans or points sampled from
the model's mean surface. ICP starts from the scan's placement, with no centroid shift: a partial view's centroid is
not the part's, so shifting centroids would move a roughly placed scan away from its place; and from the placement
turned by ``START_DEGREES`` about each axis, the start with the smallest residual after the coarsest level going on
(from the placement alone, 2 of 16 good full-resolution bunny views placed by hand ended in a wrong pose). Large
rotations (tens of degrees and more) need a global registration first; this module does not attempt one.

Each Gauss-Newton step minimises the robust (Huber) point-to-plane residuals plus a Gaussian prior on the total
motion, rotation about the scan's centroid with standard deviation ``PRIOR_DEGREES`` and translation with
``PRIOR_SIZE`` of the target's size (a maximum a posteriori registration). Where the view pins the pose, thousands of
residuals outweigh the prior and it changes nothing; where it does not (a flat or cylindrical patch slides along
itself at no cost), plain ICP drifts by chance, and the prior keeps the scan where it was placed. The steps are plain
numpy on a k-d tree, so a scan is registered the same way on every run (open3d's ICP is not: on such a patch
repeated runs drifted to different places).

Inspection registers every scan it scores with ``align=True`` (:class:`inspection.config.InspectionConfig`), the
calibration scans included, onto :meth:`Aligner.from_scans` of the good training scans; the aligner is stored with
the calibration, so a scan is moved the same way whenever and wherever it is scored.
"""
import numpy as np

DEFAULT_LEVELS = (4.0, 2.0, 1.0)  # ICP voxel sizes in multiples of the target's point spacing, coarse to fine
PRIOR_DEGREES = 5.0  # the placement prior: rotation sd (degrees) ...
PRIOR_SIZE = 0.02  # ... and translation sd per axis, in target bounding-box diagonals (module docstring)
HUBER = 1.5  # residuals beyond this many robust standard deviations count linearly (stray points, defects)
MAX_SOURCE = 5000  # a scan with more points is registered by an evenly spread subset of this many (full-resolution
# scans: the pose of a rigid part needs a few thousand residuals, and the time grows with them)
# multi-start: ICP from the scan's placement converged to a wrong pose on 2 of 16 good full-resolution bunny views
# placed by hand (5 degrees, 2 %; median residual 3x the others'); started turned by 3-6 degrees about any axis it
# found the right one (docs/results.md#parts-placed-by-hand-alignment-in-the-calibration-issue-27)
START_DEGREES = 4.0
START_ITERATIONS = 10  # ICP iterations of each start at the coarsest level, before the best one goes on alone
ALIGN_SCANS = 64  # good training scans stacked as the target (subsampled to max_points): the more, the more of the part it covers


def _cloud(points, normals=None):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
    return pcd


class Aligner:
    """Rigid registration onto a fixed reference cloud.

    Parameters
    ----------
    target_points : (n, 3) array
        Reference points in the model's frame (e.g. several training scans stacked, or mean-surface samples).
    target_normals : (n, 3) array, optional
        Estimated when absent.
    max_points : int
        The reference is randomly subsampled to this many points (seeded).
    levels : sequence of float
        Voxel sizes of the coarse-to-fine ICP, in multiples of the reference's median point spacing.
    seed : int
    iterations : int
        ICP iterations at each level.
    owners : (n,) sequence of str, optional
        The name of the scan each target point came from: :meth:`without` leaves a scan's own points out, so that
        a calibration scan is not registered onto itself (:meth:`from_scans`).
    """

    def __init__(self, target_points, target_normals=None, max_points=30000, levels=DEFAULT_LEVELS, seed=0,
                 iterations=30, owners=None):
        import open3d as o3d

        pts = np.asarray(target_points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 10:
            raise ValueError(f"alignment reference must be (n >= 10, 3) points, got {pts.shape}")
        owners = np.full(len(pts), "") if owners is None else np.asarray(owners, dtype=str)
        if owners.shape != (len(pts),):
            raise ValueError(f"owners: one scan name per target point ({len(pts)}), got shape {owners.shape}")
        rng = np.random.default_rng(seed)
        if len(pts) > max_points:
            keep = np.sort(rng.choice(len(pts), max_points, replace=False))
            pts, owners = pts[keep], owners[keep]
            target_normals = None if target_normals is None else np.asarray(target_normals)[keep]
        self.points, self.owners = pts, owners
        self.settings = dict(max_points=max_points, levels=tuple(levels), seed=seed, iterations=int(iterations))
        self.target = _cloud(pts, target_normals)
        nn = np.asarray(self.target.compute_nearest_neighbor_distance())
        self.spacing = float(np.median(nn[nn > 0])) if np.any(nn > 0) else float(np.ptp(pts, 0).max()) / 100
        if target_normals is None:
            self.target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
        self.normals = np.asarray(self.target.normals)
        self.levels = tuple(levels)
        self.iterations = int(iterations)
        self.size = float(np.linalg.norm(np.ptp(pts, axis=0)))
        self._tree = None

    @classmethod
    def from_scans(cls, scans, max_scans=ALIGN_SCANS, seed=0):
        """The aligner onto up to ``max_scans`` of ``scans`` (good training scans, objects with ``points``,
        ``normals`` or None, ``name``), a seeded choice, each point owned by its scan's name."""
        from datasets.validation import points_and_normals

        scans = list(scans)
        if not scans:
            raise ValueError("alignment needs good scans to align onto, got none")
        rng = np.random.default_rng(seed)
        chosen = sorted(rng.choice(len(scans), min(max_scans, len(scans)), replace=False).tolist())
        points, normals, owners = [], [], []
        for i in chosen:
            p, n = points_and_normals(scans[i])
            points.append(np.asarray(p, dtype=np.float64).reshape(-1, 3))
            normals.append(None if n is None else np.asarray(n, dtype=np.float64).reshape(-1, 3))
            owners.append(np.full(len(points[-1]), str(getattr(scans[i], "name", "") or f"scan {i}")))
        normals = None if any(n is None for n in normals) else np.concatenate(normals)
        return cls(np.concatenate(points), normals, seed=seed, owners=np.concatenate(owners))

    def without(self, name):
        """This aligner without the target points of scan ``name`` (itself when it has none of them)."""
        keep = self.owners != str(name)
        if keep.all() or not name:
            return self
        return type(self)(self.points[keep], self.normals[keep], owners=self.owners[keep], **self.settings)

    def as_dict(self):
        """Plain values (torch tensors for the arrays) to store in a calibration record: the target and settings."""
        import torch

        return {"points": torch.from_numpy(self.points.astype(np.float32)),
                "normals": torch.from_numpy(self.normals.astype(np.float32)), "owners": self.owners.tolist(),
                **{k: list(v) if isinstance(v, tuple) else v for k, v in self.settings.items()}}

    @classmethod
    def from_dict(cls, d):
        """The aligner :meth:`as_dict` stored (the same target, hence the same registrations)."""
        d = dict(d)
        points, normals = np.asarray(d.pop("points"), dtype=np.float64), np.asarray(d.pop("normals"), np.float64)
        return cls(points, normals, owners=d.pop("owners"), **d)

    def transform(self, points, normals=None):
        """The rigid transform (4, 4) that moves ``points`` (m, 3) onto the reference (module docstring).
        ``normals`` are not needed: the residuals are along the target's normals."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(pts) == 0 or not np.isfinite(pts).all():
            raise ValueError(f"registration needs finite (m >= 1, 3) points, got {pts.shape}")
        self._kdtree()
        centre = pts.mean(0)
        if len(pts) > MAX_SOURCE:
            pts = pts[np.linspace(0, len(pts) - 1, MAX_SOURCE).round().astype(np.int64)]
        # multi-start: the placement itself, and turned by START_DEGREES about each axis either way, each through
        # START_ITERATIONS at the coarsest level; the one with the smallest residual then (the first of equals: the
        # placement itself) goes through the finer levels alone (where the time goes: more points)
        coarse, fine = self.levels[:1], self.levels[1:]
        best = None
        for start in _starts() if coarse else _starts()[:1]:
            R, t = self._icp(pts, centre, start, np.zeros(3), coarse, START_ITERATIONS)
            score = self._residual((pts - centre) @ R.T + centre + t)
            if best is None or score < best[0]:
                best = (score, R, t)
        R, t = self._icp(pts, centre, best[1], best[2], fine)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, centre + t - R @ centre
        return T

    def plane_distances(self, points, bound):
        """|point-to-plane distance| of each of ``points`` (m, 3) to its nearest target point's tangent plane, for
        the points with a target point within ``bound``: returns (which points have one (m,) bool, their distances).
        Builds the target's k-d tree on first use."""
        dist, j = self._kdtree().query(points, distance_upper_bound=bound)
        ok = np.isfinite(dist)
        return ok, np.abs(np.einsum("ij,ij->i", points[ok] - self.points[j[ok]], self.normals[j[ok]]))

    def _kdtree(self):
        """The k-d tree over the target points (built once, on first use)."""
        from scipy.spatial import cKDTree

        if self._tree is None:
            self._tree = cKDTree(self.points)
        return self._tree

    def _residual(self, moved):
        """The median point-to-plane distance of ``moved`` (m, 3) to the target, a point with no target point
        within 3 spacings counting as 3 spacings (a start that slid off the part does not win by matching few)."""
        cap = 3.0 * self.spacing
        ok, distances = self.plane_distances(moved, cap)
        r = np.full(len(moved), cap)
        r[ok] = np.minimum(distances, cap)
        return float(np.median(r))

    def _icp(self, pts, centre, R, t, levels, iterations=None):
        """Robust point-to-plane ICP with the placement prior through ``levels`` (voxel sizes in spacings, coarse to
        fine) from the motion p -> R (p - centre) + centre + t, at most ``iterations`` (default the aligner's) at
        each level: returns the final (R (3, 3), t (3,))."""
        from scipy.spatial.transform import Rotation

        # the prior's precision per squared radian / squared unit; times the residuals' variance below
        prior = np.r_[np.full(3, 1 / np.radians(PRIOR_DEGREES) ** 2), np.full(3, 1 / (PRIOR_SIZE * self.size) ** 2)]
        R, t = np.array(R, dtype=np.float64), np.array(t, dtype=np.float64)
        xi = np.r_[Rotation.from_matrix(R).as_rotvec(), t]  # the motion's rotation vector and translation (the prior's)
        for level in levels:
            voxel = level * self.spacing
            src = _voxel_subsample(pts, voxel) if voxel > self.spacing else pts
            local = src - centre
            for _ in range(self.iterations if iterations is None else iterations):
                moved = local @ R.T + centre + t
                dist, j = self._tree.query(moved, distance_upper_bound=3.0 * voxel)
                ok = np.isfinite(dist)
                if ok.sum() < 6:
                    break
                n = self.normals[j[ok]]
                r = np.einsum("ij,ij->i", moved[ok] - self.points[j[ok]], n)
                arm = moved[ok] - centre - t
                J = np.c_[np.cross(arm, n), n]  # d r / d (rotation about the centroid, translation)
                scale = max(1.4826 * np.median(np.abs(r)), 0.1 * self.spacing)
                w = np.minimum(1.0, HUBER * scale / np.maximum(np.abs(r), 1e-300))
                H = J.T @ (w[:, None] * J) + scale**2 * np.diag(prior)
                g = J.T @ (w * r) + scale**2 * prior * xi
                step = -np.linalg.solve(H, g)
                R, t = Rotation.from_rotvec(step[:3]).as_matrix() @ R, t + step[3:]
                xi = np.r_[Rotation.from_matrix(R).as_rotvec(), t]
                if np.linalg.norm(step[:3]) < 1e-7 and np.linalg.norm(step[3:]) < 1e-7 * self.size:
                    break
        return R, t

    def align(self, points, normals=None):
        """``points`` (and ``normals``) moved onto the reference: returns (points (m, 3), normals or None, T (4, 4))."""
        T = self.transform(points, normals)
        p = np.asarray(points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
        n = None if normals is None else np.asarray(normals, dtype=np.float64) @ T[:3, :3].T
        return p, n, T

    def align_scan(self, scan):
        """``scan`` moved onto the reference: a copy of a :class:`datasets.Scan` (the transform in
        ``extra['align']``, the sensor origin moved with it), or the moved (m, 3) points of an array."""
        if isinstance(scan, np.ndarray) or not hasattr(scan, "points"):
            return self.align(np.asarray(scan, dtype=np.float64).reshape(-1, 3))[0]
        return moved_by(scan, self.transform(scan.points))


def _starts():
    """The ICP's starting rotations: the identity, then +-START_DEGREES about x, y and z (7 rotation matrices)."""
    from scipy.spatial.transform import Rotation

    out = [np.eye(3)]
    for axis in range(3):
        for sign in (1.0, -1.0):
            rv = np.zeros(3)
            rv[axis] = sign * np.radians(START_DEGREES)
            out.append(Rotation.from_rotvec(rv).as_matrix())
    return out


def _voxel_subsample(points, voxel):
    """The first point (in input order) of each occupied cell of a grid of side ``voxel``: deterministic."""
    cells = np.floor(points / voxel).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    return points[np.sort(first)]


AUTO_RATIO = 1.1  # align='auto' registers scans when registration lowers the training scans' residuals this much
AUTO_SCANS = 12  # training scans registered onto the others to decide it


def pose_spread(scans, max_scans=AUTO_SCANS, seed=0):
    """How far good scans' poses spread: each of up to ``max_scans`` of them (evenly chosen) registered onto the
    others (:meth:`Aligner.from_scans` without it), the ratio of its median point-to-plane residual before and after
    the registration; returns the median ratio over those scans (1.0: registration changes nothing).

    Why this statistic: a residual ratio is free of the part's size and of the sensor's noise (both scale the
    residuals before and after alike), and a part in a fixture gives 1.0 within 1 % whatever its shape, while a
    few degrees of hand placement give 1.3 and more (docs/results.md#parts-placed-by-hand-alignment-in-the-calibration-issue-27).
    Fewer than 3 scans: 1.0 (nothing to compare).
    """
    from datasets.validation import points_and_normals

    scans = list(scans)
    if len(scans) < 3:
        return 1.0
    aligner = Aligner.from_scans(scans, seed=seed)
    pick = np.unique(np.linspace(0, len(scans) - 1, min(max_scans, len(scans))).round().astype(int))
    ratios = []
    for i in pick:
        scan = scans[i]
        others = aligner.without(str(getattr(scan, "name", "") or f"scan {i}"))
        pts = np.asarray(points_and_normals(scan)[0], dtype=np.float64).reshape(-1, 3)
        T = others.transform(pts)
        residuals = []
        for p in (pts, pts @ T[:3, :3].T + T[:3, 3]):
            ok, distances = others.plane_distances(p, 12.0 * others.spacing)
            if ok.sum() < 10:
                break
            residuals.append(np.median(distances))
        if len(residuals) == 2 and residuals[1] > 0:
            ratios.append(residuals[0] / residuals[1])
    return float(np.median(ratios)) if ratios else 1.0


GROUP_ROUNDS = 6  # at most this many rounds of registering each training scan onto the others (register_group)
GROUP_SETTLED = 0.05  # ... stopping once a round moves the median scan by less than this many point spacings


def register_group(scans, rounds=GROUP_ROUNDS, seed=0):
    """Good scans of parts placed by hand moved into one common pose: in each round every scan is registered onto
    all the others (as they stand after the previous round), until a round moves the median scan by less than
    ``GROUP_SETTLED`` point spacings (at most ``rounds``: the blur of the first target makes one round go only part
    of the way; on tests/inspection/test_align.py's corners 3 rounds settle 4 degrees), so that the target the scored
    scans are registered onto, and the per-location reference they are compared with, are as sharp as a fixture's rather than the blur
    of every placement. Returns copies of ``scans`` (the same order; :meth:`Aligner.align_scan`'s, the transform of
    all rounds in ``extra['align']`` for a :class:`datasets.Scan`). Fewer than 3 scans: returned as they are."""
    from datasets.validation import points_and_normals

    scans = list(scans)
    if len(scans) < 3:
        return scans
    names = [str(getattr(s, "name", "") or f"scan {i}") for i, s in enumerate(scans)]
    points = [np.asarray(points_and_normals(s)[0], dtype=np.float64).reshape(-1, 3) for s in scans]
    total = [np.eye(4) for _ in scans]
    for _ in range(int(rounds)):
        owners = np.concatenate([np.full(len(p), n) for p, n in zip(points, names)])
        target = Aligner(np.concatenate(points), owners=owners, seed=seed)
        steps = [target.without(n).transform(p) for p, n in zip(points, names)]  # all onto the same round's poses
        motion = []
        for i, T in enumerate(steps):
            moved = points[i] @ T[:3, :3].T + T[:3, 3]
            motion.append(np.linalg.norm(moved - points[i], axis=1).mean())
            points[i], total[i] = moved, T @ total[i]
        if np.median(motion) < GROUP_SETTLED * target.spacing:
            break
    return [np.asarray(scan, dtype=np.float64).reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
            if isinstance(scan, np.ndarray) or not hasattr(scan, "points") else moved_by(scan, T)
            for scan, T in zip(scans, total)]


def moved_by(scan, T):
    """A copy of a scan-like object (a :class:`datasets.Scan`) moved by the rigid transform ``T`` (4, 4): points,
    normals and sensor origin; the transform recorded in ``extra['align']`` when the scan has an ``extra`` dict."""
    from dataclasses import replace

    R, t = T[:3, :3], T[:3, 3]
    normals = getattr(scan, "normals", None)
    changes = dict(points=np.asarray(scan.points, dtype=np.float64) @ R.T + t,
                   normals=None if normals is None else np.asarray(normals, dtype=np.float64) @ R.T)
    if hasattr(scan, "sensor_origin"):
        origin = scan.sensor_origin
        changes["sensor_origin"] = None if origin is None else R @ np.asarray(origin, dtype=np.float64) + t
    if isinstance(getattr(scan, "extra", None), dict):
        changes["extra"] = {**scan.extra, "align": T}
    return replace(scan, **changes)
