"""Accuracy experiments: the two-robot simulation and the held-out-scan protocol on real logs.

Run ``make experiment`` (all of it) or ``.venv/bin/python bench/experiment.py sim``,
``... real``. Every step is a ``gpocc`` command, printed before it runs, so each table
can be reproduced by hand. Prints markdown tables for docs/results.md.

* ``sim``: for each seed, ``gpocc simulate`` (paper Table I platforms) -> ``gpocc grid``,
  ``gpocc train --input-noise off`` + ``map``, ``gpocc train --input-noise on`` + ``map``
  -> ``gpocc evaluate`` against the simulator's truth raster.
* ``real``: for each CARMEN log in ../shared/data/carmen, ``gpocc split --every 10``;
  dense (all other scans) and sparse (every 3rd remaining scan, every 4th beam) training
  sets -> grid and GP with input noise -> ``gpocc evaluate`` against the held-out points.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
CARMEN = ROOT.parent / "shared" / "data" / "carmen"
GPOCC = [sys.executable, "-m", "gpocc"]
SEEDS = (0, 1, 2, 3)


def gpocc(*args: str | Path) -> str:
    """Run one gpocc command (echoed on stderr) and return its stdout."""
    cmd = [str(a) for a in args]
    print("$ gpocc " + " ".join(cmd), file=sys.stderr, flush=True)
    done = subprocess.run([*GPOCC, *cmd], cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"gpocc {' '.join(cmd)} failed:\n{done.stderr}")
    return done.stdout


def evaluate(maps: list[Path], truth: Path, out: Path) -> dict[str, dict]:
    gpocc("evaluate", *maps, "--ground-truth", truth, "--out", out, "--force")
    results = json.loads((out / "results.json").read_text())
    rows = results["maps"] if isinstance(results, dict) and "maps" in results else results
    return {row["name"]: row for row in rows}


def gp_map(inputs: list[Path], config: Path, noise: str, folder: Path, resolution: float,
           bounds: list[str] | None = None) -> tuple[Path, float]:
    """Train and map one GP; returns the map folder and the wall time (s)."""
    started = time.perf_counter()
    model = folder.with_suffix(".npz")
    gpocc("train", *inputs, "--config", config, "--input-noise", noise, "--out", model, "--force")
    extra = ["--bounds", *bounds] if bounds else []
    gpocc("map", model, "--resolution", str(resolution), "--out", folder, "--force", *extra)
    return folder, time.perf_counter() - started


def table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def truth_bounds(truth_tif: Path) -> list[str]:
    from gpocc.io.rasters import read_raster

    _, spec, _ = read_raster(truth_tif)
    return [f"{v:.3f}" for v in spec.bounds]


def run_sim(work: Path, seeds: tuple[int, ...], label_share: float | None = None) -> str:
    rows = []
    for seed in seeds:
        sim = work / f"sim{seed}"
        gpocc("simulate", "--out", sim, "--seed", str(seed), "--force")
        truth = sim / "truth.tif"
        config = sim / "sim.yaml"
        if label_share is not None:
            data = yaml.safe_load(config.read_text())
            data.setdefault("samples", {})["min_label_share"] = label_share
            config = sim / "sim-label-share.yaml"
            config.write_text(yaml.safe_dump(data))
        bounds = truth_bounds(truth)
        res = "0.1"
        gpocc("grid", sim / "sim.mcap", "--config", config, "--resolution", res,
              "--out", sim / "grid", "--force", "--bounds", *bounds)
        gp_map([sim / "sim.mcap"], config, "off", sim / "gp-no-input-noise", 0.1, bounds)
        gp_map([sim / "sim.mcap"], config, "on", sim / "gp-input-noise", 0.1, bounds)
        result = evaluate([sim / "grid", sim / "gp-no-input-noise", sim / "gp-input-noise"],
                          truth, sim / "evaluation")
        for name in ("grid", "gp-no-input-noise", "gp-input-noise"):
            r = result[name]
            rows.append([str(seed), name, f"{r['auc']:.3f}", f"{r['fpr_at_tpr97']:.3f}",
                         f"{100 * r['coverage']:.1f}%"])
    return table(["seed", "method", "AUC", "FPR at TPR 0.97", "coverage"], rows)


def run_real(work: Path, logs: list[str], base_configs: dict[str, Path]) -> str:
    rows = []
    for log in logs:
        path = CARMEN / log
        if not path.is_file():
            print(f"skipping {log}: not in {CARMEN}", file=sys.stderr)
            continue
        stem = path.stem.split(".")[0].split("-")[0]
        for regime, extra in (("dense", []), ("sparse", ["--keep-every", "3",
                                                          "--beam-every", "4"])):
            folder = work / f"{stem}-{regime}"
            gpocc("split", path, "--every", "10", "--config", base_configs[log], "--out",
                  folder / "split", "--force", *extra)
            train = folder / "split" / "train.mcap"
            config = folder / "split" / "train.yaml"
            truth = folder / "split" / "heldout.csv"
            started = time.perf_counter()
            gpocc("grid", train, "--config", config, "--resolution", "0.1",
                  "--out", folder / "grid", "--force")
            grid_s = time.perf_counter() - started
            _, gp_s = gp_map([train], config, "on", folder / "gp-input-noise", 0.1)
            result = evaluate([folder / "grid", folder / "gp-input-noise"], truth,
                              folder / "evaluation")
            g, p = result["grid"], result["gp-input-noise"]
            rows.append([log, regime, f"{g['auc']:.3f}", f"{p['auc']:.3f}",
                         f"{p['auc'] - g['auc']:+.3f}", f"{g['fpr_at_tpr97']:.3f}",
                         f"{p['fpr_at_tpr97']:.3f}", f"{grid_s:.0f}", f"{gp_s:.0f}"])
    return table(["log", "regime", "grid AUC", "GP AUC", "GP - grid", "grid FPR@.97",
                  "GP FPR@.97", "grid s", "GP s"], rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("what", nargs="*", default=["sim", "real"], choices=["sim", "real"])
    parser.add_argument("--work", type=Path, default=ROOT / "out" / "experiment")
    parser.add_argument("--seeds", type=int, nargs="*", default=list(SEEDS))
    parser.add_argument("--label-share", type=float, default=None,
                        help="samples.min_label_share for the simulation's GP rows")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    if "sim" in args.what:
        print("\n## Two-robot simulation (paper Table I platforms)\n")
        print(run_sim(args.work, tuple(args.seeds), args.label_share), flush=True)
    if "real" in args.what:
        configs = {"intel.gfs.log": ROOT / "configs" / "carmen_intel.yaml",
                   "freiburg-079-corrected.log": ROOT / "configs" / "carmen_freiburg.yaml"}
        print("\n## Real logs, every 10th scan held out\n")
        print(run_real(args.work, list(configs), configs), flush=True)


if __name__ == "__main__":
    main()
