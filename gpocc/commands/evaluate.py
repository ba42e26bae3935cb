"""``gpocc evaluate``: ROC, AUC, FPR at TPR 0.97 and calibration of maps against a ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from gpocc.commands.options import Force
from gpocc.errors import GpoccError
from gpocc.evaluation.report import (
    evaluate_map,
    probability_raster,
    results_table,
    unique_names,
    write_outputs,
)
from gpocc.evaluation.truth import load_truth
from gpocc.io.atomic import prepare_output
from gpocc.progress import log


def evaluate(
    maps: list[Path] = typer.Argument(
        ..., help="Map folders (with probability.tif) or probability GeoTIFFs."
    ),
    ground_truth: Path = typer.Option(
        ..., "--ground-truth", help="GeoTIFF (1/0/no-data), map_server YAML, or x,y,label file."
    ),
    out: Path | None = typer.Option(
        None, "--out",
        help="Folder for roc.png, reliability.png, roc.csv, results.json and results.md.",
    ),
    force: Force = False,
) -> None:
    """Score maps against a ground truth: AUC, FPR at TPR 0.97, Brier, log-loss, ECE.

    Each map's probability is taken at the truth points (nearest cell); points outside a
    map or on no-data cells count as p = 0.5, and the coverage column says how many the
    map covered.
    """
    if out is not None:
        prepare_output(out, force, inputs=[*maps, ground_truth])
    located = [probability_raster(p) for p in maps]
    names = unique_names([n for n, _ in located], list(maps))
    points, labels = load_truth(ground_truth)
    n_occupied = int(np.count_nonzero(labels == 1))
    n_free = int(labels.size - n_occupied)
    if n_occupied == 0 or n_free == 0:
        raise GpoccError(
            f"{ground_truth}: the ground truth has {n_occupied} occupied and {n_free} free "
            f"points; a ROC needs both"
        )
    log(f"ground truth {ground_truth}: {n_occupied} occupied, {n_free} free points")
    results = []
    for name, (_, raster) in zip(names, located, strict=True):
        results.append(evaluate_map(name, raster, points, labels))
    typer.echo(results_table(results))
    if out is not None:
        write_outputs(out, force, results, list(maps), ground_truth, labels)
        log(f"wrote {out}/roc.png, reliability.png, roc.csv, results.json, results.md")
