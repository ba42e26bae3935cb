"""``map_scale.yaml`` + ``map_scale.png``: a Nav2 / ROS map_server map in ``scale`` mode,
which keeps the probability (``map.yaml`` stays trinary).

The image is 8-bit grey + alpha, one pixel per map cell, row 0 north: grey ``v``, the
integer nearest ``255 - 255 p`` among those that Nav2 (below) reads as ``round(100 p)``
exactly, alpha 255 where the map has data and 0 where it has none. A loader recovers
``p = (255 - v) / 255`` within 1/255 of the map's (0.5/255 unless the nearest grey reads
as a neighbouring percent).

Nav2's map_io, in ``scale`` mode, makes a cell unknown (-1) when its pixel is not
opaque; otherwise, with ``occ = (255 - v) / 255`` (``negate: 0``), 100 when
``occ > occupied_thresh``, 0 when ``occ < free_thresh`` and ``rint(100 (occ - free_thresh)
/ (occupied_thresh - free_thresh))`` between. With ``free_thresh: 0`` and
``occupied_thresh: 1`` neither end applies, so Nav2 publishes ``rint(100 occ)``, which
the grey is chosen to make ``map.mcap``'s ``/map`` value. (``100 occ`` is a multiple of
100/255 and never lies half-way between two integers, so no rounding tie arises.)
(ROS 1's map_server scales by 99 instead, and truncates: ``int(99 occ)``.) Nav2's
static costmap layer reads such a map as graded costs only with ``trinary_costmap:
false``.

The image is assembled in memory (2 bytes a cell); ``map.max_pgm_pixels`` bounds it as
it bounds ``map.pgm``.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from gpocc.gridspec import GridSpec
from gpocc.io.atomic import atomic_path

#: Thresholds written to map_scale.yaml (see the module docstring).
SCALE_FREE_THRESH, SCALE_OCCUPIED_THRESH = 0.0, 1.0
#: Grey of a no-data pixel (transparent; map.pgm's unknown grey for viewers ignoring alpha).
NO_DATA_GREY = 205


def scale_pixels(probability: np.ndarray) -> np.ndarray:
    """(h, w, 2) uint8 grey + alpha of (h, w) p(occupied), NaN no data."""
    p = np.asarray(probability)
    known = np.isfinite(p)
    out = np.empty(p.shape + (2,), dtype=np.uint8)
    # Only the known cells in double precision (most of a city is no data).
    q = np.clip(p[known].astype(np.float64), 0.0, 1.0)
    # The greys Nav2 reads as percent v: |100 (255 - g) / 255 - v| < 1/2.
    v = np.rint(100.0 * q)
    low = np.maximum(np.ceil(255.0 * (1.0 - (v + 0.5) / 100.0)), 0.0)
    high = np.minimum(np.floor(255.0 * (1.0 - (v - 0.5) / 100.0)), 255.0)
    grey = out[..., 0]
    grey[...] = NO_DATA_GREY
    grey[known] = np.clip(np.rint(255.0 - 255.0 * q), low, high).astype(np.uint8)
    out[..., 1] = np.where(known, 255, 0).astype(np.uint8)
    return out


def write_scale_map(yaml_path: str | os.PathLike[str], spec: GridSpec,
                    tiles: Iterable[tuple[GridSpec, np.ndarray]]) -> None:
    """Write ``map_scale.yaml`` and its ``.png`` from probability tiles, atomically.

    Args:
        yaml_path: the yaml; the image is written beside it with the same stem and a
            ``.png`` suffix, and named relative to it.
        spec: the whole map's grid (origin and resolution as ``map.yaml``'s).
        tiles: (tile grid, (h, w) p(occupied), NaN no data) pairs on ``spec``'s lattice;
            cells no tile covers are no data.
    """
    from PIL import Image

    from gpocc.io.mapserver import tile_offset

    yaml_path = Path(yaml_path)
    image_path = yaml_path.with_suffix(".png")
    pixels = np.zeros(spec.shape + (2,), dtype=np.uint8)
    pixels[..., 0] = NO_DATA_GREY
    for window, probability in tiles:
        row, col = tile_offset(window, spec)
        pixels[row:row + window.height, col:col + window.width] = scale_pixels(probability)
    text = (
        "# Nav2 map in scale mode written by gpocc: grey = 255 - 255 p(occupied) (within "
        "1), transparent\n# where the map has no data; Nav2 publishes round(100 p). "
        "map.yaml holds the trinary classes.\n"
        f"image: {image_path.name}\n"
        "mode: scale\n"
        f"resolution: {float(spec.resolution)!r}\n"
        f"origin: [{float(spec.x0)!r}, {float(spec.y0)!r}, 0.0]\n"
        "negate: 0\n"
        f"occupied_thresh: {SCALE_OCCUPIED_THRESH!r}\n"
        f"free_thresh: {SCALE_FREE_THRESH!r}\n"
    )
    # The image first: a yaml on disk always names a complete image.
    with atomic_path(image_path) as tmp:
        image = Image.fromarray(pixels)  # (H, W, 2) uint8: grey + alpha ("LA")
        # zlib level 1: a quarter of level 6's time on noisy maps, files 5-25 % larger.
        image.save(tmp, format="PNG", compress_level=1)
    with atomic_path(yaml_path) as tmp:
        tmp.write_text(text)
