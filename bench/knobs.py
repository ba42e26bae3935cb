"""Speed/accuracy of the inference knobs on Intel's held-out-scan protocol.

Run ``.venv/bin/python bench/knobs.py [--fraction F]``. Splits intel.gfs.log (every 10th
scan held out), trains one model with the default config, then predicts the held-out
points with each setting of the knobs (quadrature level, neighbours per local problem,
block size) exactly as ``gpocc map`` would (each point gets its block's neighbourhood) and
reports AUC, FPR at TPR 0.97 and the prediction time. The last row is the slowest, most
exact setting offered; the default must match its AUC within 0.005.

A random ``--fraction`` of the held-out points (default 0.15, seeded) keeps the exact
setting affordable; every setting is scored on the same points.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from gpocc.blas import single_threaded_blas
from gpocc.evaluation.roc import auc, fpr_at_tpr, roc_curve
from gpocc.evaluation.truth import load_truth
from gpocc.gp.local import NeighbourIndex, predict_local
from gpocc.gp.model import load_model

ROOT = Path(__file__).resolve().parents[1]
INTEL = ROOT.parent / "shared" / "data" / "carmen" / "intel.gfs.log"
GPOCC = [sys.executable, "-m", "gpocc"]

# (level, neighbours, block_size_m); the default first, the most exact last.
SETTINGS = [
    (2, 160, 1.0),
    (1, 160, 1.0),
    (3, 160, 1.0),
    (2, 96, 1.0),
    (2, 256, 1.0),
    (2, 160, 0.5),
    (2, 160, 2.0),
    (4, 256, 0.5),
]

_state: dict = {}


def _init(model_path: str) -> None:
    model = load_model(model_path)
    _state.update(model=model, index=NeighbourIndex(model.samples))


def _predict_group(args: tuple[np.ndarray, np.ndarray, int, int, float]) -> np.ndarray:
    points, centre, level, neighbours, _ = args
    model, index = _state["model"], _state["index"]
    with single_threaded_blas():
        pred = predict_local(model.kernel, model.noise_variance,
                             index.problem(centre, neighbours), points, level)
    return model.classifier.probability(pred.mean, pred.variance)


def predict_points(model_path: Path, points: np.ndarray, origin: np.ndarray, level: int,
                   neighbours: int, block: float, workers: int) -> np.ndarray:
    """p(occupied) at points, each from the neighbourhood of its map block's centre."""
    cell = np.floor((points - origin) / block).astype(np.int64)
    keys, inverse = np.unique(cell, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    groups = []
    for g, key in enumerate(keys):
        members = np.flatnonzero(inverse == g)
        centre = origin + (key + 0.5) * block
        groups.append((members, (points[members], centre, level, neighbours, block)))
    probability = np.empty(len(points))
    with ProcessPoolExecutor(workers, initializer=_init, initargs=(str(model_path),)) as pool:
        results = pool.map(_predict_group, [g[1] for g in groups], chunksize=16)
        for (members, _), values in zip(groups, results, strict=True):
            probability[members] = values
    return probability


def run(cmd: list[str]) -> None:
    print("$ gpocc " + " ".join(cmd[len(GPOCC):]), file=sys.stderr, flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--fraction", type=float, default=0.15)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args()
    if not INTEL.is_file():
        raise SystemExit(f"{INTEL} not found: the benchmark needs ../shared/data/carmen/")
    with tempfile.TemporaryDirectory(prefix="gpocc-knobs-") as tmp:
        work = Path(tmp)
        run([*GPOCC, "split", str(INTEL), "--every", "10", "--config",
             str(ROOT / "configs" / "carmen_intel.yaml"), "--out", str(work / "split")])
        model_path = work / "model.npz"
        started = time.perf_counter()
        run([*GPOCC, "train", str(work / "split" / "train.mcap"), "--config",
             str(work / "split" / "train.yaml"), "--out", str(model_path)])
        train_s = time.perf_counter() - started
        points, labels = load_truth(work / "split" / "heldout.csv")
        rng = np.random.default_rng(0)
        keep = rng.random(len(points)) < args.fraction
        points, labels = points[keep], labels[keep]
        model = load_model(model_path)
        margin = model.config.map.margin_m
        origin = np.array(model.extent[:2]) - margin
        print(f"train (default config): {train_s:.1f} s; {len(points)} held-out points "
              f"({int(labels.sum())} occupied); {args.workers} workers\n")
        print("| level | neighbours | block m | AUC | FPR@TPR0.97 | predict s | note |")
        print("|---|---|---|---|---|---|---|")
        reference = None
        rows = []
        for i, (level, neighbours, block) in enumerate(SETTINGS):
            started = time.perf_counter()
            p = predict_points(model_path, points, origin, level, neighbours, block,
                               args.workers)
            seconds = time.perf_counter() - started
            fpr, tpr, _ = roc_curve(labels, p)
            value = auc(fpr, tpr)
            note = "default" if i == 0 else ("most exact" if i == len(SETTINGS) - 1 else "")
            rows.append((level, neighbours, block, value, fpr_at_tpr(fpr, tpr), seconds, note))
            print(f"| {level} | {neighbours} | {block} | {value:.4f} | "
                  f"{fpr_at_tpr(fpr, tpr):.3f} | {seconds:.1f} | {note} |", flush=True)
            if i == len(SETTINGS) - 1:
                reference = value
        default_auc = rows[0][3]
        print(f"\ndefault AUC - most exact AUC = {default_auc - reference:+.4f} "
              f"(target: within 0.005)")


if __name__ == "__main__":
    main()
