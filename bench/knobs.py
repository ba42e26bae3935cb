"""Speed and accuracy of the mapping knobs, through ``gpocc map`` and ``gpocc evaluate``."""

from __future__ import annotations

import dataclasses
import json

from gpocc.constants import RESULTS_FILE

from .harness import gpocc
from .paths import INTEL, INTEL_CONFIG
from .registry import Context, Result, Table, benchmark, require

# (level, neighbours, block_size_m, blend_overlap); the default first, the slowest and
# most exact setting offered second.
SETTINGS = [
    (2, 128, 1.0, 1.0),
    (3, 256, 0.5, 1.0),
    (2, 160, 1.0, 1.0),
    (2, 96, 1.0, 1.0),
    (1, 160, 1.0, 1.0),
    (2, 160, 1.5, 1.0),
    (2, 128, 1.0, 0.5),
    (2, 128, 1.0, 0.25),
]
QUICK = [SETTINGS[0], SETTINGS[6]]


def with_knobs(model_path, out, level: int, neighbours: int, block: float,
               overlap: float) -> None:
    """A copy of the model whose mapping uses these knobs (hyperparameters unchanged)."""
    from gpocc.gp.model import load_model, save_model

    model = load_model(model_path)
    config = model.config
    config = dataclasses.replace(config, model=dataclasses.replace(
        config.model, quadrature_level=level, neighbours=neighbours, block_size_m=block,
        blend_overlap=overlap))
    save_model(dataclasses.replace(model, config=config), out)


@benchmark("knobs", "Speed and accuracy knobs (held-out scans of Intel)")
def knobs(ctx: Context) -> Result:
    """Every 10th scan of the Intel log held out (`gpocc split`), one model trained on
    the rest; then for each setting of the mapping knobs (`model.quadrature_level`,
    `model.neighbours`, `model.block_size_m` = anchor spacing, `model.blend_overlap`) a
    copy of the model with those settings is mapped at 0.1 m with `gpocc map` (2
    workers) and scored with `gpocc evaluate` on the held-out points. Hyperparameters
    and classifier come from the one model, so the rows differ only in how the map is
    computed. A quick run measures the default and blend overlap 0.5 only."""
    require(INTEL)
    split = ctx.work / "knobs-split"
    gpocc("split", INTEL, "--every", "10", "--config", INTEL_CONFIG, "--out", split,
          "--force")
    model_path = ctx.work / "knobs-model.npz"
    gpocc("train", split / "train.mcap", "--config", split / "train.yaml", "--out",
          model_path, "--force")
    rows = []
    for i, setting in enumerate(QUICK if ctx.quick else SETTINGS):
        variant = ctx.work / f"knobs-model-{i}.npz"
        with_knobs(model_path, variant, *setting)
        mapped = gpocc("map", variant, "--resolution", "0.1", "--workers", "2", "--out",
                       ctx.work / f"knobs-map-{i}", "--force")
        gpocc("evaluate", ctx.work / f"knobs-map-{i}", "--ground-truth",
              split / "heldout.csv", "--out", ctx.work / f"knobs-eval-{i}", "--force")
        row = json.loads((ctx.work / f"knobs-eval-{i}" / RESULTS_FILE).read_text())
        row = row["maps"][0]
        note = {SETTINGS[0]: "default", SETTINGS[1]: "most exact"}.get(setting, "")
        rows.append([*(str(k) for k in setting), f"{row['auc']:.4f}",
                     f"{row['fpr_at_tpr97']:.3f}", f"{row['brier']:.4f}",
                     f"{row['log_loss']:.3f}", f"{mapped.wall_s:.1f}", note])
    result = Result()
    result.add(Table(("level", "neighbours", "block m", "overlap", "AUC", "FPR@TPR0.97",
                      "Brier", "log-loss", "map wall s", "note"), rows))
    return result
