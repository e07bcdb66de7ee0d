"""Tests of the virtual scanner's test-sensor options (datasets.scanner, datasets.synth, the synth command): returns
lost at grazing incidence and ragged borders, and the defaults left exactly as they were."""
import numpy as np
import pytest
import trimesh

from datasets.parts import builtin_part
from datasets.scanner import VirtualScanner
from datasets.synth import synthesise


@pytest.fixture(scope="module")
def bracket():
    return builtin_part()


def _far_view(scanner, direction, distance=12.0):
    """A camera far along ``direction`` from the part's centre (nearly parallel rays: one incidence per face)."""
    direction = np.asarray(direction, dtype=np.float64)
    return scanner.center + distance * direction / np.linalg.norm(direction)


# ------------------------------------------------------------------------------------------------ defaults
# The built-in bracket scanned at the defaults by the code before these options existed (commit 39faf2d): the first
# triangles hit and the mean point. Any change of the default path's draws moves both.
REFERENCE = {
    "pinhole": ([479, 440, 438, 419, 419, 419, 419, 419],
                [-34.20109623146057, -0.10280083560943604, 23.816502011216276]),
    "line": ([830, 825, 780, 780, 780, 780, 693, 693],
             [-28.90230175256729, -0.10068970549106598, 21.034256517401037]),
}


@pytest.mark.parametrize("sensor", ["pinhole", "line"])
def test_defaults_scan_exactly_as_before(bracket, sensor):
    scanner = VirtualScanner(bracket)
    options = dict(n_points=500, noise=0.002 * scanner.diagonal, seed=12, sensor=sensor)
    default = scanner.scan(scanner.random_view(seed=11), **options)
    zero = scanner.scan(scanner.random_view(seed=11), grazing_dropout=0.0, ragged=0.0, **options)
    np.testing.assert_array_equal(default.points, zero.points)
    np.testing.assert_array_equal(default.normals, zero.normals)
    triangles, mean = REFERENCE[sensor]
    assert default.triangle_ids[:8].tolist() == triangles
    np.testing.assert_allclose(default.points.astype(np.float64).mean(axis=0), mean, rtol=1e-6)


def test_synthesise_defaults_unchanged_and_zero_losses_identical(bracket):
    small = dict(n_train=1, n_test_good=1, n_test_defective=1, defects=("dent",), n_points=300, seed=3,
                 progress=False)
    default, _ = synthesise(bracket, **small)
    zero, _ = synthesise(bracket, grazing_dropout=0.0, ragged=0.0, **small)
    for a, b in zip(default, zero):
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.normals, b.normals)
    # the scans of commit 39faf2d (mean point of each, collection frame)
    means = {"train/good/000": [-0.2779160389257595, 0.10450883461472889, -0.040956649393386516],
             "test/good/000": [-0.3171245434647426, -0.1333723618594619, -0.09381582390516996],
             "test/dent/000": [-0.016617694440064952, -0.027946633851000418, -0.07674639959664395]}
    for s in default:
        np.testing.assert_allclose(s.points.astype(np.float64).mean(axis=0), means[s.name], rtol=1e-5, atol=1e-7)


# ------------------------------------------------------------------------------------------------ grazing dropout
@pytest.mark.parametrize("k", [1.0, 2.0])
def test_grazing_dropout_keeps_hits_in_proportion_to_cosine_power(k):
    """A cube seen about 20 degrees off its top face's normal: its top near cos 20 degrees, its side near cos 70
    degrees. Each hit is kept with probability cos ** k, so the side's share of the points against the top's falls by
    the ratio of the two faces' mean cos ** k (over the hits of the same scan without losses)."""
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    scanner = VirtualScanner(cube)
    angle = np.radians(20.0)
    eye = _far_view(scanner, (np.sin(angle), 0.0, np.cos(angle)))

    def faces(**options):
        r = scanner.scan(eye, fov_deg=12.0, n_points=6000, seed=1, **options)
        normals = np.round(cube.face_normals[r.triangle_ids]).astype(int)
        top, side = normals[:, 2] == 1, normals[:, 0] == 1
        assert np.all(top | side)  # only these two faces face the camera
        rays = r.clean_points - r.ray_origins
        cosine = np.abs(np.sum(r.normals * rays, axis=1)) / np.linalg.norm(rays, axis=1)
        return top, side, cosine

    top, side, cosine = faces()
    expected = np.mean(cosine[side] ** k) / np.mean(cosine[top] ** k)
    assert 0.2 < expected < 0.5 if k == 1 else expected < 0.2  # the two faces' incidences are far apart
    lossy_top, lossy_side, _ = faces(grazing_dropout=k)
    ratio = (lossy_side.sum() / lossy_top.sum()) / (side.sum() / top.sum())
    assert ratio == pytest.approx(expected, rel=0.1)


def test_grazing_dropout_keeps_fewer_grazing_points_than_head_on(bracket):
    scanner = VirtualScanner(bracket)
    view = scanner.random_view(seed=4)

    def cosines(**options):
        r = scanner.scan(view, n_points=4000, seed=5, **options)
        rays = r.clean_points - r.ray_origins
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        return np.abs(np.sum(r.normals * rays, axis=1))

    before, after = cosines(), cosines(grazing_dropout=1.0)
    assert np.mean(after < 0.3) < 0.5 * np.mean(before < 0.3)
    assert np.mean(after > 0.9) > np.mean(before > 0.9)


# ------------------------------------------------------------------------------------------------ ragged borders
def _outline_distance(points, half):
    """Distance of (n, 3) points from the outline of the square |x|, |y| <= half (in the x-y plane)."""
    return np.min(half - np.abs(points[:, :2]), axis=1)


def test_ragged_borders_remove_points_near_the_silhouette():
    """A square plate seen head-on: a bite uniform in [0, w] along its outline loses on average half of the points
    within w of it (a point at depth x is lost where the bite exceeds x: 1 - x / w), and none farther in."""
    plate = trimesh.creation.box(extents=(2.0, 2.0, 0.01))
    scanner = VirtualScanner(plate)
    eye = _far_view(scanner, (0.0, 0.0, 1.0), distance=10.0)
    width = 0.15

    def band_over_inside(seed, **options):
        r = scanner.scan(eye, fov_deg=18.0, n_points=8000, seed=seed, **options)  # the whole plate in view
        top = r.points[r.points[:, 2] > 0]
        d = _outline_distance(top, 1.0)
        return np.sum(d < width) / np.sum(d > width + 0.02)

    ratios = [band_over_inside(s, ragged=width) / band_over_inside(s) for s in range(4)]
    assert 0.3 < np.mean(ratios) < 0.7


def test_ragged_borders_follow_occluding_edges():
    """A cube on a plate seen from above: the plate's points around the cube's foot are hidden next to the cube's top
    face, a depth discontinuity: with ragged borders both sides of it lose points, far from any silhouette."""
    plate = trimesh.creation.box(extents=(4.0, 4.0, 0.01))
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    cube.apply_translation((0.0, 0.0, 0.5))
    part = trimesh.util.concatenate([plate, cube])
    scanner = VirtualScanner(part)
    eye = scanner.center + np.array([0.0, 0.0, 20.0])
    width = 0.2

    def near_edge_share(**options):
        r = scanner.scan(eye, look_at=scanner.center, fov_deg=13.0, n_points=8000, seed=2, **options)
        on_plate = np.abs(r.points[:, 2] - 0.005) < 0.01
        inner = np.max(np.abs(r.points[:, :2]), axis=1) < 1.6  # far from the plate's own outline
        ring = inner & on_plate & (np.max(np.abs(r.points[:, :2]), axis=1) < 0.5 + width)
        top = (r.points[:, 2] > 0.99) & (_outline_distance(r.points, 0.5) < width)
        return (np.sum(ring) + np.sum(top)) / np.sum(inner)

    assert near_edge_share(ragged=width) < 0.75 * near_edge_share()


def test_losses_keep_the_exact_count_and_the_same_seed_same_scan(bracket):
    scanner = VirtualScanner(bracket)
    options = dict(n_points=1500, seed=9, grazing_dropout=1.5, ragged=0.03 * scanner.diagonal)
    for sensor in ("pinhole", "line"):
        a = scanner.scan(scanner.random_view(seed=8), sensor=sensor, **options)
        b = scanner.scan(scanner.random_view(seed=8), sensor=sensor, **options)
        assert len(a.points) == 1500 and len(np.unique(a.points, axis=0)) == 1500
        np.testing.assert_array_equal(a.points, b.points)


@pytest.mark.parametrize("option", ["grazing_dropout", "ragged"])
def test_negative_losses_are_refused_naming_the_option(bracket, option):
    scanner = VirtualScanner(bracket)
    with pytest.raises(ValueError, match=option):
        scanner.scan(scanner.random_view(seed=0), n_points=100, **{option: -1.0})
    with pytest.raises(ValueError, match=option):
        synthesise(bracket, n_train=1, n_test_good=0, n_test_defective=0, progress=False, **{option: float("nan")})


# ------------------------------------------------------------------------------------------------ synthesise
def test_another_sensor_sees_the_same_good_views(bracket):
    """Two syntheses that differ only in the sensor: each good scan from the same direction (the stand-off scaled
    with ``radius_range``), with other points."""
    small = dict(n_train=2, n_test_good=2, n_test_defective=0, n_points=600, seed=5, progress=False)
    same, frame = synthesise(bracket, **small)
    other, _ = synthesise(bracket, radius_range=(2.25, 3.3), fov_deg=30.0, ragged=0.03, grazing_dropout=1.0,
                          noise=0.008, **small)
    centre = frame.to_collection(np.asarray(VirtualScanner(bracket).center)[None])[0]
    for a, b in zip(same, other):
        assert a.name == b.name
        assert not np.array_equal(a.points, b.points)
        np.testing.assert_allclose(b.sensor_origin - centre, 1.5 * (a.sensor_origin - centre), rtol=1e-6)


def test_synth_command_takes_the_sensor_losses(tmp_path):
    from datasets.__main__ import main
    from datasets.collection import ScanCollection

    common = ["--mesh", "builtin", "--train", "1", "--test-good", "1", "--test-defective", "1", "--defects", "dent",
              "--points", "600", "--quiet"]
    assert main(["synth", *common, "--out", str(tmp_path / "plain.h5")]) == 0
    assert main(["synth", *common, "--out", str(tmp_path / "lossy.h5"), "--grazing-dropout", "1",
                 "--ragged", "0.03"]) == 0
    with ScanCollection(tmp_path / "plain.h5") as plain, ScanCollection(tmp_path / "lossy.h5") as lossy:
        assert "ragged" not in plain.provenance and "grazing_dropout" not in plain.provenance
        assert lossy.provenance["ragged"] == 0.03 and lossy.provenance["grazing_dropout"] == 1.0
        assert not np.array_equal(plain[0].points, lossy[0].points)
