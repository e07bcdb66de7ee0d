"""Registering a scan onto good scans' surface: coarse-to-fine point-to-plane ICP from the scan's own pose, with a
prior on how far the scan may move. Two motions: rigid (a part placed by hand) and scaled (a member of a product
family whose size varies, e.g. the same bracket in several lengths).

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

**Scaled** (``motion='scaled'``): the scan's points x move to R diag(exp s) (x - c) + c + t, c the target's
bounding-box centre, s a log scale along each axis of the frame (the fixture's or the CAD model's, along which a
family's members differ: a partial view's principal axes are not the part's, on a bracket they came out 45 degrees
off its length), with the rigid motion's prior on R and t and a Gaussian prior on s (``SCALE_PRIOR`` about the
expected size ``scale_centre``), s kept within ``SCALE_BOUND`` either way (:meth:`Aligner.scaled_state`). A view
that does not span a direction keeps the expected size there. Defects are local: a global scale cannot explain a
bump away, and the Huber weights keep a foreign object from pulling it. Used by :mod:`autodecoder.latent.family` to bring the scans of
a product family to one size before the latent model is trained on them (and every later scan before it is scored).

Inspection registers every scan it scores with ``align=True`` (:class:`inspection.config.InspectionConfig`), the
calibration scans included, onto :meth:`Aligner.from_scans` of the good training scans; the aligner is stored with
the calibration, so a scan is moved the same way whenever and wherever it is scored (:mod:`inspection.align` decides
when to).
"""
from contextlib import contextmanager

import numpy as np

from datasets.parallel import parallel_map
from datasets.validation import points_and_normals

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
SCALE_PRIOR = 0.25  # scaled motion: prior sd of each axis's log scale (a family's members differ by tens of %)
SCALE_STARTS = (0.7, 0.8, 0.9, 1.1, 1.25, 1.4)  # ... and started at these sizes along each axis it is estimated on
SCALE_BOUND = 1.5  # ... and kept within 1 / this and this (a view squashed flat along one axis fits a flat face)
SCALE_EXTENT = 0.5  # ... a scale is estimated only along an axis the scan spans at least this share of the target on
SCALED_LEVELS = (16.0, 8.0, 4.0, 2.0, 1.0)  # scaled motion: voxel sizes of its ICP (coarser first: a member 20 %
# longer has its ends a tenth of its length from the target's, beyond the finer levels' reach)
MOTIONS = ("rigid", "scaled")
ALIGN_SCANS = 64  # good training scans stacked as the target (subsampled to max_points): the more, the more of the part it covers
# good scans' poses spread (inspection's align='auto' registers scans; training moves them into one pose first) when
# registration lowers their residuals this much
AUTO_RATIO = 1.1
AUTO_SCANS = 12  # training scans registered onto the others to decide it


def _cloud(points, normals=None):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
    return pcd


class Aligner:
    """Registration (rigid or scaled, ``motion``) onto a fixed reference cloud.

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
    motion : {'rigid', 'scaled'}
        What a registration may do to a scan (module docstring).
    scale_centre : (3,) floats
        The scaled motion's prior mean of the log scales (the frame's axes): the size a scan is expected to need,
        which is also what a scan gets along an axis its view does not pin. 0: its own size. A family's common
        size sets it to the scale its typical member needed (:func:`autodecoder.latent.family.fit_family`).
    scale_axes : (3,) bools
        The axes of the frame along which the scaled motion may change a scan's size (the others keep
        ``scale_centre``): a family's, along which its members differ.
    """

    def __init__(self, target_points, target_normals=None, max_points=30000, levels=DEFAULT_LEVELS, seed=0,
                 iterations=30, owners=None, motion="rigid", scale_centre=(0.0, 0.0, 0.0),
                 scale_axes=(True, True, True)):
        import open3d as o3d

        if motion not in MOTIONS:
            raise ValueError(f"registration motion must be one of {MOTIONS}, got {motion!r}")

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
        self.settings = dict(max_points=max_points, levels=tuple(levels), seed=seed, iterations=int(iterations),
                             motion=motion, scale_centre=[float(v) for v in scale_centre],
                             scale_axes=[bool(v) for v in scale_axes])
        self.motion = motion
        self.scale_centre = np.asarray(scale_centre, dtype=np.float64).reshape(3)
        self.scale_axes = np.asarray(scale_axes, dtype=bool).reshape(3)
        self.target = _cloud(pts, target_normals)
        nn = np.asarray(self.target.compute_nearest_neighbor_distance())
        self.spacing = float(np.median(nn[nn > 0])) if np.any(nn > 0) else float(np.ptp(pts, 0).max()) / 100
        if target_normals is None:
            self.target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
        self.normals = np.asarray(self.target.normals)
        self.levels = tuple(levels)
        self.iterations = int(iterations)
        self.size = float(np.linalg.norm(np.ptp(pts, axis=0)))
        self.centre = (pts.min(0) + pts.max(0)) / 2
        self._tree = None

    @classmethod
    def from_scans(cls, scans, max_scans=ALIGN_SCANS, seed=0, motion="rigid", scale_centre=(0.0, 0.0, 0.0),
                   scale_axes=(True, True, True)):
        """The aligner onto up to ``max_scans`` of ``scans`` (good training scans, objects with ``points``,
        ``normals`` or None, ``name``), a seeded choice, each point owned by its scan's name."""
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
        return cls(np.concatenate(points), normals, seed=seed, owners=np.concatenate(owners), motion=motion,
                   scale_centre=scale_centre, scale_axes=scale_axes)

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
        return cls(points, normals, owners=d.pop("owners"), **d)  # (a record from before 'motion': rigid)

    def transform(self, points, normals=None):
        """The transform (4, 4; rigid or affine, the aligner's ``motion``) that moves ``points`` (m, 3) onto the
        reference (module docstring). ``normals`` are not needed: the residuals are along the target's normals."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(pts) == 0 or not np.isfinite(pts).all():
            raise ValueError(f"registration needs finite (m >= 1, 3) points, got {pts.shape}")
        self._kdtree()
        centre = pts.mean(0)
        if len(pts) > MAX_SOURCE:
            pts = pts[np.linspace(0, len(pts) - 1, MAX_SOURCE).round().astype(np.int64)]
        if self.motion == "scaled":  # a fixtured family member: from its place, no turned starts
            return self.scaled_matrix(*self.scaled_state(pts))
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
        ok, j = self._kdtree().nearest_within(points, bound)
        return ok, np.abs(np.einsum("ij,ij->i", points[ok] - self.points[j[ok]], self.normals[j[ok]]))

    def _kdtree(self):
        """The k-d tree over the target points (built once, on first use): a
        :class:`datasets.neighbours.NearestNeighbours`, the same neighbours as scipy's cKDTree in about two thirds of
        the time (the ICP's correspondences are most of a registration's)."""
        from datasets.neighbours import NearestNeighbours

        if self._tree is None:
            self._tree = NearestNeighbours(self.points)
        return self._tree

    def _residual(self, moved):
        """The median point-to-plane distance of ``moved`` (m, 3) to the target, a point with no target point
        within 3 spacings counting as 3 spacings (a start that slid off the part does not win by matching few)."""
        cap = 3.0 * self.spacing
        ok, distances = self.plane_distances(moved, cap)
        r = np.full(len(moved), cap)
        r[ok] = np.minimum(distances, cap)
        return float(np.median(r))

    def _matched(self, moved, voxel, minimum):
        """One ICP step's correspondences: the moved points with a target point within 3 ``voxel``s, their target
        normals and point-to-plane residuals, the residuals' robust scale and Huber weights; None when fewer than
        ``minimum`` points have one. Returns (ok (m,) bool, normals (k, 3), r (k,), scale, weights (k,))."""
        ok, j = self._tree.nearest_within(moved, 3.0 * voxel)
        if ok.sum() < minimum:
            return None
        n = self.normals[j[ok]]
        r = np.einsum("ij,ij->i", moved[ok] - self.points[j[ok]], n)
        scale = max(1.4826 * np.median(np.abs(r)), 0.1 * self.spacing)
        return ok, n, r, scale, np.minimum(1.0, HUBER * scale / np.maximum(np.abs(r), 1e-300))

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
                matched = self._matched(moved, voxel, 6)
                if matched is None:
                    break
                ok, n, r, scale, w = matched
                arm = moved[ok] - centre - t
                J = np.c_[np.cross(arm, n), n]  # d r / d (rotation about the centroid, translation)
                H = J.T @ (w[:, None] * J) + scale**2 * np.diag(prior)
                g = J.T @ (w * r) + scale**2 * prior * xi
                step = -np.linalg.solve(H, g)
                R, t = Rotation.from_rotvec(step[:3]).as_matrix() @ R, t + step[3:]
                xi = np.r_[Rotation.from_matrix(R).as_rotvec(), t]
                if np.linalg.norm(step[:3]) < 1e-7 and np.linalg.norm(step[3:]) < 1e-7 * self.size:
                    break
        return R, t

    def scaled_state(self, points, start=None):
        """The scaled motion's registration of ``points`` (m, 3) as its state (R (3, 3), t (3,), s (3,): the
        transform :meth:`scaled_matrix` makes of it), from ``start`` (a state; None: the scan where it is, at the
        expected size ``scale_centre``).

        The prior is on the state itself, i.e. on the scan's own place and its size relative to the expected one,
        wherever the search starts: a start only says where to look. The scale along an axis on which the scan
        spans less than ``SCALE_EXTENT`` of the target's extent is the expected one (``scale_centre``): a view that
        barely spans a direction does not say how long the part is along it (and a flat view squashed flat along
        its normal would fit any flat face). Local ICP from a single start ended in a wrong size on a bracket 1.5
        times as long as the target (x scale 0.72 and a y scale of 0.79 where 0.67 and 1 were right): like the
        rigid motion's turned starts, each free axis is also started at the sizes ``SCALE_STARTS`` times the
        start's, each start goes through the coarsest level, and the one
        with the smallest residual goes on through the finer ones."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(pts) == 0 or not np.isfinite(pts).all():
            raise ValueError(f"registration needs finite (m >= 1, 3) points, got {pts.shape}")
        self._kdtree()
        if len(pts) > MAX_SOURCE:
            pts = pts[np.linspace(0, len(pts) - 1, MAX_SOURCE).round().astype(np.int64)]
        spread = lambda p: np.subtract(*np.percentile(p, [99, 1], axis=0))  # noqa: E731 (per axis of the frame)
        free = (spread(pts) >= SCALE_EXTENT * spread(self.points)) & self.scale_axes
        levels = SCALED_LEVELS if self.levels == DEFAULT_LEVELS else self.levels
        R0, t0, s0 = ((np.eye(3), np.zeros(3), self.scale_centre.copy()) if start is None else
                      (np.array(x, dtype=np.float64) for x in start))
        s0 = np.where(free, s0, self.scale_centre)  # an axis the view does not pin has the expected size
        starts = [s0]
        for k in np.flatnonzero(free):
            for f in SCALE_STARTS:
                shifted = s0.copy()
                shifted[k] += np.log(f)
                starts.append(np.clip(shifted, -np.log(SCALE_BOUND), np.log(SCALE_BOUND)))
        best = None
        for s_start in starts:
            state = self._scaled_icp(pts, levels[:1], free, (R0, t0, s_start), START_ITERATIONS)
            T = self.scaled_matrix(*state)
            score = self._residual(pts @ T[:3, :3].T + T[:3, 3])
            if best is None or score < best[0]:
                best = (score, state)
        return self._scaled_icp(pts, levels[1:], free, best[1])

    def scaled_matrix(self, R, t, s):
        """The (4, 4) affine transform of the scaled motion's state (R, t, s) about this target's centre
        (:func:`scaled_affine`)."""
        return scaled_affine(self.centre, R, t, s)

    def _scaled_icp(self, pts, levels, free, state, iterations=None):
        """Robust point-to-plane ICP of the scaled motion x -> R diag(exp s) (x - c) + c + t (c: the target's box
        centre) with its prior, from ``state`` (R, t, s) through ``levels``, at most
        ``iterations`` (default the aligner's) at each; only the ``free`` (3,) bool axes' scales move. Returns the
        final (R, t, s)."""
        from scipy.spatial.transform import Rotation

        c = self.centre
        prior = np.r_[np.full(3, 1 / np.radians(PRIOR_DEGREES) ** 2), np.full(3, 1 / (PRIOR_SIZE * self.size) ** 2),
                      np.where(free, 1 / SCALE_PRIOR**2, 1e12)]
        R, t, s = (np.array(x, dtype=np.float64) for x in state)
        for level in levels:
            voxel = level * self.spacing
            src = _voxel_subsample(pts, voxel) if voxel > self.spacing else pts
            for _ in range(self.iterations if iterations is None else iterations):
                q = src - c  # about the target's centre
                scaled = q * np.exp(s)  # (m, 3), about c
                moved = scaled @ R.T + c + t
                matched = self._matched(moved, voxel, 9)
                if matched is None:
                    break
                ok, n, r, sigma, w = matched
                arm = scaled[ok] @ R.T
                d_scale = (n @ R) * scaled[ok]  # d r / d s_k = n . R e_k (scaled_k)
                J = np.c_[np.cross(arm, n), n, d_scale]
                theta = np.r_[Rotation.from_matrix(R).as_rotvec(), t, s - self.scale_centre]
                H = J.T @ (w[:, None] * J) + sigma**2 * np.diag(prior)
                g = J.T @ (w * r) + sigma**2 * prior * theta
                step = -np.linalg.solve(H, g)
                R, t = Rotation.from_rotvec(step[:3]).as_matrix() @ R, t + step[3:6]
                s = np.clip(s + step[6:], -np.log(SCALE_BOUND), np.log(SCALE_BOUND))
                if np.abs(step).max() < 1e-7:
                    break
        return R, t, s

    def align(self, points, normals=None):
        """``points`` (and ``normals``) moved onto the reference: returns (points (m, 3), normals or None, T (4, 4))."""
        T = self.transform(points, normals)
        p, n = apply_transform(T, points, normals)
        return p, n, T

    def align_scan(self, scan):
        """``scan`` moved onto the reference: a copy of a :class:`datasets.Scan` (the transform in
        ``extra['align']``, the sensor origin moved with it), or the moved (m, 3) points of an array."""
        if isinstance(scan, np.ndarray) or not hasattr(scan, "points"):
            return self.align(np.asarray(scan, dtype=np.float64).reshape(-1, 3))[0]
        return moved_by(scan, self.transform(scan.points))


def scaled_affine(centre, R, t, s):
    """The (4, 4) affine transform x -> R diag(exp s) (x - c) + c + t of a scaled motion's state (R (3, 3), t (3,),
    s (3,) log scales) about ``centre`` c (3,)."""
    c = np.asarray(centre, dtype=np.float64)
    L = R @ np.diag(np.exp(s))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = L, c + t - L @ c
    return T


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


@contextmanager
def registration_ticks(desc, show=True):
    """A progress bar counting registrations, for work made of them whose number depends on how soon rounds settle
    (:func:`register_group`, :func:`pose_spread`: no total; seconds each on scans of tens of thousands of points).
    Yields the ``tick`` those take (None when not ``show``)."""
    if not show:
        yield None
        return
    from tqdm.auto import tqdm

    with tqdm(desc=desc, unit=" registrations", dynamic_ncols=True) as bar:
        yield lambda: bar.update(1)


GROUP_ROUNDS = 6  # at most this many rounds of registering each training scan onto the others (register_group)
GROUP_SETTLED = 0.05  # ... stopping once a round moves the median scan by less than this many point spacings


def register_group(scans, rounds=GROUP_ROUNDS, seed=0, motion="rigid", return_transforms=False, tick=None):
    """Good scans moved into one common pose (``motion`` 'rigid': parts placed by hand) or one common pose and size
    ('scaled': the members of a product family): in each round every scan is registered onto all the others (as
    they stand after the previous round), until a round moves the median scan by less than ``GROUP_SETTLED`` point
    spacings (at most ``rounds``: the blur of the first target makes one round go only part of the way; on
    tests/inspection/test_align.py's corners 3 rounds settle 4 degrees), so that the target later scans are
    registered onto, and the per-location reference they are compared with, are as sharp as a fixture's rather than
    the blur of every placement (or every size). With 'scaled' every registration starts from the scan's size in
    the previous round (the first from the size its extent suggests) and is held by the prior to the scan's own
    size, so that the common size is the scans' typical size and does not drift (:func:`_scaled_group`). Returns copies of ``scans`` (the same order; :meth:`Aligner.align_scan`'s, the
    transform of all rounds in ``extra['align']`` for a :class:`datasets.Scan`), and with ``return_transforms``
    also each scan's transform (4, 4). Fewer than 3 scans: returned as they are (identity transforms). ``tick``
    (optional) is called once per registration of a scan, for a progress bar over work of unknown length."""
    scans = list(scans)
    if len(scans) < 3:
        return (scans, [np.eye(4) for _ in scans]) if return_transforms else scans
    names = [str(getattr(s, "name", "") or f"scan {i}") for i, s in enumerate(scans)]
    points = [np.asarray(points_and_normals(s)[0], dtype=np.float64).reshape(-1, 3) for s in scans]
    tick = tick or (lambda: None)
    if motion == "scaled":
        total = _scaled_group(points, names, rounds, seed, tick)
    else:
        total = _rigid_group(points, names, rounds, seed, tick)
    moved = [np.asarray(scan, dtype=np.float64).reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
             if isinstance(scan, np.ndarray) or not hasattr(scan, "points") else moved_by(scan, T)
             for scan, T in zip(scans, total)]
    return (moved, total) if return_transforms else moved


def _rigid_group(points, names, rounds, seed, tick):
    """:func:`register_group`'s rounds for the rigid motion; returns each scan's total transform (4, 4)."""
    points = list(points)
    total = [np.eye(4) for _ in points]
    for _ in range(int(rounds)):
        owners = np.concatenate([np.full(len(p), n) for p, n in zip(points, names)])
        target = Aligner(np.concatenate(points), owners=owners, seed=seed)
        # all onto the same round's poses, side by side (datasets.parallel)
        steps = parallel_map(lambda i: target.without(names[i]).transform(points[i]), range(len(points)), tick)
        motion_sizes = []
        for i, T in enumerate(steps):
            moved = points[i] @ T[:3, :3].T + T[:3, 3]
            motion_sizes.append(np.linalg.norm(moved - points[i], axis=1).mean())
            points[i], total[i] = moved, T @ total[i]
        if np.median(motion_sizes) < GROUP_SETTLED * target.spacing:
            break
    return total


def _scaled_group(points, names, rounds, seed, tick):
    """:func:`register_group`'s rounds for the scaled motion; returns each scan's total transform (4, 4).

    The union of all members' scans fits every scan as it is (its own member's other scans are in it), so
    registering each onto all the others from where it lies would move none. The first round therefore starts each
    scan at the size its extent suggests (:func:`_extent_factors`), a start and not a prior: every registration is
    of the scan's own points, with the prior on its own place and size (:meth:`Aligner.scaled_state`), so that a
    view whose extent misled the start (a view of a part's depth that sees less of it) but does not pin its size
    returns to its own size. From the second round on, the expected size (the prior's mean, and the size of an axis
    a view does not pin) is the mean over the scans of the log sizes the previous round gave them: the common size's
    typical member, rather than each view's own size (a mean, not a median: a family of shorter and longer members
    and none in between has its median in one of the two clusters)."""
    raw = list(points)
    factors, centre = _extent_factors(raw)
    moved = [centre + f * (p - centre) for p, f in zip(raw, factors)]
    states, total = [None] * len(raw), [None] * len(raw)
    expected = np.zeros(3)
    for _ in range(int(rounds)):
        owners = np.concatenate([np.full(len(p), n) for p, n in zip(moved, names)])
        target = Aligner(np.concatenate(moved), owners=owners, seed=seed, motion="scaled", scale_centre=expected)

        def register(i, target=target):  # onto the same round's target, side by side (datasets.parallel)
            aligner, start = target.without(names[i]), states[i]
            if start is None:  # the extent's size, about the scans' centre, in this aligner's parameters
                S = np.diag(factors[i])
                start = (np.eye(3), (np.eye(3) - S) @ (centre - aligner.centre), np.log(factors[i]))
            state = aligner.scaled_state(raw[i], start)
            return state, aligner.scaled_matrix(*state)

        steps = parallel_map(register, range(len(raw)), tick)
        motion_sizes = []
        for i, (state, T) in enumerate(steps):
            now = raw[i] @ T[:3, :3].T + T[:3, 3]
            motion_sizes.append(np.linalg.norm(now - moved[i], axis=1).mean())
            moved[i], states[i], total[i] = now, state, T
        expected = np.mean([state[2] for state, _ in steps], axis=0)
        if np.median(motion_sizes) < GROUP_SETTLED * target.spacing:
            break
    return total


def _extent_factors(points):
    """Each scan's starting size for :func:`_scaled_group`: along each axis of the frame, the median extent of the
    scans over its own (the 1st to 99th percentile of its points), 1 where that is beyond ``SCALE_BOUND`` either
    way (a view that does not span the part's length): a view that spans the part's length says how long it is.
    Returns ((n, 3) factors, the centre of all the scans' bounding box (3,), about which they scale)."""
    extent = np.array([np.subtract(*np.percentile(p, [99, 1], axis=0)) for p in points])  # (n, 3)
    lo = np.min([p.min(0) for p in points], axis=0)
    hi = np.max([p.max(0) for p in points], axis=0)
    factors = np.median(extent, axis=0) / np.maximum(extent, 1e-12)
    factors[(factors > SCALE_BOUND) | (factors < 1 / SCALE_BOUND)] = 1.0
    return factors, (lo + hi) / 2


def apply_transform(T, points, normals=None):
    """``points`` (m, 3) and ``normals`` (m, 3, optional) moved by ``T`` (4, 4, rigid or affine): points by T,
    normals by the inverse transpose of its linear part and made unit again (a stretched surface's normals turn
    towards the stretched direction's normal). Returns float64 (points, normals or None)."""
    L = np.asarray(T, dtype=np.float64)[:3, :3]
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3) @ L.T + np.asarray(T, dtype=np.float64)[:3, 3]
    if normals is None:
        return p, None
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3) @ np.linalg.inv(L)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return p, n


def moved_by(scan, T):
    """A copy of a scan-like object (a :class:`datasets.Scan`) moved by the transform ``T`` (4, 4; rigid or affine,
    :func:`apply_transform`): points, normals and sensor origin; the transform recorded in ``extra['align']`` when
    the scan has an ``extra`` dict (composed after one already there: the scan's total motion). A per-point deviation
    (a length along the normal n) is divided by |L^-T n| (L: T's linear part), its plane's stretch along it."""
    from dataclasses import replace

    points, normals = apply_transform(T, scan.points, getattr(scan, "normals", None))
    changes = dict(points=points, normals=normals)
    if getattr(scan, "point_deviation", None) is not None and normals is not None:
        inverse = np.linalg.inv(np.asarray(T, dtype=np.float64)[:3, :3])
        changes["point_deviation"] = scan.point_deviation / np.linalg.norm(scan.normals @ inverse, axis=1)
    if hasattr(scan, "sensor_origin"):
        origin = scan.sensor_origin
        changes["sensor_origin"] = (None if origin is None else
                                    apply_transform(T, np.asarray(origin, dtype=np.float64)[None])[0][0])
    if isinstance(getattr(scan, "extra", None), dict):
        before = scan.extra.get("align")
        changes["extra"] = {**scan.extra, "align": T if before is None else np.asarray(T) @ np.asarray(before)}
    return replace(scan, **changes)


def pose_spread(scans, max_scans=AUTO_SCANS, seed=0, tick=None):
    """How far good scans' poses spread: each of up to ``max_scans`` of them (evenly chosen) registered onto the
    others (:meth:`Aligner.from_scans` without it), the ratio of its median point-to-plane residual before and after
    the registration; returns the median ratio over those scans (1.0: registration changes nothing).

    Why this statistic: a residual ratio is free of the part's size and of the sensor's noise (both scale the
    residuals before and after alike), and a part in a fixture gives 1.0 within 1 % whatever its shape, while a
    few degrees of hand placement give 1.3 and more (docs/results.md#parts-placed-by-hand-alignment-in-the-calibration-issue-27).
    Fewer than 3 scans: 1.0 (nothing to compare). ``tick`` (optional) is called once per registered scan.
    """
    scans = list(scans)
    if len(scans) < 3:
        return 1.0
    aligner = Aligner.from_scans(scans, seed=seed)
    pick = np.unique(np.linspace(0, len(scans) - 1, min(max_scans, len(scans))).round().astype(int))

    def ratio(i):  # one scan's residual before over after its registration (None: too few matched points)
        others = aligner.without(str(getattr(scans[i], "name", "") or f"scan {i}"))
        pts = np.asarray(points_and_normals(scans[i])[0], dtype=np.float64).reshape(-1, 3)
        T = others.transform(pts)
        residuals = []
        for p in (pts, pts @ T[:3, :3].T + T[:3, 3]):
            ok, distances = others.plane_distances(p, 12.0 * others.spacing)
            if ok.sum() < 10:
                return None
            residuals.append(np.median(distances))
        return residuals[0] / residuals[1] if residuals[1] > 0 else None

    ratios = [r for r in parallel_map(ratio, pick, tick) if r is not None]  # side by side (datasets.parallel)
    return float(np.median(ratios)) if ratios else 1.0
