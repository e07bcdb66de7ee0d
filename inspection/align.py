"""Registering a scan into the model's frame: coarse-to-fine point-to-plane ICP (open3d) from the scan's own pose.

For parts not held in a fixture (a few degrees of pose error): the scan (source) is moved onto a reference cloud
(target) that covers the part better than one view does, e.g. the union of training scans or points sampled from
the model's mean surface. ICP starts from the identity, with no centroid shift: a partial view's centroid is not
the part's, so shifting centroids would move a roughly placed scan away from its place. Large rotations (tens of
degrees and more) need a global registration first; this module does not attempt one.
"""
from pathlib import Path

import numpy as np

from .errors import InspectionError
from .loading import COLLECTION_SUFFIXES

DEFAULT_LEVELS = (4.0, 2.0, 1.0)  # ICP voxel sizes in multiples of the target's point spacing, coarse to fine


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
    """

    def __init__(self, target_points, target_normals=None, max_points=30000, levels=DEFAULT_LEVELS, seed=0,
                 iterations=30):
        import open3d as o3d

        pts = np.asarray(target_points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 10:
            raise ValueError(f"alignment reference must be (n >= 10, 3) points, got {pts.shape}")
        rng = np.random.default_rng(seed)
        if len(pts) > max_points:
            keep = rng.choice(len(pts), max_points, replace=False)
            pts = pts[keep]
            target_normals = None if target_normals is None else np.asarray(target_normals)[keep]
        self.target = _cloud(pts, target_normals)
        nn = np.asarray(self.target.compute_nearest_neighbor_distance())
        self.spacing = float(np.median(nn[nn > 0])) if np.any(nn > 0) else float(np.ptp(pts, 0).max()) / 100
        if target_normals is None:
            self.target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
        self.levels = tuple(levels)
        self.iterations = int(iterations)
        self._targets = {}

    def _target_at(self, voxel):
        if voxel not in self._targets:
            self._targets[voxel] = self.target.voxel_down_sample(voxel) if voxel > self.spacing else self.target
        return self._targets[voxel]

    def transform(self, points, normals=None):
        """The rigid transform (4, 4) that moves ``points`` (m, 3) onto the reference."""
        import open3d as o3d

        reg = o3d.pipelines.registration
        source = _cloud(points, normals)
        if normals is None:
            source.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
        # start from the identity: a fixture-less part is still roughly in place; a centroid shift would be biased
        # by the view (a partial scan's centroid is not the part's)
        T = np.eye(4)
        for level in self.levels:
            voxel = level * self.spacing
            src = source.voxel_down_sample(voxel) if voxel > self.spacing else source
            result = reg.registration_icp(src, self._target_at(voxel), 3.0 * voxel, T,
                                          reg.TransformationEstimationPointToPlane(),
                                          reg.ICPConvergenceCriteria(max_iteration=self.iterations))
            T = result.transformation
        return T

    def align(self, points, normals=None):
        """``points`` (and ``normals``) moved onto the reference: returns (points (m, 3), normals or None, T (4, 4))."""
        T = self.transform(points, normals)
        p = np.asarray(points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
        n = None if normals is None else np.asarray(normals, dtype=np.float64) @ T[:3, :3].T
        return p, n, T

    def align_scan(self, scan):
        """A copy of ``scan`` (a datasets.Scan) moved onto the reference; the transform goes in ``extra['align']``."""
        from dataclasses import replace

        p, n, T = self.align(scan.points, scan.normals)
        origin = None if scan.sensor_origin is None else (T[:3, :3] @ scan.sensor_origin + T[:3, 3])
        return replace(scan, points=p, normals=n, sensor_origin=origin, extra={**scan.extra, "align": T})


def make_aligner(handle, data_info, reference=None, seed=0):
    """The :class:`Aligner` of ``score --align`` onto: ``reference`` (a collection: its good training scans; a cloud file),
    else the good training scans of the data's collection, else the model's mean surface."""
    def from_collection(path):
        from datasets import ScanCollection

        with ScanCollection(path) as c:
            idx = c.select(split="train", label="good")
            if not idx:
                idx = c.select(label="good")
            rng = np.random.default_rng(seed)
            idx = sorted(rng.choice(idx, min(8, len(idx)), replace=False).tolist()) if idx else []
            scans = c.read_many(idx)
        if not scans:
            raise InspectionError(f"{path}: no good scans to align against")
        return (np.concatenate([s.points for s in scans]), np.concatenate([s.normals for s in scans]))

    if reference is not None:
        ref = Path(reference)
        if ref.suffix.lower() in COLLECTION_SUFFIXES:
            pts, nrm = from_collection(ref)
        else:
            from datasets import read_cloud

            pts, nrm = read_cloud(ref)
        return Aligner(pts, nrm, seed=seed)
    if data_info.get("kind") == "collection":
        from datasets import ScanCollection

        with ScanCollection(data_info["source"]) as c:
            has_train = bool(c.select(split="train", label="good"))
        if has_train:
            return Aligner(*from_collection(data_info["source"]), seed=seed)
    return Aligner(*handle.reference_points(seed=seed), seed=seed)
