"""The main job on the built-in part: synthesise scans with defects, train, calibrate on held-back good scans, score.

``python -m inspection demo --out demo_output`` (``make demo``). Seeded; everything lands in the output folder:
``tree.h5`` (the synthetic collection), ``model.pt`` (the trained, calibrated model), ``results/`` (report.html,
scores.csv, summary.json, roc.png, scores.png, maps/).
"""
import time
from pathlib import Path

# Sizes chosen to keep the whole demo under 5 minutes on a 2-core CPU.
DEMO_SIZES = dict(n_train=24, n_validation=10, n_test_good=8, n_test_defective=6, n_points=2500)
QUICK_SIZES = dict(n_train=8, n_validation=4, n_test_good=4, n_test_defective=2, n_points=800)
DEMO_EPOCHS = None  # the trainer's default budget
QUICK_EPOCHS = 3


def run_demo(out="demo_output", seed=0, quick=False, progress=True, echo=print):
    """Run the demo into ``out``; returns the score summary (dict)."""
    from datasets import ScanCollection
    from datasets.parts import builtin_part
    from datasets.synth import synthesise

    from .job import calibrate, describe_calibration
    from .run import score

    t_start = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sizes = QUICK_SIZES if quick else DEMO_SIZES
    data, model = out / "tree.h5", out / "model.pt"
    echo(f"[1/4] synthesising scans of the built-in part: {sizes}")
    scans, frame = synthesise(builtin_part(), seed=seed, progress=progress, **sizes)
    ScanCollection.create(data, scans, frame=frame, provenance={"source": "inspection demo", "seed": seed,
                                                                **sizes}, overwrite=True)
    t1 = time.perf_counter()
    from .training import train_model

    epochs = QUICK_EPOCHS if quick else DEMO_EPOCHS
    echo(f"[2/4] training the latent model ({'the default number of' if epochs is None else epochs} epochs; the "
         f"validation scans are held back for calibration)")
    train_model(data, model, calibration_fraction=0.2, seed=seed, quiet=not progress, overwrite=True,
                epochs=epochs)
    echo(f"      trained with autodecoder.latent.train (what train_latent.py runs) -> {model}")
    t2 = time.perf_counter()
    echo("[3/4] calibrating with the defaults (the validation scans and the training scans, cross-fitted)")
    insp, info = calibrate(model, data, progress=progress)
    for line in describe_calibration(insp, info):
        echo(f"      {line}")
    t3 = time.perf_counter()
    echo("[4/4] scoring the test split")
    summary = score(model, data, out / "results", split="test", progress=progress, echo=echo, maps="flagged")
    t4 = time.perf_counter()
    echo(f"timings: synth {t1 - t_start:.0f} s, train {t2 - t1:.0f} s, calibrate {t3 - t2:.0f} s, score "
         f"{t4 - t3:.0f} s, total {t4 - t_start:.0f} s")
    echo(f"open in a browser: {(out / 'results' / 'report.html').resolve().as_uri()} (offline, one file)")
    echo(f"pictures: {out / 'results' / 'roc.png'}, {out / 'results' / 'scores.png'}, coloured clouds in "
         f"{out / 'results' / 'maps'} (colour legend: maps/legend.png)")
    return summary
