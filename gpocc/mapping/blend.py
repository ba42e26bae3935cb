"""A tile's layers from the blended predictions of the anchors around it.

Each cell's latent mean, variance and prior variance are the bilinear blends ``sum w_k
x_k`` (weights summing to one) of its anchors' predictions. Every anchor approximates the
same GP posterior, so the blend interpolates approximations; it is not a mixture of
different models. The mixture variance ``sum w_k (v_k + mu_k^2) - mean^2`` was tried:
where anchors extrapolate differently (behind walls) the spread of their means made
ripples with the lattice's period, 20 times steeper than a per-cell prediction
(tests/mapping/test_support.py). Cells outside
the data's support, and anchors whose whole footprint is outside, are not computed.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from gpocc.gridspec import GridSpec
from gpocc.mapping.blocks import Anchor, AnchorLattice, Block
from gpocc.mapping.executors import AnchorExecutor, run_anchors
from gpocc.mapping.support import Support


@dataclass(frozen=True)
class TileLayers:
    """A tile's (H, W) layers; NaN / False outside the support.

    ``mean``, ``variance``, ``prior_variance``: latent GP (float64); ``probability``:
    p(occupied) (float32); ``unsure``: variance above ``max_variance_ratio`` x prior.
    ``anchors``: local problems computed for this tile.
    """

    mean: np.ndarray
    variance: np.ndarray
    prior_variance: np.ndarray
    probability: np.ndarray
    unsure: np.ndarray
    anchors: int


def supported_anchors(lattice: AnchorLattice, anchors: list[Anchor], mask: np.ndarray,
                      row0: int = 0, col0: int = 0) -> tuple[list[Anchor], list[Anchor]]:
    """Split ``anchors`` into those whose footprint holds a supported cell, each with its
    ``inside`` mask (only those cells are predicted: the others become nodata anyway),
    and the rest. ``mask`` (H, W) bool covers the lattice's cells from (row0, col0) on
    and holds every footprint."""
    kept, skipped = [], []
    # A footprint's rows depend on its anchor's row alone and its columns on its column:
    # per lattice row, prefix counts of the mask columns that hold a supported cell answer
    # "any in this footprint?" for each anchor without touching its cells (slicing and
    # testing every footprint was a large share of a city map's main process, which
    # shares the cores with the workers).
    bands: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    columns: dict[int, tuple[int, int]] = {}
    for anchor in anchors:
        if anchor.row not in bands or anchor.col not in columns:
            fp = lattice.footprint_block(anchor)
            columns[anchor.col] = fp.col0 - col0, fp.cols
            if anchor.row not in bands:
                band = mask[fp.row0 - row0:fp.row0 + fp.rows - row0]
                bands[anchor.row] = band, np.concatenate(([0], np.cumsum(band.any(axis=0))))
        band, counts = bands[anchor.row]
        first, width = columns[anchor.col]
        if counts[first + width] > counts[first]:
            kept.append(Anchor(anchor.row, anchor.col, inside=band[:, first:first + width].copy()))
        else:
            skipped.append(anchor)
    return kept, skipped


#: Lattice rows of anchors laid out (support mask, supported anchors) and queued at a
#: time: the workers start on the first rows while the rest are laid out (the Intel
#: map's layout took 0.13 s, in which both workers waited).
BAND_ROWS = 4


class _TileSupport:
    """The support mask of a tile and two blocks around it (which hold the footprint of
    every anchor over the tile), computed a band of anchors at a time and only as far
    down as their footprints reach. Every piece is computed in the whole map's frame
    (:meth:`Support.mask` with rows and columns), so it is bit for bit that part of the
    map's mask: whether a cell is inside, and an anchor computed, does not depend on the
    tiling or the bands."""

    def __init__(self, lattice: AnchorLattice, support: Support, tile: Block) -> None:
        spec, cells = lattice.spec, lattice.cells
        self.lattice, self.support, self.tile = lattice, support, tile
        # From whole blocks of the map (Support.mask's groups), wherever the tile starts.
        self.r0 = max(0, (tile.row0 // cells - 2) * cells)
        self.c0 = max(0, (tile.col0 // cells - 2) * cells)
        self.r1 = min(spec.height, tile.row0 + tile.rows + 2 * cells)
        self.c1 = min(spec.width, tile.col0 + tile.cols + 2 * cells)
        self.mask = np.zeros((self.r1 - self.r0, self.c1 - self.c0), dtype=bool)
        self.done = self.r0  # rows [r0, done) of the mask are computed

    def _compute_to(self, row: int) -> None:
        # Whole blocks from r0 on (the last one cut at r1).
        cells = self.lattice.cells
        row = min(self.r1, self.r0 + -(-(row - self.r0) // cells) * cells)
        if row > self.done:
            self.mask[self.done - self.r0:row - self.r0] = self.support.mask(
                self.lattice.spec, cells, rows=(self.done, row), cols=(self.c0, self.c1))
            self.done = row

    def split(self, anchors: list[Anchor]) -> tuple[list[Anchor], list[Anchor]]:
        """:func:`supported_anchors` of ``anchors`` (some of the tile's)."""
        if anchors:
            # A footprint's rows depend on its anchor's row alone: the lowest row reaches
            # farthest (supported_anchors below takes every anchor's footprint).
            lowest = self.lattice.footprint_block(max(anchors, key=lambda a: a.row))
            self._compute_to(lowest.row0 + lowest.rows)
        return supported_anchors(self.lattice, anchors, self.mask, self.r0, self.c0)

    def inside(self) -> np.ndarray:
        """(rows, cols) bool: the tile's cells inside the support."""
        self._compute_to(self.r1)
        t = self.tile
        return self.mask[t.row0 - self.r0:t.row0 + t.rows - self.r0,
                         t.col0 - self.c0:t.col0 + t.cols - self.c0]


def predict_tile(
    model,
    lattice: AnchorLattice,
    row0: int,
    col0: int,
    window: GridSpec,
    support: Support | None,
    workers: int = 1,
    scheduler: str | None = None,
    progress: Callable[[int], None] | None = None,
    executor: AnchorExecutor | None = None,
    while_running: Callable[[], None] | None = None,
) -> TileLayers:
    """Blend the anchors over the tile ``window`` whose top-left cell is (row0, col0) of
    ``lattice.spec``; ``progress(n)`` counts the tile's own anchors (one per block).
    ``executor`` runs the anchors (one for every tile of a map), each band of
    :data:`BAND_ROWS` queued as soon as it is laid out; without it, ``workers`` and
    ``scheduler`` choose a new one for this tile. ``while_running()`` is called once if
    the tile has anchors, after they are all queued for ``executor``'s workers and
    before their results are collected (an executor that computes in this process, or
    none, computes them as they are collected: nothing overlaps)."""
    tile = Block(row0, col0, window.height, window.width)
    anchors = lattice.anchors_over(tile)
    cells = lattice.cells

    def owned(anchor) -> bool:
        return (row0 <= anchor.row * cells < row0 + tile.rows
                and col0 <= anchor.col * cells < col0 + tile.cols)

    if support is not None:
        tile_support = _TileSupport(lattice, support, tile)
        runs, computed = [], []
        # anchors_over gives the anchors row by row.
        by_row = [list(row) for _, row in itertools.groupby(anchors, key=lambda a: a.row)]
        for first in range(0, len(by_row), BAND_ROWS):
            band = [a for row in by_row[first:first + BAND_ROWS] for a in row]
            kept, skipped = tile_support.split(band)
            if progress:
                progress(sum(owned(a) for a in skipped))
            computed += kept
            if executor is not None and kept:
                runs.append(executor.run(lattice, kept))
        inside = tile_support.inside()
        anchors = computed
        results = (itertools.chain.from_iterable(runs) if executor is not None
                   else run_anchors(model, lattice, anchors, workers, scheduler))
    else:
        inside = np.ones(window.shape, dtype=bool)
        results = (executor.run(lattice, anchors) if executor is not None
                   else run_anchors(model, lattice, anchors, workers, scheduler))

    sum_w = np.zeros(window.shape)
    sum_mean = np.zeros(window.shape)
    sum_variance = np.zeros(window.shape)
    sum_prior = np.zeros(window.shape)
    if while_running is not None and anchors:
        while_running()
    for result in results:
        b = result.block
        r_lo, r_hi = max(b.row0, row0), min(b.row0 + b.rows, row0 + tile.rows)
        c_lo, c_hi = max(b.col0, col0), min(b.col0 + b.cols, col0 + tile.cols)
        if progress and owned(result.anchor):
            progress(1)
        if r_lo >= r_hi or c_lo >= c_hi:
            continue
        src = (slice(r_lo - b.row0, r_hi - b.row0), slice(c_lo - b.col0, c_hi - b.col0))
        dst = (slice(r_lo - row0, r_hi - row0), slice(c_lo - col0, c_hi - col0))
        w, mu = result.weight[src], result.mean[src]
        sum_w[dst] += w
        sum_mean[dst] += w * mu
        sum_variance[dst] += w * result.variance[src]
        sum_prior[dst] += w * result.prior_variance[src]

    valid = inside & (sum_w > 0)
    # In place: a 4096-cell tile's float64 layers are 134 MB each.
    invalid = ~valid
    mean, variance, prior = sum_mean, sum_variance, sum_prior
    for layer in (mean, variance, prior):
        np.divide(layer, sum_w, out=layer, where=valid)
        layer[invalid] = np.nan
    del sum_w
    probability = np.full(window.shape, np.nan, dtype=np.float32)
    probability[valid] = model.classifier.probability(mean[valid], variance[valid])
    ratio = model.config.classify.max_variance_ratio
    unsure = np.zeros(window.shape, dtype=bool)
    unsure[valid] = variance[valid] > ratio * prior[valid]
    return TileLayers(mean, variance, prior, probability, unsure, len(anchors))
