"""How much the members of a family differ in shape, place by place: the record a calibration keeps
(:mod:`inspection.member_surface` measures it and carries the good surface by it)."""
from dataclasses import dataclass

import numpy as np

# the members differ in shape when they do over at least this share of the anchors: the partial views of one part
# differ over a few % (fandisk, the cup, the real bunny), members bent 6-12 and 24-48 degrees either way over a
# quarter to a half (docs/results_archive.md, issue 52); below it, the good points' term is a part of one shape's,
# at its cost
MEMBER_SHARE = 0.15
# anchors averaged per point when the members' variance is read at a point
MEMBER_NEIGHBOURS = 4


@dataclass
class MemberSpread:
    """How much a family's members differ, at anchor points of the good surface (model frame).

    Attributes
    ----------
    anchors : (a, 3) float32 array
    between : (a,) float32 array
        The members' variance tau^2 of the surface's place along its normal (squared world units, >= 0).
    """

    anchors: np.ndarray
    between: np.ndarray

    def __post_init__(self):
        self.anchors = np.asarray(self.anchors, dtype=np.float32).reshape(-1, 3)
        self.between = np.asarray(self.between, dtype=np.float32).reshape(-1)
        if len(self.anchors) != len(self.between) or len(self.anchors) == 0:
            raise ValueError(f"a member spread needs one variance per anchor, got {len(self.anchors)} anchors and "
                             f"{len(self.between)} variances")
        if not (np.isfinite(self.anchors).all() and np.isfinite(self.between).all() and (self.between >= 0).all()):
            raise ValueError("a member spread needs finite anchors and finite variances >= 0")
        self._index = self._moving = None

    @property
    def share(self):
        """The share of the anchors where the members differ (variance > 0), 0..1."""
        return float(np.mean(self.between > 0))

    @property
    def differs(self):
        """Whether the members differ in shape: over at least ``MEMBER_SHARE`` of the anchors. Then the good points'
        term compares a scan with the good surface carried to its member; else with the good points as they lie."""
        return self.share >= MEMBER_SHARE

    @property
    def extent(self):
        """How far a member's surface may lie from the good points (world units): 3 standard deviations of the
        members' variance where it is widest (its 99th percentile over the anchors). A scanned point this much
        farther from the good points than their neighbourhood may still be among the members."""
        return 3.0 * float(np.sqrt(np.quantile(self.between, 0.99)))

    def moving_index(self):
        """A k-d tree (``scipy.spatial.cKDTree``) over the anchors where the members differ (variance > 0), built
        once: every scan asks which of its points lie near them."""
        from scipy.spatial import cKDTree

        if self._moving is None:
            self._moving = cKDTree(self.anchors[self.between > 0])
        return self._moving

    def at(self, points):
        """tau^2 (m,) at (m, 3) points: the mean over their ``MEMBER_NEIGHBOURS`` nearest anchors."""
        from datasets.neighbours import NearestNeighbours

        if self._index is None:
            self._index = NearestNeighbours(self.anchors)
        k = min(MEMBER_NEIGHBOURS, self._index.n)
        _, idx = self._index.query(np.asarray(points, dtype=np.float64).reshape(-1, 3), k)
        return self.between[idx.reshape(len(idx), -1)].astype(np.float64).mean(1)

    def as_dict(self):
        """Plain values (torch tensors) to store in a calibration record."""
        import torch

        return {"anchors": torch.from_numpy(self.anchors.copy()), "between": torch.from_numpy(self.between.copy())}

    @classmethod
    def from_dict(cls, d):
        """The spread :meth:`as_dict` stored, None for None; a ValueError for anything else."""
        if d is None:
            return None
        try:
            return cls(np.asarray(d["anchors"], dtype=np.float32), np.asarray(d["between"], dtype=np.float32))
        except (KeyError, TypeError, IndexError) as exc:
            raise ValueError(f"damaged member_spread ({type(exc).__name__}: {exc})") from None
