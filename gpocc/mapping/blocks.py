"""Map blocks and the overlapping local problems that predict them.

A map is covered by square blocks of ``cells`` x ``cells``. One local GP problem (the
``neighbours`` training samples nearest a point, centred there) is anchored at the centre
of every block. Each cell is predicted by the (up to) four anchors around it and the
predictions are blended with weights that form a continuous partition of unity over the
anchor lattice, so probability and variance have no seams where the anchors change.

Along each axis an anchor's weight is a trapezoid in the distance d (in blocks) from it:
1 for d <= (1 - o) / 2, falling linearly to 0 at d = (1 + o) / 2, with ``o`` the blend
overlap (``model.blend_overlap``). With o = 1 this is the bilinear tent, positive on the
cells less than one block away; with o < 1 a block's centre is predicted by its own
anchor alone and each cell by (1 + o)^2 anchors on average. The band is never narrower
than two cells (:attr:`AnchorLattice.blend`). Along the lattice's edges the weights are
clamped, so edge cells keep full weight.

A lattice covers the grid it is made on (its ``spec``). A map window is computed on the
lattice of the model's whole map, as part of that grid
(:func:`gpocc.mapping.mapper.lattice_frame`): on the whole map's cells and inside it, it
holds the whole map's values; off them, or reaching beyond the whole map, it differs
where that function says.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from gpocc.config import ModelConfig
from gpocc.gp.local import LocalProblem, NeighbourIndex, predict_locals
from gpocc.gp.model import GPModel
from gpocc.gridspec import GridSpec


@dataclass(frozen=True)
class Block:
    """Cells ``[row0, row0 + rows) x [col0, col0 + cols)`` of a grid."""

    row0: int
    col0: int
    rows: int
    cols: int


@dataclass(frozen=True)
class Anchor:
    """Local problem (row, col) of a map's anchor lattice: centred on block (row, col).

    ``inside``: optional (rows, cols) bool over the anchor's footprint, the cells to
    predict (the data's support); the others are left at zero and must not be used.
    """

    row: int
    col: int
    inside: np.ndarray | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class AnchorResult:
    """One anchor's prediction over the cells where its weight is positive.

    ``block`` gives those cells (whole-map rows and columns); ``weight``, ``mean``,
    ``variance`` and ``prior_variance`` are (rows, cols): the blending weight and the
    latent GP mean, variance and prior variance from this anchor's problem.
    """

    anchor: Anchor
    block: Block
    weight: np.ndarray
    mean: np.ndarray
    variance: np.ndarray
    prior_variance: np.ndarray


def block_cells(block_size_m: float, resolution: float) -> int:
    """Cells per block side for a block of about ``block_size_m`` metres (at least 1)."""
    return max(1, int(math.floor(block_size_m / resolution + 1e-9)))


@functools.lru_cache(maxsize=4096)
def _axis(cells: int, index: int, n_cells: int, n_anchors: int,
          overlap: float = 1.0) -> tuple[int, np.ndarray]:
    """First cell and (n,) weights of anchor ``index`` along one axis of ``n_cells`` cells
    and ``n_anchors`` anchors, ``cells`` a block, ``overlap`` the blend overlap (see the
    module docstring). Cached: a map asks for the same few rows and columns thousands of
    times (0.5 s of the Intel map's main process before)."""
    lo = max(0, (index - 1) * cells)
    hi = min(n_cells, (index + 2) * cells)
    u = (np.arange(lo, hi) + 0.5) / cells - 0.5  # anchor coordinate of each cell
    u = np.clip(u, 0.0, n_anchors - 1)
    # The trapezoid; with overlap 1 exactly the tent max(0, 1 - d).
    w = np.clip((1.0 + overlap) / (2.0 * overlap) - np.abs(u - index) / overlap, 0.0, 1.0)
    # A cell centre exactly at the band's outer edge rounds to ~1e-15 instead of 0: it
    # would widen the footprint by a row, and could keep an anchor alive for nothing.
    w[w < 1e-9] = 0.0
    nonzero = np.flatnonzero(w > 0)
    weights = w[nonzero[0]:nonzero[-1] + 1]
    weights.setflags(write=False)  # shared by every caller
    return lo + int(nonzero[0]), weights


def _meets(axis: tuple[int, np.ndarray], start: int, length: int) -> bool:
    """Whether an anchor's range along one axis (:func:`_axis`) meets cells
    [start, start + length)."""
    first, weights = axis
    return first < start + length and start < first + len(weights)


@dataclass(frozen=True)
class AnchorLattice:
    """The anchors of a whole map ``spec`` with blocks of ``cells`` a side, blended with
    ``overlap`` (``model.blend_overlap``)."""

    spec: GridSpec
    cells: int
    overlap: float = 1.0
    #: Where the anchors' positions are measured from when ``spec`` grew from another grid
    #: by whole blocks: that grid's north-west corner (x, y metres) and the blocks ``spec``
    #: added to its north and west. The same anchor then has, bit for bit, the centre it
    #: has on that grid (its neighbours do not depend on the growth). None: ``spec``'s.
    origin: tuple[float, float] | None = None
    shift: tuple[int, int] = (0, 0)

    @property
    def blend(self) -> float:
        """The overlap the weights use: ``overlap``, but at least two cells of a block
        (a band narrower than a cell holds no cell centre, and the blend would become a
        step, a seam), and at most 1."""
        return min(1.0, max(self.overlap, 2.0 / self.cells))

    @classmethod
    def of_model(cls, spec: GridSpec, model: ModelConfig) -> AnchorLattice:
        """The lattice of a map ``spec`` under ``model``'s block size and blend overlap."""
        return cls(spec, block_cells(model.block_size_m, spec.resolution), model.blend_overlap)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of anchors: one per block."""
        return (math.ceil(self.spec.height / self.cells), math.ceil(self.spec.width / self.cells))

    def centre(self, anchor: Anchor) -> np.ndarray:
        """(2,) metres: the centre of the anchor's (full-size) block."""
        half = self.cells / 2.0
        res = self.spec.resolution
        x0, y1 = (self.spec.x0, self.spec.y1) if self.origin is None else self.origin
        row, col = anchor.row - self.shift[0], anchor.col - self.shift[1]
        return np.array([x0 + (col * self.cells + half) * res,
                         y1 - (row * self.cells + half) * res])

    def footprint(self, anchor: Anchor) -> tuple[Block, np.ndarray]:
        """The cells where ``anchor``'s weight is positive, and the (rows, cols) weights."""
        (r0, wr), (c0, wc) = self._axes(anchor)
        return Block(r0, c0, len(wr), len(wc)), np.outer(wr, wc)

    def footprint_block(self, anchor: Anchor) -> Block:
        """The block of :meth:`footprint` alone (no weights: a third of its time)."""
        (r0, wr), (c0, wc) = self._axes(anchor)
        return Block(r0, c0, len(wr), len(wc))

    def _axes(self, anchor: Anchor) -> tuple[tuple[int, np.ndarray], tuple[int, np.ndarray]]:
        return self._row_axis(anchor.row), self._col_axis(anchor.col)

    def _row_axis(self, row: int) -> tuple[int, np.ndarray]:
        """First cell row and weights of the anchors in lattice row ``row``."""
        return _axis(self.cells, row, self.spec.height, self.shape[0], self.blend)

    def _col_axis(self, col: int) -> tuple[int, np.ndarray]:
        """First cell column and weights of the anchors in lattice column ``col``."""
        return _axis(self.cells, col, self.spec.width, self.shape[1], self.blend)

    def anchors_over(self, block: Block) -> list[Anchor]:
        """Anchors whose footprint meets ``block`` (row-major order)."""
        n_rows, n_cols = self.shape
        near_rows = range(max(0, block.row0 // self.cells - 1),
                          min(n_rows, (block.row0 + block.rows - 1) // self.cells + 2))
        near_cols = range(max(0, block.col0 // self.cells - 1),
                          min(n_cols, (block.col0 + block.cols - 1) // self.cells + 2))
        # A footprint is the product of its row and column ranges: test each range once
        # (testing every anchor's footprint took 0.07-0.13 s of the Intel map).
        rows = [r for r in near_rows if _meets(self._row_axis(r), block.row0, block.rows)]
        cols = [c for c in near_cols if _meets(self._col_axis(c), block.col0, block.cols)]
        return [Anchor(r, c) for r in rows for c in cols]


def predict_anchor(model: GPModel, index: NeighbourIndex, lattice: AnchorLattice,
                   anchor: Anchor, problem: LocalProblem | None = None) -> AnchorResult:
    """Predict the cells of ``anchor``'s footprint (those in ``anchor.inside``, or all)
    from the neighbours of its centre (``problem``, if the caller looked them up:
    :func:`anchor_problems`).

    The footprint never depends on how the map is tiled, so neither do the values.
    """
    if problem is None:
        problem = anchor_problems(model, index, lattice, [anchor])[0]
    return predict_anchors(model, lattice, [anchor], [problem])[0]


def predict_anchors(model: GPModel, lattice: AnchorLattice, anchors: list[Anchor],
                    problems: list[LocalProblem]) -> list[AnchorResult]:
    """:func:`predict_anchor` of each of ``anchors`` from its ``problems`` entry, as one
    batch of local predictions (:func:`gpocc.gp.local.predict_locals`)."""
    footprints, queries = [], []
    for anchor in anchors:
        block, weight = lattice.footprint(anchor)
        window = lattice.spec.window(block.row0, block.col0, block.rows, block.cols)
        shape = (block.rows, block.cols)
        wanted = np.ones(shape, dtype=bool) if anchor.inside is None else anchor.inside
        if wanted.shape != shape:
            raise ValueError(f"anchor mask {wanted.shape} does not match its footprint "
                             f"{shape}")
        footprints.append((block, weight, wanted))
        queries.append(np.column_stack(window.cell_centres_at(*np.nonzero(wanted))))
    predictions = predict_locals(model.kernel, model.noise_variance, problems, queries,
                                 model.level, model.backend)
    results = []
    for anchor, (block, weight, wanted), pred in zip(anchors, footprints, predictions,
                                                     strict=True):
        layers = []
        for values in (pred.mean, pred.variance, pred.prior_variance):
            layer = np.zeros(wanted.shape)
            layer[wanted] = values
            layers.append(layer)
        results.append(AnchorResult(anchor, block, weight, *layers))
    return results


def anchor_problems(model: GPModel, index: NeighbourIndex, lattice: AnchorLattice,
                    anchors: list[Anchor]) -> list[LocalProblem]:
    """The local problem of each of ``anchors``: its centre's neighbours, from one look-up."""
    centres = [lattice.centre(anchor) for anchor in anchors]
    return index.problems(centres, model.config.model.neighbours)
