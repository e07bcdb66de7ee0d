"""datasets.parallel: a map over threads gives what a loop gives (order, ticks, errors), and the registrations that
run through it (register_group both motions, pose_spread) give the same transforms to the bit as one after the
other."""
import threading

import numpy as np
import pytest

from datasets.parallel import parallel_map, usable_cores

from .test_registration import _part


def test_the_map_keeps_order_ticks_once_per_piece_and_runs_side_by_side():
    ticks, seen = [], set()

    def piece(x):
        seen.add(threading.get_ident())
        return x * x

    assert parallel_map(piece, range(20), tick=lambda: ticks.append(1), workers=2) == [x * x for x in range(20)]
    assert len(ticks) == 20
    assert parallel_map(piece, [], workers=2) == []
    assert parallel_map(piece, [3], tick=lambda: ticks.append(1), workers=1) == [9] and len(ticks) == 21
    assert usable_cores() >= 1


def test_a_failing_piece_raises_its_own_error():
    def piece(x):
        if x == 3:
            raise ValueError("piece 3 failed")
        return x

    with pytest.raises(ValueError, match="piece 3 failed"):
        parallel_map(piece, range(6), workers=2)


def _one_at_a_time(monkeypatch):
    """datasets.registration's and autodecoder.latent.family's maps as plain loops."""
    import datasets.parallel as parallel

    original = parallel.parallel_map
    monkeypatch.setattr(parallel, "parallel_map", lambda fn, items, tick=None, workers=None:
                        original(fn, items, tick, workers=1))
    import datasets.registration as registration

    monkeypatch.setattr(registration, "parallel_map", parallel.parallel_map)


@pytest.mark.parametrize("motion", ["rigid", "scaled"])
def test_group_registration_side_by_side_equals_one_after_the_other(motion, monkeypatch):
    from datasets.registration import pose_spread, register_group

    scans = [_part(s, n=1500, seed=i, name=f"scan{i}") for i, s in enumerate([0.9, 0.95, 1.05, 1.1])]
    ticks = []
    _, threaded = register_group(scans, rounds=2, motion=motion, return_transforms=True,
                                 tick=lambda: ticks.append(1))
    spread = pose_spread(scans)
    _one_at_a_time(monkeypatch)
    _, looped = register_group(scans, rounds=2, motion=motion, return_transforms=True)
    for a, b in zip(threaded, looped):
        np.testing.assert_array_equal(a, b)
    assert pose_spread(scans) == spread
    assert len(ticks) % len(scans) == 0 and len(ticks) >= len(scans)
