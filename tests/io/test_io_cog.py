"""GeoTIFF layers as GIS tools see them: COG layout, nodata, colour table, metadata,
georeferencing, checked with GDAL (rasterio) and rio-cogeo as independent oracles; and
reading any single-band GeoTIFF GDAL writes."""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
import rasterio.shutil
from rio_cogeo.cogeo import cog_validate

from gpocc.config import GeorefConfig
from gpocc.errors import GpoccError
from gpocc.gp.classify import classify
from gpocc.gridspec import GridSpec
from gpocc.io.rasters import (
    CLASS_BAND,
    PROBABILITY_BAND,
    VARIANCE_BAND,
    read_raster,
    write_geotiff,
    write_vrt,
)

NAN = float("nan")


def _rio() -> str:
    """The ``rio`` command installed beside this Python (rasterio's CLI, with rio-cogeo)."""
    rio = Path(sys.executable).with_name("rio")
    return str(rio) if rio.exists() else shutil.which("rio") or "rio"


def _assert_cog(path: Path, cli: bool = False) -> None:
    """rio-cogeo's validator (strict: warnings fail too); ``cli`` also runs the command."""
    valid, errors, warnings = cog_validate(str(path), strict=True)
    assert valid, (path, errors, warnings)
    # GDAL's ghost area right after the header announces the COG layout to readers.
    head = path.read_bytes()[:400]
    assert b"GDAL_STRUCTURAL_METADATA" in head and b"LAYOUT=IFDS_BEFORE_DATA" in head
    assert b"BLOCK_ORDER=ROW_MAJOR" in head
    if not cli:
        return
    done = subprocess.run([_rio(), "cogeo", "validate", "--strict", str(path)],
                          capture_output=True, text=True)
    assert done.returncode == 0 and "is a valid cloud optimized GeoTIFF" in done.stdout, (
        done.stdout + done.stderr)


def _probability_with_holes(spec: GridSpec, seed: int = 0) -> np.ndarray:
    """p in 0..1 with a no-data hole (NaN) crossing tile and overview-block edges."""
    rng = np.random.default_rng(seed)
    p = rng.random(spec.shape).astype(np.float32)
    p[: spec.height // 3, spec.width // 4: spec.width // 2 + 3] = np.nan
    p[-1, :] = np.nan
    return p


@pytest.mark.parametrize("shape", [(700, 900), (200, 130), (257, 1025)])
def test_every_layer_is_a_valid_cog_and_nodata_is_used(tmp_path, shape):
    spec = GridSpec(-12.3, 4.5, 0.05, shape[1], shape[0])
    p = _probability_with_holes(spec)
    v = np.where(np.isnan(p), np.nan, p * (1 - p)).astype(np.float32)
    classes = classify(p, 0.65, 0.35)
    layers = {"probability": (p, NAN, PROBABILITY_BAND), "variance": (v, NAN, VARIANCE_BAND),
              "class": (classes, 255, CLASS_BAND)}
    for name, (array, nodata, band) in layers.items():
        path = tmp_path / f"{name}.tif"
        write_geotiff(path, array, spec, nodata=nodata, band=band)
        _assert_cog(path, cli=shape == (700, 900))
        with rasterio.open(path) as ds:
            masked = ds.read(1, masked=True)
            assert ds.descriptions == (band.description,)
            assert ds.units == (band.units,)
            assert ds.compression.value == "DEFLATE"
            if max(shape) > 256:
                assert ds.overviews(1)
        # GDAL's own mask: exactly the NaN cells of the input have no data.
        np.testing.assert_array_equal(np.ma.getmaskarray(masked), np.isnan(p))
        assert np.isnan(p).any()


def test_class_layer_has_colour_table_and_category_names(tmp_path):
    spec = GridSpec(0.0, 0.0, 0.1, 300, 280)
    classes = classify(_probability_with_holes(spec, 1), 0.65, 0.35)
    classes[100:110, 100:110] = 2
    path = tmp_path / "class.tif"
    write_geotiff(path, classes, spec, nodata=255, band=CLASS_BAND)
    with rasterio.open(path) as ds:
        cmap = ds.colormap(1)
        tags = ds.tags(1)
        assert ds.colorinterp[0].name == "palette"
        assert ds.nodata == 255
    names = {0: "free", 1: "occupied", 2: "unsure", 255: "no data"}
    for value, name in names.items():
        assert tags[f"CATEGORY_{value}"] == name
    # Distinct colours: free white, occupied black, unsure coloured, no data transparent.
    assert cmap[0] == (255, 255, 255, 255) and cmap[1] == (0, 0, 0, 255)
    assert len({cmap[0][:3], cmap[1][:3], cmap[2][:3]}) == 3 and cmap[2][3] == 255
    assert cmap[255][3] == 0

    # A tiled map's VRT carries the same colour table and names.
    write_vrt(tmp_path / "class.vrt", [(path, spec)], spec, "uint8", 255, None, CLASS_BAND)
    with rasterio.open(tmp_path / "class.vrt") as ds:
        assert ds.colormap(1)[2] == cmap[2]
        assert ds.tags(1)["CATEGORY_1"] == "occupied"
        assert ds.descriptions == (CLASS_BAND.description,)
        np.testing.assert_array_equal(ds.read(1), classes)
        # GDAL parsed the VRT's CategoryNames: its GTiff copy keeps them (in PAM).
        rasterio.shutil.copy(ds, tmp_path / "copy.tif", driver="GTiff")
    pam = (tmp_path / "copy.tif.aux.xml").read_text()
    assert "<Category>free</Category>" in pam and "<Category>unsure</Category>" in pam


def _map_to_crs(georef: GeorefConfig, x: float, y: float) -> tuple[float, float]:
    """Independent rigid transform: rotate the map point by yaw, then translate."""
    yaw = math.radians(georef.yaw_deg)
    rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    e, n = rot @ np.array([x, y]) + np.array([georef.easting_m, georef.northing_m])
    return float(e), float(n)


@pytest.mark.parametrize("yaw_deg", [0.0, 30.0, -121.5, 90.0])
def test_georef_corners_land_where_gdal_reads_them(tmp_path, yaw_deg):
    georef = GeorefConfig(epsg=32633, easting_m=412_345.6, northing_m=5_801_234.5,
                          yaw_deg=yaw_deg)
    spec = GridSpec(-12.0, -3.5, 0.05, 420, 300)
    p = _probability_with_holes(spec, 2)
    path = tmp_path / "probability.tif"
    write_geotiff(path, p, spec, nodata=NAN, georef=georef, band=PROBABILITY_BAND)
    _assert_cog(path)
    with rasterio.open(path) as ds:
        assert ds.crs.to_epsg() == 32633
        t = ds.transform
        # Pixel corners (col, row) and the map-frame corners they must be.
        corners = {(0, 0): (spec.x0, spec.y1), (spec.width, 0): (spec.x1, spec.y1),
                   (0, spec.height): (spec.x0, spec.y0),
                   (spec.width, spec.height): (spec.x1, spec.y0)}
        for (col, row), (x, y) in corners.items():
            assert t @ (col, row) == pytest.approx(_map_to_crs(georef, x, y), abs=1e-6)
        # A cell centre: rasterio's xy() of the cell under a map point.
        row, col = 57, 311
        centre = spec.x0 + (col + 0.5) * spec.resolution, spec.y1 - (row + 0.5) * spec.resolution
        assert ds.xy(row, col) == pytest.approx(_map_to_crs(georef, *centre), abs=1e-6)
        np.testing.assert_array_equal(ds.read(1), p)
    # gpocc reads its own georeferenced map back in the map frame.
    back, back_spec, _ = read_raster(path)
    assert (back_spec.x0, back_spec.y0, back_spec.resolution) == pytest.approx(
        (spec.x0, spec.y0, spec.resolution))
    assert back_spec.shape == spec.shape


def test_georef_vrt_mosaic_matches_its_tiles(tmp_path):
    georef = GeorefConfig(epsg=25832, easting_m=600_000.0, northing_m=5_300_000.0,
                          yaw_deg=17.0)
    full = GridSpec(-5.0, -2.0, 0.1, 300, 200)
    p = _probability_with_holes(full, 3)
    tiles = []
    for r in range(0, full.height, 128):
        for c in range(0, full.width, 128):
            window = full.window(r, c, 128, 128)
            path = tmp_path / "tiles" / f"p_{r}_{c}.tif"
            path.parent.mkdir(exist_ok=True)
            write_geotiff(path, p[r:r + window.height, c:c + window.width], window,
                          nodata=NAN, georef=georef, band=PROBABILITY_BAND)
            _assert_cog(path)
            tiles.append((path, window))
    vrt = tmp_path / "probability.vrt"
    write_vrt(vrt, tiles, full, "float32", NAN, georef, PROBABILITY_BAND)
    with rasterio.open(vrt) as ds:
        np.testing.assert_array_equal(ds.read(1), p)
        assert ds.transform @ (0, 0) == pytest.approx(_map_to_crs(georef, full.x0, full.y1))
        assert ds.crs.to_epsg() == 25832
    back, spec, _ = read_raster(vrt)
    np.testing.assert_array_equal(back, p)
    assert (spec.x0, spec.y0) == pytest.approx((full.x0, full.y0))


GDAL_VARIANTS = [
    dict(compress="lzw"),
    dict(compress="lzw", predictor=2),
    dict(compress="zstd", predictor=2),
    dict(compress="deflate", predictor=2, tiled=True, blockxsize=32, blockysize=32),
    dict(compress="packbits"),
    dict(),  # uncompressed strips
]


@pytest.mark.parametrize("options", GDAL_VARIANTS)
@pytest.mark.parametrize("dtype", ["uint8", "int16", "float32"])
def test_reads_any_single_band_geotiff_gdal_writes(tmp_path, options, dtype):
    rng = np.random.default_rng(4)
    a = (rng.random((53, 71)) * 100).astype(dtype)
    transform = rasterio.Affine(0.25, 0, -3.0, 0, -0.25, 9.5)
    path = tmp_path / "gdal.tif"
    with rasterio.open(path, "w", driver="GTiff", width=71, height=53, count=1, dtype=dtype,
                       transform=transform, nodata=7, **options) as ds:
        ds.write(a, 1)
    back, spec, nodata = read_raster(path)
    np.testing.assert_array_equal(back, a)
    assert (spec.x0, spec.y1, spec.resolution) == pytest.approx((-3.0, 9.5, 0.25))
    assert nodata == 7


@pytest.mark.parametrize("predictor", [1, 3])
def test_reads_gdal_cogs_and_float_predictor(tmp_path, predictor):
    a = np.random.default_rng(5).random((300, 260)).astype("float64")
    a[:10] = np.nan
    transform = rasterio.Affine(0.5, 0, 100.0, 0, -0.5, 50.0)
    staged = tmp_path / "staged.tif"
    with rasterio.open(staged, "w", driver="GTiff", width=260, height=300, count=1,
                       dtype="float64", transform=transform, nodata=np.nan) as ds:
        ds.write(a, 1)
    cog = tmp_path / "cog.tif"
    with rasterio.open(staged) as src:
        rasterio.shutil.copy(src, cog, driver="COG", COMPRESS="ZSTD", PREDICTOR=str(predictor))
    back, spec, nodata = read_raster(cog)
    np.testing.assert_array_equal(back, a)
    assert math.isnan(nodata) and spec.resolution == 0.5


def test_multiband_and_unreadable_rasters_name_the_file_not_a_codec(tmp_path):
    path = tmp_path / "rgb.tif"
    with rasterio.open(path, "w", driver="GTiff", width=4, height=3, count=3, dtype="uint8",
                       transform=rasterio.Affine(1, 0, 0, 0, -1, 3)) as ds:
        ds.write(np.zeros((3, 3, 4), np.uint8))
    with pytest.raises(GpoccError, match="rgb.tif: expected one band, found 3"):
        read_raster(path)
    (tmp_path / "junk.tif").write_bytes(b"not a tiff at all")
    with pytest.raises(GpoccError, match="junk.tif: GDAL cannot read it") as info:
        read_raster(tmp_path / "junk.tif")
    assert "imagecodecs" not in str(info.value)


def test_map_grid_is_ignored_once_the_file_is_georeferenced_anew(tmp_path):
    """gdalwarp / gdal_edit keep metadata: a stale map grid must not override GDAL's."""
    georef = GeorefConfig(epsg=32633, easting_m=500_000.0, northing_m=5_000_000.0)
    spec = GridSpec(-3.0, -2.0, 0.5, 40, 30)
    path = tmp_path / "p.tif"
    write_geotiff(path, _probability_with_holes(spec, 6), spec, nodata=NAN, georef=georef)
    assert read_raster(path)[1] == spec  # the map frame while the transform is ours
    moved = rasterio.Affine(0.5, 0.0, 500_100.0, 0.0, -0.5, 5_000_200.0)
    with rasterio.open(path, "r+", IGNORE_COG_LAYOUT_BREAK="YES") as ds:
        ds.transform = moved
    _, back, _ = read_raster(path)
    assert (back.x0, back.y1, back.resolution) == pytest.approx((500_100.0, 5_000_200.0, 0.5))
