"""The region-level metrics of ``benchmarks.metrics`` (AU-PRO as MVTec 3D-AD scores it, region overlap, false
regions per scan) against values worked out by hand and a naive reference: thresholds one at a time, regions by
brute-force union-find over all point pairs."""
import numpy as np
import pytest

from benchmarks import metrics


def _line(n, step=1.0):
    """n points on the x axis, ``step`` apart (median nearest-neighbour spacing ``step``: link 3 ``step``)."""
    return np.column_stack([np.arange(n) * step, np.zeros(n), np.zeros(n)])


# ------------------------------------------------------------------------------------------ naive reference
def _naive_regions(points, labels):
    """Components of the labelled points, linked when closer than 3 x the median nearest-neighbour distance, from
    the full distance matrix and union-find. Returns a list of index arrays."""
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    np.fill_diagonal(d, np.inf)
    link = 3.0 * np.median(d.min(axis=1))
    rows = list(np.flatnonzero(labels))
    parent = {r: r for r in rows}

    def root(r):
        while parent[r] != r:
            r = parent[r]
        return r

    for a in rows:
        for b in rows:
            if a < b and d[a, b] < link:
                parent[root(a)] = root(b)
    groups = {}
    for r in rows:
        groups.setdefault(root(r), []).append(r)
    return [np.array(g) for g in groups.values()]


def _naive_au_pro(points, labels, maps, max_fpr):
    regions = [(i, g) for i, (p, l) in enumerate(zip(points, labels)) for g in _naive_regions(p, l)]
    normal = np.concatenate([m[l == 0] for m, l in zip(maps, labels)])
    fprs, pros = [0.0], [0.0]
    for t in np.unique(np.concatenate(maps))[::-1]:  # each distinct value, highest first: positive = map >= t
        fprs.append(np.mean(normal >= t))
        pros.append(np.mean([np.mean(maps[i][g] >= t) for i, g in regions]))
    fprs, pros = np.array(fprs + [1.0]), np.array(pros + [1.0])
    last = np.flatnonzero(fprs <= max_fpr)[-1]  # the curve is non-decreasing in FPR: its last point within
    x, y = list(fprs[:last + 1]), list(pros[:last + 1])
    if x[-1] < max_fpr:  # interpolate linearly between that point and the next
        x.append(max_fpr)
        y.append(pros[last] + (pros[last + 1] - pros[last]) * (max_fpr - fprs[last]) / (fprs[last + 1] - fprs[last]))
    return np.trapezoid(y, x) / max_fpr


def _blob_scans(seed, n_scans=5, m=120):
    """Random scans in the unit cube, labels in 0-3 spatial blobs (balls round random points; some scans good),
    maps rounded to 2 decimals (many ties), higher on the labelled points."""
    rng = np.random.default_rng(seed)
    points, labels, maps = [], [], []
    for s in range(n_scans):
        xyz = rng.random((m, 3))
        lab = np.zeros(m, int)
        for c in xyz[rng.choice(m, rng.integers(0, 4), replace=False)]:
            lab[np.linalg.norm(xyz - c, axis=1) < rng.uniform(0.1, 0.25)] = 1
        if s == 0:  # at least one region, at least one normal point
            lab[:10], lab[10:20] = 1, 0
        points.append(xyz)
        labels.append(lab)
        maps.append(np.round(rng.random(m) + rng.uniform(0, 1) * lab, 2))
    return points, labels, maps


# ------------------------------------------------------------------------------------------------- regions
def test_truth_regions_are_the_components_of_the_labelled_points():
    labels = np.array([0, 1, 1, 0, 0, 0, 0, 1, 1, 1, 0, 1])
    # spacing 1 -> link 3: points 1, 2 one region; 7, 8, 9, 11 another (9 and 11 are 2 apart)
    assert metrics.truth_regions(_line(12), labels).tolist() == [-1, 0, 0, -1, -1, -1, -1, 1, 1, 1, -1, 1]
    # link 1.5: 11 on its own; link exactly 2 does not link 9 and 11 (closer than, strictly)
    assert metrics.truth_regions(_line(12), labels, link=1.5).tolist()[-1] == 2
    assert metrics.truth_regions(_line(12), labels, link=2.0).tolist()[-1] == 2
    assert (metrics.truth_regions(_line(4), None) == -1).all()
    for seed in range(3):
        points, labels, _ = _blob_scans(seed, n_scans=3)
        for p, l in zip(points, labels):
            got = metrics.truth_regions(p, l)
            want = _naive_regions(p, l)
            assert sorted(sorted(np.flatnonzero(got == k)) for k in range(got.max() + 1)) == \
                sorted(sorted(g) for g in want)


# -------------------------------------------------------------------------------------------------- AU-PRO
def test_a_perfect_map_gives_one_and_a_constant_map_half_the_limit():
    points = [_line(10), _line(8), _line(6)]
    labels = [np.r_[np.zeros(3), np.ones(3), np.zeros(4)].astype(int), np.r_[np.ones(2), np.zeros(6)].astype(int),
              np.zeros(6, int)]
    perfect = [l.astype(float) for l in labels]
    for max_fpr in (0.3, 0.05, 1.0):
        assert metrics.au_pro(points, labels, perfect, max_fpr) == pytest.approx(1.0, abs=1e-12)
        # one threshold: the curve goes (0, 0) -> (1, 1), PRO = FPR: area max_fpr^2 / 2, divided by max_fpr
        constant = [np.full(len(l), 0.7) for l in labels]
        assert metrics.au_pro(points, labels, constant, max_fpr) == pytest.approx(max_fpr / 2, abs=1e-12)
    # a map that puts every normal point above every labelled one: PRO 0 until FPR 1
    assert metrics.au_pro(points, labels, [1.0 - m for m in perfect]) == pytest.approx(0.0, abs=1e-12)


def test_au_pro_of_a_hand_worked_example():
    # scan A: 6 points, region RA = {2, 3}; scan B: 5 points, region RB = {1, 2, 3}; 6 normal points in all
    points = [_line(6), _line(5)]
    labels = [np.array([0, 0, 1, 1, 0, 0]), np.array([0, 1, 1, 1, 0])]
    maps = [np.array([0.1, 0.2, 0.8, 0.4, 0.5, 0.1]), np.array([0.3, 0.9, 0.6, 0.2, 0.7])]
    # threshold (positive: map >= t), FPR = normal points positive / 6, PRO = (share of RA + share of RB) / 2
    # 0.9: 0,     (0 + 1/3)/2 = 1/6     0.8: 0,   (1/2 + 1/3)/2 = 5/12   0.7: 1/6, 5/12
    # 0.6: 1/6,   (1/2 + 2/3)/2 = 7/12  0.5: 1/3, 7/12                   0.4: 1/3, (1 + 2/3)/2 = 5/6
    # 0.3: 1/2,   5/6                   0.2: 2/3, 1                      0.1: 1,   1
    fprs, pros = metrics.pro_curve(points, labels, maps)
    np.testing.assert_allclose(fprs, [0, 0, 0, 1/6, 1/6, 1/3, 1/3, 1/2, 2/3, 1, 1], atol=1e-12)
    np.testing.assert_allclose(pros, [0, 1/6, 5/12, 5/12, 7/12, 7/12, 5/6, 5/6, 1, 1, 1], atol=1e-12)
    # up to 0.3: 5/12 over [0, 1/6], 7/12 over [1/6, 0.3]: 5/72 + 7/90 = 53/360, / 0.3
    assert metrics.au_pro(points, labels, maps) == pytest.approx(53 / 360 / 0.3, abs=1e-12)
    # up to 0.5 (an FPR of the curve): 5/72 + 7/72 + 5/6 x 1/6 = 11/36, / 0.5
    assert metrics.au_pro(points, labels, maps, max_fpr=0.5) == pytest.approx(11 / 36 / 0.5, abs=1e-12)
    # up to 0.6: PRO at 0.6 interpolated between (1/2, 5/6) and (2/3, 1): 14/15; + (5/6 + 14/15) / 2 x 0.1
    assert metrics.au_pro(points, labels, maps, max_fpr=0.6) == pytest.approx((11 / 36 + 53 / 600) / 0.6, abs=1e-12)


@pytest.mark.parametrize("seed", range(6))
def test_au_pro_matches_the_naive_reference_on_random_blobs(seed):
    points, labels, maps = _blob_scans(seed)
    for max_fpr in (0.3, 0.05, 0.5, 1.0):
        assert metrics.au_pro(points, labels, maps, max_fpr) == pytest.approx(
            _naive_au_pro(points, labels, maps, max_fpr), abs=1e-10)


def test_au_pro_refuses_what_it_cannot_score():
    points, labels, maps = [_line(4)], [np.array([0, 1, 1, 0])], [np.arange(4.0)]
    with pytest.raises(ValueError, match="one entry per scan"):
        metrics.au_pro(points, labels, maps + maps)
    with pytest.raises(ValueError, match="like points"):
        metrics.au_pro(points, labels, [np.arange(3.0)])
    with pytest.raises(ValueError, match="labels must be"):
        metrics.au_pro(points, [np.array([0, 1, 1])], maps)
    with pytest.raises(ValueError, match="no labelled point"):
        metrics.au_pro(points, [np.zeros(4, int)], maps)
    with pytest.raises(ValueError, match="no normal point"):
        metrics.au_pro(points, [np.ones(4, int)], maps)
    with pytest.raises(ValueError, match="0 \\(normal\\) or 1"):
        metrics.au_pro(points, [np.array([0, 2, 1, 0])], maps)
    with pytest.raises(ValueError, match="max_fpr"):
        metrics.au_pro(points, labels, maps, max_fpr=0.0)


# ------------------------------------------------------------------------------------------ region overlap
def test_region_overlap_matches_and_ious():
    # scan 0: truth {2..5}; predicted 0 = {2..5} exactly (IoU 1)
    # scan 1: truth {2..5} and {14..15} (12 apart: two regions); predicted 3 = {4..7}: IoU 2/6 with the first;
    #         predicted 0 = {10, 11} on normal points only; nothing on the second region
    points = [_line(10), _line(16)]
    truth = [np.isin(np.arange(10), [2, 3, 4, 5]).astype(int), np.isin(np.arange(16), [2, 3, 4, 5, 14, 15]).astype(int)]
    predicted = [np.where(truth[0] == 1, 0, -1), np.full(16, -1)]
    predicted[1][4:8], predicted[1][10:12] = 3, 0
    out = metrics.region_overlap(points, truth, predicted)
    assert out["regions"] == 3 and out["detected"] == pytest.approx(2 / 3)
    got = [(m["scan"], m["region"], m["points"].tolist(), m["predicted"], m["detected"]) for m in out["matches"]]
    assert got == [(0, 0, [2, 3, 4, 5], 0, True), (1, 0, [2, 3, 4, 5], 3, True), (1, 1, [14, 15], -1, False)]
    assert [m["iou"] for m in out["matches"]] == pytest.approx([1.0, 1 / 3, 0.0])
    strict = metrics.region_overlap(points, truth, predicted, min_iou=0.5)
    assert strict["detected"] == pytest.approx(1 / 3)
    # the best of two overlapping predictions: {2, 3} (IoU 2/4) beats {4..9} (IoU 2/8)
    two = np.full(10, -1)
    two[2:4], two[4:10] = 1, 0
    match = metrics.region_overlap(points[:1], truth[:1], [two])["matches"][0]
    assert (match["predicted"], match["iou"]) == (1, pytest.approx(0.5))
    assert np.isnan(metrics.region_overlap([_line(3)], [None], [np.full(3, -1)])["detected"])
    with pytest.raises(ValueError, match="-1 \\(no region\\)"):
        metrics.region_overlap(points[:1], truth[:1], [np.full(10, -2)])


def test_false_regions_per_scan_counts_regions_on_normal_points_only():
    labels = [np.array([0, 0, 1, 1, 0, 0]), np.zeros(4, int), None]
    predicted = [np.array([0, 0, 0, -1, 1, 1]),  # region 0 touches a labelled point; region 1 is false
                 np.array([5, 5, -1, 7]),  # both false
                 np.array([-1, -1])]  # none
    assert metrics.false_regions_per_scan(predicted, labels) == pytest.approx(3 / 3)
    assert metrics.false_regions_per_scan(predicted[:1], labels[:1]) == pytest.approx(1.0)
    assert metrics.false_regions_per_scan([np.array([-1, -1, 0, 1, 1, -1])], labels[:1]) == 0.0
    with pytest.raises(ValueError, match="one entry per scan"):
        metrics.false_regions_per_scan(predicted, labels[:2])
    with pytest.raises(ValueError, match="no scan"):
        metrics.false_regions_per_scan([], [])


def test_the_defects_suite_measures_the_truth_as_the_regions_measure_a_footprint():
    from benchmarks.suites import defects
    from inspection.regions import FOOTPRINT_FRACTION

    assert defects.FOOTPRINT_FRACTION == FOOTPRINT_FRACTION
    deviation = np.array([0.0, -0.5, -0.04, -0.2, 0.3])
    labels = np.array([False, True, True, True, False])
    areas = np.array([1.0, 2.0, 4.0, 8.0, 16.0])
    assert defects.truth_size(deviation, labels, areas) == (0.5, 10.0)  # -0.04 moved less than 10 % of 0.5
    assert defects.truth_size(np.zeros(5), labels, areas) == (None, None)


def test_the_defects_suites_rule_at_1_2_is_the_regions_own():
    """The suite's alternative rules are weighed against the regions' own: at fill + aspect >= 1.2 they agree."""
    from benchmarks.suites import defects
    from inspection.regions import SHARPNESS, DefectRegion, region_type

    assert SHARPNESS == 1.2
    rng = np.random.default_rng(0)
    for _ in range(300):
        area, deviation = rng.uniform(0.5, 2.0), rng.uniform(-1.5, 1.5)
        fill, rays = rng.choice([None, rng.uniform(0.3, 1.0)]), rng.choice([0.0, rng.uniform(0, 1)])
        region = DefectRegion(0, "", np.arange(3), 5.0, deviation, 0.1, area, area, area, 1.0, None, None,
                              np.zeros(3), np.zeros(3), ray_share=rays, fill=fill)
        match = {"deviation": deviation, "area": area, "fill": fill, "ray_share": rays}
        assert defects._typed(match, defects._RULES["fill + aspect >= 1.2"]) == region_type(region)
