"""Scoring maps against a ground truth and writing the evaluation report files.

A ground truth whose points carry kinds (``gpocc split``'s ``heldout.csv``: ``hit``,
``free``, ``near-wall``) is scored under several protocols (:func:`protocols`): the
occupied points with each kind of free point on its own, and all points together
(``union``). Free points drawn along whole beams rarely fall just in front of a wall, so
that protocol alone rewards maps with thick walls; the near-wall protocol penalises them.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gpocc.constants import RESULTS_FILE
from gpocc.errors import GpoccError
from gpocc.evaluation.calibration import CALIBRATION_BINS, LOG_LOSS_CLIP
from gpocc.evaluation.roc import RocResult, evaluate_scores
from gpocc.gridspec import GridSpec
from gpocc.io.atomic import atomic_directory
from gpocc.io.rasters import (
    BERNOULLI_VARIANCE_BAND,
    CLASS_BAND,
    VARIANCE_BAND,
    band_description,
    read_raster,
    sample_raster,
)
from gpocc.io.rosmap import read_map_mcap
from gpocc.mapping.render import render_reliability, render_roc
from gpocc.progress import log

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


#: Band descriptions of gpocc's layers that hold no probability, and their names.
_NOT_PROBABILITY = {VARIANCE_BAND.description: "variance",
                    BERNOULLI_VARIANCE_BAND.description: "variance",
                    CLASS_BAND.description: "class"}


def sample_map(raster: Path, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One map's probability at the (N, 2) truth points (nearest cell): (N,) scores (NaN
    on no-data) and (N,) inside the map."""
    layer = (_NOT_PROBABILITY.get(band_description(raster) or "")
             if raster.suffix.lower() != ".mcap" else None)
    if layer is not None:  # before reading it whole
        raise GpoccError(f"{raster}: a gpocc {layer} layer, not a probability; pass "
                         "probability.tif (or its map folder)")
    values, spec, nodata = read_probability(raster)
    scores, inside = sample_raster(values, spec, nodata, points)
    finite = scores[np.isfinite(scores) & inside]
    if finite.size and (finite.min() < 0.0 or finite.max() > 1.0):
        raise GpoccError(
            f"{raster}: values outside [0, 1] ({finite.min():g} .. {finite.max():g}); "
            f"pass a probability map (probability.tif), not another layer"
        )
    return scores, inside


def evaluate_map(
    name: str, raster: Path, points: np.ndarray, labels: np.ndarray
) -> RocResult:
    """Sample one map's probability at the truth points (nearest cell) and score it."""
    scores, inside = sample_map(raster, points)
    return evaluate_scores(name, labels, scores, inside)


#: The protocol of a truth without kinds, and of all points of one with kinds.
ALL, UNION = "all", "union"


@dataclass(frozen=True)
class Protocol:
    """A subset of the truth points scored on its own.

    Attributes:
        name: ``all`` (a truth without kinds), ``hits+<kind>`` (the occupied points and
            the free points of one kind) or ``union`` (every point).
        mask: (N,) bool, the points it scores.
    """

    name: str
    mask: np.ndarray


def protocols(labels: np.ndarray, kinds: np.ndarray | None) -> list[Protocol]:
    """The protocols of (N,) labels (1 occupied, 0 free) and their (N,) kinds (or None).

    Without kinds, or when the free points are of one kind only, one protocol of every
    point; otherwise one per kind of free point (the occupied points with it, in order of
    first appearance), then ``union``.
    """
    everything = np.ones(labels.shape, dtype=bool)
    if kinds is None:
        return [Protocol(ALL, everything)]
    free_kinds = list(dict.fromkeys(kinds[labels == 0].tolist()))
    if len(free_kinds) < 2:
        return [Protocol(ALL, everything)]
    occupied = labels == 1
    return [Protocol(f"hits+{k}", occupied | ((kinds == k) & ~occupied)) for k in free_kinds] \
        + [Protocol(UNION, everything)]


@dataclass(frozen=True)
class ProtocolResults:
    """Every map's scores under one protocol.

    Attributes:
        name: the protocol's name (:class:`Protocol`).
        n_occupied: occupied points it scores.
        n_free: free points it scores.
        results: one :class:`RocResult` per map, in the maps' order.
    """

    name: str
    n_occupied: int
    n_free: int
    results: list[RocResult]


def score_protocols(names: list[str], sampled: list[tuple[np.ndarray, np.ndarray]],
                    labels: np.ndarray, kinds: np.ndarray | None,
                    stated: np.ndarray | None = None) -> list[ProtocolResults]:
    """Score every map's sampled ``(scores, inside)`` (:func:`sample_map`) under every
    protocol (:func:`protocols`) of ``kinds`` and the labels the points were drawn with,
    ``stated`` (N,; None: ``labels``). Points relabelled by a truth raster keep the
    protocols of their kinds: a held-out hit in ``hits+free`` whatever its label."""
    out = []
    for protocol in protocols(labels if stated is None else stated, kinds):
        m = protocol.mask
        y = labels[m]
        if not (np.any(y == 1) and np.any(y == 0)):  # relabelled: a kind may hold one label
            log(f"note: protocol {protocol.name} holds {y.size} points of one label; "
                "not scored")
            continue
        results = [evaluate_scores(name, y, scores[m], inside[m])
                   for name, (scores, inside) in zip(names, sampled, strict=True)]
        n_occupied = int(np.count_nonzero(y == 1))
        out.append(ProtocolResults(protocol.name, n_occupied, int(y.size) - n_occupied,
                                   results))
    return out


def kind_summary(names: list[str], sampled: list[tuple[np.ndarray, np.ndarray]],
                 labels: np.ndarray, kinds: np.ndarray | None) -> dict[str, dict]:
    """Per kind of point: its label, count and, per map, the mean p there and its Brier
    score (uncovered points at p = 0.5); empty without kinds."""
    if kinds is None:
        return {}
    summary: dict[str, dict] = {}
    for kind in dict.fromkeys(kinds.tolist()):
        m = kinds == kind
        y = labels[m].astype(float)
        per_map = {}
        for name, (scores, inside) in zip(names, sampled, strict=True):
            s = scores[m]
            p = np.where(inside[m] & np.isfinite(s), s, 0.5)
            per_map[name] = {"mean_p": float(p.mean()), "brier": float(np.mean((p - y) ** 2))}
        summary[kind] = {"n_points": int(m.sum()), "n_occupied": int(np.count_nonzero(y == 1)),
                         "maps": per_map}
    return summary


def _score_cells(r: RocResult) -> tuple[str, ...]:
    return (f"{r.auc:.4f}", f"{r.fpr_at_tpr97:.4f}", f"{r.calibration.brier:.4f}",
            f"{r.calibration.log_loss:.4f}", f"{r.calibration.ece:.4f}",
            f"{100 * r.coverage:.1f}%")


def results_table(results: list[RocResult] | list[ProtocolResults]) -> str:
    """An aligned plain-text table: map, AUC, FPR at TPR 0.97, Brier, log-loss, ECE,
    coverage; given several protocols, a protocol column first (left-aligned too)."""
    header: tuple[str, ...] = ("map", "AUC", "FPR@TPR0.97", "Brier", "log-loss", "ECE",
                               "coverage")
    text_columns = 1
    if results and isinstance(results[0], ProtocolResults):
        groups: list[ProtocolResults] = results  # type: ignore[assignment]
        if len(groups) == 1:
            return results_table(groups[0].results)
        header = ("protocol", *header)
        text_columns = 2
        rows = [(g.name, r.name, *_score_cells(r)) for g in groups for r in g.results]
    else:
        rows = [(r.name, *_score_cells(r)) for r in results]  # type: ignore[union-attr]
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header))]
    lines = []
    for row in [header, *rows]:
        cells = [c.ljust(w) if i < text_columns else c.rjust(w)
                 for i, (c, w) in enumerate(zip(row, widths, strict=True))]
        lines.append("  ".join(cells).rstrip())
    return "\n".join(lines)


#: How the calibration columns are computed, for the report files.
CALIBRATION_NOTE = (
    f"Brier: mean (p - label)^2. Log-loss: mean negative log-likelihood in nats, p clipped "
    f"to [{LOG_LOSS_CLIP:g}, 1 - {LOG_LOSS_CLIP:g}]. ECE: point-weighted mean "
    f"|fraction occupied - mean p| over {CALIBRATION_BINS} equal-width p bins. Points a map "
    f"does not cover count as p = 0.5 in every column."
)


def results_markdown(results: list[RocResult], truth: Path, n_occupied: int, n_free: int,
                     protocols: list[ProtocolResults] | None = None,
                     labels_from: dict[str, Any] | None = None) -> str:
    """The results as a markdown table, with the ground truth named above it; with
    several ``protocols``, one table per protocol (``results`` is then the last, union);
    ``labels_from`` as :func:`write_outputs`'."""
    lines = [f"Ground truth: `{truth}` ({n_occupied} occupied, {n_free} free points)"]
    if labels_from:
        lines[0] += (f", labelled by `{labels_from['raster']}` ({labels_from['relabelled']} "
                     f"relabelled, {labels_from['left_out']} on its unknown cells or "
                     "outside it left out)")
    groups = protocols if protocols and len(protocols) > 1 else [
        ProtocolResults(ALL, n_occupied, n_free, results)]
    for g in groups:
        if len(groups) > 1:
            lines += ["", f"Protocol `{g.name}` ({g.n_occupied} occupied, {g.n_free} free "
                          f"points)"]
        lines += [
            "",
            "| map | AUC | FPR at TPR 0.97 | Brier | log-loss | ECE | coverage |",
            "|:----|----:|----:|----:|----:|----:|----:|",
        ]
        lines += [
            f"| {r.name} | {r.auc:.4f} | {r.fpr_at_tpr97:.4f} | {r.calibration.brier:.4f} | "
            f"{r.calibration.log_loss:.4f} | {r.calibration.ece:.4f} | "
            f"{100 * r.coverage:.1f}% |"
            for r in g.results
        ]
    lines += ["", CALIBRATION_NOTE]
    return "\n".join(lines) + "\n"


def _map_json(r: RocResult, path: Path) -> dict:
    return {
        "name": r.name,
        "path": str(path),
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


def write_outputs(
    out: Path,
    force: bool,
    results: list[RocResult],
    paths: list[Path],
    truth: Path,
    labels: np.ndarray,
    protocol_results: list[ProtocolResults] | None = None,
    kinds: dict[str, dict] | None = None,
    labels_from: dict[str, Any] | None = None,
) -> None:
    """roc.png, reliability.png, roc.csv, results.json and results.md in a new folder,
    atomically. ``results`` score every truth point (the union); results.json's
    ``protocols`` holds every protocol's (:func:`score_protocols`) and ``kinds`` the
    per-kind summary (:func:`kind_summary`); ``labels_from``: the truth raster that
    labelled the points (``raster``, ``relabelled`` and ``left_out`` counts), or None."""
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
            "labels_from": labels_from,
            "n_points": int(labels.size),
            "n_occupied": n_occupied,
            "n_free": n_free,
            "unknown_score": 0.5,
            "calibration": {"log_loss_clip": LOG_LOSS_CLIP, "ece_bins": CALIBRATION_BINS,
                            "binning": "equal-width in p", "note": CALIBRATION_NOTE},
            "maps": [_map_json(r, p) for r, p in zip(results, paths, strict=True)],
            "protocols": [
                {"name": g.name, "n_occupied": g.n_occupied, "n_free": g.n_free,
                 "maps": [_map_json(r, p) for r, p in zip(g.results, paths, strict=True)]}
                for g in (protocol_results or [ProtocolResults(ALL, n_occupied, n_free,
                                                               results)])
            ],
            "kinds": kinds or {},
        }
        (tmp / RESULTS_FILE).write_text(json.dumps(summary, indent=2) + "\n")
        (tmp / "results.md").write_text(
            results_markdown(results, truth, n_occupied, n_free, protocol_results,
                             labels_from))
