"""Sample a trained model on a raster and write the map folder.

A map is computed tile by tile (``map.tile_pixels`` cells a side); each cell is the
blend of the local GP problems anchored on the blocks around it
(:mod:`gpocc.mapping.blend`), and cells far from every beam are nodata. A map of one
tile is written as single GeoTIFFs; a larger one as tile files under ``tiles/<layer>/``
plus a GDAL VRT mosaic per layer, so no process ever holds the whole map. The map_server
export and the preview are made from the whole map when it is one tile, and from a
decimated copy otherwise.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import gpocc
from gpocc.gp.classify import NO_DATA, class_counts, classify
from gpocc.gridspec import GridSpec
from gpocc.io.atomic import atomic_path
from gpocc.io.mapserver import write_map_server
from gpocc.io.rasters import write_geotiff, write_vrt
from gpocc.mapping.blend import predict_tile
from gpocc.mapping.blocks import AnchorLattice, block_cells
from gpocc.mapping.render import preview_factor, render_preview
from gpocc.mapping.support import model_support

LAYERS = ("probability", "variance", "class")
_PREVIEW_PIXELS = 2000


@dataclass(frozen=True)
class MapSummary:
    """What ``make_map`` wrote: grid, tiles, timings (seconds) and class counts."""

    spec: GridSpec
    tiles: int
    blocks: int
    seconds: float
    class_counts: dict[str, int]


def default_spec(model, resolution: float, margin: float) -> GridSpec:
    """The samples' extent plus ``margin`` metres, at ``resolution`` metres."""
    x0, y0, x1, y1 = model.extent
    return GridSpec.from_bounds(x0 - margin, y0 - margin, x1 + margin, y1 + margin, resolution)


def _tile_windows(spec: GridSpec, tile: int) -> list[tuple[int, int, GridSpec]]:
    return [(r, c, spec.window(r, c, tile, tile))
            for r in range(0, spec.height, tile) for c in range(0, spec.width, tile)]


def make_map(
    model,
    spec: GridSpec,
    out_dir: Path,
    workers: int = 1,
    scheduler: str | None = None,
    progress: Callable[[int], None] | None = None,
) -> MapSummary:
    """Compute the map of ``model`` over ``spec`` and write every layer into ``out_dir``."""
    started = time.perf_counter()
    config = model.config
    occupied, free = config.classify.occupied, config.classify.free
    cells = block_cells(config.model.block_size_m, spec.resolution)
    lattice = AnchorLattice(spec, cells)
    support = model_support(model)
    # Tiles hold whole blocks, so block boundaries are the same however the map is tiled.
    tile = max(cells, (config.map.tile_pixels // cells) * cells)
    windows = _tile_windows(spec, tile)
    tiled = len(windows) > 1
    stride = preview_factor(spec.shape, _PREVIEW_PIXELS)
    preview_spec = spec.decimated(stride)
    preview_v = np.full(preview_spec.shape, np.nan, dtype=np.float32)
    preview_decided = np.full(preview_spec.shape, np.nan, dtype=np.float32)
    tile_files: dict[str, list[tuple[Path, GridSpec]]] = {name: [] for name in LAYERS}
    counts = {"free": 0, "occupied": 0, "unsure": 0}
    n_blocks = 0
    epsg = config.map.epsg

    for row0, col0, window in windows:
        layers = predict_tile(model, lattice, row0, col0, window, support, workers,
                              scheduler, progress)
        n_blocks += layers.anchors
        probability, unsure = layers.probability, layers.unsure
        variance = layers.variance.astype(np.float32)
        classes = classify(probability, occupied, free, unsure)
        for key, value in class_counts(classes).items():
            counts[key] += value
        layers = {"probability": (probability, np.nan), "variance": (variance, np.nan),
                  "class": (classes, NO_DATA)}
        for name, (array, nodata) in layers.items():
            if tiled:
                path = out_dir / "tiles" / name / f"{name}_{row0 // tile}_{col0 // tile}.tif"
                path.parent.mkdir(parents=True, exist_ok=True)
                write_geotiff(path, array, window, nodata=nodata, epsg=epsg)
                tile_files[name].append((path, window))
            else:
                write_geotiff(out_dir / f"{name}.tif", array, window, nodata=nodata, epsg=epsg)
        # Decimated copies for the preview and map_server: the first cell of every
        # stride x stride group (stride 1 unless the map is very large).
        r_off = (-row0) % stride
        c_off = (-col0) % stride
        pr, pc = (row0 + r_off) // stride, (col0 + c_off) // stride
        # map_server has no "unsure by variance": such cells are exported as unknown.
        decided = np.where(unsure, np.nan, probability)
        for target, source in ((preview_v, variance), (preview_decided, decided)):
            part = source[r_off::stride, c_off::stride]
            target[pr:pr + part.shape[0], pc:pc + part.shape[1]] = part

    if tiled:
        for name in LAYERS:
            dtype = "uint8" if name == "class" else "float32"
            nodata = NO_DATA if name == "class" else float("nan")
            write_vrt(out_dir / f"{name}.vrt", tile_files[name], spec, dtype, nodata, epsg)
    write_map_server(out_dir / "map.yaml", preview_decided, preview_spec, occupied, free)
    title = f"gpocc map ({'input noise' if model.input_noise else 'no input noise'})"
    # The preview shows what a user may rely on: cells too uncertain to classify (and so
    # exported as unknown) are drawn as no data; probability.tif keeps the model's value.
    render_preview(out_dir / "preview.png", preview_decided, preview_v, preview_spec,
                   title=title, no_data_label="no data or too uncertain (class: unsure)")
    return MapSummary(spec=spec, tiles=len(windows), blocks=n_blocks,
                      seconds=time.perf_counter() - started, class_counts=counts)


def write_metadata(path: Path, model_path: str, model, summary: MapSummary,
                   extra: dict | None = None) -> None:
    """``metadata.json``: model, resolution, bounds, thresholds, timings, versions."""
    spec = summary.spec
    meta = {
        "gpocc_version": gpocc.__version__,
        "method": "gp" if model.input_noise else "gp-no-input-noise",
        "model": str(model_path),
        "model_versions": model.training.get("versions"),
        "resolution_m": spec.resolution,
        "bounds_m": list(spec.bounds),
        "size_cells": [spec.width, spec.height],
        "epsg": model.config.map.epsg,
        "thresholds": {"occupied": model.config.classify.occupied,
                       "free": model.config.classify.free},
        "kernel": type(model.kernel).__name__,
        "input_noise": model.input_noise,
        "quadrature_level": model.level,
        "neighbours": model.config.model.neighbours,
        "block_size_m": model.config.model.block_size_m,
        "tiles": summary.tiles,
        "blocks": summary.blocks,
        "class_counts": summary.class_counts,
        "timings_s": {"map": round(summary.seconds, 3)},
        "layers": {"probability": "p(occupied), float32",
                   "variance": "latent GP predictive variance, float32",
                   "class": "uint8: 0 free, 1 occupied, 2 unsure, 255 no data"},
    }
    if extra:
        meta.update(extra)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(meta, indent=2) + "\n")
