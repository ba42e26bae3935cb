"""The one writer of map folders, for GP maps (``gpocc map``) and the grid baseline
(``gpocc grid``), so that ``gpocc evaluate`` reads both alike and a change of output
format is one change.

A folder holds ``probability.tif``, ``variance.tif`` and ``class.tif`` (or, for a map of
several tiles, ``tiles/<layer>/*.tif`` plus a GDAL VRT mosaic per layer), ``map.yaml`` +
``map.pgm`` (ROS map_server / Nav2, trinary), ``map_scale.yaml`` + ``map_scale.png`` (Nav2
scale mode: the probability), ``map.mcap`` (the three layers as ROS 2 OccupancyGrids),
``preview.png`` and ``metadata.json``. Layers arrive tile by tile (:meth:`MapFolder.add`),
so no process has to hold a large map; the map_server exports and ``map.mcap`` are always
at the map's resolution (assembled from the layer tiles, one tile or message in memory at a
time; ``map_scale.png`` whole); the preview is made from the whole map when it is at most
``MAX_PREVIEW_PIXELS`` a side, and from a decimated copy (the first cell of every stride x
stride group) otherwise.
"""

from __future__ import annotations

import json
from concurrent.futures import Future, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Any

import numpy as np

import gpocc
from gpocc.config import Config
from gpocc.constants import METADATA_FILE, NO_DATA
from gpocc.gp.classify import class_counts
from gpocc.gridspec import GridSpec, georef_metadata
from gpocc.io.atomic import atomic_path
from gpocc.io.mapserver import class_pixels, tile_offset, write_map_server_tiles
from gpocc.io.rasters import (
    CLASS_BAND,
    PROBABILITY_BAND,
    VARIANCE_BAND,
    Band,
    read_raster,
    write_geotiff,
    write_vrt,
)
from gpocc.io.rosmap import (
    CLASS_TOPIC,
    FRAME_ID,
    MAP_TOPIC,
    MAX_MESSAGE_SIDE,
    UNKNOWN,
    VARIANCE_TOPIC,
    GridLayer,
    class_values,
    occupancy_values,
    stamp_nanoseconds,
    variance_scale,
    variance_values,
    write_map_mcap,
)
from gpocc.io.scalemap import SCALE_FREE_THRESH, SCALE_OCCUPIED_THRESH, write_scale_map
from gpocc.mapping.render import (
    MAX_PREVIEW_PIXELS,
    orientation_label,
    preview_factor,
    render_preview,
)
from gpocc.versions import software_versions

LAYERS = ("probability", "variance", "class")
#: Band descriptions and units of a GP map's layers (a baseline may pass its own).
GP_BANDS = {"probability": PROBABILITY_BAND, "variance": VARIANCE_BAND, "class": CLASS_BAND}
CLASS_LAYER = "uint8: 0 free, 1 occupied, 2 unsure, 255 no data"


class MapFolder:
    """Writes the layers of one map into ``out_dir`` (a temporary folder: see
    :func:`gpocc.io.atomic.atomic_directory`).

    Args:
        out_dir: the folder.
        spec: the whole map's raster geometry.
        config: gives the thresholds (``classify``) and the CRS (``map.georef``).
        tiled: write tiles + VRT mosaics instead of single GeoTIFFs.
        tile: tile side in cells (names the tile files).
        bands: description and unit of each layer's band (default: a GP map's).
        stamp_s: the map's time, seconds (the last scan's stamp; None: unknown, 0 in
            ``map.mcap``).
        max_message_side: largest side of one OccupancyGrid of ``map.mcap``, cells
            (larger maps are split into tiles, :mod:`gpocc.io.rosmap`).
    """

    def __init__(self, out_dir: Path, spec: GridSpec, config: Config, tiled: bool = False,
                 tile: int = 0, bands: dict[str, Band] | None = None,
                 stamp_s: float | None = None,
                 max_message_side: int = MAX_MESSAGE_SIDE) -> None:
        self.out_dir = out_dir
        self.spec = spec
        self.georef = config.map.georef
        self.max_pgm_pixels = config.map.max_pgm_pixels
        self.bands = {**GP_BANDS, **(bands or {})}
        # Every written layer raster (tile) and its grid: the exports are made from them.
        self.layer_files: dict[str, list[tuple[Path, GridSpec]]] = {n: [] for n in LAYERS}
        self.stamp_s = stamp_s
        self.max_message_side = max_message_side
        self.largest_variance = float("nan")
        #: What ``finish`` wrote for ROS (``metadata.json``'s ``ros``).
        self.ros_outputs: dict[str, Any] = {}
        self.occupied = config.classify.occupied
        self.free = config.classify.free
        self.tiled = tiled
        self.tile = tile
        self.stride = preview_factor(spec.shape, MAX_PREVIEW_PIXELS)
        self.preview_spec = spec.decimated(self.stride)
        self.preview_variance = np.full(self.preview_spec.shape, np.nan, dtype=np.float32)
        self.preview_decided = np.full(self.preview_spec.shape, np.nan, dtype=np.float32)
        self.tile_files: dict[str, list[tuple[Path, GridSpec]]] = {n: [] for n in LAYERS}
        self.counts = {"free": 0, "occupied": 0, "unsure": 0}

    def add(self, row0: int, col0: int, window: GridSpec, probability: np.ndarray,
            variance: np.ndarray, classes: np.ndarray,
            decided: np.ndarray | None = None) -> None:
        """Write one tile (the whole map when not tiled) at cell offset (row0, col0).

        Args:
            probability, variance: (h, w) float32, NaN no data.
            classes: (h, w) uint8 (:func:`gpocc.gp.classify.classify`).
            decided: (h, w) the probability a user may rely on, NaN where it is too
                uncertain to classify; the preview shows it (default: ``probability``).
                map.pgm is made from ``classes``.
        """
        for key, value in class_counts(classes).items():
            self.counts[key] += value
        if np.isfinite(variance).any():
            self.largest_variance = float(np.fmax(self.largest_variance, np.nanmax(variance)))
        layers = {"probability": (probability, np.nan), "variance": (variance, np.nan),
                  "class": (classes, NO_DATA)}
        for name, (array, nodata) in layers.items():
            if self.tiled:
                path = (self.out_dir / "tiles" / name
                        / f"{name}_{row0 // self.tile}_{col0 // self.tile}.tif")
                path.parent.mkdir(parents=True, exist_ok=True)
                self.tile_files[name].append((path, window))
            else:
                path = self.out_dir / f"{name}.tif"
            write_geotiff(path, array, window, nodata=nodata, georef=self.georef,
                          band=self.bands[name])
            self.layer_files[name].append((path, window))
        stride = self.stride
        r_off, c_off = (-row0) % stride, (-col0) % stride
        pr, pc = (row0 + r_off) // stride, (col0 + c_off) // stride
        decided = probability if decided is None else decided
        for target, source in ((self.preview_variance, variance),
                               (self.preview_decided, decided)):
            part = source[r_off::stride, c_off::stride]
            target[pr:pr + part.shape[0], pc:pc + part.shape[1]] = part

    def finish(self, title: str, no_data_label: str = "no data") -> dict[str, int]:
        """Write the VRT mosaics (tiled), map_server files and preview; return the class
        counts."""
        if self.tiled:
            for name in LAYERS:
                dtype = "uint8" if name == "class" else "float32"
                nodata = NO_DATA if name == "class" else float("nan")
                write_vrt(self.out_dir / f"{name}.vrt", self.tile_files[name], self.spec,
                          dtype, nodata, self.georef, self.bands[name])
        # The exports are independent files, each made from the layer files: written side
        # by side (their compression, GDAL's reads and most numpy work release the GIL;
        # a 500 m city at 0.1 m: scale map, map.mcap and preview 5, 4 and 3 s one after
        # another).
        with ThreadPoolExecutor(3, thread_name_prefix="gpocc-map-exports") as pool:
            exports = [pool.submit(self._write_map_server), pool.submit(self._write_scale),
                       pool.submit(self._write_mcap)]
            try:
                render_preview(self.out_dir / "preview.png", self.preview_decided,
                               self.preview_variance, self.preview_spec, title=title,
                               no_data_label=no_data_label,
                               orientation=orientation_label(
                                   None if self.georef is None else self.georef.yaw_deg))
            finally:
                # The folder is removed on an error: no thread may still write into it.
                for export in exports:
                    wait_through_interrupts(export)
            for export in exports:
                export.result()
        return dict(self.counts)

    def _write_map_server(self) -> None:
        """map.pgm at full resolution from the class tiles, one tile in memory at a
        time."""
        pgm_tiles = ((window, class_pixels(read_raster(path)[0]))
                     for path, window in self.layer_files["class"])
        write_map_server_tiles(self.out_dir / "map.yaml", self.spec, pgm_tiles, self.occupied,
                               self.free, self.max_pgm_pixels)

    def _write_scale(self) -> None:
        """map_scale.yaml + .png from the probability tiles."""
        write_scale_map(self.out_dir / "map_scale.yaml", self.spec,
                        ((window, read_raster(path)[0])
                         for path, window in self.layer_files["probability"]))

    def _write_mcap(self) -> None:
        """``map.mcap`` from the layer files, one message's cells in memory at a time."""
        scale = variance_scale(self.largest_variance)
        unit = self.bands["variance"].units
        files = self.layer_files
        layers = [
            GridLayer(MAP_TOPIC, lambda w: _assemble(files["probability"], w, self.spec,
                                                     occupancy_values),
                      {"layer": "probability", "values": "round(100 p(occupied)), -1 no data"}),
            GridLayer(CLASS_TOPIC, lambda w: _assemble(files["class"], w, self.spec,
                                                       class_values),
                      {"layer": "class", "values": "0 free, 100 occupied, -1 unsure or no data"}),
            GridLayer(VARIANCE_TOPIC, lambda w: _assemble(
                files["variance"], w, self.spec, lambda v: variance_values(v, scale)),
                {"layer": "variance", "variance_scale": repr(scale), "variance_unit": unit,
                 "values": "round(100 variance / variance_scale) clipped to 0..100, -1 no "
                           "data; variance = value / 100 * variance_scale"}),
        ]
        stamp_ns = stamp_nanoseconds(self.stamp_s)
        topics = write_map_mcap(self.out_dir / "map.mcap", self.spec, layers, stamp_ns,
                                self.max_message_side)
        self.ros_outputs = {
            "map_mcap": {
                "file": "map.mcap",
                "message_type": "nav_msgs/msg/OccupancyGrid",
                "frame_id": FRAME_ID,
                "stamp_ns": stamp_ns,
                "stamp": ("the last scan's" if self.stamp_s is not None
                          else "unknown (0): the model file does not record its scans' times"),
                "topics": topics,
                "max_message_side_cells": self.max_message_side,
                "variance_scale": scale,
                "frame_in_crs": frame_in_crs(self.georef),
            },
            "map_scale": {
                "file": "map_scale.yaml",
                "mode": "scale",
                "free_thresh": SCALE_FREE_THRESH,
                "occupied_thresh": SCALE_OCCUPIED_THRESH,
                "pixels": "grey = 255 - 255 p within 1, alpha 0 where no data; Nav2 "
                          "publishes round(100 (255 - grey) / 255), which is round(100 p)",
            },
        }


def wait_through_interrupts(future: Future) -> None:
    """Wait for ``future`` even through further Ctrl-Cs: on the way out of a failed or
    interrupted map, the output folder's clean-up must not race a thread still writing
    into it (it could leave the temporary folder behind)."""
    while True:
        try:
            wait([future])
            return
        except KeyboardInterrupt:
            continue


def _assemble(files: list[tuple[Path, GridSpec]], window: GridSpec, spec: GridSpec,
              convert: Any) -> np.ndarray:
    """(h, w) int8 OccupancyGrid cells of ``window`` (of ``spec``) from the layer's tile
    files, ``convert``-ed; cells no tile covers are unknown (-1)."""
    out = np.full(window.shape, UNKNOWN, dtype=np.int8)
    wr, wc = tile_offset(window, spec)
    for path, tile in files:
        tr, tc = tile_offset(tile, spec)
        r0, r1 = max(wr, tr), min(wr + window.height, tr + tile.height)
        c0, c1 = max(wc, tc), min(wc + window.width, tc + tile.width)
        if r0 >= r1 or c0 >= c1:
            continue
        part = read_raster(path)[0][r0 - tr:r1 - tr, c0 - tc:c1 - tc]
        out[r0 - wr:r1 - wr, c0 - wc:c1 - wc] = convert(part)
    return out


def frame_in_crs(georef: Any) -> dict[str, Any] | None:
    """How the ROS ``map`` frame of ``map.mcap`` lies in ``map.georef``'s CRS (None: the
    map has no CRS; the frame is the map's local metric frame)."""
    if georef is None:
        return None
    return {
        "epsg": georef.epsg,
        "origin_easting_m": georef.easting_m,
        "origin_northing_m": georef.northing_m,
        "x_axis_yaw_deg": georef.yaw_deg,
        "transform": "E = origin_easting_m + cos(yaw) x - sin(yaw) y, "
                     "N = origin_northing_m + sin(yaw) x + cos(yaw) y, for (x, y) metres in "
                     "frame map and yaw = x_axis_yaw_deg counter-clockwise from east",
    }


def folder_metadata(method: str, spec: GridSpec, config: Config, counts: dict[str, int],
                    layers: dict[str, str], timings_s: dict[str, float],
                    ros: dict[str, Any] | None = None, **extra: Any) -> dict[str, Any]:
    """The content of ``metadata.json``: what every map folder states, then ``extra``.

    Args:
        method: ``grid``, ``gp`` or ``gp-no-input-noise``.
        spec: the map's raster geometry.
        config: gives the CRS and thresholds.
        counts: class counts (:meth:`MapFolder.finish`).
        layers: what the probability and variance layers hold (the class layer is the
            same for every method).
        timings_s: wall seconds per stage (rounded to ms here).
        ros: what the folder wrote for ROS (:attr:`MapFolder.ros_outputs`).
    """
    return {
        "gpocc_version": gpocc.__version__,
        "versions": software_versions(),
        "method": method,
        "resolution_m": spec.resolution,
        "bounds_m": list(spec.bounds),
        "size_cells": [spec.width, spec.height],
        "georef": georef_metadata(config.map.georef),
        "thresholds": {"occupied": config.classify.occupied, "free": config.classify.free},
        "class_counts": counts,
        "timings_s": {k: round(v, 3) for k, v in timings_s.items()},
        "layers": {**layers, "class": CLASS_LAYER},
        **({"ros": ros} if ros else {}),
        **extra,
    }


def write_metadata(out_dir: Path, meta: dict[str, Any]) -> None:
    """Write ``metadata.json`` (from :func:`folder_metadata`) atomically."""
    with atomic_path(out_dir / METADATA_FILE) as tmp:
        tmp.write_text(json.dumps(meta, indent=2) + "\n")
