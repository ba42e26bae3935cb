"""Preview images: the probability and variance maps, and ROC curves, as PNG.

The map preview is drawn with Pillow (every ``gpocc map`` writes one, and importing
matplotlib cost a second). The ROC and reliability plots of ``gpocc evaluate`` are drawn
on matplotlib's Agg canvas directly (``Figure`` + ``FigureCanvasAgg``), never through
pyplot, so no display is needed, no global backend is switched and rendering is safe in
worker threads.
"""

from __future__ import annotations

import math
import os

import numpy as np

from gpocc.gridspec import GridSpec
from gpocc.io.atomic import atomic_path

#: Largest preview raster side, pixels; larger maps are block-averaged down to it.
MAX_PREVIEW_PIXELS = 2000
#: Colour of cells without data in the preview.
NO_DATA_COLOUR = "#d9480f"


def downsample(array: np.ndarray, factor: int) -> np.ndarray:
    """Mean of each ``factor`` x ``factor`` block of (H, W), ignoring NaN.

    Returns (ceil(H / factor), ceil(W / factor)) float32; a block with no finite value
    is NaN. Partial blocks on the south and east edges average what they hold.
    """
    a = np.asarray(array, dtype=np.float32)
    if factor <= 1:
        return a.copy()
    h, w = a.shape
    hh, ww = math.ceil(h / factor), math.ceil(w / factor)
    padded = np.full((hh * factor, ww * factor), np.nan, dtype=np.float32)
    padded[:h, :w] = a
    blocks = padded.reshape(hh, factor, ww, factor)
    valid = np.isfinite(blocks)
    total = np.where(valid, blocks, np.float32(0)).sum(axis=(1, 3), dtype=np.float64)
    count = valid.sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return out.astype(np.float32)


def preview_factor(shape: tuple[int, int], max_pixels: int = MAX_PREVIEW_PIXELS) -> int:
    """Smallest integer factor bringing both sides of ``shape`` to <= ``max_pixels``."""
    return max(1, math.ceil(max(shape) / max_pixels))


def orientation_label(yaw_deg: float | None) -> str:
    """Where the CRS's north lies in a preview, whose up is the map frame's +y.

    ``yaw_deg``: the map frame's +x axis, degrees counter-clockwise from the CRS's east
    (``map.georef.yaw_deg``); None for the local frame, whose +y is its north. The
    frame's +y is then ``yaw_deg`` counter-clockwise from north: north is that many
    degrees clockwise from up.
    """
    yaw = 0.0 if yaw_deg is None else float(yaw_deg)
    turn = -((-yaw + 180.0) % 360.0 - 180.0)  # in (-180, 180]
    if abs(turn) < 0.05:
        return "north up"
    side = "clockwise" if turn > 0 else "counter-clockwise"
    return f"map frame +y up; grid north {abs(turn):.1f} deg {side} from up"


def prepare_preview() -> None:
    """Import Pillow and its PNG writer now (0.07 s), for a caller with time to spare
    before its :func:`render_preview` (a map, while its workers compute)."""
    from PIL import Image, ImageDraw, ImageFont, PngImagePlugin  # noqa: F401


def render_preview(
    path: str | os.PathLike[str],
    probability: np.ndarray,
    variance: np.ndarray,
    spec: GridSpec,
    title: str = "",
    no_data_label: str = "no data",
    orientation: str = "north up",
) -> None:
    """Write a PNG: p(occupied) and predictive variance side by side, atomically.

    Args:
        path: output ``.png``.
        probability: (H, W) p(occupied) in 0..1 on ``spec``, NaN = no data.
        variance: (H, W) variance on ``spec`` (units of the latent GP), NaN = no data.
        spec: the grid; its extent in metres is written under the panels.
        title: figure title.
        no_data_label: what NaN cells of ``probability`` mean, for the figure's key.
        orientation: where north is in the panels, for the extent line
            (:func:`orientation_label`); up is the map frame's +y.

    Maps larger than :data:`MAX_PREVIEW_PIXELS` a side are block-averaged first; small
    maps are enlarged by whole pixels. Probability is grey (free white, occupied black);
    variance uses viridis; cells without data are :data:`NO_DATA_COLOUR` on both panels;
    each panel has a colour bar. Drawn with Pillow: importing matplotlib and laying out
    a figure took 1.7 s of the Intel map's 12 s.
    """
    from PIL import Image, ImageDraw

    p = np.asarray(probability)
    v = np.asarray(variance)
    if p.shape != spec.shape or v.shape != spec.shape:
        raise ValueError(f"layers {p.shape}, {v.shape} do not match the grid {spec.shape}")
    factor = preview_factor(spec.shape)
    p = downsample(p, factor)
    v = downsample(v, factor)
    lo, hi = _variance_range(v)
    panels = [_colour(p, _GREY), _colour((v - lo) / (hi - lo), _VIRIDIS)]
    height, width = p.shape
    zoom = max(1, _PANEL_PIXELS // max(height, width))
    panels = [np.repeat(np.repeat(a, zoom, axis=0), zoom, axis=1) for a in panels]
    ph, pw = height * zoom, width * zoom

    font = _font(18)
    small = _font(14)
    title_font = _font(22)
    margin, top, bar = 30, 80 if title else 50, 16
    labels = (("p(occupied)", 0.0, 1.0, _GREY),
              ("predictive variance", lo, hi, _VIRIDIS))
    extent = (f"x {spec.x0:.1f} .. {spec.x1:.1f} m, y {spec.y0:.1f} .. {spec.y1:.1f} m, "
              f"{spec.resolution * factor:g} m cells ({orientation})")
    # Each panel sits centred in a slot wide enough for its label and colour-bar ticks,
    # and the canvas is wide enough for the title and text lines: a corridor a few
    # cells wide would otherwise have its text cut and its labels drawn over each other.
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    slot = max(pw, _MIN_SLOT_PIXELS,
               *(int(math.ceil(measure.textlength(label, font=font))) + 10
                 for label, *_ in labels))
    text_w = max(measure.textlength(extent, font=small),
                 26 + measure.textlength(no_data_label, font=small),
                 measure.textlength(title, font=title_font) if title else 0.0)
    canvas_w = max(2 * slot + 3 * margin, int(math.ceil(text_w)) + 2 * margin)
    canvas_h = top + ph + bar + 110
    image = Image.new("RGB", (canvas_w, canvas_h), "white")
    draw = ImageDraw.Draw(image)
    if title:
        draw.text((canvas_w // 2, 20), title, fill="black", font=title_font, anchor="mt")
    for k, (panel, (label, vmin, vmax, colours)) in enumerate(zip(panels, labels,
                                                                   strict=True)):
        x_slot = margin + k * (slot + margin)
        x0 = x_slot + (slot - pw) // 2
        image.paste(Image.fromarray(panel), (x0, top))
        draw.rectangle((x0 - 1, top - 1, x0 + pw, top + ph), outline="black")
        draw.text((x_slot + slot // 2, top - 8), label, fill="black", font=font, anchor="mb")
        # Colour bar under the panel's slot, with its range.
        ramp = _colour(np.tile(np.linspace(0.0, 1.0, slot), (bar, 1)), colours)
        y_bar = top + ph + 12
        image.paste(Image.fromarray(ramp), (x_slot, y_bar))
        for frac, value in ((0.0, vmin), (0.5, 0.5 * (vmin + vmax)), (1.0, vmax)):
            anchor = "lt" if frac == 0.0 else "rt" if frac == 1.0 else "mt"
            draw.text((x_slot + frac * (slot - 1), y_bar + bar + 4), f"{value:.3g}",
                      fill="black", font=small, anchor=anchor)
    y_text = top + ph + bar + 44
    draw.text((margin, y_text), extent, fill="black", font=small)
    if np.isnan(p).any():
        draw.rectangle((margin, y_text + 28, margin + 18, y_text + 46), fill=NO_DATA_COLOUR)
        draw.text((margin + 26, y_text + 28), no_data_label, fill=NO_DATA_COLOUR, font=small)
    with atomic_path(path) as tmp:
        # zlib level 1: a quarter of the encoding time for a file ~20% larger.
        image.save(tmp, format="PNG", compress_level=1)


#: Longer side of a preview panel for small maps, pixels (enlarged by whole pixels).
_PANEL_PIXELS = 800
#: Narrowest slot of a panel, its label and its colour bar (three tick values), pixels.
_MIN_SLOT_PIXELS = 240
#: Colour ramps, 0..255 RGB at evenly spaced stops from 0 to 1. Viridis: 17 colours of
#: matplotlib's table (CC0), interpolated linearly (within 6/255 of it: tests).
_GREY = np.array([[255, 255, 255], [0, 0, 0]], dtype=float)
_VIRIDIS = np.array([
    [68, 1, 84], [72, 24, 106], [71, 45, 123], [66, 64, 134], [59, 82, 139], [51, 99, 141],
    [44, 114, 142], [38, 130, 142], [33, 145, 140], [31, 160, 136], [40, 174, 128],
    [63, 188, 115], [94, 201, 98], [132, 212, 75], [173, 220, 48], [216, 226, 25],
    [253, 231, 37]], dtype=float)


def _colour(values: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: ``values`` in 0..1 (clipped) through the ramp ``stops``; NaN cells
    in :data:`NO_DATA_COLOUR`."""
    t = np.clip(np.nan_to_num(values, nan=0.0), 0.0, 1.0) * (len(stops) - 1)
    i = np.minimum(t.astype(int), len(stops) - 2)
    f = t - i
    rest = 1.0 - f
    no_data = np.isnan(values)
    rgb = np.empty((*np.shape(values), 3), dtype=np.uint8)
    # Channel by channel: (H, W) temporaries instead of (H, W, 3) ones (a city's preview
    # took seconds).
    for c, no_data_value in enumerate(int(NO_DATA_COLOUR[k:k + 2], 16) for k in (1, 3, 5)):
        channel = stops[i, c] * rest + stops[i + 1, c] * f
        channel[no_data] = no_data_value
        rgb[..., c] = np.round(channel)
    return rgb


def _font(size: int):
    from PIL import ImageFont

    return ImageFont.load_default(size=size)


def _variance_range(v: np.ndarray) -> tuple[float, float]:
    finite = v[np.isfinite(v)]
    if finite.size == 0:
        return 0.0, 1.0
    lo, hi = float(finite.min()), float(finite.max())
    if hi <= lo:
        hi = lo + 1.0
    return lo, hi


def _write_unit_square_plot(
    path: str | os.PathLike[str],
    lines: list[tuple[np.ndarray, np.ndarray, str]],
    diagonal_label: str,
    axis_labels: tuple[str, str],
    title: str,
    legend_loc: str,
    marker: str | None = None,
) -> None:
    """A square [0, 1]^2 plot of ``(x, y, label)`` lines over the dashed diagonal, as PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.0, 6.0), dpi=150, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    ax.plot([0.0, 1.0], [0.0, 1.0], linestyle="--", color="0.6", linewidth=1.0,
            label=diagonal_label)
    for x, y, label in lines:
        ax.plot(np.asarray(x), np.asarray(y), marker=marker, linewidth=1.6, label=label)
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.0)
    ax.set_aspect("equal")
    ax.set_xlabel(axis_labels[0])
    ax.set_ylabel(axis_labels[1])
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(loc=legend_loc)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")


def render_roc(
    path: str | os.PathLike[str],
    curves: list[tuple[str, np.ndarray, np.ndarray, float]],
    title: str = "ROC",
) -> None:
    """Write a PNG of ROC curves with the no-discrimination diagonal, atomically.

    Args:
        path: output ``.png``.
        curves: ``(name, fpr (T,), tpr (T,), auc)`` per method; the legend shows the AUC.
        title: plot title.
    """
    _write_unit_square_plot(
        path, [(fpr, tpr, f"{name} (AUC = {auc:.3f})") for name, fpr, tpr, auc in curves],
        "no discrimination", ("false positive rate", "true positive rate"), title,
        "lower right")


def render_reliability(
    path: str | os.PathLike[str],
    curves: list[tuple[str, np.ndarray, np.ndarray, float, float]],
    title: str = "Reliability",
) -> None:
    """Write a PNG reliability diagram (fraction occupied against mean p), atomically.

    Args:
        path: output ``.png``.
        curves: ``(name, mean p (K,), fraction occupied (K,), brier, ece)`` per method,
            one point per non-empty probability bin; the legend shows Brier and ECE.
        title: plot title.
    """
    _write_unit_square_plot(
        path, [(mean_p, fraction, f"{name} (Brier {brier:.3f}, ECE {ece:.3f})")
               for name, mean_p, fraction, brier, ece in curves],
        "perfectly calibrated",
        ("mean predicted p(occupied) in bin", "fraction of points occupied"), title,
        "upper left", marker="o")
