"""Sample a trained model on a raster and write the map folder.

A map is computed tile by tile (``map.tile_pixels`` cells a side); each cell is the
blend of the local GP problems anchored on the blocks around it
(:mod:`gpocc.mapping.blend`), and cells far from every beam are nodata. Each tile is
handed to the folder writer (:class:`gpocc.mapping.folder.MapFolder`) as soon as it is
done, so no process ever holds the whole map.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from gpocc.config import ModelConfig
from gpocc.gp.classify import classify
from gpocc.gp.growth import input_listing
from gpocc.gp.model import GPModel, kernel_parameters
from gpocc.gridspec import CELL_TOLERANCE, GridSpec
from gpocc.io.mapserver import check_map_server_size
from gpocc.io.rasters import prepare_writer
from gpocc.mapping.blend import predict_tile
from gpocc.mapping.blocks import AnchorLattice, block_cells
from gpocc.mapping.executors import anchor_executor
from gpocc.mapping.folder import MapFolder, folder_metadata
from gpocc.mapping.folder import wait_through_interrupts as _wait_through_interrupts
from gpocc.mapping.render import prepare_preview
from gpocc.mapping.support import model_support


@dataclass(frozen=True)
class MapSummary:
    """What ``make_map`` wrote: grid, tiles, timings (seconds) and class counts.

    ``frame``: the grid whose anchor lattice made the map (:func:`lattice_frame`).
    ``stage_seconds``: wall seconds of ``predict`` (local problems and blending, all
    tiles, with what the map process does meanwhile: loading the writers, the caller's
    ``while_running``), ``write`` (tile rasters) and ``finish`` (mosaics, map_server
    files, preview; the caller's ``while_writing`` runs beside the last tile's rasters
    and these).
    """

    spec: GridSpec
    frame: GridSpec
    tiles: int
    blocks: int
    seconds: float
    class_counts: dict[str, int]
    stage_seconds: dict[str, float]
    ros_outputs: dict[str, Any] = field(default_factory=dict)


def default_spec(model: GPModel, resolution: float, margin: float) -> GridSpec:
    """The samples' extent plus ``margin`` metres, at ``resolution`` metres."""
    x0, y0, x1, y1 = model.extent
    return GridSpec.from_bounds(x0 - margin, y0 - margin, x1 + margin, y1 + margin, resolution)


@dataclass(frozen=True)
class MapFrame:
    """Where a map's cells sit on the anchor lattice that computes them.

    ``grid``: the grid the lattice is laid on; the map's first cell is its cell (``row0``,
    ``col0``). ``origin`` and ``shift`` (:class:`AnchorLattice`'s): set when ``grid`` grew
    from the whole map by whole blocks, so that its anchors keep the whole map's centres.
    """

    grid: GridSpec
    row0: int
    col0: int
    origin: tuple[float, float] | None = None
    shift: tuple[int, int] = (0, 0)

    def lattice(self, model: ModelConfig) -> AnchorLattice:
        """The anchor lattice under ``model``'s block size and blend overlap."""
        return replace(AnchorLattice.of_model(self.grid, model), origin=self.origin,
                       shift=self.shift)


def lattice_frame(whole: GridSpec, spec: GridSpec, cells: int) -> MapFrame:
    """The :class:`MapFrame` of a map over ``spec`` whose anchor lattice (``cells`` a
    block) is that of ``whole``.

    ``whole`` is the model's whole map at ``spec``'s resolution (:func:`whole_map`).
    A window on ``whole``'s cells and inside it is mapped on ``whole`` itself, so it
    holds exactly the whole map's values there; one off those cells, on ``whole`` moved
    by at most half a cell onto its own. A window reaching beyond ``whole`` on a side
    grows the grid there by whole blocks (the anchors stay where they are, bit for bit)
    to a block past the window, so that no cell of the window lies where the lattice's
    edge weights are clamped: windows beyond the whole map join without a seam, and
    within half a spacing of the whole map's edge on that side they differ from it (its
    edge cells take their edge anchors' weight whole).
    """
    res = spec.resolution
    cols = (spec.x0 - whole.x0) / res
    rows = (whole.y1 - spec.y1) / res
    # Halves round up, whatever the floating-point noise: windows on the same cells get
    # the same grid.
    col0, row0 = math.floor(cols + 0.5 + 1e-9), math.floor(rows + 0.5 + 1e-9)
    shifted = abs(cols - col0) > CELL_TOLERANCE or abs(rows - row0) > CELL_TOLERANCE
    frame = whole
    if shifted:
        frame = GridSpec(whole.x0 + (cols - col0) * res, whole.y0 - (rows - row0) * res, res,
                         whole.width, whole.height)

    def grown(start: int, length: int, size: int) -> tuple[int, int]:
        """Cells added before and after ``size`` along an axis for ``[start, start +
        length)``: none on a side the window stays within, else whole blocks to a block
        past it."""
        before = (math.ceil(-start / cells) + 1) * cells if start < 0 else 0
        end = start + before + length
        after = 0
        if end > size + before:
            after = (math.ceil(end / cells) + 1) * cells - size - before
        return before, after

    west, east = grown(col0, spec.width, frame.width)
    north, south = grown(row0, spec.height, frame.height)
    if not (west or east or north or south):
        return MapFrame(frame, row0, col0)
    width, height = frame.width + west + east, frame.height + north + south
    top = frame.y1 + north * res
    grid = GridSpec(frame.x0 - west * res, top - height * res, res, width, height)
    # A grid moved onto the window's cells has anchors of its own anyway.
    anchors = {} if shifted else {"origin": (whole.x0, whole.y1),
                                  "shift": (north // cells, west // cells)}
    return MapFrame(grid, row0 + north, col0 + west, **anchors)


def whole_map(model: GPModel, resolution: float) -> GridSpec:
    """The grid of the model's whole map, whose anchor lattice every map of the model
    uses, in cells of ``resolution`` metres: the samples' extent plus ``map.margin_m`` at
    the config's ``map.resolution_m`` (grown north and west to a whole number of
    ``model.block_size_m`` from ``map.anchor_origin_m`` when set), and at another
    resolution a grid from the same north-west corner that covers it. So maps at
    resolutions that divide ``model.block_size_m`` have the same anchors, and their cells
    nest."""
    config = model.config.map
    base = default_spec(model, config.resolution_m, config.margin_m)
    if config.anchor_origin_m is not None:
        # The lattice's corner nearest north-west of the whole map that covers it, whole
        # blocks from the pin: every model pinned there then has its anchors on one lattice
        # at each resolution that divides the block, whatever its map.resolution_m.
        block = model.config.model.block_size_m
        ox, oy = config.anchor_origin_m
        x0 = ox + math.floor((base.x0 - ox) / block + 1e-9) * block
        top = oy - math.floor((oy - base.y1) / block + 1e-9) * block
        res = base.resolution
        width = max(1, math.ceil((base.x1 - x0) / res - CELL_TOLERANCE))
        height = max(1, math.ceil((top - base.y0) / res - CELL_TOLERANCE))
        base = GridSpec(x0, top - height * res, res, width, height)
    if resolution == base.resolution:
        return base
    width = max(1, math.ceil(base.width * base.resolution / resolution - CELL_TOLERANCE))
    height = max(1, math.ceil(base.height * base.resolution / resolution - CELL_TOLERANCE))
    return GridSpec(base.x0, base.y1 - height * resolution, resolution, width, height)


def map_frame(model: GPModel, spec: GridSpec, whole: GridSpec | None = None) -> MapFrame:
    """:func:`lattice_frame` of a map of ``model`` over ``spec``, within ``whole``
    (default: :func:`whole_map` at ``spec``'s resolution)."""
    if whole is None:
        whole = whole_map(model, spec.resolution)
    block = model.config.model.block_size_m
    return lattice_frame(whole, spec, block_cells(block, spec.resolution))


def block_count(model: GPModel, spec: GridSpec, whole: GridSpec | None = None) -> int:
    """The blocks of a map of ``model`` over ``spec`` (:func:`make_map`'s ``progress``
    counts them): the anchors of its lattice whose block's north-west cell is in it."""
    frame = map_frame(model, spec, whole)
    cells = block_cells(model.config.model.block_size_m, spec.resolution)

    def on_axis(first: int, length: int) -> int:
        return len(range(-(-first // cells) * cells, first + length, cells))

    return on_axis(frame.row0, spec.height) * on_axis(frame.col0, spec.width)


def last_scan_stamp(model: GPModel) -> float | None:
    """The stamp of the model's last training scan, seconds (None: a model file written
    before gpocc recorded it)."""
    span = model.training.get("scan_stamps_s")
    if isinstance(span, list | tuple) and len(span) == 2 and isinstance(span[1], int | float):
        return float(span[1])
    return None


def _tile_windows(spec: GridSpec, tile: int) -> list[tuple[int, int, GridSpec]]:
    return [(r, c, spec.window(r, c, tile, tile))
            for r in range(0, spec.height, tile) for c in range(0, spec.width, tile)]


class _SideWork:
    """The map process's own work beside the workers' (loading the writers, the caller's
    ``while_running``): done on the first call only, which is on the first tile whose
    anchors are out, or after the last tile if none had any."""

    def __init__(self, work: list[Callable[[], None]]) -> None:
        self._work = work

    def __call__(self) -> None:
        work, self._work = self._work, []
        for call in work:
            call()


def _write_tile(folder: MapFolder, row0: int, col0: int, window: GridSpec, layers,
                occupied: float, free: float) -> None:
    """Classify one tile's layers (:func:`gpocc.mapping.blend.predict_tile`) and hand
    them to ``folder``."""
    probability, unsure = layers.probability, layers.unsure
    variance = layers.variance.astype(np.float32)
    classes = classify(probability, occupied, free, unsure)
    # The preview draws cells too uncertain to classify as no data.
    folder.add(row0, col0, window, probability, variance, classes,
               decided=np.where(unsure, np.nan, probability))


def make_map(
    model: GPModel,
    spec: GridSpec,
    out_dir: Path,
    workers: int = 1,
    scheduler: str | None = None,
    progress: Callable[[int], None] | None = None,
    while_running: Callable[[], None] | None = None,
    while_writing: Callable[[], None] | None = None,
    whole: GridSpec | None = None,
) -> MapSummary:
    """Compute the map of ``model`` over ``spec`` and write its layers into ``out_dir``
    (:class:`gpocc.mapping.folder.MapFolder`; ``metadata.json`` is the caller's).

    ``while_running()`` is called exactly once: as soon as the first tile with anchors
    has queued them for the local workers, so that the caller's own work is done while
    they compute (the map loads its GeoTIFF and PNG writers there); after the last tile if
    no tile had anchors. With one worker the anchors are computed in this process as
    they are collected, and nothing overlaps. ``while_writing()`` runs on a thread of
    this process while the last tile's rasters and the mosaics, map_server files and
    preview are written, when a core is free (``gpocc build`` writes its model file
    there); its error, if any, is raised after them.

    The local problems are those of the whole map, ``whole`` (default: the model's,
    :func:`whole_map`): a ``spec`` that is a window of it holds its values there
    (:func:`lattice_frame`)."""
    started = time.perf_counter()
    config = model.config
    occupied, free = config.classify.occupied, config.classify.free
    check_map_server_size(spec, config.map.max_pgm_pixels)  # before any work
    frame = map_frame(model, spec, whole)
    lattice = frame.lattice(config.model)
    cells = lattice.cells
    support = model_support(model)
    # Tiles of whole blocks: each tile's anchors are laid out from whole block rows. (The
    # values never depend on the tiling: a window's tiles start where the window does.)
    tile = max(cells, (config.map.tile_pixels // cells) * cells)
    windows = _tile_windows(spec, tile)
    folder = MapFolder(out_dir, spec, config, tiled=len(windows) > 1, tile=tile,
                       stamp_s=last_scan_stamp(model))
    n_blocks = 0
    stages = {"predict": 0.0, "write": 0.0, "finish": 0.0}

    # One set of workers for every tile, started before the first tile is laid out: they
    # load the compiled kernels meanwhile.
    # At most the anchors whose footprints meet the map (a count, not a list of them).
    anchors = (math.ceil(spec.height / cells) + 2) * (math.ceil(spec.width / cells) + 2)
    tick = time.perf_counter()
    beside: Future | None = None
    written: Future | None = None  # the tile being written while the next one is computed
    with contextlib.ExitStack() as helper:
        with anchor_executor(model, workers, scheduler, anchors) as executor:
            # A tile's rasters are written on this thread while the workers compute the
            # next tile (before, they waited: 4 tiles of a 500 m city at 0.1 m, 2-3 s
            # each). One tile is in flight at a time, written in order, so the folder
            # gets the same calls as without it. Started after the workers were forked.
            writer = (helper.enter_context(ThreadPoolExecutor(
                1, thread_name_prefix="gpocc-tile-writing")) if len(windows) > 1 else None)
            # The GeoTIFF and PNG writers are loaded once the workers have the first
            # tile's anchors: before, the workers waited for them (0.3 s of every Intel
            # map).
            side = _SideWork(
                ([prepare_writer, prepare_preview] if executor.local_workers else [])
                + ([while_running] if while_running is not None else []))
            stages["predict"] += time.perf_counter() - tick
            for row0, col0, window in windows:
                tick = time.perf_counter()
                layers = predict_tile(model, lattice, frame.row0 + row0, frame.col0 + col0,
                                      window, support,
                                      progress=progress, executor=executor,
                                      while_running=side)
                stages["predict"] += time.perf_counter() - tick
                tick = time.perf_counter()
                if while_writing is not None and (row0, col0) == windows[-1][:2]:
                    # After the workers were forked (never fork beside a thread), when
                    # their last anchors are in and a core is free.
                    beside = helper.enter_context(ThreadPoolExecutor(
                        1, thread_name_prefix="gpocc-map-writing")).submit(while_writing)
                    helper.callback(_wait_through_interrupts, beside)
                n_blocks += layers.anchors
                if written is not None:
                    written.result()
                if writer is None:
                    _write_tile(folder, row0, col0, window, layers, occupied, free)
                else:
                    written = writer.submit(_write_tile, folder, row0, col0, window, layers,
                                            occupied, free)
                    helper.callback(_wait_through_interrupts, written)
                stages["write"] += time.perf_counter() - tick
            tick = time.perf_counter()
            if written is not None:
                written.result()
            stages["write"] += time.perf_counter() - tick

        tick = time.perf_counter()
        side()  # no tile had anchors; counted in predict, as on a tile that had some
        stages["predict"] += time.perf_counter() - tick
        title = f"gpocc map ({'input noise' if model.input_noise else 'no input noise'})"
        # The preview shows what a user may rely on: cells too uncertain to classify (and
        # so exported as unknown) are drawn as no data; probability.tif keeps the model's
        # value.
        tick = time.perf_counter()
        counts = folder.finish(title,
                               no_data_label="no data or too uncertain (class: unsure)")
        if beside is not None:
            beside.result()
        stages["finish"] = time.perf_counter() - tick
    return MapSummary(spec=spec, frame=frame.grid, tiles=len(windows), blocks=n_blocks,
                      seconds=time.perf_counter() - started, class_counts=counts,
                      stage_seconds=stages, ros_outputs=folder.ros_outputs)


def map_metadata(model_path: str, model: GPModel, summary: MapSummary,
                 **extra: Any) -> dict[str, Any]:
    """``metadata.json`` of a GP map: the common fields, the model and its versions."""
    cfg = model.config
    lattice = AnchorLattice.of_model(summary.spec, cfg.model)
    return folder_metadata(
        "gp" if model.input_noise else "gp-no-input-noise", summary.spec, cfg,
        summary.class_counts,
        {"probability": "p(occupied), float32",
         "variance": "latent GP predictive variance, float32"},
        {"map": summary.seconds, **summary.stage_seconds},
        ros=summary.ros_outputs,
        model=str(model_path),
        model_versions=dict(model.versions),
        model_sensors=list(model.samples.sensor_names),
        inputs=input_listing(model.growth, model.inputs),
        kernel=kernel_parameters(model.kernel),
        input_noise=model.input_noise,
        quadrature_level=model.level,
        neighbours=cfg.model.neighbours,
        block_size_m=cfg.model.block_size_m,
        # The anchors' spacing on this map: block_size_m rounded down to whole cells, so
        # maps of one model at two resolutions can differ where it does.
        anchor_spacing_m=round(lattice.cells * summary.spec.resolution, 9),
        # The north-west corner of the first anchor's block: anchors sit at its east and
        # south by half a spacing plus whole spacings.
        anchor_origin_m=[summary.frame.x0, summary.frame.y1],
        blend_overlap=lattice.blend,
        tiles=summary.tiles,
        blocks=summary.blocks,
        **extra,
    )
