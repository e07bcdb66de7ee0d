"""Registration of a real range scan placed by hand: a known 5 degree / 2 % motion of a real view of the Stanford
bunny is undone to within a fraction of the view's point spacing. Uses ../shared/realscans (skipped, with the reason,
when that shared data is absent)."""
from pathlib import Path

import numpy as np
import pytest

REALSCANS = Path(__file__).resolve().parents[3] / "shared" / "realscans" / "bunny"


@pytest.mark.skipif(not REALSCANS.is_dir(), reason=f"needs the real Stanford range scans (shared data, not in the "
                                                     f"repository) at {REALSCANS}")
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_real_view_moved_by_hand_is_registered_back(seed):
    from scipy.spatial.transform import Rotation

    from datasets import read_cloud
    from inspection.align import Aligner

    full, _ = read_cloud(REALSCANS / "bun045.ply")
    full = np.asarray(full, dtype=np.float64)
    diagonal = float(np.linalg.norm(np.ptp(full, axis=0)))
    rng = np.random.default_rng(seed)
    scan = full[rng.choice(len(full), 4000, replace=False)]  # a fresh subset: no point lies exactly on a target one
    axis = rng.normal(size=3)
    rotation = Rotation.from_rotvec(np.radians(5.0) * axis / np.linalg.norm(axis)).as_matrix()
    shift = rng.normal(size=3)
    shift *= 0.02 * diagonal / np.linalg.norm(shift)
    centre = scan.mean(0)
    placed = (scan - centre) @ rotation.T + centre + shift  # 5 degrees about the view's centre, 2 % of its size
    aligner = Aligner(full, seed=0)
    moved_back, _, transform = aligner.align(placed)
    error = np.linalg.norm(moved_back - scan, axis=1)
    assert np.median(error) < 0.1 * aligner.spacing and error.max() < 0.5 * aligner.spacing
    # the transform found is the inverse of the one applied
    undo = Rotation.from_matrix(transform[:3, :3] @ rotation).magnitude()
    assert np.degrees(undo) < 0.1
