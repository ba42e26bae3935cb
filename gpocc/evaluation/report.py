"""Scoring maps against a ground truth and writing the evaluation report files."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from gpocc.errors import GpoccError
from gpocc.evaluation.calibration import CALIBRATION_BINS, LOG_LOSS_CLIP
from gpocc.evaluation.roc import RocResult, evaluate_scores
from gpocc.gridspec import GridSpec
from gpocc.io.atomic import atomic_directory
from gpocc.io.rasters import read_raster, sample_raster
from gpocc.io.rosmap import read_map_mcap
from gpocc.mapping.render import render_reliability, render_roc

# A folder's rasters first (full float precision); map.mcap holds p in steps of 0.01.
_MAP_FILES = ("probability.tif", "probability.vrt", "map.mcap")
_RASTER_SUFFIXES = {".tif", ".tiff", ".vrt", ".mcap"}


def probability_raster(path: Path) -> tuple[str, Path]:
    """The name and probability raster of a map folder, a probability GeoTIFF/VRT or a
    ``map.mcap`` (its ``/map`` OccupancyGrid, :func:`read_probability`)."""
    if path.is_dir():
        for name in _MAP_FILES:
            if (path / name).is_file():
                return (path.resolve().name or str(path)), path / name
        raise GpoccError(
            f"{path}: no {' or '.join(_MAP_FILES)} in this folder; pass a map folder written "
            f"by gpocc or a probability GeoTIFF"
        )
    if not path.exists():
        raise GpoccError(f"{path}: map not found; pass a map folder or a probability GeoTIFF")
    if path.suffix.lower() not in _RASTER_SUFFIXES:
        raise GpoccError(
            f"{path}: not a map; pass a map folder (with probability.tif) or a probability "
            f"GeoTIFF (.tif), VRT mosaic (.vrt) or map.mcap (.mcap)"
        )
    return path.stem, path


def read_probability(path: Path) -> tuple[np.ndarray, GridSpec, float | int | None]:
    """``(values (H, W), grid, nodata)`` of a probability raster or an MCAP map (p =
    OccupancyGrid value / 100, unknown cells NaN), row 0 north."""
    if path.suffix.lower() == ".mcap":
        return read_map_mcap(path)
    return read_raster(path)


def unique_names(names: list[str], paths: list[Path]) -> list[str]:
    """The names, with colliding ones replaced by the path as given."""
    return [str(p) if names.count(n) > 1 else n for n, p in zip(names, paths, strict=True)]


def evaluate_map(
    name: str, raster: Path, points: np.ndarray, labels: np.ndarray
) -> RocResult:
    """Sample one map's probability at the truth points (nearest cell) and score it."""
    values, spec, nodata = read_probability(raster)
    scores, inside = sample_raster(values, spec, nodata, points)
    finite = scores[np.isfinite(scores) & inside]
    if finite.size and (finite.min() < 0.0 or finite.max() > 1.0):
        raise GpoccError(
            f"{raster}: values outside [0, 1] ({finite.min():g} .. {finite.max():g}); "
            f"pass a probability map (probability.tif), not another layer"
        )
    return evaluate_scores(name, labels, scores, inside)


def results_table(results: list[RocResult]) -> str:
    """An aligned plain-text table: map, AUC, FPR at TPR 0.97, Brier, log-loss, ECE, coverage."""
    header = ("map", "AUC", "FPR@TPR0.97", "Brier", "log-loss", "ECE", "coverage")
    rows = [
        (r.name, f"{r.auc:.4f}", f"{r.fpr_at_tpr97:.4f}", f"{r.calibration.brier:.4f}",
         f"{r.calibration.log_loss:.4f}", f"{r.calibration.ece:.4f}",
         f"{100 * r.coverage:.1f}%")
        for r in results
    ]
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header))]
    lines = []
    for row in [header, *rows]:
        numbers = zip(row[1:], widths[1:], strict=True)
        cells = [row[0].ljust(widths[0])] + [c.rjust(w) for c, w in numbers]
        lines.append("  ".join(cells).rstrip())
    return "\n".join(lines)


#: How the calibration columns are computed, for the report files.
CALIBRATION_NOTE = (
    f"Brier: mean (p - label)^2. Log-loss: mean negative log-likelihood in nats, p clipped "
    f"to [{LOG_LOSS_CLIP:g}, 1 - {LOG_LOSS_CLIP:g}]. ECE: point-weighted mean "
    f"|fraction occupied - mean p| over {CALIBRATION_BINS} equal-width p bins. Points a map "
    f"does not cover count as p = 0.5 in every column."
)


def results_markdown(results: list[RocResult], truth: Path, n_occupied: int, n_free: int) -> str:
    """The results as a markdown table, with the ground truth named above it."""
    lines = [
        f"Ground truth: `{truth}` ({n_occupied} occupied, {n_free} free points)",
        "",
        "| map | AUC | FPR at TPR 0.97 | Brier | log-loss | ECE | coverage |",
        "|:----|----:|----:|----:|----:|----:|----:|",
    ]
    lines += [
        f"| {r.name} | {r.auc:.4f} | {r.fpr_at_tpr97:.4f} | {r.calibration.brier:.4f} | "
        f"{r.calibration.log_loss:.4f} | {r.calibration.ece:.4f} | {100 * r.coverage:.1f}% |"
        for r in results
    ]
    lines += ["", CALIBRATION_NOTE]
    return "\n".join(lines) + "\n"


def write_outputs(
    out: Path,
    force: bool,
    results: list[RocResult],
    paths: list[Path],
    truth: Path,
    labels: np.ndarray,
) -> None:
    """roc.png, reliability.png, roc.csv, results.json and results.md in a new folder,
    atomically."""
    n_occupied = int(np.count_nonzero(labels == 1))
    n_free = int(labels.size - n_occupied)
    with atomic_directory(out, force=force) as tmp:
        render_roc(tmp / "roc.png", [(r.name, r.fpr, r.tpr, r.auc) for r in results])
        render_reliability(tmp / "reliability.png", [
            (r.name, r.calibration.bin_mean_p, r.calibration.bin_fraction_occupied,
             r.calibration.brier, r.calibration.ece) for r in results
        ])
        with (tmp / "roc.csv").open("w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(["map", "fpr", "tpr"])
            for r in results:
                writer.writerows(
                    (r.name, f"{f:.9g}", f"{t:.9g}") for f, t in zip(r.fpr, r.tpr, strict=True)
                )
        summary = {
            "ground_truth": str(truth),
            "n_points": int(labels.size),
            "n_occupied": n_occupied,
            "n_free": n_free,
            "unknown_score": 0.5,
            "calibration": {"log_loss_clip": LOG_LOSS_CLIP, "ece_bins": CALIBRATION_BINS,
                            "binning": "equal-width in p", "note": CALIBRATION_NOTE},
            "maps": [
                {
                    "name": r.name,
                    "path": str(p),
                    "auc": r.auc,
                    "fpr_at_tpr97": r.fpr_at_tpr97,
                    "coverage": r.coverage,
                    "n_points": r.n_points,
                    "brier": r.calibration.brier,
                    "log_loss": r.calibration.log_loss,
                    "ece": r.calibration.ece,
                    "reliability": {
                        "mean_p": r.calibration.bin_mean_p.tolist(),
                        "fraction_occupied": r.calibration.bin_fraction_occupied.tolist(),
                        "count": r.calibration.bin_counts.tolist(),
                    },
                }
                for r, p in zip(results, paths, strict=True)
            ],
        }
        (tmp / "results.json").write_text(json.dumps(summary, indent=2) + "\n")
        (tmp / "results.md").write_text(results_markdown(results, truth, n_occupied, n_free))
