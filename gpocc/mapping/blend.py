"""A tile's layers from the blended predictions of the anchors around it.

Each cell's latent mean, variance and prior variance are the bilinear blends ``sum w_k
x_k`` (weights summing to one) of its anchors' predictions. Every anchor approximates the
same GP posterior, so the blend interpolates approximations; it is not a mixture of
different models. The mixture variance ``sum w_k (v_k + mu_k^2) - mean^2`` was tried:
where anchors extrapolate differently (behind walls) the spread of their means made
ripples with the lattice's period, 20 times steeper than a per-cell prediction
(tests/test_support.py). Cells outside
the data's support, and anchors whose whole footprint is outside, are not computed.
"""

from __future__ import annotations

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
    for anchor in anchors:
        fp = lattice.footprint_block(anchor)
        inside = mask[fp.row0 - row0:fp.row0 + fp.rows - row0,
                      fp.col0 - col0:fp.col0 + fp.cols - col0]
        if inside.any():
            kept.append(Anchor(anchor.row, anchor.col, inside=inside.copy()))
        else:
            skipped.append(anchor)
    return kept, skipped


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
    ``executor`` runs the anchors (one for every tile of a map); without it, ``workers``
    and ``scheduler`` choose a new one for this tile. ``while_running()`` is called once
    if the tile has anchors, after they are queued for ``executor``'s workers and
    before their results are collected (an executor that computes in this process, or
    none, computes them as they are collected: nothing overlaps)."""
    tile = Block(row0, col0, window.height, window.width)
    anchors = lattice.anchors_over(tile)
    cells = lattice.cells

    def owned(anchor) -> bool:
        return (row0 <= anchor.row * cells < row0 + tile.rows
                and col0 <= anchor.col * cells < col0 + tile.cols)

    if support is not None:
        # The support of the tile and two blocks around it, which holds the footprint of
        # every anchor over the tile: an anchor is computed only if its footprint holds a
        # supported cell, so the choice does not depend on the tiling.
        spec = lattice.spec
        er0, ec0 = max(0, row0 - 2 * cells), max(0, col0 - 2 * cells)
        er1 = min(spec.height, row0 + tile.rows + 2 * cells)
        ec1 = min(spec.width, col0 + tile.cols + 2 * cells)
        around = support.mask(spec.window(er0, ec0, er1 - er0, ec1 - ec0), cells)
        anchors, skipped = supported_anchors(lattice, anchors, around, er0, ec0)
        inside = around[row0 - er0:row0 + tile.rows - er0, col0 - ec0:col0 + tile.cols - ec0]
        if progress:
            progress(sum(owned(a) for a in skipped))
    else:
        inside = np.ones(window.shape, dtype=bool)

    sum_w = np.zeros(window.shape)
    sum_mean = np.zeros(window.shape)
    sum_variance = np.zeros(window.shape)
    sum_prior = np.zeros(window.shape)
    results = (executor.run(lattice, anchors) if executor is not None
               else run_anchors(model, lattice, anchors, workers, scheduler))
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
