"""Map blocks: square groups of cells that share one local GP problem."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gpocc.gp.local import NeighbourIndex, predict_local
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
class BlockResult:
    """Latent mean, variance, prior variance and p(occupied), each (rows, cols), of a block."""

    block: Block
    mean: np.ndarray
    variance: np.ndarray
    prior_variance: np.ndarray
    probability: np.ndarray


def block_cells(block_size_m: float, resolution: float) -> int:
    """Cells per block side for a block of about ``block_size_m`` metres (at least 1)."""
    return max(1, int(math.floor(block_size_m / resolution + 1e-9)))


def plan_blocks(spec: GridSpec, cells: int) -> list[Block]:
    """Cover ``spec`` with blocks of ``cells`` x ``cells`` (smaller at the east/south edges)."""
    return [
        Block(r, c, min(cells, spec.height - r), min(cells, spec.width - c))
        for r in range(0, spec.height, cells)
        for c in range(0, spec.width, cells)
    ]


def predict_block(model: GPModel, index: NeighbourIndex, spec: GridSpec,
                  block: Block) -> BlockResult:
    """Predict every cell centre of ``block`` from the neighbours of the block's centre."""
    window = spec.window(block.row0, block.col0, block.rows, block.cols)
    xs, ys = window.cell_centres()
    queries = np.column_stack([xs.ravel(), ys.ravel()])
    centre = np.array([(window.x0 + window.x1) / 2.0, (window.y0 + window.y1) / 2.0])
    problem = index.problem(centre, model.config.model.neighbours)
    pred = predict_local(model.kernel, model.noise_variance, problem, queries, model.level)
    probability = model.classifier.probability(pred.mean, pred.variance)
    shape = (block.rows, block.cols)
    return BlockResult(block, pred.mean.reshape(shape), pred.variance.reshape(shape),
                       pred.prior_variance.reshape(shape), probability.reshape(shape))
