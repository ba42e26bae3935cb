"""GeoTIFF and VRT rasters: written with tifffile, readable by GDAL/rasterio and by us.

The GeoTIFFs are single-band, internally tiled, deflate-compressed, carry their
overviews as following pages marked ``NewSubfileType = 1`` (reduced-resolution image,
which is where GDAL looks for internal overviews), and are georeferenced with
ModelPixelScale + ModelTiepoint (north-up, ``RasterPixelIsArea``). Without an EPSG code
the GeoKeys describe a user-defined model in metres, which GDAL reads as a
``LOCAL_CS`` (an engineering frame: metric, not geographic); with one they name the
projected CRS. No-data goes in GDAL's own ASCII tag (42113).

Very large maps are written as tiles plus a GDAL VRT mosaic (:func:`write_vrt`), so no
process needs to hold the whole map; :func:`read_raster` reads either back.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import tifffile

from gpocc.errors import GpoccError
from gpocc.gridspec import GridSpec
from gpocc.io.atomic import atomic_path

try:  # Only imagecodecs has the floating-point predictor; without it floats go unpredicted.
    import imagecodecs  # noqa: F401

    _FLOAT_PREDICTOR = 3
except ImportError:  # pragma: no cover - depends on the environment
    _FLOAT_PREDICTOR = 1

Nodata = float | int | None

#: Name of the local engineering frame written when no EPSG code is given.
LOCAL_FRAME_NAME = "gpocc local map frame"
#: The same frame as GDAL reports it (used as the SRS of VRT mosaics).
LOCAL_FRAME_WKT = (
    f'LOCAL_CS["{LOCAL_FRAME_NAME}",UNIT["metre",1,AUTHORITY["EPSG","9001"]],'
    'AXIS["Easting",EAST],AXIS["Northing",NORTH]]'
)

# TIFF / GeoTIFF tag codes.
_MODEL_PIXEL_SCALE = 33550
_MODEL_TIEPOINT = 33922
_MODEL_TRANSFORMATION = 34264
_GEO_KEY_DIRECTORY = 34735
_GEO_ASCII_PARAMS = 34737
_GDAL_NODATA = 42113

# GeoKey ids and values (GeoTIFF 1.1, OGC 19-008r4).
_GT_MODEL_TYPE = 1024
_GT_RASTER_TYPE = 1025
_GT_CITATION = 1026
_PROJECTED_CS_TYPE = 3072
_PROJ_LINEAR_UNITS = 3076
_MODEL_TYPE_PROJECTED = 1
_USER_DEFINED = 32767
_RASTER_PIXEL_IS_AREA = 1
_RASTER_PIXEL_IS_POINT = 2
_LINEAR_METRE = 9001

_GDAL_TYPES = {
    "uint8": "Byte", "int8": "Int8", "uint16": "UInt16", "int16": "Int16",
    "uint32": "UInt32", "int32": "Int32", "float32": "Float32", "float64": "Float64",
}
_NUMPY_TYPES = {v: k for k, v in _GDAL_TYPES.items()}

_MAX_VRT_DEPTH = 4


# --------------------------------------------------------------------------- writing


def write_geotiff(
    path: str | os.PathLike[str],
    array: np.ndarray,
    spec: GridSpec,
    *,
    nodata: Nodata,
    epsg: int | None = None,
    tile: int = 256,
    overviews: bool = True,
) -> None:
    """Write a single-band, tiled, deflate-compressed GeoTIFF with overviews, atomically.

    Args:
        path: output file; replaced atomically (the caller checks overwrite permission).
        array: (H, W) values; row 0 is north. Any of uint8, int8, (u)int16, (u)int32,
            float32, float64.
        spec: the grid of ``array`` (``spec.shape == array.shape``).
        nodata: value marking cells without data (NaN allowed for floats), or None.
        epsg: projected CRS code; None for a local metric frame (GDAL: ``LOCAL_CS``).
        tile: tile edge in pixels, a multiple of 16.
        overviews: add 2x, 4x, ... reduced pages until the largest side is <= ``tile``.
            Floats are averaged over valid cells; integers (classes) keep the top-left
            cell of each 2 x 2 group, so no class is ever invented.
    """
    a = np.asarray(array)
    if a.ndim != 2 or a.shape != spec.shape:
        raise ValueError(f"array shape {a.shape} does not match the grid {spec.shape}")
    if a.dtype.name not in _GDAL_TYPES:
        raise ValueError(f"cannot write dtype {a.dtype} to a GeoTIFF; use {list(_GDAL_TYPES)}")
    if tile <= 0 or tile % 16:
        raise ValueError(f"tile must be a positive multiple of 16, got {tile}")
    nodata = _check_nodata(nodata, a.dtype)

    extratags = _geotiff_tags(spec, nodata, epsg)
    if a.dtype.kind == "f":
        predictor = _FLOAT_PREDICTOR
    else:
        predictor = 2  # horizontal differencing: long runs of one class become zeros
    options: dict[str, Any] = dict(
        tile=(tile, tile), compression="zlib", predictor=predictor, photometric="minisblack",
        metadata=None, software="gpocc",
    )
    levels = _overview_levels(a, nodata, tile) if overviews else []
    total = a.nbytes + sum(level.nbytes for level in levels)
    with atomic_path(path) as tmp:
        # Classic TIFF offsets are 32-bit; compression rarely grows data, but be safe.
        with tifffile.TiffWriter(tmp, bigtiff=total > 2**31) as tw:
            tw.write(np.ascontiguousarray(a), extratags=extratags, **options)
            for level in levels:
                tw.write(level, subfiletype=1, **options)


def _check_nodata(nodata: Nodata, dtype: np.dtype) -> Nodata:
    if nodata is None:
        return None
    if dtype.kind == "f":
        return float(nodata)
    if isinstance(nodata, float) and not (math.isfinite(nodata) and nodata.is_integer()):
        raise ValueError(f"nodata {nodata} is not representable in {dtype}")
    info = np.iinfo(dtype)
    if not info.min <= int(nodata) <= info.max:
        raise ValueError(f"nodata {nodata} is outside the range of {dtype}")
    return int(nodata)


def _format_nodata(nodata: float | int) -> str:
    if isinstance(nodata, float):
        if math.isnan(nodata):
            return "nan"
        if nodata.is_integer():
            return str(int(nodata))
        return repr(nodata)
    return str(nodata)


def _geotiff_tags(spec: GridSpec, nodata: Nodata, epsg: int | None) -> list[tuple]:
    """tifffile ``extratags``: (code, type, count, value, writeonce)."""
    res = float(spec.resolution)
    keys: list[tuple[int, int, int, int]] = []
    ascii_params = ""
    if epsg is None:
        # What GDAL reads back as LOCAL_CS in metres: a user-defined model whose only
        # definition is a citation and linear units.
        ascii_params = LOCAL_FRAME_NAME + "|"
        keys += [
            (_GT_MODEL_TYPE, 0, 1, _USER_DEFINED),
            (_GT_RASTER_TYPE, 0, 1, _RASTER_PIXEL_IS_AREA),
            (_GT_CITATION, _GEO_ASCII_PARAMS, len(ascii_params), 0),
            (_PROJ_LINEAR_UNITS, 0, 1, _LINEAR_METRE),
        ]
    else:
        if not (isinstance(epsg, int | np.integer) and 1024 <= int(epsg) < _USER_DEFINED):
            raise GpoccError(f"map.epsg: {epsg!r} is not a projected EPSG code (e.g. 32633)")
        keys += [
            (_GT_MODEL_TYPE, 0, 1, _MODEL_TYPE_PROJECTED),
            (_GT_RASTER_TYPE, 0, 1, _RASTER_PIXEL_IS_AREA),
            (_PROJECTED_CS_TYPE, 0, 1, int(epsg)),
        ]
    directory = [1, 1, 0, len(keys)] + [v for key in keys for v in key]
    tags: list[tuple] = [
        (_MODEL_PIXEL_SCALE, 12, 3, (res, res, 0.0), True),
        (_MODEL_TIEPOINT, 12, 6, (0.0, 0.0, 0.0, float(spec.x0), float(spec.y1), 0.0), True),
        (_GEO_KEY_DIRECTORY, 3, len(directory), tuple(directory), True),
    ]
    if ascii_params:
        tags.append((_GEO_ASCII_PARAMS, 2, 0, ascii_params, True))
    if nodata is not None:
        tags.append((_GDAL_NODATA, 2, 0, _format_nodata(nodata), True))
    return tags


def _overview_levels(a: np.ndarray, nodata: Nodata, tile: int) -> list[np.ndarray]:
    """Each level halves the previous one (ceil), as GDAL sizes 2x, 4x, ... overviews."""
    levels = []
    current = a
    while max(current.shape) > tile:
        current = _halve(current, nodata)
        levels.append(current)
    return levels


def _halve(a: np.ndarray, nodata: Nodata) -> np.ndarray:
    """(ceil(H/2), ceil(W/2)): mean of valid cells for floats, top-left cell otherwise."""
    if a.dtype.kind != "f":
        return np.ascontiguousarray(a[::2, ::2])
    h, w = a.shape
    work = np.float64 if a.dtype == np.float64 else np.float32
    padded = np.full((h + h % 2, w + w % 2), np.nan, dtype=work)
    padded[:h, :w] = a
    valid = ~np.isnan(padded)
    if nodata is not None and not math.isnan(nodata):
        valid &= padded != nodata
    values = np.where(valid, padded, work(0))
    # Four strided adds: much faster than reshaping to (h, 2, w, 2) and summing axes.
    total = values[0::2, 0::2] + values[1::2, 0::2] + values[0::2, 1::2] + values[1::2, 1::2]
    count = (valid[0::2, 0::2].astype(np.uint8) + valid[1::2, 0::2] + valid[0::2, 1::2]
             + valid[1::2, 1::2])
    fill = np.nan if nodata is None else nodata
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(count > 0, total / np.maximum(count, 1), fill)
    return out.astype(a.dtype)


def write_vrt(
    path: str | os.PathLike[str],
    layer_tiles: list[tuple[Path, GridSpec]],
    full: GridSpec,
    dtype: Any,
    nodata: Nodata,
    epsg: int | None = None,
) -> None:
    """Write a GDAL VRT mosaic of GeoTIFF tiles, atomically.

    Args:
        path: the ``.vrt`` file; tile paths are stored relative to its folder.
        layer_tiles: (tile file, tile grid) pairs; each grid must lie on ``full``'s
            lattice (same resolution, whole-cell offsets) and inside it.
        full: the mosaic's grid.
        dtype: the tiles' numpy dtype (e.g. ``"float32"``, ``np.uint8``).
        nodata: the tiles' no-data value (also what uncovered cells read as), or None.
        epsg: projected CRS code, or None for the local metric frame.
    """
    vrt_path = Path(path)
    dt = np.dtype(dtype)
    if dt.name not in _GDAL_TYPES:
        raise ValueError(f"cannot mosaic dtype {dt}; use one of {list(_GDAL_TYPES)}")
    nodata = _check_nodata(nodata, dt)
    root = ET.Element("VRTDataset", rasterXSize=str(full.width), rasterYSize=str(full.height))
    srs = ET.SubElement(root, "SRS")
    srs.text = LOCAL_FRAME_WKT if epsg is None else f"EPSG:{int(epsg)}"
    transform = ET.SubElement(root, "GeoTransform")
    transform.text = ", ".join(
        repr(float(v)) for v in (full.x0, full.resolution, 0.0, full.y1, 0.0, -full.resolution)
    )
    band = ET.SubElement(root, "VRTRasterBand", dataType=_GDAL_TYPES[dt.name], band="1")
    if nodata is not None:
        ET.SubElement(band, "NoDataValue").text = _format_nodata(nodata)
    ET.SubElement(band, "ColorInterp").text = "Gray"
    for tile_path, spec in layer_tiles:
        row, col = _offset_in(spec, full, tile_path)
        source = ET.SubElement(band, "SimpleSource")
        rel = os.path.relpath(Path(tile_path).resolve(), vrt_path.parent.resolve())
        ET.SubElement(source, "SourceFilename", relativeToVRT="1").text = Path(rel).as_posix()
        ET.SubElement(source, "SourceBand").text = "1"
        size = dict(xSize=str(spec.width), ySize=str(spec.height))
        ET.SubElement(source, "SrcRect", xOff="0", yOff="0", **size)
        ET.SubElement(source, "DstRect", xOff=str(col), yOff=str(row), **size)
    ET.indent(root)
    with atomic_path(vrt_path) as tmp:
        ET.ElementTree(root).write(tmp, encoding="utf-8", xml_declaration=False)


def _offset_in(spec: GridSpec, full: GridSpec, name: Any) -> tuple[int, int]:
    """(row, col) of ``spec``'s top-left cell in ``full``; it must sit on the lattice."""
    res = full.resolution
    if not math.isclose(spec.resolution, res, rel_tol=1e-9):
        raise ValueError(f"{name}: tile resolution {spec.resolution} differs from {res}")
    col_f = (spec.x0 - full.x0) / res
    row_f = (full.y1 - spec.y1) / res
    col, row = round(col_f), round(row_f)
    if abs(col_f - col) > 1e-6 or abs(row_f - row) > 1e-6:
        raise ValueError(f"{name}: tile is not aligned to the mosaic's cells")
    if col < 0 or row < 0 or col + spec.width > full.width or row + spec.height > full.height:
        raise ValueError(f"{name}: tile extends outside the mosaic")
    return row, col


# --------------------------------------------------------------------------- reading


def read_raster(path: str | os.PathLike[str]) -> tuple[np.ndarray, GridSpec, Nodata]:
    """Read a north-up single-band GeoTIFF or a VRT mosaic of them.

    Returns:
        ``(array (H, W) in the file's dtype, grid, nodata or None)``; row 0 is north.

    Raises:
        GpoccError: missing, unreadable or corrupt file; not georeferenced; rotated,
            sheared, flipped or non-square pixels; more than one band.
    """
    return _read(Path(path), depth=0)


def _read(path: Path, depth: int) -> tuple[np.ndarray, GridSpec, Nodata]:
    if not path.is_file():
        raise GpoccError(f"{path}: raster not found; check the path")
    if path.suffix.lower() == ".vrt":
        if depth >= _MAX_VRT_DEPTH:
            raise GpoccError(f"{path}: VRTs nest too deeply (a VRT referring to itself?)")
        return _read_vrt(path, depth)
    return _read_geotiff(path)


def _read_geotiff(path: Path) -> tuple[np.ndarray, GridSpec, Nodata]:
    fix = "write it as a single-band GeoTIFF (e.g. gdal_translate -of GTiff)"
    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages.first
            tags = {tag.code: tag.value for tag in page.tags.values()}
            if page.samplesperpixel != 1 or len(page.shape) != 2:
                raise GpoccError(f"{path}: expected one band, found shape {page.shape}; {fix}")
            # tifffile fills tiles lying past the end of the file silently; refuse them.
            end = max((o + n for o, n in zip(page.dataoffsets, page.databytecounts,
                                             strict=True)), default=0)
            if end > path.stat().st_size:
                raise GpoccError(f"{path}: the file is truncated (a copy or download was "
                                 f"cut short); write or copy it again")
            array = page.asarray()
    except GpoccError:
        raise
    except Exception as exc:  # tifffile raises many types for bad or unsupported files
        raise GpoccError(
            f"{path}: not a readable TIFF ({type(exc).__name__}: {exc}); {fix}"
        ) from None
    if array.ndim != 2:
        raise GpoccError(f"{path}: expected one band, found shape {array.shape}; {fix}")
    spec = _geotiff_grid(path, tags, array.shape)
    nodata = _parse_nodata(path, tags.get(_GDAL_NODATA), array.dtype)
    return array, spec, nodata


def _geotiff_grid(path: Path, tags: dict[int, Any], shape: tuple[int, int]) -> GridSpec:
    height, width = shape
    fix = "georeference it as a north-up raster (e.g. gdalwarp, or gdal_translate -a_ullr)"
    if _MODEL_TRANSFORMATION in tags:
        m = np.asarray(tags[_MODEL_TRANSFORMATION], dtype=float)
        if m.size != 16:
            raise GpoccError(f"{path}: malformed ModelTransformation tag; {fix}")
        m = m.reshape(4, 4)
        sx, rx, ox = m[0, 0], m[0, 1], m[0, 3]
        ry, sy, oy = m[1, 0], m[1, 1], m[1, 3]
        if rx != 0.0 or ry != 0.0:
            raise GpoccError(f"{path}: the raster is rotated or sheared; {fix}")
        if not sy < 0:
            raise GpoccError(f"{path}: the raster is not north-up (row 0 is south); {fix}")
        sy = -sy
        i0 = j0 = 0.0
    elif _MODEL_PIXEL_SCALE in tags and _MODEL_TIEPOINT in tags:
        scale = np.asarray(tags[_MODEL_PIXEL_SCALE], dtype=float)
        tie = np.asarray(tags[_MODEL_TIEPOINT], dtype=float)
        if scale.size < 2 or tie.size != 6:
            raise GpoccError(
                f"{path}: has {tie.size // 6} tie points (ground control points), "
                f"not one tie point and a pixel scale; {fix}"
            )
        sx, sy = scale[0], scale[1]
        if not sy > 0:
            raise GpoccError(f"{path}: the raster is not north-up (row 0 is south); {fix}")
        i0, j0, ox, oy = tie[0], tie[1], tie[3], tie[4]
    else:
        raise GpoccError(f"{path}: not georeferenced (no GeoTIFF transform tags); {fix}")
    if not (sx > 0 and math.isfinite(sx) and math.isfinite(sy)):
        raise GpoccError(f"{path}: invalid pixel size {sx} x {sy}; {fix}")
    if not math.isclose(sx, sy, rel_tol=1e-9):
        raise GpoccError(
            f"{path}: pixels are not square ({sx} x {sy} m); resample with gdalwarp -tr R R"
        )
    west = ox - i0 * sx
    north = oy + j0 * sy
    if _raster_type(tags) == _RASTER_PIXEL_IS_POINT:
        # The tie point is a cell centre; GDAL shifts it to the corner the same way.
        west -= 0.5 * sx
        north += 0.5 * sy
    return GridSpec(float(west), float(north - height * sy), float(sx), int(width), int(height))


def _raster_type(tags: dict[int, Any]) -> int:
    directory = tags.get(_GEO_KEY_DIRECTORY)
    if directory is None or len(directory) < 4:
        return _RASTER_PIXEL_IS_AREA
    keys = np.asarray(directory[4:], dtype=np.int64)
    for k in range(min(int(directory[3]), keys.size // 4)):
        key_id, location, _, value = keys[4 * k:4 * k + 4]
        if key_id == _GT_RASTER_TYPE and location == 0:
            return int(value)
    return _RASTER_PIXEL_IS_AREA


def _parse_nodata(path: Path, text: Any, dtype: np.dtype) -> Nodata:
    if text is None:
        return None
    text = str(text).strip().strip("\x00")
    if not text:
        return None
    try:
        value = float(text)
    except ValueError:
        raise GpoccError(
            f"{path}: unreadable no-data value {text!r}; set one with gdal_edit -a_nodata"
        ) from None
    if dtype.kind in "iu" and math.isfinite(value) and value.is_integer():
        return int(value)
    return value


def _read_vrt(path: Path, depth: int) -> tuple[np.ndarray, GridSpec, Nodata]:
    fix = "write the mosaic with gpocc or gdalbuildvrt"
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise GpoccError(f"{path}: not a valid VRT (XML error: {exc}); {fix}") from None
    try:
        width = int(root.attrib["rasterXSize"])
        height = int(root.attrib["rasterYSize"])
        gt = [float(v) for v in root.findtext("GeoTransform", "").split(",")]
    except (KeyError, ValueError):
        raise GpoccError(f"{path}: VRT lacks its size or GeoTransform; {fix}") from None
    bands = root.findall("VRTRasterBand")
    if root.tag != "VRTDataset" or len(gt) != 6 or len(bands) != 1:
        raise GpoccError(f"{path}: expected a single-band VRTDataset with a GeoTransform; {fix}")
    x0, sx, rx, y1, ry, sy = gt
    if rx != 0.0 or ry != 0.0:
        raise GpoccError(f"{path}: the mosaic is rotated or sheared; {fix}")
    if not (sx > 0 and sy < 0 and math.isclose(sx, -sy, rel_tol=1e-9)):
        raise GpoccError(f"{path}: the mosaic is not north-up with square pixels; {fix}")
    spec = GridSpec(x0, y1 + height * sy, sx, width, height)
    band = bands[0]
    type_name = band.attrib.get("dataType", "Byte")
    if type_name not in _NUMPY_TYPES:
        raise GpoccError(f"{path}: unsupported VRT data type {type_name}; {fix}")
    dtype = np.dtype(_NUMPY_TYPES[type_name])
    nodata = _parse_nodata(path, band.findtext("NoDataValue"), dtype)
    # GDAL fills cells no source covers with the no-data value, else zero.
    out = np.full((height, width), 0 if nodata is None else nodata, dtype=dtype)
    for source in band:
        if source.tag not in ("SimpleSource", "ComplexSource"):
            continue
        _paste_source(path, source, out, depth)
    return out, spec, nodata


def _paste_source(vrt: Path, source: ET.Element, out: np.ndarray, depth: int) -> None:
    element = source.find("SourceFilename")
    if element is None or not element.text:
        raise GpoccError(f"{vrt}: a VRT source has no SourceFilename")
    name = element.text.strip()
    relative = element.attrib.get("relativeToVRT", "0") == "1"
    src_path = (vrt.parent / name) if relative else Path(name)
    if source.findtext("SourceBand", "1").strip() != "1":
        raise GpoccError(f"{vrt}: source {name} uses a band other than 1 (unsupported)")
    data, _, _ = _read(src_path, depth + 1)
    src = _rect(source.find("SrcRect"), data.shape)
    dst = _rect(source.find("DstRect"), data.shape)
    if src[2:] != dst[2:]:
        raise GpoccError(f"{vrt}: source {name} is resampled (SrcRect != DstRect size); "
                         f"gpocc reads only unscaled mosaics")
    (sc, sr, w, h), (dc, dr, _, _) = src, dst
    block = data[sr:sr + h, sc:sc + w]
    # Clip the destination to the mosaic, as GDAL does.
    r0, c0 = max(dr, 0), max(dc, 0)
    r1, c1 = min(dr + block.shape[0], out.shape[0]), min(dc + block.shape[1], out.shape[1])
    if r1 <= r0 or c1 <= c0:
        return
    block = block[r0 - dr:r1 - dr, c0 - dc:c1 - dc]
    target = out[r0:r1, c0:c1]
    if source.tag == "ComplexSource" and source.findtext("NODATA") is not None:
        # ComplexSource no-data cells are transparent: they do not overwrite.
        nd = _parse_nodata(vrt, source.findtext("NODATA"), block.dtype)
        keep = np.isnan(block) if _is_nan(nd) else block == nd
        target[...] = np.where(keep, target, block)
    else:
        target[...] = block


def _is_nan(value: Nodata) -> bool:
    return isinstance(value, float) and math.isnan(value)


def _rect(element: ET.Element | None, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """(xOff, yOff, xSize, ySize); a missing rect is the whole source."""
    if element is None:
        return 0, 0, shape[1], shape[0]
    a = element.attrib
    values = (a.get("xOff", 0), a.get("yOff", 0), a.get("xSize", shape[1]),
              a.get("ySize", shape[0]))
    return tuple(int(round(float(v))) for v in values)  # type: ignore[return-value]


# --------------------------------------------------------------------------- sampling


def sample_raster(
    array: np.ndarray, spec: GridSpec, nodata: Nodata, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Value of the cell holding each point (nearest-cell lookup).

    Args:
        array: (H, W) raster on ``spec``.
        spec: its grid.
        nodata: cells equal to this (or NaN) hold no data; None if none.
        points: (N, 2) x, y metres.

    Returns:
        ``(values (N,) float64, inside (N,) bool)``: ``inside`` says whether the point
        falls in the grid; ``values`` is NaN outside the grid and on no-data cells.
        A point on an edge shared by two cells belongs to the cell east of a vertical
        edge and north of a horizontal one (the cell whose west / south edge it is).
    """
    a = np.asarray(array)
    if a.shape != spec.shape:
        raise ValueError(f"array shape {a.shape} does not match the grid {spec.shape}")
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    row, col, inside = spec.index_of(pts)
    values = np.full(pts.shape[0], np.nan)
    values[inside] = a[row[inside], col[inside]]
    if nodata is not None and not _is_nan(nodata):
        values[inside & (values == nodata)] = np.nan
    return values, inside
