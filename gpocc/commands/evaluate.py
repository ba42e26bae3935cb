"""``gpocc evaluate``: ROC, AUC, FPR at TPR 0.97 and calibration of maps against a ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from gpocc.commands.options import Force
from gpocc.errors import GpoccError, check_distinct
from gpocc.evaluation.report import (
    kind_summary,
    probability_raster,
    read_probability,
    results_table,
    sample_map,
    score_protocols,
    unique_names,
    write_outputs,
)
from gpocc.evaluation.truth import labels_at, load_truth_kinds
from gpocc.io.atomic import prepare_output
from gpocc.progress import log


def evaluate(
    maps: list[Path] = typer.Argument(
        ..., help="Map folders (with probability.tif or, tiled, probability.vrt), probability "
        "GeoTIFFs or map.mcap files."
    ),
    ground_truth: Path = typer.Option(
        ..., "--ground-truth", help="GeoTIFF (1/0/no-data), map_server YAML, or x,y,label file."
    ),
    out: Path | None = typer.Option(
        None, "--out",
        help="Folder for roc.png, reliability.png, roc.csv, results.json and results.md.",
    ),
    labels_from: Path | None = typer.Option(
        None, "--labels-from",
        help="Truth raster (GeoTIFF 1/0/no-data, or map_server YAML) that labels each "
        "ground-truth point instead of the file: points on its unknown cells or outside "
        "it are left out.",
    ),
    force: Force = False,
) -> None:
    """Score maps against a ground truth: AUC, FPR at TPR 0.97, Brier, log-loss, ECE.

    Each map's probability is taken at the truth points (nearest cell); points outside a
    map or on no-data cells count as p = 0.5, and the coverage column says how many the
    map covered. A point file with a kind column (gpocc split's heldout.csv: hit, free,
    near-wall) is scored per protocol: the hits with each kind of free point, and all
    points together (union).

    --labels-from scores the same points with the labels of a truth raster at their
    positions: the held-out points of a simulated log are measured with its sensors'
    noise (a noisy hit can land in free space), the simulator's truth raster is exact.
    """
    if out is not None:
        prepare_output(out, force, inputs=[*maps, ground_truth,
                                           *([labels_from] if labels_from else [])])
    check_distinct(maps, "or it is scored twice")
    located = [probability_raster(p) for p in maps]
    names = unique_names([n for n, _ in located], list(maps))
    points, labels, kinds = load_truth_kinds(ground_truth)
    stated = None
    relabelling = None
    if labels_from is not None:
        given = len(points)
        points, labels, kinds, stated = _relabelled(points, labels, kinds, labels_from,
                                                    ground_truth)
        relabelling = {"raster": str(labels_from),
                       "relabelled": int(np.count_nonzero(stated != labels)),
                       "left_out": given - len(points)}
    n_occupied = int(np.count_nonzero(labels == 1))
    n_free = int(labels.size - n_occupied)
    if n_occupied == 0 or n_free == 0:
        raise GpoccError(
            f"{ground_truth}: the ground truth has {n_occupied} occupied and {n_free} free "
            f"points; a ROC needs both"
        )
    log(f"ground truth {ground_truth}: {n_occupied} occupied, {n_free} free points")
    sampled = [sample_map(raster, points) for _, raster in located]
    uncovered = [not np.any(inside & np.isfinite(scores)) for scores, inside in sampled]
    # One map that covers no point: the error below gives both extents. Of several, each
    # uncovered map's warning gives its own.
    if len(located) > 1 or not all(uncovered):
        for (_, raster), missed in zip(located, uncovered, strict=True):
            if missed:
                warn_uncovered(raster, points)
    scored = score_protocols(names, sampled, labels, kinds, stated)
    results = scored[-1].results  # every point: "all" or "union"
    if all(r.coverage == 0.0 for r in results):
        # Every score would be that of p = 0.5 at every point (AUC 0.5): not a result.
        where = (f"the map ({_map_extent(located[0][1])})" if len(results) == 1
                 else f"any of the {len(results)} maps")
        raise GpoccError(
            f"{ground_truth}: none of its {labels.size} points ({_points_extent(points)}) "
            f"lies on a cell with data in {where}; the truth and the map"
            f"{'' if len(results) == 1 else 's'} must share one frame"
        )
    typer.echo(results_table(scored))
    if out is not None:
        write_outputs(out, force, results, list(maps), ground_truth, labels, scored,
                      kind_summary(names, sampled, labels, kinds),
                      labels_from=relabelling)
        log(f"wrote {out}/roc.png, reliability.png, roc.csv, results.json, results.md")


def _relabelled(points: np.ndarray, labels: np.ndarray, kinds: np.ndarray | None,
                raster: Path, ground_truth: Path
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """The (N, 2) points that ``raster`` labels, with its labels, their kinds and the
    labels ``ground_truth`` gave them."""
    truth, known = labels_at(points, raster)
    if not known.any():
        raise GpoccError(
            f"{raster}: none of the {len(points)} points of {ground_truth} "
            f"({_points_extent(points)}) lies on a labelled cell of it; the truth raster "
            "and the points must share one frame"
        )
    changed = int(np.count_nonzero(truth[known] != labels[known]))
    log(f"labels from {raster}: {changed} of {int(known.sum())} points relabelled"
        + (f", {int((~known).sum())} on unknown cells or outside it left out"
           if not known.all() else ""))
    return (points[known], truth[known], None if kinds is None else kinds[known],
            labels[known])


def warn_uncovered(raster: Path, points: np.ndarray) -> None:
    """A warning on stderr for a map that has no value at any truth point, with both
    extents: a truth in another frame, or a map of another area, scores AUC 0.5."""
    log(f"warning: {raster}: none of the {len(points)} truth points lies on a cell with data; "
        f"the map spans {_map_extent(raster)}, the points {_points_extent(points)}; its "
        f"scores count every point as p = 0.5")


def _map_extent(raster: Path) -> str:
    x0, y0, x1, y1 = read_probability(raster)[1].bounds
    return f"x {x0:.1f} .. {x1:.1f}, y {y0:.1f} .. {y1:.1f} m"


def _points_extent(points: np.ndarray) -> str:
    (x0, y0), (x1, y1) = points.min(axis=0), points.max(axis=0)
    return f"x {x0:.1f} .. {x1:.1f}, y {y0:.1f} .. {y1:.1f} m"
