"""Where the data are: a coarse raster of the cells that some laser beam passed through.

The map is nodata farther than ``map.max_beam_distance_m`` from every beam (the segment
from the sensor to the hit, or to the free extent of a no-return beam). The training
samples are a poor proxy for the beams: free samples start one spacing (0.4 m) from the
sensor and stop a gap (up to metres with noisy ranges) before the hit, and thinning keeps
one per 0.15 m cell and label. So the model stores, at train time, a boolean raster of
``COVERAGE_CELL_M`` cells marked wherever a point taken every cell side along any beam
fell. Distances to the centres of marked cells then differ from the exact point-to-beam
distance by at most :attr:`Coverage.error_m` (half a cell diagonal plus half a step):
0.24 m, a few kilobytes per building, about 1 s per 1000 scans of 180 beams to build.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gpocc import compiled
from gpocc.config import Config, SensorConfig
from gpocc.io.scans import ScanBatch
from gpocc.samples.beam_rules import (
    beam_points,
    checked_poses,
    classify_beams,
    laser_poses,
    mount_vector,
    no_return_free_m,
    sensor_config,
)

#: Coverage cell side, metres.
COVERAGE_CELL_M = 0.2


@dataclass(frozen=True)
class Coverage:
    """Cells of a raster that some beam crossed.

    Attributes:
        x0, y0: lower-left corner of cell (0, 0), metres, map frame.
        cell_m: cell side, metres.
        step_m: spacing of the points taken along beams, metres.
        covered: (H, W) bool; ``covered[i, j]`` is the cell ``[x0 + j cell, x0 + (j+1)
            cell) x [y0 + i cell, y0 + (i+1) cell)`` (row 0 is the south row).
    """

    x0: float
    y0: float
    cell_m: float
    step_m: float
    covered: np.ndarray

    @property
    def error_m(self) -> float:
        """Bound on |distance to the nearest marked-cell centre - distance to the beams|.

        A beam point is within ``step / 2`` of a marked point, which is within half a
        diagonal of its cell's centre; and every marked centre is within half a diagonal
        of a beam point.
        """
        return self.cell_m * math.sqrt(0.5) + self.step_m / 2.0

    def centres(self) -> np.ndarray:
        """(K, 2) metres: centres of the covered cells, in row-major order."""
        rows, cols = np.nonzero(self.covered)
        return np.column_stack([self.x0 + (cols + 0.5) * self.cell_m,
                                self.y0 + (rows + 0.5) * self.cell_m])


def beam_segments(batch: ScanBatch, sensor: SensorConfig, config: Config
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Start and end points, each (N, 2) metres, of the beams that gave training samples.

    The same scans and beams as :func:`gpocc.samples.beams.build_samples` (strides, REP
    117 classes of :mod:`gpocc.samples.beam_rules`): a hit runs from the sensor to the reading,
    a no-return beam to ``min(no_return_free_m, range_max)``; invalid readings give
    nothing.
    """
    cfg = config.samples
    scans = np.arange(0, batch.n_scans, cfg.scan_stride)
    beams = np.arange(0, batch.n_beams, cfg.beam_stride)
    ranges = np.asarray(batch.ranges, dtype=float)[np.ix_(scans, beams)]
    bearings = np.asarray(batch.angles, dtype=float)[beams]
    classes = classify_beams(ranges, float(batch.range_min), float(batch.range_max))
    limit = no_return_free_m(sensor, float(batch.range_max))
    length = np.where(classes.hit, ranges, np.where(classes.no_return, limit, 0.0))
    scan_i, beam_i = np.nonzero(~classes.invalid & (length > 0))
    lasers = laser_poses(checked_poses(batch, scans), mount_vector(sensor))[scan_i]
    start = lasers[:, :2].copy()
    end = beam_points(lasers, bearings[beam_i], length[scan_i, beam_i])
    return start, end


def coverage_of_segments(start: np.ndarray, end: np.ndarray,
                         cell_m: float = COVERAGE_CELL_M) -> Coverage:
    """The coverage raster of (N, 2) segments ``start -> end`` (metres)."""
    return _coverage_of_parts([(start, end)], cell_m)


def _coverage_of_parts(parts: list[tuple[np.ndarray, np.ndarray]], cell_m: float
                       ) -> Coverage:
    """The coverage raster of the segments of every part, each a pair of (N_k, 2)
    ``start``, ``end`` arrays (metres): :func:`coverage_of_segments` of their
    concatenation, marked part by part (a city's beams concatenated took seconds)."""
    step = cell_m
    parts = [(start, end) for start, end in parts if len(start)]
    if not parts:
        return Coverage(0.0, 0.0, cell_m, step, np.zeros((0, 0), dtype=bool))
    # Column by column: numpy reduces an (N, 2) array along axis 0 two numbers at a time
    # (0.25 s for Freiburg 079's 1.7 million beams, against 0.01 s).
    lo = np.array([min(min(s[:, j].min(), e[:, j].min()) for s, e in parts) for j in (0, 1)])
    hi = np.array([max(max(s[:, j].max(), e[:, j].max()) for s, e in parts) for j in (0, 1)])
    x0, y0 = (np.floor(lo / cell_m) - 1) * cell_m
    width = int(np.floor((hi[0] - x0) / cell_m)) + 2
    height = int(np.floor((hi[1] - y0) / cell_m)) + 2
    covered = np.zeros((height, width), dtype=bool)
    # Points in cell units relative to the corner (non-negative): the cell index is the
    # integer part.
    origin = np.array([x0, y0])
    for start, end in parts:
        compiled.mark_segments((start - origin) / cell_m, (end - origin) / cell_m, covered)
    return Coverage(float(x0), float(y0), cell_m, step, covered)


def beam_coverage(batches: list[ScanBatch], config: Config,
                  cell_m: float = COVERAGE_CELL_M) -> Coverage:
    """The coverage raster of every beam of ``batches`` that gave training samples."""
    return _coverage_of_parts(
        [beam_segments(batch, sensor_config(batch, config), config) for batch in batches],
        cell_m)


def sample_coverage(means: np.ndarray, cell_m: float = COVERAGE_CELL_M) -> Coverage:
    """A stand-in for models without beams (built from samples alone, or older files):
    the cells holding a training sample's mean. Its distances overstate the distance to
    the beams by up to about half the free spacing plus the hit gap."""
    pts = np.asarray(means, dtype=float)
    return coverage_of_segments(pts, pts, cell_m)


def union_coverage(first: Coverage, second: Coverage) -> Coverage:
    """The cells either raster covers, on a raster grown to both extents.

    Both rasters lie on the lattice of ``cell_m`` multiples that
    :func:`coverage_of_segments` uses, so their cells line up; the result is the raster
    of both rasters' beams (up to beam points on cell edges, which float round-off may
    put in the neighbouring cell).

    Raises:
        ValueError: rasters of different cell or step sizes.
    """
    if first.cell_m != second.cell_m or first.step_m != second.step_m:
        raise ValueError(f"coverage rasters of {first.cell_m} m and {second.cell_m} m cells "
                         "cannot be joined")
    if first.covered.size == 0:
        return second
    if second.covered.size == 0:
        return first
    cell = first.cell_m
    origins = [(round(c.x0 / cell), round(c.y0 / cell)) for c in (first, second)]
    col0 = min(o[0] for o in origins)
    row0 = min(o[1] for o in origins)
    cols = max(o[0] + c.covered.shape[1] for o, c in zip(origins, (first, second),
                                                          strict=True)) - col0
    rows = max(o[1] + c.covered.shape[0] for o, c in zip(origins, (first, second),
                                                          strict=True)) - row0
    covered = np.zeros((rows, cols), dtype=bool)
    for (c0, r0), cov in zip(origins, (first, second), strict=True):
        h, w = cov.covered.shape
        covered[r0 - row0:r0 - row0 + h, c0 - col0:c0 - col0 + w] |= cov.covered
    x0 = first.x0 if origins[0][0] == col0 else second.x0
    y0 = first.y0 if origins[0][1] == row0 else second.y0
    return Coverage(float(x0), float(y0), cell, first.step_m, covered)
