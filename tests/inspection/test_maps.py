"""inspection.maps: the anomaly map's patch residuals, against brute force, and what the Inspector and the PLY maps
show."""
import numpy as np
import pytest
from sklearn.metrics import roc_auc_score

from inspection import Inspector
from inspection.maps import MAP_NEIGHBOURS, map_values, patch_residuals

from tests.inspection.spheres import SphereModel, sphere_scan


def _brute_force(points, residuals, k, excluded):
    """Each point's k nearest kept points by a full distance matrix, then the rms of their residuals."""
    kept = np.flatnonzero(~excluded)
    out = residuals.astype(np.float64).copy()
    d = np.linalg.norm(points[:, None, :] - points[None, kept, :], axis=2)
    for i in kept:
        nearest = kept[np.argsort(d[i], kind="stable")[:k]]
        out[i] = np.sqrt(np.mean(residuals[nearest] ** 2))
    return out


def test_patch_residuals_match_brute_force_and_leave_stray_points_out():
    rng = np.random.default_rng(0)
    points = rng.random((300, 3))
    residuals = rng.exponential(size=300)
    excluded = np.zeros(300, dtype=bool)
    excluded[rng.choice(300, 12, replace=False)] = True
    residuals[excluded] = 40.0  # stray returns far off: they must colour no one's patch
    got = patch_residuals(points, residuals, neighbours=9, excluded=excluded)
    np.testing.assert_allclose(got, _brute_force(points, residuals, 9, excluded), rtol=1e-12)
    assert np.all(got[excluded] == 40.0) and got[~excluded].max() < 10
    np.testing.assert_allclose(patch_residuals(points, residuals, neighbours=9),
                               _brute_force(points, residuals, 9, np.zeros(300, dtype=bool)), rtol=1e-12)


def test_patch_residuals_edge_cases_and_errors():
    points = np.random.default_rng(1).random((20, 3))
    np.testing.assert_allclose(patch_residuals(points, np.full(20, 2.5)), 2.5)  # a uniform patch keeps its value
    r = np.arange(20.0)
    np.testing.assert_array_equal(patch_residuals(points, r, neighbours=1), r)
    # more neighbours than points: every patch is the whole scan
    np.testing.assert_allclose(patch_residuals(points, r, neighbours=50), np.sqrt(np.mean(r ** 2)))
    with pytest.raises(ValueError, match="20 points but 3 residuals"):
        patch_residuals(points, r[:3])
    with pytest.raises(ValueError, match="neighbours"):
        patch_residuals(points, r, neighbours=0)
    with pytest.raises(ValueError, match="exclusion"):
        patch_residuals(points, r, excluded=np.zeros(3, dtype=bool))


def test_the_inspectors_map_is_the_patch_of_its_point_scores_and_finds_a_shallow_dent_better():
    """A dent only 2 noise deviations deep: single points barely stand out; their patches do. The map a user gets
    from the Inspector is the patch residual of the point scores, stray points left out."""
    good = [sphere_scan(seed=s)[0] for s in range(10, 30)]
    insp = Inspector(SphereModel(), alpha=0.1).fit(good)
    dented = sphere_scan(seed=300, dent=0.006)[0]
    centre = np.array([0.1, -0.2, 0.05])
    unit = (dented - centre) / np.linalg.norm(dented - centre, axis=1, keepdims=True)
    in_dent = np.arccos(np.clip(unit[:, 2], -1, 1)) < 0.25  # the dent's deeper part (it fades out at 0.35 rad)
    res = insp.inspect_components(dented)
    amap = insp.anomaly_map(dented)
    np.testing.assert_allclose(amap, patch_residuals(dented, res.point_scores, MAP_NEIGHBOURS, res.stray),
                               rtol=1e-12)
    np.testing.assert_allclose(map_values(insp.settings_, dented, res)[0], amap, rtol=1e-12)
    raw_auc, map_auc = roc_auc_score(in_dent, res.point_scores), roc_auc_score(in_dent, amap)
    assert raw_auc < 0.7 and map_auc > 0.9  # measured: 0.64 and 0.94
