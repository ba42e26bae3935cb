"""GeoTIFF and VRT rasters: Cloud Optimized GeoTIFFs written and read through GDAL.

Every layer is written by GDAL's own COG driver (through rasterio, whose wheels bundle
GDAL), so the layout is exactly what ``rio cogeo validate`` expects: all IFDs (full
resolution, then 2x, 4x, ... overviews) at the start of the file, followed by the tile
data from the smallest overview to the full resolution, tiles in row order. Layers are
single-band, 256 x 256 tiles, deflate with the horizontal (integers) or floating-point
predictor. Overviews average the valid cells of floats and keep the nearest cell of
class layers, so no class is ever invented.

No-data is declared (``GDAL_NODATA``) and used: NaN in float layers, 255 in class
layers. A layer may carry a band description, units, a colour table and category names
as band metadata ``CATEGORY_<value>`` (GDAL's GTiff driver keeps its own CategoryNames
only in a ``.aux.xml`` sidecar, which copies lose; VRT mosaics carry them natively), and
a ``GPOCC_MAP_GRID`` item recording its grid in the robot's map frame.

Georeferencing: without :class:`~gpocc.config.GeorefConfig` the raster is in a local
engineering frame in metres (GDAL: ``LOCAL_CS``), the map frame itself. With one, the
map frame's origin and yaw place it in the projected CRS; a yawed map gets a rotated
geotransform (GeoTIFF ``ModelTransformationTag``), so every cell lands where the robot
saw it while the raster keeps the map's rows and columns.

Very large maps are written as tiles plus a GDAL VRT mosaic (:func:`write_vrt`), each tile
a COG; :func:`read_raster` reads either back, and reads any single-band raster GDAL
reads (any compression, predictor, striped or tiled) for ground truth and evaluation.
"""

from __future__ import annotations

import math
import os
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gpocc.constants import FREE, NO_DATA, OCCUPIED, UNSURE
from gpocc.errors import GpoccError, check_regular_file, first_line
from gpocc.gridspec import GridSpec, geotransform
from gpocc.io.atomic import atomic_path

Nodata = float | int | None

#: Name of the local engineering frame written when no georeference is given.
LOCAL_FRAME_NAME = "gpocc local map frame"
#: The same frame as GDAL reports it (the SRS of local rasters and VRT mosaics).
LOCAL_FRAME_WKT = (
    f'LOCAL_CS["{LOCAL_FRAME_NAME}",UNIT["metre",1,AUTHORITY["EPSG","9001"]],'
    'AXIS["Easting",EAST],AXIS["Northing",NORTH]]'
)
#: Dataset metadata item: ``x0 y0 resolution`` of the raster in the map frame, then the
#: six-number GDAL geotransform it was written with. A reader trusts the map grid only
#: while the file still has that geotransform (gdalwarp and friends copy metadata).
MAP_GRID_TAG = "GPOCC_MAP_GRID"

_GDAL_TYPES = {
    "uint8": "Byte", "int8": "Int8", "uint16": "UInt16", "int16": "Int16",
    "uint32": "UInt32", "int32": "Int32", "float32": "Float32", "float64": "Float64",
}
_NUMPY_TYPES = {v: k for k, v in _GDAL_TYPES.items()}

_MAX_VRT_DEPTH = 4


@dataclass(frozen=True)
class Category:
    """One value of a class layer: its name and RGBA colour (0..255 each)."""

    value: int
    name: str
    rgba: tuple[int, int, int, int]


@dataclass(frozen=True)
class Band:
    """What a layer's band holds: a description, its units, and classes if categorical."""

    description: str
    units: str = ""
    categories: tuple[Category, ...] = ()


def _class_categories() -> tuple[Category, ...]:
    # Free white, occupied black (as in map_server images), unsure amber, no data clear.
    return (Category(FREE, "free", (255, 255, 255, 255)),
            Category(OCCUPIED, "occupied", (0, 0, 0, 255)),
            Category(UNSURE, "unsure", (230, 159, 0, 255)),
            Category(NO_DATA, "no data", (0, 0, 0, 0)))


#: The bands of a map folder's layers.
PROBABILITY_BAND = Band("p(occupied): probability that the cell is occupied", "probability")
VARIANCE_BAND = Band("latent GP predictive variance (of the regression on labels -1/+1)",
                     "label^2")
BERNOULLI_VARIANCE_BAND = Band("Bernoulli variance p (1 - p) of the occupancy", "probability^2")
CLASS_BAND = Band("occupancy class: 0 free, 1 occupied, 2 unsure, 255 no data", "class",
                  _class_categories())
TRUTH_BAND = Band("ground-truth occupancy: 0 free, 1 occupied, 255 unknown", "class",
                  tuple(c for c in _class_categories() if c.value != 2))


# --------------------------------------------------------------------------- writing


def prepare_writer() -> None:
    """Import rasterio and register GDAL's drivers now (0.3-0.4 s), for a caller with time
    to spare before its first :func:`write_geotiff` (a map, while its workers compute)."""
    import rasterio
    import rasterio.io  # noqa: F401
    import rasterio.shutil  # noqa: F401

    with rasterio.Env(GDAL_PAM_ENABLED="NO"):
        pass


def write_geotiff(
    path: str | os.PathLike[str],
    array: np.ndarray,
    spec: GridSpec,
    *,
    nodata: Nodata,
    georef: Any = None,
    band: Band | None = None,
    tile: int = 256,
    overviews: bool = True,
) -> None:
    """Write a single-band Cloud Optimized GeoTIFF with overviews, atomically.

    Args:
        path: output file; replaced atomically (the caller checks overwrite permission).
        array: (H, W) values; row 0 is north. Any of uint8, int8, (u)int16, (u)int32,
            float32, float64. NaN cells of a float layer are no data.
        spec: the grid of ``array`` in the map frame (``spec.shape == array.shape``).
        nodata: value marking cells without data (NaN for floats), or None.
        georef: a :class:`~gpocc.config.GeorefConfig` (EPSG code, origin, yaw) or None
            for a local metric frame (GDAL: ``LOCAL_CS``).
        band: description, units and categories (colour table) of the band.
        tile: tile edge in pixels, a multiple of 16.
        overviews: add 2x, 4x, ... overviews until the largest side fits one tile.
    """
    import rasterio
    from rasterio.io import MemoryFile
    from rasterio.shutil import copy as gdal_copy

    a = np.asarray(array)
    if a.ndim != 2 or a.shape != spec.shape:
        raise ValueError(f"array shape {a.shape} does not match the grid {spec.shape}")
    if a.dtype.name not in _GDAL_TYPES:
        raise ValueError(f"cannot write dtype {a.dtype} to a GeoTIFF; use {list(_GDAL_TYPES)}")
    if tile <= 0 or tile % 16:
        raise ValueError(f"tile must be a positive multiple of 16, got {tile}")
    nodata = _check_nodata(nodata, a.dtype)
    categorical = band is not None and bool(band.categories)
    if categorical and a.dtype != np.uint8:
        raise ValueError(f"a colour table needs uint8 values, got {a.dtype}")

    profile = dict(
        driver="GTiff", width=spec.width, height=spec.height, count=1, dtype=a.dtype.name,
        nodata=nodata, crs=_crs(georef), transform=_affine(spec, georef),
    )
    options = dict(
        COMPRESS="DEFLATE", PREDICTOR="3" if a.dtype.kind == "f" else "2",
        BLOCKSIZE=str(tile), BIGTIFF="IF_SAFER",
        OVERVIEWS="AUTO" if overviews else "NONE",
        # Averages of valid cells for values; the nearest cell for classes.
        OVERVIEW_RESAMPLING="NEAREST" if a.dtype.kind in "iu" else "AVERAGE",
    )
    with rasterio.Env(GDAL_PAM_ENABLED="NO"), atomic_path(path) as tmp:
        # GDAL builds the COG from a finished dataset: stage it in memory (uncompressed,
        # one copy of the array), then let the COG driver lay out IFDs, overviews and
        # tiles, in memory too. The file is written here: a full disk is an OSError
        # (ENOSPC, one line from the CLI), where libtiff printed its own lines and GDAL
        # raised a seek error that named no cause.
        with MemoryFile() as staged:
            with staged.open(**profile) as ds:
                ds.write(a, 1)
                ds.update_tags(**{MAP_GRID_TAG: _map_grid_text(spec, georef)})
                if band is not None:
                    _describe(ds, band)
            with staged.open() as src, MemoryFile(ext=".tif") as cog:
                try:
                    gdal_copy(src, cog.name, driver="COG", **options)
                except MemoryError:
                    raise
                except Exception as exc:  # GDAL's errors (CPLE_*) share no public base
                    raise GpoccError(f"{path}: GDAL could not make the GeoTIFF "
                                     f"({first_line(exc)})") from None
                with open(tmp, "wb") as f:
                    f.write(cog.getbuffer())


def _describe(ds: Any, band: Band) -> None:
    ds.set_band_description(1, band.description)
    if band.units:
        ds.set_band_unit(1, band.units)
    if band.categories:
        ds.write_colormap(1, {c.value: c.rgba for c in band.categories})
        ds.update_tags(1, **{f"CATEGORY_{c.value}": c.name for c in band.categories})


def _map_grid_text(spec: GridSpec, georef: Any) -> str:
    values = (spec.x0, spec.y0, spec.resolution, *geotransform(spec, georef))
    return " ".join(repr(float(v)) for v in values)


def _crs(georef: Any) -> Any:
    from rasterio.crs import CRS

    if georef is None:
        return CRS.from_wkt(LOCAL_FRAME_WKT)
    return CRS.from_epsg(int(georef.epsg))


def _affine(spec: GridSpec, georef: Any) -> Any:
    from affine import Affine

    return Affine.from_gdal(*geotransform(spec, georef))


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


def write_vrt(
    path: str | os.PathLike[str],
    layer_tiles: list[tuple[Path, GridSpec]],
    full: GridSpec,
    dtype: Any,
    nodata: Nodata,
    georef: Any = None,
    band: Band | None = None,
) -> None:
    """Write a GDAL VRT mosaic of GeoTIFF tiles, atomically.

    Args:
        path: the ``.vrt`` file; tile paths are stored relative to its folder.
        layer_tiles: (tile file, tile grid) pairs; each grid must lie on ``full``'s
            lattice (same resolution, whole-cell offsets) and inside it.
        full: the mosaic's grid in the map frame.
        dtype: the tiles' numpy dtype (e.g. ``"float32"``, ``np.uint8``).
        nodata: the tiles' no-data value (also what uncovered cells read as), or None.
        georef: as for :func:`write_geotiff`; None for the local metric frame.
        band: description, units and categories, as for :func:`write_geotiff`.
    """
    vrt_path = Path(path)
    dt = np.dtype(dtype)
    if dt.name not in _GDAL_TYPES:
        raise ValueError(f"cannot mosaic dtype {dt}; use one of {list(_GDAL_TYPES)}")
    nodata = _check_nodata(nodata, dt)
    root = ET.Element("VRTDataset", rasterXSize=str(full.width), rasterYSize=str(full.height))
    srs = ET.SubElement(root, "SRS")
    srs.text = LOCAL_FRAME_WKT if georef is None else f"EPSG:{int(georef.epsg)}"
    transform = ET.SubElement(root, "GeoTransform")
    transform.text = ", ".join(repr(float(v)) for v in geotransform(full, georef))
    metadata = ET.SubElement(root, "Metadata")
    ET.SubElement(metadata, "MDI", key=MAP_GRID_TAG).text = _map_grid_text(full, georef)
    vrt_band = ET.SubElement(root, "VRTRasterBand", dataType=_GDAL_TYPES[dt.name], band="1")
    if band is not None:
        ET.SubElement(vrt_band, "Description").text = band.description
    if nodata is not None:
        ET.SubElement(vrt_band, "NoDataValue").text = _format_nodata(nodata)
    if band is not None and band.units:
        ET.SubElement(vrt_band, "UnitType").text = band.units
    if band is not None and band.categories:
        ET.SubElement(vrt_band, "ColorInterp").text = "Palette"
        by_value = {c.value: c for c in band.categories}
        top = max(by_value)
        table = ET.SubElement(vrt_band, "ColorTable")
        names = ET.SubElement(vrt_band, "CategoryNames")
        for value in range(top + 1):
            rgba = by_value[value].rgba if value in by_value else (0, 0, 0, 0)
            ET.SubElement(table, "Entry", c1=str(rgba[0]), c2=str(rgba[1]), c3=str(rgba[2]),
                          c4=str(rgba[3]))
            ET.SubElement(names, "Category").text = (
                by_value[value].name if value in by_value else "")
        band_md = ET.SubElement(vrt_band, "Metadata")
        for c in band.categories:
            ET.SubElement(band_md, "MDI", key=f"CATEGORY_{c.value}").text = c.name
    else:
        ET.SubElement(vrt_band, "ColorInterp").text = "Gray"
    for tile_path, spec in layer_tiles:
        row, col = _offset_in(spec, full, tile_path)
        source = ET.SubElement(vrt_band, "SimpleSource")
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


def band_description(path: str | os.PathLike[str]) -> str | None:
    """The first band's description of a raster GDAL reads (what gpocc writes as each
    layer's :class:`Band`), or None when it has none or cannot be read."""
    import rasterio

    try:
        with rasterio.Env(GDAL_PAM_ENABLED="NO"), rasterio.open(path) as ds:
            return ds.descriptions[0] if ds.count else None
    except Exception:  # rasterio's and GDAL's errors: read_raster reports them
        return None


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
    check_regular_file(path, "raster", "check the path")
    if path.suffix.lower() == ".vrt":
        if depth >= _MAX_VRT_DEPTH:
            raise GpoccError(f"{path}: VRTs nest too deeply (a VRT referring to itself?)")
        return _read_vrt(path, depth)
    return _read_geotiff(path)


def _read_geotiff(path: Path) -> tuple[np.ndarray, GridSpec, Nodata]:
    """Any single-band raster GDAL reads (any TIFF compression, predictor, layout)."""
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning, RasterioError

    fix = "write it as a single-band GeoTIFF (e.g. gdal_translate -b 1 -of GTiff)"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.Env(GDAL_PAM_ENABLED="NO"), rasterio.open(path) as ds:
                if ds.count != 1:
                    raise GpoccError(f"{path}: expected one band, found {ds.count}; {fix}")
                transform, gcps = ds.transform, ds.gcps[0]
                nodata = ds.nodata
                grid_text = ds.tags().get(MAP_GRID_TAG)
                array = ds.read(1)
    except GpoccError:
        raise
    except (RasterioError, OSError) as exc:
        raise GpoccError(
            f"{path}: GDAL cannot read it ({first_line(exc)}); the file is corrupt, truncated "
            f"or not a raster: write or copy it again"
        ) from None
    spec = _map_grid(path, grid_text, transform.to_gdal(), array.shape)
    if spec is None:
        spec = _north_up_grid(path, transform, bool(gcps), array.shape)
    return array, spec, _nodata_for(nodata, array.dtype)


def _map_grid(path: Path, text: str | None, gt: Any,
              shape: tuple[int, int]) -> GridSpec | None:
    """The map-frame grid gpocc recorded in its own raster (whatever its georeference),
    or None when there is none or the file's geotransform changed since (warped, edited)."""
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split()]
        if len(values) != 9:
            raise ValueError
        x0, y0, res = values[:3]
        if not all(math.isclose(a, b, rel_tol=1e-12, abs_tol=1e-9)
                   for a, b in zip(values[3:], gt, strict=True)):
            return None
        return GridSpec(x0, y0, res, int(shape[1]), int(shape[0]))
    except (ValueError, GpoccError):
        raise GpoccError(
            f"{path}: malformed {MAP_GRID_TAG} metadata {text!r}; remove it with "
            f"gdal_edit -unsetmd or write the raster again"
        ) from None


def _north_up_grid(path: Path, t: Any, has_gcps: bool, shape: tuple[int, int]) -> GridSpec:
    height, width = shape
    fix = "georeference it as a north-up raster (e.g. gdalwarp, or gdal_translate -a_ullr)"
    if t.is_identity:
        if has_gcps:
            raise GpoccError(
                f"{path}: georeferenced by ground control points, not one transform; "
                f"warp it first (gdalwarp)")
        raise GpoccError(f"{path}: not georeferenced (no GeoTIFF transform tags); {fix}")
    if t.b != 0.0 or t.d != 0.0:
        raise GpoccError(f"{path}: the raster is rotated or sheared; {fix}")
    if not t.e < 0:
        raise GpoccError(f"{path}: the raster is not north-up (row 0 is south); {fix}")
    sx, sy = t.a, -t.e
    if not (sx > 0 and math.isfinite(sx) and math.isfinite(sy)):
        raise GpoccError(f"{path}: invalid pixel size {sx} x {sy}; {fix}")
    if not math.isclose(sx, sy, rel_tol=1e-9):
        raise GpoccError(
            f"{path}: pixels are not square ({sx} x {sy} m); resample with gdalwarp -tr R R"
        )
    return GridSpec(float(t.c), float(t.f - height * sy), float(sx), int(width), int(height))


def _nodata_for(value: float | None, dtype: np.dtype) -> Nodata:
    if value is None:
        return None
    value = float(value)
    if dtype.kind in "iu" and math.isfinite(value) and value.is_integer():
        return int(value)
    return value


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
    return _nodata_for(value, dtype)


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
    grid_text = None
    for item in root.iterfind("Metadata/MDI"):
        if item.attrib.get("key") == MAP_GRID_TAG:
            grid_text = item.text or ""
    spec = _map_grid(path, grid_text, gt, (height, width))
    if spec is None:
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
