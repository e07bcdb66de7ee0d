"""Benchmark of scan-collection I/O: write throughput, random-read latency, streaming memory, import throughput.

Run by hand: ``.venv/bin/python benchmarks/collection_io.py [--scans 2000] [--points 20000] [--out DIR]``.
Prints numbers; writes nothing outside ``--out`` (a temporary folder, removed at the end, by default).
"""
import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from datasets import Scan, ScanCollection, write_cloud  # noqa: E402
from datasets.importer import import_tree  # noqa: E402

COMPRESSIONS = {"gzip": ("gzip", 1), "gzip4": ("gzip", 4), "lzf": ("lzf", None), "none": (None, None)}

# run in a fresh interpreter so its peak RSS (VmHWM) belongs to one collection size only
_ITERATE = r"""
import sys, numpy as np
sys.path.insert(0, {repo!r})
from datasets import ScanCollection
def hwm():
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM"):
            return int(line.split()[1]) / 1024
with ScanCollection({path!r}) as c:
    before = hwm()
    total = 0
    for s in c:
        total += len(s)
print(before, hwm(), total)
"""


def scan_stream(n_scans, n_points, seed=0):
    """Synthetic partial scans: a noisy, randomly placed sphere cap per scan (smooth like real surfaces).

    Yields ``Scan`` objects one at a time so writing never holds the whole collection in memory.
    """
    rng = np.random.default_rng(seed)
    for i in range(n_scans):
        d = rng.normal(size=(n_points, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d[:, 2] = np.abs(d[:, 2])  # a hemisphere: what one view of a ball sees
        points = 0.3 * d + rng.uniform(-0.1, 0.1, 3) + rng.normal(scale=1e-3, size=(n_points, 3))
        yield Scan(name=f"train/good/{i:06d}", points=points, normals=d, split="train")


def measure_write(path, n_scans, n_points, compression):
    t = time.perf_counter()
    ScanCollection.create(path, scan_stream(n_scans, n_points), compression=compression, overwrite=True)
    dt = time.perf_counter() - t
    return dt, path.stat().st_size


def measure_reads(path, n_reads=200, seed=1):
    rng = np.random.default_rng(seed)
    with ScanCollection(path) as c:
        idx = rng.integers(0, len(c), n_reads)
        c[0]  # first read pays for the chunk-index B-tree pages
        wall, cpu = [], []
        for i in idx:
            t, t_cpu = time.perf_counter(), time.process_time()
            c[int(i)]
            wall.append(time.perf_counter() - t)
            cpu.append(time.process_time() - t_cpu)
    wall, cpu = np.array(wall) * 1e3, np.array(cpu) * 1e3
    # CPU time as well as wall time: on a shared machine the wall time mostly measures the other users' load
    return float(np.median(wall)), float(np.percentile(wall, 95)), float(np.median(cpu)), float(np.percentile(cpu, 95))


def measure_iter_rss(path):
    repo = str(Path(__file__).resolve().parents[1])
    out = subprocess.run([sys.executable, "-c", _ITERATE.format(repo=repo, path=str(path))], check=True,
                         capture_output=True, text=True).stdout.split()
    return float(out[0]), float(out[1]), int(out[2])


def measure_import(folder, n_files, n_points, normals):
    """Write ``n_files`` PLY sphere scans (with or without normals) and import them as a tree."""
    rng = np.random.default_rng(2)
    src = folder / ("tree_normals" if normals else "tree_no_normals")
    for i in range(n_files):
        d = rng.normal(size=(n_points, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        split = "train/good" if i < n_files // 2 else "test/good"
        write_cloud(src / split / f"{i:04d}.ply", 25.0 * d + [100.0, 50.0, 0.0], d if normals else None)
    t = time.perf_counter()
    import_tree(src, folder / "imported.h5", overwrite=True, progress=False)
    return time.perf_counter() - t


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scans", type=int, default=2000)
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--out", type=Path, default=None, help="work folder (default: a temporary one, removed)")
    ap.add_argument("--compression", default="gzip,lzf,none",
                    help="comma list among gzip (level 1, the default), gzip4, lzf, none (first: rest of run)")
    ap.add_argument("--small-scans", type=int, default=500, help="second collection size for the RSS comparison")
    ap.add_argument("--import-files", type=int, default=200)
    ap.add_argument("--import-points", type=int, default=20000)
    args = ap.parse_args(argv)

    work = args.out or Path(tempfile.mkdtemp(prefix="collection_io_"))
    work.mkdir(parents=True, exist_ok=True)
    print(f"cpus {os.cpu_count()}, load average at start {os.getloadavg()}, work folder {work}")
    raw_mb = args.scans * args.points * 24 / 2**20
    try:
        names = args.compression.split(",")
        for name in names:
            path = work / f"big_{name}.h5"
            dt, size = measure_write(path, args.scans, args.points, COMPRESSIONS[name])
            med, p95, cmed, cp95 = measure_reads(path)
            print(f"[{name}] write {args.scans} scans x {args.points} points: {dt:.1f} s = {args.scans / dt:.0f} "
                  f"scans/s ({raw_mb / dt:.0f} MB/s of points+normals), file {size / 2**20:.0f} MB "
                  f"(raw {raw_mb:.0f} MB); random single-scan read over 200: wall median {med:.2f} ms, p95 {p95:.2f} ms; "
                  f"CPU median {cmed:.2f} ms, p95 {cp95:.2f} ms (page cache warm)")
        main_name = names[0]
        big = work / f"big_{main_name}.h5"
        small = work / f"small_{main_name}.h5"
        measure_write(small, args.small_scans, args.points, COMPRESSIONS[main_name])
        for n, path in ((args.small_scans, small), (args.scans, big)):
            base, peak, total = measure_iter_rss(path)
            print(f"[{main_name}] iterate {n} scans ({total} points): peak RSS {peak:.0f} MB "
                  f"(after open {base:.0f} MB, +{peak - base:.0f} MB while streaming)")
        for normals in (True, False):
            dt = measure_import(work, args.import_files, args.import_points, normals)
            print(f"import {args.import_files} PLY files x {args.import_points} points "
                  f"({'with normals' if normals else 'normals estimated'}): {dt:.1f} s = "
                  f"{args.import_files / dt:.1f} files/s")
        print(f"load average at end {os.getloadavg()}")
    finally:
        if args.out is None:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
