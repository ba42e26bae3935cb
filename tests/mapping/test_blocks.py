"""The anchor lattice's blending weights: a partition of unity for every blend overlap."""

from __future__ import annotations

import numpy as np
import pytest
from blendweights import trapezoid

from gpocc.config import config_from_dict
from gpocc.errors import GpoccError
from gpocc.gridspec import GridSpec
from gpocc.mapping.blocks import Anchor, AnchorLattice, Block


def summed_weights(lattice: AnchorLattice) -> tuple[np.ndarray, np.ndarray]:
    """Every cell's summed weight and number of anchors with a positive weight there."""
    total = np.zeros(lattice.spec.shape)
    count = np.zeros(lattice.spec.shape, dtype=int)
    rows, cols = lattice.shape
    for r in range(rows):
        for c in range(cols):
            block, weight = lattice.footprint(Anchor(r, c))
            assert lattice.footprint_block(Anchor(r, c)) == block
            window = (slice(block.row0, block.row0 + block.rows),
                      slice(block.col0, block.col0 + block.cols))
            assert np.all((weight >= 0) & (weight <= 1))
            total[window] += weight
            count[window] += weight > 0
    return total, count


@pytest.mark.parametrize("overlap", [1.0, 0.5, 0.25, 0.1])
def test_weights_are_a_partition_of_unity_with_the_stated_overlap(overlap):
    cells = 10
    spec = GridSpec.from_bounds(0.0, 0.0, 5.3, 4.7, 0.1)  # 53 x 47 cells: partial blocks
    lattice = AnchorLattice(spec, cells, overlap)
    total, count = summed_weights(lattice)
    np.testing.assert_allclose(total, 1.0, rtol=0, atol=1e-12)
    # Away from the edges, each axis has 1 + o anchors per cell on average (one cell of
    # rounding either way), so a cell costs (1 + o)^2 local problems.
    interior = count[cells:3 * cells, cells:3 * cells]
    per_axis = np.sqrt(interior.mean())
    assert lattice.blend == max(overlap, 0.2)  # at least two cells: 0.1 becomes 0.2
    assert abs(per_axis - (1 + lattice.blend)) <= 1.0 / cells + 1e-9
    # The weights themselves, against the definition, at cells inside the lattice.
    anchor = Anchor(2, 1)
    block, weight = lattice.footprint(anchor)
    for r in range(block.rows):
        for c in range(block.cols):
            dr = abs((block.row0 + r + 0.5) / cells - 0.5 - anchor.row)
            dc = abs((block.col0 + c + 0.5) / cells - 0.5 - anchor.col)
            expected = trapezoid(dr, lattice.blend) * trapezoid(dc, lattice.blend)
            assert weight[r, c] == pytest.approx(expected, abs=1e-12)


def test_smaller_overlap_shrinks_the_footprint_and_keeps_the_centre():
    spec = GridSpec.from_bounds(0.0, 0.0, 6.0, 6.0, 0.1)
    full, _ = AnchorLattice(spec, 10, 1.0).footprint(Anchor(3, 3))
    half, weight = AnchorLattice(spec, 10, 0.5).footprint(Anchor(3, 3))
    assert (full.rows, full.cols) == (20, 20)
    # Cells whose centres lie less than 0.75 blocks from the anchor (at cell 35.0).
    assert (half.row0, half.rows, half.cols) == (28, 14, 14)
    # The block's own central half is its anchor's alone.
    inner = weight[(32 - half.row0):(38 - half.row0), (32 - half.col0):(38 - half.col0)]
    np.testing.assert_array_equal(inner, 1.0)


@pytest.mark.parametrize("overlap", [0.0, -0.5, 1.5])
def test_blend_overlap_outside_its_range_is_a_config_error(overlap):
    with pytest.raises(GpoccError, match="model.blend_overlap"):
        config_from_dict({"model": {"blend_overlap": overlap}}, "job.yaml")


@pytest.mark.parametrize("cells", [4, 5, 10, 15, 25])
@pytest.mark.parametrize("overlap", [0.05, 0.1, 0.2, 0.3, 0.6, 0.7, 1.0])
def test_blending_is_never_a_step_and_footprints_hold_no_rounding_dust(cells, overlap):
    """However narrow the configured band, an anchor's weight changes by at most half
    between adjacent cells (a band of at least two cells: no seam), and no footprint
    carries weights that are zero but for rounding (they would cost whole problems)."""
    spec = GridSpec.from_bounds(0.0, 0.0, 8 * cells * 0.1, 6 * cells * 0.1, 0.1)
    lattice = AnchorLattice(spec, cells, overlap)
    for anchor in (Anchor(3, 4), Anchor(0, 0), Anchor(5, 7)):
        _, weight = lattice.footprint(anchor)
        assert weight.min() >= 0.0
        assert weight[weight > 0].min() > 1e-6
        assert np.abs(np.diff(weight, axis=0)).max() <= 0.5 + 1e-9
        assert np.abs(np.diff(weight, axis=1)).max() <= 0.5 + 1e-9
        # Interior anchors' footprints are symmetric about their centre.
        if anchor == Anchor(3, 4):
            np.testing.assert_allclose(weight, weight[::-1, ::-1], rtol=0, atol=1e-12)


def test_cell_centres_at_picks_the_same_values_as_the_whole_grid():
    # A window off the grid's origin at an awkward resolution: the per-cell values must
    # equal cell_centres()'s bit for bit (map anchors use them; tiles use the grid).
    spec = GridSpec(x0=-20.891522300137005, y0=-26.51194809182128, resolution=0.1,
                    width=422, height=403).window(137, 251, 20, 20)
    rng = np.random.default_rng(3)
    wanted = rng.random((spec.height, spec.width)) < 0.6
    xs, ys = spec.cell_centres()
    x_at, y_at = spec.cell_centres_at(*np.nonzero(wanted))
    assert np.array_equal(x_at, xs[wanted]) and np.array_equal(y_at, ys[wanted])
    # Both against the grid's geometry, written out: row 0 is the north edge.
    rows, cols = np.nonzero(wanted)
    np.testing.assert_allclose(x_at, spec.x0 + (cols + 0.5) * spec.resolution,
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(y_at, spec.y1 - (rows + 0.5) * spec.resolution,
                               rtol=0, atol=1e-12)
    # And bit for bit against the meshgrid the maps used before (tiles still do).
    old_x, old_y = np.meshgrid(spec.x0 + (np.arange(spec.width) + 0.5) * spec.resolution,
                               spec.y0 + (spec.height - np.arange(spec.height) - 0.5)
                               * spec.resolution)
    assert np.array_equal(x_at, old_x[wanted]) and np.array_equal(y_at, old_y[wanted])


@pytest.mark.parametrize("overlap", [1.0, 0.5, 0.2])
def test_anchors_over_a_block_are_those_whose_footprint_meets_it(overlap):
    # Oracle: every anchor of the lattice, its footprint tested cell range by cell range.
    spec = GridSpec.from_bounds(0.0, 0.0, 5.3, 4.7, 0.1)  # partial blocks at the edges
    lattice = AnchorLattice(spec, 10, overlap)
    rows, cols = lattice.shape
    rng = np.random.default_rng(7)
    blocks = [Block(0, 0, spec.height, spec.width), Block(40, 50, 7, 3)]
    for _ in range(30):
        r0, c0 = int(rng.integers(spec.height)), int(rng.integers(spec.width))
        blocks.append(Block(r0, c0, int(rng.integers(1, spec.height - r0 + 1)),
                            int(rng.integers(1, spec.width - c0 + 1))))
    for block in blocks:
        expected = []
        for r in range(rows):
            for c in range(cols):
                fp = lattice.footprint_block(Anchor(r, c))
                if (fp.row0 < block.row0 + block.rows and block.row0 < fp.row0 + fp.rows
                        and fp.col0 < block.col0 + block.cols
                        and block.col0 < fp.col0 + fp.cols):
                    expected.append(Anchor(r, c))
        assert lattice.anchors_over(block) == expected
