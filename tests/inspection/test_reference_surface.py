"""inspection.scores: the good scans' own surface (LocalReference.surface) and the 'joint' point score."""
import math

import numpy as np
import pytest

from autodecoder.field.protocol import Field
from inspection import point_scores
from inspection.reference import LocalReference
from inspection.scores import fit_term_variances, joint_score


def _naive_surface(reference_points, query, k, self_distance):
    """Brute force: the k nearest distinct reference points other than the query itself, plane by SVD."""
    distinct = np.unique(np.asarray(reference_points, dtype=np.float32), axis=0).astype(np.float64)
    offsets, spreads = [], []
    for p in query:
        d = np.linalg.norm(distinct - p, axis=1)
        order = [i for i in np.argsort(d, kind="stable") if d[i] > self_distance][:k]
        nb = distinct[order]
        c = nb.mean(0)
        _, s, vt = np.linalg.svd(nb - c)
        offsets.append(vt[-1] @ (p - c))
        spreads.append(s[-1] ** 2 / k)
    return np.array(offsets), np.array(spreads)


def _tilted_plane(n, seed, noise):
    """Points on the plane z = 0.3 x - 0.2 y (unit normal below) with noise along the normal."""
    rng = np.random.default_rng(seed)
    normal = np.array([-0.3, 0.2, 1.0]) / math.sqrt(1.13)
    xy = rng.uniform(-1, 1, (n, 2))
    pts = np.c_[xy, 0.3 * xy[:, 0] - 0.2 * xy[:, 1]] + noise * rng.normal(size=(n, 1)) * normal
    return pts, normal


def test_surface_offset_is_the_distance_to_the_plane_and_matches_brute_force():
    pts, normal = _tilted_plane(3000, 0, noise=0.0)
    ref = LocalReference(pts, np.zeros(len(pts)), k=12)
    heights = np.array([0.0, 0.01, -0.05, 0.2])
    base = np.array([[0.1, 0.2, 0.0], [-0.3, 0.0, 0.0], [0.0, -0.4, 0.0], [0.5, 0.5, 0.0]])
    base[:, 2] = 0.3 * base[:, 0] - 0.2 * base[:, 1]
    query = base + heights[:, None] * normal
    offset, spread = ref.surface(query)
    np.testing.assert_allclose(np.abs(offset), np.abs(heights), atol=1e-6)  # exact plane (float32 storage)
    np.testing.assert_allclose(spread, 0.0, atol=1e-12)
    # noisy: against the brute-force plane fit
    noisy, _ = _tilted_plane(800, 1, noise=0.01)
    ref = LocalReference(noisy, np.zeros(len(noisy)), k=10)
    q = noisy[:50] + np.random.default_rng(2).normal(0, 0.02, (50, 3))
    self_distance = 1e-6 * float(np.linalg.norm(np.ptp(np.unique(ref.points, axis=0), axis=0)))
    exp_off, exp_spread = _naive_surface(noisy, q, 10, self_distance)
    offset, spread = ref.surface(q)
    np.testing.assert_allclose(np.abs(offset), np.abs(exp_off), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(spread, exp_spread, rtol=1e-6, atol=1e-12)


def test_surface_leaves_the_point_itself_out_and_counts_shared_points_once():
    """A calibration view of a template shares its points with the reference's views: the point is not evidence
    for itself, and a point in several views is one point of the surface."""
    pts, _ = _tilted_plane(500, 3, noise=0.01)
    ref = LocalReference(pts, np.zeros(len(pts)), k=8)
    twice = LocalReference(np.r_[pts, pts, pts], np.zeros(3 * len(pts)), k=8)
    offset, spread = ref.surface(pts[:40])
    np.testing.assert_array_equal(twice.surface(pts[:40])[0], offset)
    # brute force without the point itself (stored as float32: it lies within ~1e-8 of its float64 query)
    exp_off, exp_spread = _naive_surface(pts, pts[:40], 8, 1e-6)
    np.testing.assert_allclose(np.abs(offset), np.abs(exp_off), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(spread, exp_spread, rtol=1e-5, atol=1e-12)
    # with the point in its own plane fit, the offset would be shrunk toward 0
    assert np.mean(np.abs(offset)) > 1.02 * np.mean(np.abs(_naive_surface(pts, pts[:40], 8, -1.0)[0]))
    with pytest.raises(ValueError, match="distinct"):
        LocalReference(np.zeros((20, 3)), np.zeros(20), k=4).surface(np.ones((1, 3)))


def test_surface_scores_and_joint_score_formulae():
    pts, normal = _tilted_plane(2000, 4, noise=0.0)
    ref = LocalReference(pts, np.zeros(len(pts)), k=12, quantity="distance", grazing_scale=2.0)
    q = np.array([[0.0, 0.0, 0.0]]) + 0.03 * normal
    # spread 0 on an exact plane: 0.03 / sqrt(noise^2 (1 + 2 g))
    assert ref.surface_scores(q, 0.01)[0] == pytest.approx(3.0, rel=1e-4)
    assert ref.surface_scores(q, 0.01, np.array([4.0]))[0] == pytest.approx(0.03 / math.sqrt(1e-4 * 9), rel=1e-4)
    np.testing.assert_allclose(joint_score([3.0, 0.0, 1.0], [4.0, 2.0, 1.0]), [math.sqrt(12.5), math.sqrt(2), 1.0])
    with pytest.raises(ValueError, match="one surface score per distance score"):
        joint_score([1.0, 2.0], [1.0])


def test_fitted_term_variances_recover_a_known_noisy_term_and_weigh_it_down():
    """Terms drawn with known spreads (the field's 2 standard deviations, the good points' 0.5) give back their
    variances; weighed by them, the joint score is the likelihood's closed form and ranks scans whose defect shows in
    the quiet term above good scans better than equal weights do (where the noisy term's largest values, not the
    defect, set a scan's worst points)."""
    rng = np.random.default_rng(0)
    z_d, z_s = np.abs(rng.normal(0, 2.0, 200000)), np.abs(rng.normal(0, 0.5, 200000))
    v_d, v_s = fit_term_variances(z_d, z_s)
    assert v_d == pytest.approx(4.0, rel=0.02) and v_s == pytest.approx(0.25, rel=0.02)
    # robust: 1 % of the good points far out (a cross-fitted scan's surface no other scan saw) barely moves it
    far = z_s.copy()
    far[:2000] = 30.0
    assert fit_term_variances(z_d, far)[1] == pytest.approx(0.25, rel=0.05)
    np.testing.assert_allclose(joint_score([2.0, 0.0], [0.5, 1.0], variances=(4.0, 0.25)), [1.0, math.sqrt(2.0)])

    def scan_scores(variances, defective, n_scans=200, m=400):
        out = []
        for _ in range(n_scans):
            d, s = np.abs(rng.normal(0, 2.0, m)), np.abs(rng.normal(0, 0.5, m))
            if defective:
                s[:8] += 1.5  # 3 of the quiet term's standard deviations, on 2 % of the points
            out.append(np.sort(joint_score(d, s, variances=variances))[-4:].mean())  # the worst 1 %
        return np.array(out)

    def auroc(variances):
        good, bad = scan_scores(variances, False), scan_scores(variances, True)
        return np.mean(bad[:, None] > good[None, :])

    fitted, equal = auroc((v_d, v_s)), auroc((1.0, 1.0))
    assert fitted > 0.9 and fitted > equal + 0.2
    with pytest.raises(ValueError, match="at least one point"):
        fit_term_variances([], [])
    with pytest.raises(ValueError, match="positive finite"):
        joint_score([1.0], [1.0], variances=(0.0, 1.0))


class _PlaneField(Field):
    """E f = the signed height above the plane z = 0 (so the distance quantity is the height), variance 1e-4."""

    def __init__(self, offset=0.0):
        self.noise, self.offset = 0.01, offset

    def mean(self, x):
        return np.asarray(x)[:, 2] + self.offset

    def variance(self, x):
        return np.full(len(x), 1e-4)

    def mean_gradient(self, x):
        return np.tile([0.0, 0.0, 1.0], (len(x), 1))


def test_joint_point_score_combines_the_distance_and_surface_scores():
    rng = np.random.default_rng(5)
    pts = np.c_[rng.uniform(-1, 1, (2000, 2)), np.zeros(2000)]
    ref = LocalReference(pts, rng.normal(0, 0.005, 2000), k=16, quantity="distance", variance_scale=0.5)
    x = np.c_[rng.uniform(-0.5, 0.5, (30, 2)), rng.normal(0, 0.02, 30)]
    f = _PlaneField()
    dist = point_scores(f, x, "distance", reference=ref)
    surf = ref.surface_scores(x, f.noise)
    np.testing.assert_allclose(point_scores(f, x, "joint", reference=ref), np.sqrt((dist**2 + surf**2) / 2),
                               rtol=1e-12)
    # a field that misses a good point (E f = 0.05 where the point lies on the good scans' plane) scores it lower
    # under 'joint' than under 'distance': the good scans' surface explains it
    on, off = np.c_[rng.uniform(-0.5, 0.5, (30, 2)), np.zeros(30)], _PlaneField(offset=0.05)
    assert np.all(point_scores(off, on, "joint", reference=ref) < point_scores(off, on, "distance", reference=ref))


def test_surface_points_beyond_the_reference_points_leave_scans_out_and_are_stored():
    """The surface can come from more good scans than the projected reference (every training scan); cross-fitting
    leaves a scan's surface points out with its reference points, and the calibration stores the distinct ones."""
    import torch  # noqa: F401  (as_dict holds tensors)

    left, _ = _tilted_plane(600, 6, noise=0.005)
    right = left + np.array([0.0, 0.0, 5.0])  # a parallel patch far from the reference points
    halves = np.arange(600) % 2  # the reference points come from good scans 0 and 1
    ref = LocalReference(left, np.zeros(len(left)), k=8, owners=halves, quantity="distance",
                         surface_points=np.r_[left, right, right],
                         surface_owners=np.r_[halves, np.full(600, -3), np.full(600, -4)])
    plain = LocalReference(left, np.zeros(len(left)), k=8, quantity="distance")
    q = right[:20] + 0.001
    assert np.all(ref.surface_scores(q, 0.005) < 3) and np.all(plain.surface_scores(q, 0.005) > 3)
    alone = ref.without(0)
    assert len(alone.surface_points) == 1500 and not np.any(alone.surface_owners == 0)
    restored = LocalReference.from_dict(ref.as_dict())
    assert len(restored.surface_points) == 1200  # the distinct points: 'right' counted once
    np.testing.assert_array_equal(restored.surface_scores(q, 0.005), ref.surface_scores(q, 0.005))
    with pytest.raises(ValueError, match="surface_owners"):
        LocalReference(left, np.zeros(len(left)), k=8, surface_owners=np.zeros(600))


def test_surface_with_normals_fits_the_plane_on_the_scored_points_side_of_a_thin_wall():
    """Two faces of a wall thinner than the points' spacing, outward normals opposite: with the scored point's
    normal the plane goes through its own face's points (offset 0 on it); without, through both (mid-wall)."""
    rng = np.random.default_rng(7)
    xy = rng.uniform(-1, 1, (2000, 2))
    gap = 0.01  # the spacing is ~0.045
    top, bottom = np.c_[xy[:1000], np.full(1000, gap)], np.c_[xy[1000:], np.zeros(1000)]
    normals = np.r_[np.tile([0.0, 0.0, 1.0], (1000, 1)), np.tile([0.0, 0.0, -1.0], (1000, 1))]
    ref = LocalReference(np.r_[top, bottom], np.zeros(2000), k=8, surface_points=np.r_[top, bottom],
                         surface_normals=normals)
    q = np.c_[rng.uniform(-0.5, 0.5, (20, 2)), np.full(20, gap)]  # on the top face
    up = np.tile([0.0, 0.0, 2.0], (20, 1))  # any length
    offset, spread = ref.surface(q, up)
    np.testing.assert_allclose(offset, 0.0, atol=1e-6)
    np.testing.assert_allclose(spread, 0.0, atol=1e-9)
    mixed, mixed_spread = ref.surface(q)  # no normals given: both faces, the plane inside the wall
    assert np.mean(np.abs(mixed)) > 0.3 * gap and np.all(np.abs(mixed) < gap)
    assert np.mean(mixed_spread) > 0.1 * gap**2
    # the bottom face's side: offset = the gap
    np.testing.assert_allclose(np.abs(ref.surface(q, -up)[0]), gap, atol=1e-6)
    restored = LocalReference.from_dict(ref.as_dict())
    np.testing.assert_array_equal(restored.surface(q, up)[0], offset)
    # support: both faces were seen; with the top face alone a point of the bottom's side has none of its own
    assert ref.surface(q, up, with_support=True)[2].all() and ref.surface(q, -up, with_support=True)[2].all()
    only_top = LocalReference(top, np.zeros(1000), k=8, surface_points=top, surface_normals=normals[:1000])
    assert only_top.surface(q, up, with_support=True)[2].all()
    assert not only_top.surface(q, -up, with_support=True)[2].any()
    assert only_top.surface(q, with_support=True)[2].all()  # without the point's normal: no side to judge
    with pytest.raises(ValueError, match="surface_normals"):
        LocalReference(top, np.zeros(1000), k=8, surface_normals=normals[:1000])


def _wide_surface(ref, points, normals):
    """LocalReference.surface as one wide query for every point (the rule as written, without the narrow first
    query that settles most points)."""
    from inspection.reference import SURFACE_CANDIDATES

    tree, surface_normals, self_distance = ref._surface_tree()
    k = min(ref.k, tree.n - 1)
    dist, idx = tree.query(points, min(SURFACE_CANDIDATES * k + 1, tree.n))
    valid = dist > self_distance
    same = np.einsum("mj,mkj->mk", normals, surface_normals[idx]) > 0
    valid &= same | ~((valid & same).sum(1) >= 3)[:, None]
    weight = (valid & (np.cumsum(valid, 1) <= k)).astype(np.float64)
    nb = tree.data[idx]
    centroid = np.einsum("mk,mki->mi", weight, nb) / weight.sum(1)[:, None]
    centred = nb - centroid[:, None]
    cov = np.einsum("mk,mki,mkj->mij", weight, centred, centred) / weight.sum(1)[:, None, None]
    eigval, eigvec = np.linalg.eigh(cov)
    return np.einsum("mi,mi->m", eigvec[:, :, 0], points - centroid), np.maximum(eigval[:, 0], 0.0)


def test_sided_surface_settles_most_points_on_a_narrow_query_with_the_wide_querys_answer(monkeypatch):
    """Points whose k + 1 nearest hold k on their own side take the plane of those; the others (near a thin wall's
    edge, where the faces mix) are queried wide. Both give what one wide query for every point gives."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(-1, 1, (3000, 2))
    gap = 0.01
    top, bottom = np.c_[xy[:1500], np.full(1500, gap)], np.c_[xy[1500:], np.zeros(1500)]
    normals = np.r_[np.tile([0.0, 0.0, 1.0], (1500, 1)), np.tile([0.0, 0.0, -1.0], (1500, 1))]
    # a tilted patch where the faces' normals disagree with some scored points' (the wide path)
    normals[:200] = [0.0, 0.7, 0.7]
    ref = LocalReference(np.r_[top, bottom], np.zeros(3000), k=8, surface_points=np.r_[top, bottom],
                         surface_normals=normals)
    q = np.c_[rng.uniform(-0.9, 0.9, (400, 2)), rng.uniform(-0.02, 0.03, 400)]
    qn = rng.normal(size=(400, 3))
    queried = []
    tree = ref._surface_tree()[0]
    monkeypatch.setattr(ref, "_surface", (_Counting(tree, queried),) + ref._surface_tree()[1:])
    offset, spread = ref.surface(q, qn)
    assert queried[0] == (400, 9) and 0 < queried[1][0] < 400 and queried[1][1] == 33  # both paths taken
    exp_offset, exp_spread = _wide_surface(ref, q, qn)
    np.testing.assert_allclose(np.abs(offset), np.abs(exp_offset), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(spread, exp_spread, rtol=1e-9, atol=1e-15)


class _Counting:
    """A KD-tree that records the (points, k) of each query."""

    def __init__(self, tree, log):
        self._tree, self._log = tree, log
        self.n, self.data = tree.n, tree.data

    def query(self, x, k):
        self._log.append((len(x), k))
        return self._tree.query(x, k)


def test_queries_in_blocks_give_the_answer_of_one_block(monkeypatch):
    """A full-resolution scan is scored in blocks of QUERY_CHUNK points (bounded memory): the surface offsets and
    the reference statistics are those of one query over every point, sided or not."""
    import inspection.reference as reference

    rng = np.random.default_rng(5)
    pts, normal = _tilted_plane(3000, 5, 0.01)
    normals = np.tile(normal, (3000, 1))
    normals[:300] *= -1  # a few points facing the other way take the wide query
    ref = LocalReference(pts, rng.normal(size=3000), k=8, surface_points=pts, surface_normals=normals)
    q = _tilted_plane(700, 6, 0.02)[0]
    qn = np.tile(normal, (700, 1)) * rng.choice([-1.0, 1.0], size=(700, 1))
    whole = ref.surface(q, qn), ref.surface(q), ref.stats(q)
    monkeypatch.setattr(reference, "QUERY_CHUNK", 64)
    blocked = ref.surface(q, qn), ref.surface(q), ref.stats(q)
    for a, b in zip(whole, blocked):
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])


def test_a_point_pressed_through_a_thin_wall_finds_its_own_side_among_more_candidates():
    """A sheet 0.004 thick of two faces (normals up and down), points 0.005 apart: a point of the upper face pressed
    0.1 down lies nearer the lower face's points, and its own side is found only among more candidates; then its
    offset is its depth."""
    g = np.arange(-0.15, 0.1501, 0.005)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    top, bottom = np.c_[xy, np.full(len(xy), 0.002)], np.c_[xy, np.full(len(xy), -0.002)]
    up = np.tile([0.0, 0.0, 1.0], (len(xy), 1))
    sheet = np.r_[top, bottom]
    ref = LocalReference(sheet, np.zeros(len(sheet)), k=8, surface_points=sheet, surface_normals=np.r_[up, -up])
    pressed = np.array([[0.0011, 0.0009, 0.002 - 0.1]])
    offset, _, supported = ref.surface(pressed, up[:1], with_support=True)
    assert not supported[0]
    offset, _, supported = ref.surface(pressed, up[:1], with_support=True, candidates=16)
    assert supported[0] and abs(offset[0]) == pytest.approx(0.1, abs=1e-6)
