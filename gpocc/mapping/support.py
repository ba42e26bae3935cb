"""The data's support: which map cells lie within ``map.max_beam_distance_m`` of a beam.

Cells outside are nodata in every layer (NaN probability and variance, 255 class,
unknown in map.pgm), and local problems whose cells all lie outside are not computed.
Distances are to the centres of the model's coverage cells
(:mod:`gpocc.samples.coverage`), within ``coverage.error_m`` of the distance to the beams.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from gpocc.gridspec import GridSpec
from gpocc.samples.coverage import Coverage, sample_coverage

#: Cells per KD-tree look-up of :meth:`Support.mask` (its temporaries: about 50 MB).
_LOOKUP_BATCH = 1 << 20


class Support:
    """Distance look-ups against a coverage raster, for one ``max_distance_m`` (metres)."""

    def __init__(self, coverage: Coverage, max_distance_m: float) -> None:
        self.coverage = coverage
        self.max_distance_m = float(max_distance_m)
        centres = coverage.centres()
        self._tree = cKDTree(centres) if len(centres) else None

    def within(self, points: np.ndarray, radius_m: float = 0.0) -> np.ndarray:
        """(N,) bool: whether each (N, 2) point lies within ``max_distance_m + radius_m``
        of a covered cell's centre."""
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        if self._tree is None:
            return np.zeros(len(pts), dtype=bool)
        limit = self.max_distance_m + radius_m
        # Strictly beyond the limit is outside; the tree's bound is exclusive, so nudge it.
        distance, _ = self._tree.query(pts, k=1, distance_upper_bound=limit * (1 + 1e-12)
                                       + 1e-12)
        return distance <= limit

    def mask(self, spec: GridSpec, cells: int, rows: tuple[int, int] | None = None,
             cols: tuple[int, int] | None = None) -> np.ndarray:
        """(H, W) bool of ``spec``'s cells inside the support; with ``rows`` and ``cols``
        ([start, stop) cell indices of ``spec``, starts multiples of ``cells``), only
        that part of it.

        Whole ``cells`` x ``cells`` groups are decided from their centre when it lies
        farther than the group's half-diagonal from the support boundary (the distance is
        1-Lipschitz), so only groups near the boundary query every cell. Every coordinate
        is computed in ``spec``'s frame, so a part is bit for bit that part of the whole:
        a cell exactly at the limit stays on the same side however the mask is cut.
        """
        r_lo, r_hi = (0, spec.height) if rows is None else rows
        c_lo, c_hi = (0, spec.width) if cols is None else cols
        if r_lo % cells or c_lo % cells or not (0 <= r_lo <= r_hi <= spec.height
                                                 and 0 <= c_lo <= c_hi <= spec.width):
            raise ValueError(f"rows {rows} and cols {cols} must start on a multiple of "
                             f"{cells} and lie in the {spec.height} x {spec.width} grid")
        shape = (r_hi - r_lo, c_hi - c_lo)
        half = cells * spec.resolution * math.sqrt(0.5)
        group_rows = np.arange(r_lo, r_hi, cells)
        group_cols = np.arange(c_lo, c_hi, cells)
        if not (group_rows.size and group_cols.size):
            return np.zeros(shape, dtype=bool)
        # Group centres, (rows, cols) of groups flattened row-major.
        xs = spec.x0 + (group_cols + np.minimum(cells, spec.width - group_cols) / 2) \
            * spec.resolution
        ys = spec.y1 - (group_rows + np.minimum(cells, spec.height - group_rows) / 2) \
            * spec.resolution
        centres = np.column_stack([np.tile(xs, ys.size), np.repeat(ys, xs.size)])
        grid = (group_rows.size, group_cols.size)
        maybe = self.within(centres, half).reshape(grid)
        surely = (self.within(centres, -half).reshape(grid) if self.max_distance_m > half
                  else np.zeros(grid, dtype=bool))

        def cells_of(groups: np.ndarray) -> np.ndarray:
            """Each group's flag on its cells (the last row and column of groups cut)."""
            return np.repeat(np.repeat(groups, cells, axis=0), cells, axis=1)[:shape[0],
                                                                              :shape[1]]

        inside = cells_of(maybe & surely)
        boundary = cells_of(maybe & ~surely)
        # The cells of the boundary groups in batches of look-ups (one per group took
        # two thirds of the Intel map's mask), row-major like ``boundary``'s True cells.
        local_rows, local_cols = np.nonzero(boundary)
        found = np.empty(local_rows.size, dtype=bool)
        for lo in range(0, local_rows.size, _LOOKUP_BATCH):
            r = local_rows[lo:lo + _LOOKUP_BATCH] + r_lo
            c = local_cols[lo:lo + _LOOKUP_BATCH] + c_lo
            xs, ys = spec.cell_centres_at(r, c)
            found[lo:lo + r.size] = self.within(np.column_stack([xs, ys]))
        inside[local_rows, local_cols] = found
        return inside


def model_support(model) -> Support | None:
    """The support of ``model`` under its ``map.max_beam_distance_m`` (None: no mask).

    Models trained from beams carry their coverage; others (built from samples alone, or
    written before coverage existed) fall back to the cells holding a training sample.
    """
    limit = model.config.map.max_beam_distance_m
    if limit is None:
        return None
    coverage = getattr(model, "coverage", None)
    if coverage is None:
        coverage = sample_coverage(model.samples.means)
    return Support(coverage, limit)
