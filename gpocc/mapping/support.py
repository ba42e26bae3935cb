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
        inside = np.zeros((r_hi - r_lo, c_hi - c_lo), dtype=bool)
        half = cells * spec.resolution * math.sqrt(0.5)
        groups = [(r, c) for r in range(r_lo, r_hi, cells) for c in range(c_lo, c_hi, cells)]
        if not groups:
            return inside
        centres = np.array([
            [spec.x0 + (c + min(cells, spec.width - c) / 2) * spec.resolution,
             spec.y1 - (r + min(cells, spec.height - r) / 2) * spec.resolution]
            for r, c in groups])
        maybe = self.within(centres, half)
        surely = self.within(centres, -half) if self.max_distance_m > half else \
            np.zeros(len(groups), dtype=bool)
        boundary = np.zeros(inside.shape, dtype=bool)
        for (r, c), m, s in zip(groups, maybe, surely, strict=True):
            if m:
                window = (slice(r - r_lo, r - r_lo + cells), slice(c - c_lo, c - c_lo + cells))
                (inside if s else boundary)[window] = True
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
