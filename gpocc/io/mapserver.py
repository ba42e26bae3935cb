"""ROS map_server / Nav2 occupancy maps: a ``map.yaml`` beside an 8-bit image.

map_server turns a pixel ``v`` (the mean of its colour channels, inverted when
``negate: 1``) into ``p = (255 - v) / 255`` and then, in ``trinary`` mode: occupied when
``p > occupied_thresh``, free when ``p < free_thresh``, unknown otherwise (Nav2's
``map_io``: ``>=`` and ``<=``; our pixels sit clear of both rules). ``origin`` is
the pose (x, y, yaw) of the lower-left corner of the lower-left pixel; image row 0 is
the top (north) row.

We write only the three values 0 (occupied, p = 1), 254 (free, p = 1/255) and 205
(unknown, p = 50/255 = 0.19608), with ``occupied_thresh: 0.65`` and ``free_thresh:
0.196`` (the ROS defaults): 205 then sits just above the free threshold, so map_server
reads back exactly our three classes. The image always has one pixel per map cell:
a large map is assembled tile by tile, never coarsened (an optional size limit errors).
"""

from __future__ import annotations

import errno
import math
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from gpocc.constants import FREE as CLASS_FREE
from gpocc.constants import OCCUPIED as CLASS_OCCUPIED
from gpocc.errors import GpoccError, check_regular_file, first_line
from gpocc.gridspec import GridSpec
from gpocc.io.atomic import atomic_path

#: Pixel values written for each class.
OCCUPIED_PIXEL, FREE_PIXEL, UNKNOWN_PIXEL = 0, 254, 205
#: map_server thresholds written to the yaml (they reproduce the three pixel classes).
YAML_OCCUPIED_THRESH, YAML_FREE_THRESH = 0.65, 0.196
#: Classes returned by :func:`read_map_server`.
FREE, OCCUPIED, UNKNOWN = 0, 1, 2


def map_server_pixels(
    probability: np.ndarray, occupied_threshold: float, free_threshold: float
) -> np.ndarray:
    """(H, W) uint8 pixels of p(occupied): occupied above, free below, else (and NaN) unknown."""
    p = np.asarray(probability, dtype=float)
    if not 0.0 <= free_threshold <= occupied_threshold <= 1.0:
        raise GpoccError(
            f"classify thresholds must satisfy 0 <= free <= occupied <= 1, got free "
            f"{free_threshold}, occupied {occupied_threshold}"
        )
    pixels = np.full(p.shape, UNKNOWN_PIXEL, dtype=np.uint8)
    with np.errstate(invalid="ignore"):  # NaN compares False: stays unknown
        pixels[p > occupied_threshold] = OCCUPIED_PIXEL
        pixels[p < free_threshold] = FREE_PIXEL
    return pixels


def class_pixels(classes: np.ndarray) -> np.ndarray:
    """(H, W) uint8 pixels of gpocc classes: 1 occupied, 0 free, anything else unknown.

    Unsure (2) and no-data (255) cells become unknown: map_server has no other state.
    """
    c = np.asarray(classes)
    pixels = np.full(c.shape, UNKNOWN_PIXEL, dtype=np.uint8)
    pixels[c == CLASS_OCCUPIED] = OCCUPIED_PIXEL
    pixels[c == CLASS_FREE] = FREE_PIXEL
    return pixels


def check_map_server_size(spec: GridSpec, max_pixels: int | None) -> None:
    """Refuse a map whose image would exceed ``max_pixels`` a side (None: no limit).

    The image is never coarsened to fit: a smaller map needs a coarser ``--resolution``
    or smaller bounds, chosen by the user.
    """
    if max_pixels is not None and max(spec.width, spec.height) > max_pixels:
        raise GpoccError(
            f"map.pgm would be {spec.width} x {spec.height} pixels, over map.max_pgm_pixels "
            f"= {max_pixels}; use a coarser resolution or smaller bounds, or raise or "
            f"remove map.max_pgm_pixels"
        )


def write_map_server(
    yaml_path: str | os.PathLike[str],
    probability: np.ndarray,
    spec: GridSpec,
    occupied_threshold: float,
    free_threshold: float,
    max_pixels: int | None = None,
) -> None:
    """Write ``map.yaml`` and its ``.pgm`` (binary P5, 8-bit, trinary), atomically.

    Args:
        yaml_path: the yaml; the image is written beside it with the same stem and a
            ``.pgm`` suffix, and named relative to it.
        probability: (H, W) p(occupied) on ``spec``, NaN where there is no data.
        spec: the grid; its lower-left corner becomes ``origin`` and its cell size
            ``resolution`` (metres). The image has exactly one pixel per cell.
        occupied_threshold: p above it is occupied.
        free_threshold: p below it is free; in between (and NaN) is unknown.
        max_pixels: optional limit on the image side (see :func:`check_map_server_size`).
    """
    p = np.asarray(probability)
    if p.shape != spec.shape:
        raise ValueError(f"probability shape {p.shape} does not match the grid {spec.shape}")
    pixels = map_server_pixels(p, occupied_threshold, free_threshold)
    write_map_server_tiles(yaml_path, spec, [(spec, pixels)], occupied_threshold,
                           free_threshold, max_pixels)


def write_map_server_tiles(
    yaml_path: str | os.PathLike[str],
    spec: GridSpec,
    tiles: Iterable[tuple[GridSpec, np.ndarray]],
    occupied_threshold: float,
    free_threshold: float,
    max_pixels: int | None = None,
) -> None:
    """Write ``map.yaml`` and a full-resolution ``.pgm`` assembled from tiles, atomically.

    Args:
        yaml_path: as for :func:`write_map_server`.
        spec: the whole map's grid.
        tiles: (tile grid, (h, w) uint8 pixels from :func:`map_server_pixels` or
            :func:`class_pixels`) pairs; each tile lies on ``spec``'s lattice. Only one
            tile is in memory at a time; cells no tile covers are unknown.
        occupied_threshold, free_threshold: the thresholds the pixels were made with
            (recorded in the yaml's comment).
        max_pixels: optional limit on the image side (see :func:`check_map_server_size`).
    """
    check_map_server_size(spec, max_pixels)
    yaml_path = Path(yaml_path)
    image_path = yaml_path.with_suffix(".pgm")
    header = (
        f"P5\n# gpocc occupancy map, {spec.resolution!r} m/cell\n"
        f"{spec.width} {spec.height}\n255\n"
    ).encode("ascii")
    # Nav2's map_io: occupied when (255 - v) / 255 >= occupied_thresh, free when it is
    # <= free_thresh (ROS 1 map_server: > and <); our 0 / 254 / 205 pixels give 1.0,
    # 0.0039 and 0.19608, so either rule reads back exactly our three classes.
    text = (
        f"# ROS map_server / Nav2 map written by gpocc: free where p(occupied) < "
        f"{free_threshold!r}, occupied where p > {occupied_threshold!r}; one pixel per "
        f"map cell.\n"
        f"image: {image_path.name}\n"
        f"mode: trinary\n"
        f"resolution: {float(spec.resolution)!r}\n"
        f"origin: [{float(spec.x0)!r}, {float(spec.y0)!r}, 0.0]\n"
        f"negate: 0\n"
        f"occupied_thresh: {YAML_OCCUPIED_THRESH!r}\n"
        f"free_thresh: {YAML_FREE_THRESH!r}\n"
    )
    # The image first: a yaml on disk always names a complete image.
    with atomic_path(image_path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header)
        _write_pixels(tmp, len(header), spec, tiles)
    with atomic_path(yaml_path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def _write_pixels(path: Path, offset: int, spec: GridSpec,
                  tiles: Iterable[tuple[GridSpec, np.ndarray]]) -> None:
    """Fill the image body after the header, one tile at a time, via a memory map."""
    size = offset + spec.width * spec.height
    with open(path, "r+b") as f:
        f.truncate(size)
        # Reserve the blocks now: a memory map over a file the disk cannot hold dies of
        # SIGBUS at the first page it cannot store, where a write would raise ENOSPC.
        if hasattr(os, "posix_fallocate"):
            try:
                os.posix_fallocate(f.fileno(), 0, size)
            except OSError as exc:
                if exc.errno not in (errno.EINVAL, errno.EOPNOTSUPP, errno.ENOSYS):
                    raise OSError(exc.errno, exc.strerror, str(path)) from None
    body = np.memmap(path, dtype=np.uint8, mode="r+", offset=offset, shape=spec.shape)
    try:
        body[...] = UNKNOWN_PIXEL
        for window, pixels in tiles:
            row, col = tile_offset(window, spec)
            px = np.asarray(pixels, dtype=np.uint8)
            if px.shape != window.shape:
                raise ValueError(f"tile pixels {px.shape} do not match its grid {window.shape}")
            body[row:row + window.height, col:col + window.width] = px
        body.flush()
    finally:
        del body


def tile_offset(window: GridSpec, spec: GridSpec) -> tuple[int, int]:
    """(row, col) of tile ``window``'s top-left cell in ``spec``; it must lie on its cells."""
    res = spec.resolution
    col_f, row_f = (window.x0 - spec.x0) / res, (spec.y1 - window.y1) / res
    col, row = round(col_f), round(row_f)
    if (abs(col_f - col) > 1e-6 or abs(row_f - row) > 1e-6
            or not math.isclose(window.resolution, res, rel_tol=1e-9)):
        raise ValueError("a map_server tile is not on the map's cells")
    if col < 0 or row < 0 or col + window.width > spec.width or row + window.height > spec.height:
        raise ValueError("a map_server tile extends outside the map")
    return row, col


def read_map_server(yaml_path: str | os.PathLike[str]) -> tuple[np.ndarray, GridSpec]:
    """Read a map_server map with map_server's own rules.

    Supports ``mode: trinary`` and ``scale`` (where cells between the thresholds, which
    map_server grades as costs, are reported unknown), ``negate``, and PGM (P2/P5) or
    PNG images (grey, grey + alpha, RGB, RGBA: the colour channels are averaged).

    Returns:
        ``(classes (H, W) uint8: 0 free, 1 occupied, 2 unknown, grid)``; row 0 is north.

    Raises:
        GpoccError: missing or malformed yaml, missing keys, ``mode: raw``, a rotated
            origin (yaw != 0), a missing or unreadable image.
    """
    yaml_path = Path(yaml_path)
    meta = _load_yaml(yaml_path)
    fix = "see the ROS map_server map.yaml format"

    def number(key: str, default: float | None = None) -> float:
        value = meta.get(key, default)
        if value is None:
            raise GpoccError(f"{yaml_path}: missing key '{key}'; {fix}")
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise GpoccError(f"{yaml_path}: '{key}' must be a number, got {value!r}") from None
        if not math.isfinite(value):
            raise GpoccError(f"{yaml_path}: '{key}' must be finite, got {value!r}")
        return value

    resolution = number("resolution")
    occupied_thresh = number("occupied_thresh")
    free_thresh = number("free_thresh")
    if not 0.0 <= free_thresh < occupied_thresh <= 1.0:
        raise GpoccError(
            f"{yaml_path}: needs 0 <= free_thresh < occupied_thresh <= 1, got free_thresh "
            f"{free_thresh}, occupied_thresh {occupied_thresh}; {fix}"
        )
    negate = bool(int(number("negate", 0)))
    mode = str(meta.get("mode", "trinary")).strip().lower()
    if mode not in ("trinary", "scale"):
        raise GpoccError(
            f"{yaml_path}: mode '{mode}' is not supported (use trinary or scale)"
        )
    origin = meta.get("origin")
    if not (isinstance(origin, list | tuple) and len(origin) == 3):
        raise GpoccError(f"{yaml_path}: 'origin' must be a list [x, y, yaw]; {fix}")
    try:
        x0, y0, yaw = (float(v) for v in origin)
    except (TypeError, ValueError):
        raise GpoccError(f"{yaml_path}: 'origin' must hold three numbers, got {origin}") from None
    if abs(yaw) > 1e-9:
        raise GpoccError(
            f"{yaml_path}: origin yaw {yaw} rad is not supported (rotated map); "
            f"set it to 0 or rotate the image"
        )
    image = meta.get("image")
    if not isinstance(image, str) or not image:
        raise GpoccError(f"{yaml_path}: missing key 'image' (the map image file); {fix}")
    image_path = Path(image) if os.path.isabs(image) else yaml_path.parent / image

    if not image_path.is_file():
        where = "" if os.path.isabs(image) else " (relative to the yaml's folder)"
        raise GpoccError(f"{yaml_path}: its image {image_path} is not found; fix the yaml's "
                         f"'image'{where} or restore the file")
    # Transparency matters to map_server only between the thresholds, which are
    # unknown here in either mode, so only the colour channels are used.
    grey = _read_image(image_path)
    height, width = grey.shape
    classes = map_server_classes(grey, occupied_thresh, free_thresh, negate)
    try:
        spec = GridSpec(x0, y0, resolution, width, height)
    except GpoccError as exc:
        raise GpoccError(f"{yaml_path}: {exc}") from None
    return classes, spec


def map_server_classes(
    value: np.ndarray, occupied_thresh: float, free_thresh: float, negate: bool
) -> np.ndarray:
    """map_server's trinary rule on (H, W) channel-mean pixel values 0..255.

    Returns uint8 classes: 0 free, 1 occupied, 2 unknown.
    """
    v = np.asarray(value, dtype=np.float64)
    if negate:
        v = 255.0 - v
    occ = (255.0 - v) / 255.0
    classes = np.full(v.shape, UNKNOWN, dtype=np.uint8)
    classes[occ > occupied_thresh] = OCCUPIED
    classes[occ < free_thresh] = FREE
    return classes


def _load_yaml(path: Path) -> dict[str, Any]:
    check_regular_file(path, "map yaml", "check the path")
    try:
        meta = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise GpoccError(f"{path}: not valid YAML ({first_line(exc)}); fix the syntax") from None
    if not isinstance(meta, dict):
        raise GpoccError(f"{path}: expected a map_server yaml mapping (image, resolution, ...)")
    return meta


def _read_image(path: Path) -> np.ndarray:
    """(H, W) colour-channel mean 0..255, an integer as map_server computes it, of an
    existing image file."""
    with open(path, "rb") as f:
        magic = f.read(2)
    if magic in (b"P5", b"P2"):
        return _read_pgm(path)
    if magic == b"\x89P":
        return _read_png(path)
    raise GpoccError(f"{path}: map image must be a PGM (P5/P2) or PNG file")


def _read_pgm(path: Path) -> np.ndarray:
    data = path.read_bytes()
    fields: list[bytes] = []
    pos = 0
    # Header: magic, width, height, maxval, separated by whitespace; '#' starts a comment.
    while len(fields) < 4:
        while pos < len(data) and data[pos:pos + 1].isspace():
            pos += 1
        if pos < len(data) and data[pos:pos + 1] == b"#":
            end = data.find(b"\n", pos)
            pos = len(data) if end < 0 else end + 1
            continue
        start = pos
        while pos < len(data) and not data[pos:pos + 1].isspace():
            pos += 1
        if start == pos:
            raise GpoccError(f"{path}: truncated PGM header")
        fields.append(data[start:pos])
    try:
        width, height, maxval = (int(v) for v in fields[1:])
    except ValueError:
        raise GpoccError(f"{path}: malformed PGM header {fields!r}") from None
    if width <= 0 or height <= 0 or not 0 < maxval < 65536:
        raise GpoccError(f"{path}: malformed PGM header {fields!r}")
    if fields[0] == b"P2":
        try:
            values = np.array(data[pos:].split(), dtype=np.int64)
        except ValueError:
            raise GpoccError(f"{path}: non-numeric pixel in the ASCII PGM") from None
        if values.size < width * height:
            raise GpoccError(f"{path}: truncated PGM ({values.size} of {width * height} pixels)")
        pixels = values[: width * height]
    else:
        pos += 1  # exactly one whitespace byte ends the header
        dtype = np.dtype(np.uint8) if maxval < 256 else np.dtype(">u2")
        n = width * height * dtype.itemsize
        if len(data) - pos < n:
            raise GpoccError(f"{path}: truncated PGM ({len(data) - pos} of {n} pixel bytes)")
        pixels = np.frombuffer(data, dtype=dtype, count=width * height, offset=pos)
    grey = pixels.reshape(height, width).astype(np.int64)
    if maxval != 255:
        # map_server loads through SDL, which yields 8-bit pixels.
        grey = np.round(grey * (255.0 / maxval)).astype(np.int64)
    return grey


def _read_png(path: Path) -> np.ndarray:
    import matplotlib.image

    try:
        img = matplotlib.image.imread(path, format="png")
    except Exception as exc:  # Pillow raises several types for corrupt files
        raise GpoccError(f"{path}: unreadable PNG ({exc})") from None
    a = np.asarray(img)
    if a.dtype.kind == "f":  # matplotlib scales PNG samples to 0..1
        a = np.round(a * 255.0).astype(np.int64)
    else:
        a = a.astype(np.int64)
    if a.ndim == 2:
        return a
    channels = a.shape[2]
    colour = a[:, :, : channels - 1] if channels in (2, 4) else a  # drop alpha
    # map_server sums the colour channels and divides as integers.
    return colour.sum(axis=2) // colour.shape[2]
