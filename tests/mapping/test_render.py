"""Preview and ROC images."""

from __future__ import annotations

import math

import numpy as np
import pytest
from matplotlib.colors import to_rgb
from matplotlib.image import imread

from gpocc.gridspec import GridSpec
from gpocc.mapping.render import (
    MAX_PREVIEW_PIXELS,
    NO_DATA_COLOUR,
    downsample,
    preview_factor,
    render_preview,
    render_roc,
)


def _brute_force_block_mean(a, f):
    h, w = a.shape
    out = np.full((math.ceil(h / f), math.ceil(w / f)), np.nan)
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            block = a[i * f:(i + 1) * f, j * f:(j + 1) * f]
            finite = block[np.isfinite(block)]
            if finite.size:
                out[i, j] = finite.mean()
    return out


@pytest.mark.parametrize(("shape", "factor"), [((17, 23), 3), ((40, 40), 4), ((5, 9), 1),
                                               ((7, 3), 8)])
def test_downsample_is_the_nan_ignoring_block_mean(shape, factor):
    rng = np.random.default_rng(0)
    a = rng.random(shape)
    a[rng.random(shape) < 0.3] = np.nan
    a[:factor, :factor] = np.nan  # a block with no data stays no data
    np.testing.assert_allclose(downsample(a, factor), _brute_force_block_mean(a, factor),
                               rtol=1e-6)


def test_preview_factor_bounds_the_preview_size():
    assert preview_factor((100, 2000)) == 1
    assert preview_factor((2001, 10)) == 2
    for shape in [(4100, 300), (30000, 12345), (2000, 6001)]:
        f = preview_factor(shape)
        assert max(math.ceil(s / f) for s in shape) <= MAX_PREVIEW_PIXELS
        assert max(math.ceil(s / (f - 1)) for s in shape) > MAX_PREVIEW_PIXELS


def _colour_pixels(png, colour):
    rgb = imread(png)[:, :, :3]
    return int(np.count_nonzero(np.all(np.abs(rgb - np.array(to_rgb(colour))) < 1 / 255, axis=2)))


def test_preview_png_shows_no_data_distinctly(tmp_path):
    spec = GridSpec(-15.0, -10.0, 0.05, 800, 500)
    x, y = spec.cell_centres()
    p = 1.0 / (1.0 + np.exp(-(x - 5.0)))
    v = 0.1 + 0.01 * np.abs(y)
    render_preview(tmp_path / "full.png", p, v, spec, title="no gaps")
    p[y > 10] = np.nan  # the top 5 m: a fifth of the map
    v[y > 10] = np.nan
    render_preview(tmp_path / "gaps.png", p, v, spec, title="gaps")
    assert sorted(f.name for f in tmp_path.iterdir()) == ["full.png", "gaps.png"]

    image = imread(tmp_path / "gaps.png")
    assert image.ndim == 3 and image.shape[0] < image.shape[1] <= 3000
    assert _colour_pixels(tmp_path / "full.png", NO_DATA_COLOUR) == 0
    # Two panels of ~ 5 inch x 1 inch no-data strips at 150 dpi: far more than a label.
    assert _colour_pixels(tmp_path / "gaps.png", NO_DATA_COLOUR) > 20000


def test_large_maps_are_previewed_at_bounded_size(tmp_path):
    spec = GridSpec(0.0, 0.0, 0.1, 300, 4100)
    p = np.random.default_rng(1).random(spec.shape).astype(np.float32)
    render_preview(tmp_path / "tall.png", p, p, spec)
    image = imread(tmp_path / "tall.png")
    assert max(image.shape[:2]) <= 3000


def test_roc_png(tmp_path):
    fpr = np.linspace(0.0, 1.0, 40)
    render_roc(tmp_path / "roc.png", [("gp", fpr, np.sqrt(fpr), 0.667),
                                      ("grid", fpr, fpr, 0.5)])
    image = imread(tmp_path / "roc.png")
    assert image.shape[0] == image.shape[1] >= 600
    assert [f.name for f in tmp_path.iterdir()] == ["roc.png"]


def test_preview_colour_ramps_match_matplotlibs():
    """Free white, occupied black; viridis within 6/255 of matplotlib's table; no data in
    its own colour."""
    from matplotlib import colormaps

    from gpocc.mapping.render import _GREY, _VIRIDIS, _colour

    t = np.linspace(0.0, 1.0, 1001)
    got = _colour(t[None, :], _VIRIDIS)[0].astype(float)
    want = colormaps["viridis"](t)[:, :3] * 255
    assert np.abs(got - want).max() <= 6
    grey = _colour(np.array([[0.0, 0.5, 1.0, np.nan]]), _GREY)[0]
    np.testing.assert_array_equal(grey[:3], [[255, 255, 255], [128, 128, 128], [0, 0, 0]])
    np.testing.assert_array_equal(grey[3], np.round(np.array(to_rgb(NO_DATA_COLOUR)) * 255))


def _panel_origin(image, colour):
    """Top-left (row, col) of the first pixel of ``colour`` (0..1 RGB) in an (H, W, 3) image."""
    rows, cols = np.nonzero(np.all(np.abs(image - np.array(colour)) < 0.5 / 255, axis=2))
    return rows.min(), cols[rows == rows.min()].min()


def test_preview_panel_is_the_map_north_up_cell_for_cell(tmp_path):
    # An asymmetric map: its north-west cell is marked by a no-data cell, a bright
    # (free) column runs along the west edge and the south row is occupied. Read back
    # from the PNG with matplotlib, the p(occupied) panel must be the array itself
    # (row 0 = north at the top), enlarged by the whole-pixel zoom.
    spec = GridSpec(2.0, -3.0, 0.1, 40, 25)
    rng = np.random.default_rng(3)
    p = rng.uniform(0.2, 0.8, spec.shape)
    p[:, 0] = 0.0
    p[-1, :] = 1.0
    p[0, 0] = np.nan
    render_preview(tmp_path / "p.png", p, np.full(spec.shape, 0.5), spec)
    image = imread(tmp_path / "p.png")[:, :, :3]
    zoom = 800 // max(spec.shape)  # panels of small maps are enlarged to ~800 px
    top, left = _panel_origin(image, to_rgb(NO_DATA_COLOUR))  # the NaN north-west cell
    panel = image[top:top + spec.height * zoom:zoom, left:left + spec.width * zoom:zoom]
    grey = np.round(255 * panel[:, :, 0])
    expected = np.round(255 * (1 - p))
    ok = ~np.isnan(p)
    np.testing.assert_allclose(grey[ok], expected[ok], atol=1)
    # The panel is exactly zoom x (H, W): framed by the black border on every side.
    assert np.all(image[top - 1, left:left + spec.width * zoom] < 0.05)
    assert np.all(image[top + spec.height * zoom, left:left + spec.width * zoom] < 0.05)


@pytest.mark.parametrize("shape", [(60, 1), (800, 3), (2, 900)])
def test_preview_of_a_narrow_map_keeps_its_text_inside_the_image(tmp_path, shape):
    # A corridor mapped with --bounds: the panels are a few pixels wide. The title,
    # panel labels, colour-bar ticks and extent line must not be cut at the image's
    # edges nor drawn over each other.
    spec = GridSpec(-3.0, -3.0, 0.1, shape[1], shape[0])
    p = np.random.default_rng(0).random(spec.shape)
    p[0, 0] = np.nan
    render_preview(tmp_path / "narrow.png", p, p, spec, title="gpocc map (input noise)",
                   no_data_label="no data or too uncertain (class: unsure)")
    image = imread(tmp_path / "narrow.png")[:, :, :3]
    ink = np.any(image < 0.6, axis=2)  # text and frames; not the white background
    # Nothing is cut at the edges: a blank border all round.
    assert not ink[:, :10].any() and not ink[:, -10:].any()
    assert not ink[:5].any() and not ink[-5:].any()
    # The two panel labels (just above the panels, whose north-west cell is the NaN
    # one) are separate words with blank columns between them.
    top, _ = _panel_origin(image, to_rgb(NO_DATA_COLOUR))
    label_rows = ink[top - 26:top - 3]
    columns = np.flatnonzero(label_rows.any(axis=0))
    gaps = np.diff(columns)
    assert gaps.max() >= 20, "the panel labels run into each other"


@pytest.mark.parametrize("yaw_deg", [None, 0.0, 30.0, -75.0, 135.0, 190.0])
def test_preview_says_where_grid_north_is_as_gdal_places_the_raster(tmp_path, yaw_deg):
    # The preview is drawn in the map frame (+y up). With a georeference whose yaw is
    # not zero, "north up" would be false: the label must give north's direction as
    # GDAL's geotransform of the same map's GeoTIFF has it.
    import re

    import rasterio

    from gpocc.config import GeorefConfig
    from gpocc.io.rasters import write_geotiff
    from gpocc.mapping.render import orientation_label

    spec = GridSpec(-3.0, -2.0, 0.5, 12, 8)
    georef = None if yaw_deg is None else GeorefConfig(
        epsg=32633, easting_m=400000.0, northing_m=5800000.0, yaw_deg=yaw_deg)
    write_geotiff(tmp_path / "p.tif", np.zeros(spec.shape, np.float32), spec,
                  nodata=float("nan"), georef=georef)
    with rasterio.open(tmp_path / "p.tif") as ds:
        inverse = ~ds.transform
        e, n = ds.transform @ (6.0, 4.0)
    (c0, r0), (c1, r1) = inverse @ (e, n), inverse @ (e, n + 10.0)  # 10 m grid north
    clockwise_from_up = math.degrees(math.atan2(c1 - c0, -(r1 - r0)))
    label = orientation_label(yaw_deg)
    if abs(clockwise_from_up) < 0.05:
        assert label == "north up"
        return
    said = re.fullmatch(r"map frame \+y up; grid north ([\d.]+) deg (clockwise|"
                        r"counter-clockwise) from up", label)
    assert said, label
    angle = float(said[1]) * (1 if said[2] == "clockwise" else -1)
    assert (angle - clockwise_from_up + 180) % 360 - 180 == pytest.approx(0, abs=0.06)
