"""The latent model's training budget: object AUROC of verdicts.py's collections against the settings that set the
training time (steps, samples per step, net size).

Run by hand from the repository root (not a test):

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/latent_budget.py --name s512e450 \
        --options '{"mean_samples": 512, "screen_samples": 256, "epochs": 450}' --parts enclosure,cup --seeds 0,1,2

For each part and seed: benchmarks/verdicts.py's collection (made, or reused from ``--single``, its work folder) is
copied into ``WORK/<name>/<part>_<key>/``, a model is trained there with ``train_collection(**options)`` (the
library's defaults for everything not in ``--options``; the training seed is the collection's seed) and timed, then
verdicts.py scores it with its defaults (``--work WORK/<name>``: calibration on the held-back scans, rays where the
scans have sensor origins) and prints its table. Training times are wall times of ``train_collection`` in this process
(one torch thread under ``OMP_NUM_THREADS=1``) with the load average at start and end; other work on the machine
slows them down.
"""
import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: spinning OpenMP threads crawl on a shared CPU
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import verdicts  # noqa: E402  (benchmarks/verdicts.py, beside this script)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--name", required=True, help="names the variant's work folder")
    p.add_argument("--options", default="{}", help="JSON object of LatentOptions overrides (e.g. epochs)")
    p.add_argument("--parts", default="fandisk,builtin,enclosure,cup")
    p.add_argument("--seeds", default="0")
    p.add_argument("--single", default="results/verdicts", help="verdicts.py's work folder (collections reused)")
    p.add_argument("--work", default="results/latent_budget")
    args = p.parse_args(argv)
    options = json.loads(args.options)
    if not isinstance(options, dict):
        raise SystemExit("--options must be a JSON object")
    import dataclasses

    import torch

    from autodecoder.latent.train import LatentOptions, train_collection

    unknown = sorted(set(options) - {f.name for f in dataclasses.fields(LatentOptions)})
    if unknown:  # the trainer ignores unknown keys (old checkpoints' configurations): a typo would train the default
        raise SystemExit(f"--options: not LatentOptions fields: {', '.join(unknown)}")

    work = Path(args.work) / args.name
    for seed in [int(s) for s in args.seeds.split(",")]:
        parts = args.parts.split(",")
        for part in parts:
            # verdicts.py's own collection (its cache key), made in --single when missing
            source = verdicts.synth(part, verdicts.main_args(["--parts", part, "--seed", str(seed), "--quiet"]),
                                    Path(args.single))
            folder = work / source.parent.name
            folder.mkdir(parents=True, exist_ok=True)
            if not (folder / "tree.h5").is_file():
                shutil.copyfile(source, folder / "tree.h5")
            model = folder / "model.pt"
            if model.is_file():
                print(f"{part} seed {seed}: model cached: {model}")
                continue
            load0, t0 = os.getloadavg()[0], time.perf_counter()
            train_collection(folder / "tree.h5", model, quiet=True, seed=seed, **options)
            print(f"{part} seed {seed}: trained in {time.perf_counter() - t0:.1f} s ({torch.get_num_threads()} "
                  f"thread(s), load {load0:.1f}-{os.getloadavg()[0]:.1f}) with {json.dumps(options)} -> {model}",
                  flush=True)
        verdicts.main(["--parts", ",".join(parts), "--seed", str(seed), "--quiet", "--work", str(work)])


if __name__ == "__main__":
    main()
