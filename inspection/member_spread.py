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
    low, high : (a,) float32 arrays or None
        The trained members' envelope at each anchor: the least and the greatest first-order distance of the anchor
        to a good scan's own field, over every reference scan's field (world units; NaN where fewer than
        ``inspection.member_surface.MEMBER_MIN_SCANS`` scans saw the anchor). A scan's member whose field lies beyond
        it over much of the surface where the members differ is outside the trained family
        (:mod:`inspection.family_range`).
        None (a calibration of version 5 or older): not measured, and no scan is told it lies outside.
    own : (a,) float32 array or None
        The reference's own spread s_ref at each anchor (world units): how far good scans' fields miss their own
        points there, the scale the envelope's margin is measured in. With ``low`` and ``high``.
    """

    anchors: np.ndarray
    between: np.ndarray
    low: np.ndarray = None
    high: np.ndarray = None
    own: np.ndarray = None

    def __post_init__(self):
        self.anchors = np.asarray(self.anchors, dtype=np.float32).reshape(-1, 3)
        self.between = np.asarray(self.between, dtype=np.float32).reshape(-1)
        if len(self.anchors) != len(self.between) or len(self.anchors) == 0:
            raise ValueError(f"a member spread needs one variance per anchor, got {len(self.anchors)} anchors and "
                             f"{len(self.between)} variances")
        if not (np.isfinite(self.anchors).all() and np.isfinite(self.between).all() and (self.between >= 0).all()):
            raise ValueError("a member spread needs finite anchors and finite variances >= 0")
        envelope = [self.low, self.high, self.own]
        if any(e is None for e in envelope) and not all(e is None for e in envelope):
            raise ValueError("a member spread's envelope needs low, high and own together (or none of them)")
        if self.low is not None:
            self.low, self.high, self.own = (np.asarray(e, dtype=np.float32).reshape(-1) for e in envelope)
            if any(len(e) != len(self.anchors) for e in (self.low, self.high, self.own)):
                raise ValueError(f"a member spread's envelope needs one low, high and own per anchor "
                                 f"({len(self.anchors)} anchors)")
            measured = np.isfinite(self.low)
            if not (np.array_equal(measured, np.isfinite(self.high)) and (self.high[measured] >= self.low[measured])
                    .all() and np.isfinite(self.own).all() and (self.own >= 0).all()):
                raise ValueError("a member spread's envelope needs high >= low (NaN together) and finite own >= 0")
        self._index = self._moving = self._sides = None

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

    def anchor_sides(self, reference):
        """The anchors' outward normals (a, 3): those of ``reference``'s distinct surface points, which the anchors
        are (the side whose scans the calibration counted there); looked up once."""
        if self._sides is None:
            index, normals = reference.distinct_surface()
            _, idx = index.query(self.anchors.astype(np.float64), 1)
            self._sides = np.asarray(normals, dtype=np.float64)[np.asarray(idx).reshape(-1)]
        return self._sides

    @property
    def has_envelope(self):
        """Whether the trained members' envelope was measured (``low``, ``high``, ``own``)."""
        return self.low is not None

    def as_dict(self):
        """Plain values (torch tensors; the envelope's None where not measured) to store in a calibration record."""
        import torch

        def tensor(a):
            return None if a is None else torch.from_numpy(a.copy())

        return {"anchors": tensor(self.anchors), "between": tensor(self.between), "low": tensor(self.low),
                "high": tensor(self.high), "own": tensor(self.own)}

    @classmethod
    def from_dict(cls, d):
        """The spread :meth:`as_dict` stored, None for None (a record of version 5 has no envelope: None); a
        ValueError for anything else."""
        if d is None:
            return None
        try:
            envelope = [None if d.get(k) is None else np.asarray(d[k], dtype=np.float32)
                        for k in ("low", "high", "own")]
            return cls(np.asarray(d["anchors"], dtype=np.float32), np.asarray(d["between"], dtype=np.float32),
                       *envelope)
        except (KeyError, TypeError, IndexError, AttributeError) as exc:
            raise ValueError(f"damaged member_spread ({type(exc).__name__}: {exc})") from None
