"""GeoTIFF / VRT output, checked with rasterio (GDAL) as the independent reader."""

from __future__ import annotations

import errno
import math
import os
import shutil
import warnings

import numpy as np
import pytest
import rasterio
import rasterio.shutil
import tifffile
from affine import Affine  # noqa: E402  (comes with rasterio)
from rasterio.crs import CRS  # noqa: E402
from rasterio.enums import Compression  # noqa: E402

from gpocc.config import GeorefConfig  # noqa: E402
from gpocc.errors import GpoccError  # noqa: E402
from gpocc.gridspec import GridSpec  # noqa: E402
from gpocc.io.rasters import read_raster, sample_raster, write_geotiff, write_vrt  # noqa: E402

NAN = float("nan")


def _georef(epsg):
    """A CRS whose origin is the map frame's: GDAL's coordinates are the map's."""
    return None if epsg is None else GeorefConfig(epsg=epsg)


def _array(shape, dtype, rng, nodata):
    if np.dtype(dtype).kind == "f":
        a = rng.random(shape).astype(dtype)
    else:
        a = rng.integers(0, 3, size=shape).astype(dtype)
    # A no-data patch that straddles tile and overview-block edges.
    if nodata is not None:
        a[: shape[0] // 3, shape[1] // 4: shape[1] // 2 + 1] = nodata
    return a


def _expected_overview_factors(shape, tile=256):
    """GDAL-style 2x, 4x, ... until the largest side fits in one tile."""
    factors, size, factor = [], max(shape), 2
    while size > tile:
        size = math.ceil(size / 2)
        factors.append(factor)
        factor *= 2
    return factors


def _nanmean_2x2(a, nodata):
    """Independent 2 x 2 valid-cell mean (ceil-sized), via masked arrays."""
    h, w = a.shape
    padded = np.full((h + h % 2, w + w % 2), np.nan)
    padded[:h, :w] = a
    invalid = np.isnan(padded)
    if nodata is not None and not math.isnan(nodata):
        invalid |= padded == nodata
    m = np.ma.masked_array(padded, invalid).reshape(padded.shape[0] // 2, 2, -1, 2)
    mean = m.mean(axis=(1, 3))
    return mean.filled(np.nan if nodata is None else nodata)


CASES = [
    # dtype, (H, W), x0, y0, resolution, nodata, epsg
    ("float32", (300, 517), -12.3, -4.5, 0.05, NAN, None),
    ("uint8", (300, 517), -7.0, -1234.5, 0.1, 255, 32633),
    ("float32", (1030, 600), 500.25, -40.0, 0.2, -9999.0, 32633),
    ("float32", (600, 520), 3.0, -2.0, 0.05, NAN, 32633),
    ("float32", (256, 256), 0.0, 0.0, 1.0, NAN, None),
    ("uint8", (40, 70), -3.0, 2.0, 0.25, None, None),
]


@pytest.mark.parametrize(("dtype", "shape", "x0", "y0", "res", "nodata", "epsg"), CASES)
def test_geotiff_as_rasterio_reads_it(tmp_path, dtype, shape, x0, y0, res, nodata, epsg):
    rng = np.random.default_rng(1)
    spec = GridSpec(x0, y0, res, shape[1], shape[0])
    a = _array(shape, dtype, rng, nodata)
    path = tmp_path / "layer.tif"
    write_geotiff(path, a, spec, nodata=nodata, georef=_georef(epsg))
    assert [p.name for p in tmp_path.iterdir()] == ["layer.tif"]  # no temporary left

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # e.g. NotGeoreferencedWarning must not happen
        ds = rasterio.open(path)
    with ds:
        y1 = y0 + shape[0] * res
        assert ds.transform.almost_equals(Affine(res, 0, x0, 0, -res, y1), precision=1e-9)
        assert ds.bounds == pytest.approx((x0, y0, x0 + shape[1] * res, y1), abs=1e-9)
        assert (ds.count, ds.height, ds.width) == (1, shape[0], shape[1])
        assert ds.dtypes == (dtype,)
        if nodata is None:
            assert ds.nodata is None
        elif math.isnan(nodata):
            assert math.isnan(ds.nodata)
        else:
            assert ds.nodata == nodata
        np.testing.assert_array_equal(ds.read(1), a)
        assert ds.block_shapes == [(256, 256)]
        assert ds.compression == Compression.deflate
        assert ds.overviews(1) == _expected_overview_factors(shape)
        if epsg is not None:
            assert ds.crs == CRS.from_epsg(epsg)
        else:
            assert ds.crs is None or not ds.crs.is_geographic
            if ds.crs is not None:
                assert 'UNIT["metre",1' in ds.crs.to_wkt()  # a metric local frame
    if _expected_overview_factors(shape):
        with rasterio.open(path, overview_level=0) as ov:
            first = ov.read(1)
        # GDAL's COG driver rounds odd sides down (ov.transform then stretches the cells).
        assert first.shape == (shape[0] // 2, shape[1] // 2)
        even = shape[0] % 2 == 0 and shape[1] % 2 == 0
        if np.dtype(dtype).kind == "f" and even:
            expected = _nanmean_2x2(a.astype(float), nodata).astype(dtype)
            np.testing.assert_allclose(first, expected, rtol=1e-6)
        elif even:  # class layers take one cell of each 2 x 2 block, never an average
            candidates = [a[i::2, j::2] for i in (0, 1) for j in (0, 1)]
            assert np.any([first == c for c in candidates], axis=0).all()
        elif np.dtype(dtype).kind != "f":
            assert set(np.unique(first)) <= set(np.unique(a))  # no class invented


@pytest.mark.parametrize(("dtype", "shape", "x0", "y0", "res", "nodata", "epsg"), CASES[:3])
def test_read_raster_round_trip(tmp_path, dtype, shape, x0, y0, res, nodata, epsg):
    spec = GridSpec(x0, y0, res, shape[1], shape[0])
    a = _array(shape, dtype, np.random.default_rng(2), nodata)
    write_geotiff(tmp_path / "r.tif", a, spec, nodata=nodata, georef=_georef(epsg))
    back, back_spec, back_nodata = read_raster(tmp_path / "r.tif")
    assert back.dtype == a.dtype
    np.testing.assert_array_equal(back, a)
    assert (back_spec.width, back_spec.height) == (spec.width, spec.height)
    assert back_spec.x0 == pytest.approx(x0, abs=1e-9)
    assert back_spec.y0 == pytest.approx(y0, abs=1e-9)
    assert back_spec.resolution == pytest.approx(res, rel=1e-12)
    if nodata is not None and math.isnan(nodata):
        assert math.isnan(back_nodata)
    else:
        assert back_nodata == nodata


@pytest.mark.parametrize("area_or_point", ["Area", "Point"])
def test_read_raster_reads_gdal_written_geotiff(tmp_path, area_or_point):
    """A GDAL-written strip TIFF (deflate + predictor) reads with GDAL's transform."""
    a = np.arange(37 * 23, dtype=np.int16).reshape(37, 23) - 100
    transform = Affine(0.5, 0, -3.25, 0, -0.5, 7.0)
    path = tmp_path / "gdal.tif"
    with rasterio.open(path, "w", driver="GTiff", width=23, height=37, count=1, dtype="int16",
                       transform=transform, nodata=-1, compress="deflate", predictor=2) as ds:
        ds.update_tags(AREA_OR_POINT=area_or_point)
        ds.write(a, 1)
    with rasterio.open(path) as ds:
        gdal_transform = ds.transform
    back, spec, nodata = read_raster(path)
    np.testing.assert_array_equal(back, a)
    assert nodata == -1
    assert (spec.x0, spec.y1, spec.resolution) == pytest.approx(
        (gdal_transform.c, gdal_transform.f, gdal_transform.a))
    assert (spec.width, spec.height) == (23, 37)


def _tile(full, a, tmp_path, layer, tile, nodata, epsg):
    tiles = []
    for r in range(0, full.height, tile):
        for c in range(0, full.width, tile):
            window = full.window(r, c, tile, tile)
            path = tmp_path / "tiles" / layer / f"{layer}_{r // tile}_{c // tile}.tif"
            write_geotiff(path, a[r:r + window.height, c:c + window.width], window,
                          nodata=nodata, georef=_georef(epsg))
            tiles.append((path, window))
    return tiles


@pytest.mark.parametrize(("dtype", "nodata", "epsg"), [("float32", NAN, None),
                                                        ("uint8", 255, 32633)])
def test_vrt_mosaic_equals_the_original(tmp_path, dtype, nodata, epsg):
    full = GridSpec(-20.0, -7.5, 0.1, 700, 530)
    a = _array(full.shape, dtype, np.random.default_rng(3), nodata)
    original = tmp_path / "map"
    tiles = _tile(full, a, original, "probability", 256, nodata, epsg)
    vrt = original / "probability.vrt"
    write_vrt(vrt, tiles, full, dtype, nodata, _georef(epsg))
    assert str(tmp_path) not in vrt.read_text()  # tile paths are relative

    # Moving the whole map folder must keep the mosaic readable.
    moved = tmp_path / "moved"
    shutil.move(original, moved)
    vrt = moved / "probability.vrt"
    with rasterio.open(vrt) as ds:
        assert ds.transform.almost_equals(Affine(0.1, 0, -20.0, 0, -0.1, full.y1), precision=1e-9)
        assert ds.dtypes == (dtype,)
        np.testing.assert_array_equal(ds.read(1), a)
        if epsg is None:
            assert ds.crs is None or not ds.crs.is_geographic
        else:
            assert ds.crs == CRS.from_epsg(epsg)
    back, spec, back_nodata = read_raster(vrt)
    np.testing.assert_array_equal(back, a)
    assert back.dtype == np.dtype(dtype)
    assert (spec.width, spec.height) == full.shape[::-1]
    assert (spec.x0, spec.y0, spec.resolution) == pytest.approx((full.x0, full.y0, 0.1))
    assert (math.isnan(back_nodata) if dtype == "float32" else back_nodata == nodata)


def test_vrt_leaves_uncovered_cells_as_nodata(tmp_path):
    full = GridSpec(0.0, 0.0, 1.0, 50, 40)
    a = np.random.default_rng(4).random(full.shape).astype("float32")
    tiles = _tile(full, a, tmp_path, "p", 16, NAN, None)
    del tiles[3]  # a missing tile (e.g. a block with no data)
    write_vrt(tmp_path / "p.vrt", tiles, full, "float32", NAN, None)
    expected = a.copy()
    expected[0:16, 48:50] = np.nan
    with rasterio.open(tmp_path / "p.vrt") as ds:
        np.testing.assert_array_equal(ds.read(1), expected)
    np.testing.assert_array_equal(read_raster(tmp_path / "p.vrt")[0], expected)


def test_vrt_rejects_a_misaligned_tile(tmp_path):
    full = GridSpec(0.0, 0.0, 1.0, 50, 40)
    bad = GridSpec(0.5, 0.0, 1.0, 10, 10)
    with pytest.raises(ValueError, match="aligned"):
        write_vrt(tmp_path / "p.vrt", [(tmp_path / "t.tif", bad)], full, "float32", NAN, None)
    assert not (tmp_path / "p.vrt").exists()


def test_sample_raster_matches_rasterio_index(tmp_path):
    spec = GridSpec(-5.3, 2.1, 0.2, 37, 29)
    rng = np.random.default_rng(5)
    a = rng.random(spec.shape).astype("float32")
    a[3, 4] = -1.0  # no-data cell
    path = tmp_path / "s.tif"
    write_geotiff(path, a, spec, nodata=-1.0)
    pts = np.column_stack([rng.uniform(spec.x0 - 1, spec.x1 + 1, 500),
                           rng.uniform(spec.y0 - 1, spec.y1 + 1, 500)])
    centre = spec.cell_centres()
    pts[0] = (centre[0][3, 4], centre[1][3, 4])
    values, inside = sample_raster(a, spec, -1.0, pts)
    with rasterio.open(path) as ds:
        rows, cols = rasterio.transform.rowcol(ds.transform, pts[:, 0], pts[:, 1])
        data = ds.read(1)
    rows, cols = np.asarray(rows), np.asarray(cols)
    expect_inside = (rows >= 0) & (rows < spec.height) & (cols >= 0) & (cols < spec.width)
    np.testing.assert_array_equal(inside, expect_inside)
    assert expect_inside.sum() > 200 and (~expect_inside).sum() > 100
    expected = np.full(len(pts), np.nan)
    expected[expect_inside] = data[rows[expect_inside], cols[expect_inside]]
    expected[expected == -1.0] = np.nan
    np.testing.assert_array_equal(values, expected)
    assert inside[0] and np.isnan(values[0])


def test_write_is_atomic_on_failure(tmp_path, monkeypatch):
    spec = GridSpec(0.0, 0.0, 1.0, 300, 300)
    path = tmp_path / "m.tif"
    write_geotiff(path, np.zeros(spec.shape, np.float32), spec, nodata=NAN)
    before = path.read_bytes()

    def boom(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(rasterio.shutil, "copy", boom)
    with pytest.raises(KeyboardInterrupt):
        write_geotiff(path, np.ones(spec.shape, np.float32), spec, nodata=NAN)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["m.tif"]


def test_bad_rasters_give_clear_errors(tmp_path):
    a = np.arange(12 * 9, dtype=np.int16).reshape(12, 9)
    with pytest.raises(GpoccError, match="not found"):
        read_raster(tmp_path / "missing.tif")

    (tmp_path / "garbage.tif").write_bytes(b"II*\x00" + bytes(range(256)) * 4)
    with pytest.raises(GpoccError, match="garbage.tif"):
        read_raster(tmp_path / "garbage.tif")

    tifffile.imwrite(tmp_path / "plain.tif", a)
    with pytest.raises(GpoccError, match="plain.tif: not georeferenced"):
        read_raster(tmp_path / "plain.tif")

    rotated = Affine(0.5, 0.1, -3, 0.1, -0.5, 7)
    with rasterio.open(tmp_path / "rot.tif", "w", driver="GTiff", width=9, height=12, count=1,
                       dtype="int16", transform=rotated) as ds:
        ds.write(a, 1)
    with pytest.raises(GpoccError, match="rot.tif: .*rotated"):
        read_raster(tmp_path / "rot.tif")

    with rasterio.open(tmp_path / "rect.tif", "w", driver="GTiff", width=9, height=12, count=1,
                       dtype="int16", transform=Affine(0.5, 0, 0, 0, -0.25, 0)) as ds:
        ds.write(a, 1)
    with pytest.raises(GpoccError, match="not square"):
        read_raster(tmp_path / "rect.tif")

    spec = GridSpec(0.0, 0.0, 1.0, 400, 300)
    write_geotiff(tmp_path / "full.tif", np.random.default_rng(6).random(spec.shape)
                  .astype(np.float32), spec, nodata=None)
    data = (tmp_path / "full.tif").read_bytes()
    (tmp_path / "cut.tif").write_bytes(data[: len(data) // 3])
    with pytest.raises(GpoccError, match="cut.tif"):
        read_raster(tmp_path / "cut.tif")

    (tmp_path / "bad.vrt").write_text("<VRTDataset rasterXSize='3'>")
    with pytest.raises(GpoccError, match="bad.vrt: not a valid VRT"):
        read_raster(tmp_path / "bad.vrt")

    (tmp_path / "orphan.vrt").write_text(
        '<VRTDataset rasterXSize="2" rasterYSize="2"><GeoTransform>0, 1, 0, 2, 0, -1'
        '</GeoTransform><VRTRasterBand dataType="Byte" band="1"><SimpleSource>'
        '<SourceFilename relativeToVRT="1">gone.tif</SourceFilename></SimpleSource>'
        "</VRTRasterBand></VRTDataset>")
    with pytest.raises(GpoccError, match="gone.tif: raster not found"):
        read_raster(tmp_path / "orphan.vrt")


def test_a_full_disk_is_an_os_error_and_leaves_nothing(tmp_path, monkeypatch):
    # GDAL wrote the file itself: on a full disk libtiff printed its own lines and GDAL
    # raised a seek error naming no cause. The COG is now made in memory and written
    # here, so the disk's error is an OSError (ENOSPC) the CLI prints as one line.
    import builtins

    import gpocc.io.rasters as rasters

    spec = GridSpec(0.0, 0.0, 0.1, 64, 48)

    class FullDisk:
        def __init__(self, *args, **kwargs):
            self.file = builtins.open(*args, **kwargs)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.file.close()

        def write(self, data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(rasters, "open", FullDisk, raising=False)
    with pytest.raises(OSError) as raised:
        write_geotiff(tmp_path / "p.tif", np.zeros(spec.shape, np.float32), spec,
                      nodata=math.nan)
    assert raised.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == []
