"""Independent pieces of work run side by side on the machine's cores, in threads, their results in order.

Why threads: what is mapped here is numpy and k-d tree work (a scan's registration: ICP steps on a few thousand
points, :mod:`datasets.registration`), which releases Python's lock for most of its time: two threads on two cores
register about twice as many scans a second, with the same transforms to the bit (docs/results_archive.md, "Speed").
Each piece must not touch another's state; each gives the same result wherever it runs, so a map gives what a loop
gives.
"""
import os
from concurrent.futures import ThreadPoolExecutor


def usable_cores():
    """The cores this process may run on (its CPU affinity; ``os.cpu_count()`` where that is not known)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def parallel_map(fn, items, tick=None, workers=None):
    """``[fn(x) for x in items]``, with up to ``workers`` (default :func:`usable_cores`) running at once.

    Parameters
    ----------
    fn : callable
        One piece of work; independent of the others (module docstring).
    items : iterable
    tick : callable, optional
        Called once per finished piece, in ``items``' order, from the calling thread (a progress bar).
    workers : int, optional

    Returns
    -------
    list
        The results in ``items``' order. The first exception raised by a piece is raised here.
    """
    items = list(items)
    workers = min(usable_cores() if workers is None else int(workers), len(items))
    results = []
    if workers <= 1:
        for x in items:
            results.append(fn(x))
            if tick is not None:
                tick()
        return results
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="parallel_map") as pool:
        for result in pool.map(fn, items):
            results.append(result)
            if tick is not None:
                tick()
    return results
