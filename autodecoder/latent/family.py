"""The training scans brought into one common frame before the latent model is trained on them, and every later scan
registered the same way before it is projected: one size (a product family) or one pose (parts placed by hand).

A product family
----------------
Why: a latent space trained on the scans of a few members of a family does not interpolate between them. With 8
members stretched by 0.8-0.9 and 1.1-1.2 along the part's length, the nominal member (1.0) scored 0.54-0.80 AUROC
(docs/results.md#a-product-family-issue-32-the-first-measurement); the same model trained on scans whose stretch
was undone by the known factors scored 1.000. So the toolkit undoes the sizes itself, without labels: a family
whose members differ by a scale along the frame's axes (the fixture's or CAD model's: a bracket in several lengths,
a housing in three widths) becomes a part in a fixture. What it does not do: variation that is not a scale (a
hole moved, a wall thickened, a bend) is left to the latent space; and a part of the wrong size is, by
construction, not a defect.

On by default (``family='auto'``; ``nsspr-train --family on|off`` decides by hand).

* :func:`fit_family` decides it (``family='auto'``) and makes the common size: up to ``FAMILY_SCANS`` training scans
  (evenly chosen) registered onto each other with the scaled motion (:func:`datasets.registration.register_group`),
  and :func:`size_spread` of the sizes the registration gave them (per axis of the frame, the interquartile range
  of the log scales; the largest over the axes). After one round of that registration a spread at most half the
  bar ``FAMILY_SPREAD`` is one part (synthetic parts in a fixture 0.009-0.049; families stretched by 10-20 % and
  the real bunny's range scans 0.28-0.38 go on). Then what one round's sizes do to the scans decides: their union
  must be about as sharp as registered rigidly (:func:`union_residual`; rigid / sized at least
  ``FAMILY_SHARPNESS``: a family's 0.95-0.98, the real bunny's smooth views, which the scaled motion sizes at
  random, 0.27-0.42 on all its trees, a family bent by 24-48 degrees 0.66), and the sizes must be the scans' own:
  registered again onto either half of the others, each scan must get the same size (:func:`size_reproducibility`
  below ``FAMILY_REPRODUCIBLE``: a family's 0.03-0.08, the real bunny's 0.13-0.78, the bent family's 1.00). Only
  then are the scans registered to the end, and a family whose spread stays above ``FAMILY_SPREAD`` is sized
  (docs/results.md#a-product-family-told-by-default-and-an-unseen-member-fitted-as-well-as-a-trained-one-issue-32-2026-11-27;
  judged on the registration's end instead, as until 2026-11-27, the real bunny's union came out as sharp as the
  rigid one at one training seed of three, and that tree was taken for a family). How far the scans' own extents
  spread does not
  tell a family (the real bunny's views differ in depth as much as a family's lengths), nor a median absolute
  deviation of the sizes (a family of shorter and longer members has its median in one of the two clusters).

Parts placed by hand
--------------------
Why: a model trained on scans each placed by hand learns the blur of every placement; registering a new scan onto
the training scans (inspection's ``align``) then puts it into a frame the model never saw sharply. On the real
bunny's half-depth tree placed by hand (5 degrees, 2 % of its size) the field's term of a view from below (three
training scans of it) was 1.5 times a fixture's, and the tree's AUROC fell 0.02-0.04 below the same tree without the
placement at two seeds of three (docs/results.md). :func:`fit_pose` decides it the way inspection decides to
register scans (:func:`datasets.registration.pose_spread` above ``AUTO_RATIO``; on by default, ``pose='auto'``) and
moves every training scan into one common pose (:func:`datasets.registration.register_group`), the target every
later scan is registered onto with the rigid motion.

* :class:`FamilyFrame` holds the common frame: training scans, registered, as the target every scan is then
  registered onto (:meth:`FamilyFrame.normalise`; a training scan without its own points). Stored in the
  checkpoint (its ``'family'`` entry, the name it has had since sizes came first).
"""
import numpy as np

FAMILY_SPREAD = 0.2  # size_spread above this: the training scans are a family of sizes (module docstring) ...
FAMILY_SHARPNESS = 0.9  # ... when also their union registered with sizes is at least about as sharp as registered
# rigidly (rigid residual / sized residual above this; module docstring)
FAMILY_SCANS = 16  # training scans registered onto each other to decide it and to make the common size's target
FAMILY_REPRODUCIBLE = 0.25  # ... and when registering each scan again onto either half of the others gives it the
# same size: the 75th percentile of the difference, along the axis whose sizes spread most, below this share of
# that spread (module docstring)


def _evenly(n, k):
    return np.unique(np.linspace(0, n - 1, min(k, n)).round().astype(int)) if n else np.zeros(0, int)


def size_spread(transforms):
    """How far registration scaled a group of scans: per axis of the frame the interquartile range of the log of
    each transform's scale along it (the diagonal of its linear part: the scaled motion's scales are along the
    frame's axes), the largest over the three axes. 0: every scan kept its size. ``transforms``: (4, 4) each."""
    if len(transforms) < 3:
        return 0.0
    logs = np.log(np.maximum(np.abs([np.diag(np.asarray(T)[:3, :3]) for T in transforms]), 1e-12))
    return float(_axis_spreads(logs).max())


def _axis_spreads(logs):
    """(3,) interquartile range of (n, 3) log scales, per axis."""
    return np.subtract(*np.percentile(logs, [75, 25], axis=0))


def union_residual(scans, motion="rigid", seed=0):
    """How sharp registered scans' union is: the median over the scans of each one's median point-to-plane distance
    to the others (:meth:`datasets.registration.Aligner.without`), in the others' point spacings."""
    from datasets.parallel import parallel_map
    from datasets.registration import Aligner

    target = Aligner.from_scans(scans, max_scans=len(scans), seed=seed, motion=motion)
    return float(np.median(parallel_map(lambda s: target.without(str(s.name))._residual(
        np.asarray(s.points, dtype=np.float64)) / target.spacing, scans)))


def size_reproducibility(moved, transforms, seed=0, tick=None):
    """How reproducibly the scaled motion sizes a registered group of scans, as a share of how far it spreads them.

    Each scan of ``moved`` (already registered onto each other, :func:`datasets.registration.register_group`) is
    registered again with the scaled motion onto each half of the others (alternate scans); along the axis whose
    sizes ``transforms`` spread most, the 75th percentile over the scans of the absolute difference of the two log
    scales, over that axis' :func:`size_spread`. A family's members have definite sizes, which any half of the
    other members' scans gives back (0.03-0.08 on the benchmarks' stretched families after one round of
    registration); the sizes given to smooth views that do not pin theirs depend on which scans they meet (0.13-0.78
    on the real bunny's range scans; docs/results.md). nan for fewer than 5 scans. ``tick`` (optional): called
    once per registration."""
    from datasets.parallel import parallel_map
    from datasets.registration import Aligner
    from datasets.validation import points_and_normals

    if len(moved) < 5:
        return float("nan")
    logs = np.log(np.maximum(np.abs([np.diag(np.asarray(T)[:3, :3]) for T in transforms]), 1e-12))
    spreads = _axis_spreads(logs)
    axis = int(np.argmax(spreads))

    def log_size(pair):  # scan i registered onto one half of the others (alternate scans): its log size on the axis
        i, half = pair
        others = [m for j, m in enumerate(moved) if j != i][half::2]
        points = np.asarray(points_and_normals(moved[i])[0], dtype=np.float64).reshape(-1, 3)
        aligner = Aligner.from_scans(others, max_scans=len(others), seed=seed, motion="scaled")
        return np.log(abs(aligner.transform(points)[axis, axis]))

    pairs = [(i, half) for i in range(len(moved)) for half in (0, 1)]
    sizes = np.reshape(parallel_map(log_size, pairs, tick), (len(moved), 2))  # side by side (datasets.parallel)
    differences = np.abs(sizes[:, 0] - sizes[:, 1])
    return float(np.quantile(differences, 0.75) / max(spreads[axis], 1e-12))


def fit_family(scans, family="auto", max_scans=FAMILY_SCANS, seed=0, tick=None):
    """The common size of a product family's training scans, when they are one.

    Parameters
    ----------
    scans : sequence of Scan
        Good training scans (a lazy sequence is read only at the up to ``max_scans`` evenly chosen indices).
    family : {'auto', True, False}
        'auto': a family when :func:`size_spread` of the chosen scans' registration exceeds ``FAMILY_SPREAD``,
        their union registered with sizes is about as sharp as registered rigidly (``FAMILY_SHARPNESS``) and the
        sizes are reproducible (:func:`size_reproducibility` below ``FAMILY_REPRODUCIBLE``; module docstring).
    max_scans : int
    seed : int
    tick : callable, optional
        Called once per registration of a scan (a progress bar: deciding takes seconds to minutes).

    Returns
    -------
    frame : FamilyFrame or None
        None: not a family (or ``family`` False, or fewer than 3 scans).
    spread : float or None
        The measured :func:`size_spread` (None when ``family`` is False: nothing was measured; after one round of
        registration when the decision was made there, as it is for a part in a fixture; the values measured on the
        benchmarks' parts and families: docs/results.md, "A product family brought to one size").
    """
    from datasets.registration import Aligner, register_group

    if family not in ("auto", True, False):
        raise ValueError(f"family must be 'auto', True or False, got {family!r}")
    if family is False:
        return None, None
    chosen = [scans[int(i)] for i in _evenly(len(scans), max_scans)]
    if len(chosen) < 3:
        return None, 0.0
    if family == "auto":  # one round first: parts in a fixture are told apart there, in a fifth of the time, and
        # what one round's sizes do to the scans tells real scans of one part from a family (module docstring)
        first_moved, first_transforms = register_group(chosen, rounds=1, seed=seed, motion="scaled",
                                                       return_transforms=True, tick=tick)
        first = size_spread(first_transforms)
        if first <= FAMILY_SPREAD / 2:
            return None, first
        # both checks must pass; the cheaper first (a part in a fixture just above the exit above, the cup's
        # views at one seed, fails it): 2 scaled registrations a scan here, a rigid group registration of up to 6
        # rounds below (docs/results_archive.md, "Speed")
        if not size_reproducibility(first_moved, first_transforms, seed, tick) < FAMILY_REPRODUCIBLE:
            return None, first  # sizes that depend on which scans a view meets: views that do not pin their size
        if (union_residual(register_group(chosen, seed=seed, tick=tick), "rigid", seed)
                < FAMILY_SHARPNESS * union_residual(first_moved, "scaled", seed)):
            return None, first  # sizes that make the scans agree less than a rigid registration does: not a family
    moved, transforms = register_group(chosen, seed=seed, motion="scaled", return_transforms=True, tick=tick)
    spread = size_spread(transforms)
    if family == "auto" and spread <= FAMILY_SPREAD:
        return None, spread
    # a new scan is expected to need what the group's typical member needed (and gets it along an axis its view
    # does not pin): the mean of their log scales (a median would sit in one cluster of a family of shorter and
    # longer members)
    logs = np.log(np.maximum(np.abs([np.diag(np.asarray(T)[:3, :3]) for T in transforms]), 1e-12))
    typical = logs.mean(axis=0)
    # the family's axes: those along which the sizes spread; along the others a scan keeps the typical size (a
    # registration that also scaled them found a wrong pose now and then: a fandisk view squashed to 0.78 in depth)
    axes = _axis_spreads(logs) > FAMILY_SPREAD
    if not axes.any():  # family=True on scans whose sizes do not spread: every axis may scale
        axes[:] = True
    return FamilyFrame(Aligner.from_scans(moved, max_scans=len(moved), seed=seed, motion="scaled",
                                          scale_centre=typical, scale_axes=axes)), spread


def _pose_chosen(scans, max_scans=None):
    """Up to ``max_scans`` (default ``datasets.registration.ALIGN_SCANS``) evenly chosen scans of ``scans``."""
    from datasets.registration import ALIGN_SCANS

    return [scans[int(i)] for i in _evenly(len(scans), ALIGN_SCANS if max_scans is None else max_scans)]


def _spread_and_decision(chosen, seed, tick=None):
    """(:func:`datasets.registration.pose_spread` of ``chosen`` or None for fewer than 3, whether it is above
    ``AUTO_RATIO``)."""
    from datasets.registration import AUTO_RATIO, pose_spread

    if len(chosen) < 3:
        return None, False
    spread = pose_spread(chosen, seed=seed, tick=tick)
    return spread, spread > AUTO_RATIO


def pose_decision(scans, max_scans=None, seed=0):
    """What :func:`fit_pose` with ``pose='auto'`` decides, without moving anything (a few seconds): (the pose
    spread of the scans it would choose, or None for fewer than 3; whether they are to be moved into one pose)."""
    return _spread_and_decision(_pose_chosen(scans, max_scans), seed)


def fit_pose(scans, pose="auto", max_scans=None, seed=0, tick=None):
    """The common pose of training scans placed by hand, when their poses spread (module docstring).

    Parameters
    ----------
    scans : sequence of Scan
        Good training scans (a lazy sequence is read only at the up to ``max_scans`` evenly chosen indices).
    pose : {'auto', True, False}
        'auto': when :func:`datasets.registration.pose_spread` exceeds ``AUTO_RATIO`` (the rule inspection's
        ``align='auto'`` uses); True: always; False: never.
    max_scans : int, optional
        Training scans moved into the common pose and stacked as the target (default
        ``datasets.registration.ALIGN_SCANS``: a target of every training scan covers what any view sees; onto 8 of
        them a view from below slid by 10 % of the part's size, docs/results.md).
    seed : int
    tick : callable, optional
        Called once per registration of a scan (a progress bar).

    Returns
    -------
    frame : FamilyFrame or None
        With the rigid motion; None: the poses do not spread (or ``pose`` False, or fewer than 3 scans).
    spread : float or None
        The measured pose spread (None when ``pose`` is not 'auto').
    """
    from datasets.registration import Aligner, register_group

    if pose not in ("auto", True, False):
        raise ValueError(f"pose must be 'auto', True or False, got {pose!r}")
    if pose is False:
        return None, None
    chosen, spread = _pose_chosen(scans, max_scans), None
    if pose == "auto":
        spread, moves = _spread_and_decision(chosen, seed, tick)
        if not moves:
            return None, spread
    if len(chosen) < 3:
        return None, None
    moved = register_group(chosen, seed=seed, tick=tick)
    return FamilyFrame(Aligner.from_scans(moved, max_scans=len(moved), seed=seed)), spread


class FamilyFrame:
    """The common frame of a model's training scans (one size: a product family; one pose: parts placed by hand),
    and the registration of any scan onto it.

    Parameters
    ----------
    aligner : datasets.registration.Aligner
        Its target is training scans already in the common frame; ``motion='scaled'`` for a family's size,
        ``'rigid'`` for a common pose.
    """

    def __init__(self, aligner):
        if getattr(aligner, "motion", None) not in ("scaled", "rigid"):
            raise ValueError("a common frame registers scans with the scaled or the rigid motion")
        self.aligner = aligner

    @property
    def kind(self):
        """'size' (a product family: scaled motion) or 'pose' (parts placed by hand: rigid motion)."""
        return "size" if self.aligner.motion == "scaled" else "pose"

    def normalise(self, scan):
        """``scan`` registered onto the common frame: a moved copy of a :class:`datasets.Scan` (points, normals and
        sensor origin; the transform (4, 4) in ``extra['align']``), or the moved (m, 3) points of an array. A scan
        whose name is among the target's owners (a training scan) is registered onto the others."""
        name = str(getattr(scan, "name", "") or "")
        return self.aligner.without(name).align_scan(scan)

    def as_dict(self):
        """Plain values (torch tensors for the arrays) for a checkpoint."""
        return self.aligner.as_dict()

    @classmethod
    def from_dict(cls, d):
        from datasets.registration import Aligner

        return cls(Aligner.from_dict(d))


MOVED_KEPT = 32  # NormalisedScans keeps the last this many registered scans (the trainer reads a few twice)


class NormalisedScans:
    """A lazy view of ``scans`` (a sequence of Scan) with each scan registered onto ``frame`` when read; the last
    ``MOVED_KEPT`` are kept, not all (a collection streams)."""

    def __init__(self, scans, frame):
        import threading

        self.scans, self.frame = scans, frame
        names = getattr(scans, "names", None)
        self.names = list(names) if names is not None else [s.name for s in scans]

        self._moved = {}
        self._lock = threading.Lock()  # scans may be read from several threads at once (the trainer's reading)

    def __len__(self):
        return len(self.scans)

    def __getitem__(self, i):
        with self._lock:
            if i in self._moved:
                return self._moved[i]
        moved = self.frame.normalise(self.scans[i])  # outside the lock: registrations run side by side
        with self._lock:
            if i not in self._moved and len(self._moved) >= MOVED_KEPT:
                self._moved.pop(next(iter(self._moved)))  # the oldest
            self._moved[i] = moved
        return moved
