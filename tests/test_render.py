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
