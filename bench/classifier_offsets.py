"""Same GP, three classifiers: leave-one-sample-out (published, the default), fitted on
held-out beams (c and s), and the leave-one-out s with the offset c fitted on held-out
beams (``model.training.classifier_offset: beams``).

For every finished case of a ``bench/experiment.py`` work folder whose variant was
trained with ``classifier_holdout: sample``, re-squash the GP maps' probability with the
other two classifiers (the latent mean recovered from p and the variance, as
``experiment.resquashed``) and score all three with ``gpocc evaluate``. Prints
one markdown table. Usage::

    .venv/bin/python bench/classifier_offsets.py --work /tmp/exp/work \
        --variant hit-patches-clearance-0.05 --max-position-std 0.075

``--cell-jitter`` moves every held-out beam point by a uniform offset within one map cell
(``map.resolution_m``) before the two beam fits: a point then stands for the centre of the
cell holding it on a randomly shifted grid, the way a raster is read. Every run also
prints (as HTML comments) the occupied share of the held-out beam points and of each
case's truth rasters.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from experiment import case_truths, evaluate, resquashed  # noqa: E402

from gpocc.config import load_config  # noqa: E402
from gpocc.gp.classify import (  # noqa: E402
    beam_holdout_predictions,
    fit_offset,
    fit_platt,
)
from gpocc.gp.model import load_model  # noqa: E402
from gpocc.io.inputs import read_inputs  # noqa: E402
from gpocc.io.rasters import read_raster  # noqa: E402
from gpocc.samples.heldout import calibration_points  # noqa: E402


def training_input(work: Path, case_dir: Path) -> Path:
    if case_dir.parent.name == "sim":
        return work / "sim" / case_dir.name / "sim.mcap"
    return work / "real" / case_dir.name / "split" / "train-noisy.mcap"


def beam_predictions(model, inputs: Path, config_path: Path,
                     max_position_std_m: float | None = None, cell_jitter: bool = False):
    config = load_config(config_path)
    batches = read_inputs([inputs], config)
    t = model.config.model.training
    calib = calibration_points(batches, model.config, t.calibration_every,
                               max_position_std_m=max_position_std_m)
    if cell_jitter:
        half = 0.5 * model.config.map.resolution_m
        jitter = np.random.default_rng(model.config.seed + 3).uniform(-half, half,
                                                                      calib.points.shape)
        calib = dataclasses.replace(calib, points=calib.points + jitter)
    print(f"<!-- {inputs}: occupied share of held-out beam points "
          f"{np.mean(calib.labels > 0):.3f} -->", flush=True)
    m = model.config.model
    return beam_holdout_predictions(model.kernel, model.noise_variance, model.samples, calib,
                                    m.quadrature_level, m.neighbours, m.block_size_m,
                                    t.calibration_blocks,
                                    np.random.default_rng(model.config.seed + 2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--variant", default="hit-patches-clearance-0.05")
    parser.add_argument("--max-position-std", type=float, default=0.075,
                        help="metres: calibration points known at least this well "
                             "(model.training.calibration_max_position_std_m)")
    parser.add_argument("--cell-jitter", action="store_true",
                        help="fit on beam points moved uniformly within a map cell")
    args = parser.parse_args()
    print("| case | region | method | classifier | a | c | AUC | FPR@TPR0.97 | Brier | log-loss "
          "| ECE |\n|---|---|---|---|---|---|---|---|---|---|---|")
    for case_dir in sorted((args.work / args.variant).glob("*/*")):
        for truth in case_truths(args.work, case_dir).values():
            if truth.suffix == ".tif":
                labels_raster = read_raster(truth)[0]
                labelled = labels_raster[(labels_raster == 0) | (labels_raster == 1)]
                print(f"<!-- {truth}: occupied share of labelled cells "
                      f"{labelled.mean():.3f} -->", flush=True)
        for method in ("gp-no-input-noise", "gp-input-noise"):
            folder = case_dir / method
            if not (folder / "probability.tif").is_file():
                continue
            model = load_model(folder.with_suffix(".npz"))
            mean, var, labels = beam_predictions(model, training_input(args.work, case_dir),
                                                 case_dir / "config.yaml",
                                                 args.max_position_std, args.cell_jitter)
            old = model.classifier
            both = fit_platt(mean, var, labels)
            offset = fit_offset(mean, var, labels, old.extra_variance)
            maps = {"sample": folder,
                    "beams": resquashed(folder, old, both,
                                        folder.with_name(f"{folder.name}-beams")),
                    "beams-offset": resquashed(folder, old, offset,
                                               folder.with_name(f"{folder.name}-beams-offset"))}
            fits = {"sample": old, "beams": both, "beams-offset": offset}
            for scope, truth in case_truths(args.work, case_dir).items():
                rows = evaluate(list(maps.values()), truth,
                                case_dir / f"classifiers-{method}-{scope}")
                for name, row in zip(maps, rows.values(), strict=True):
                    fit = fits[name]
                    print(f"| {case_dir.name} | {scope} | {method} | {name} | {fit.a:.3g} | "
                          f"{fit.offset:.3f} | {row['auc']:.4f} | {row['fpr_at_tpr97']:.3f} | "
                          f"{row['brier']:.4f} | {row['log_loss']:.3f} | {row['ece']:.3f} |",
                          flush=True)


if __name__ == "__main__":
    main()
