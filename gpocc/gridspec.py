"""Raster geometry shared by maps, grids and ground truth: a north-up metric grid."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gpocc.errors import GpoccError

#: A box edge within this share of a cell of a cell edge is on that edge: bounds printed
#: or computed with round-off give the grid of the exact ones (the cell count here, and
#: the window's place on a map's anchor lattice, :func:`gpocc.mapping.mapper.lattice_frame`).
CELL_TOLERANCE = 1e-6


@dataclass(frozen=True)
class GridSpec:
    """A north-up raster in the map frame.

    ``(x0, y0)`` is the lower-left corner of the lower-left cell, metres. Row 0 is the
    top (north) row, as in GeoTIFF and PGM; column 0 is the west column. The centre of
    cell (row r, col c) is ``(x0 + (c + 0.5) * resolution, y0 + (height - r - 0.5) *
    resolution)``.
    """

    x0: float
    y0: float
    resolution: float
    width: int
    height: int

    def __post_init__(self) -> None:
        if not (self.resolution > 0 and math.isfinite(self.resolution)):
            raise GpoccError(
                f"resolution must be a positive number of metres, got {self.resolution}"
            )
        if self.width <= 0 or self.height <= 0:
            raise GpoccError(f"the map area is empty ({self.width} x {self.height} cells)")

    @classmethod
    def from_bounds(
        cls, x_min: float, y_min: float, x_max: float, y_max: float, resolution: float
    ) -> GridSpec:
        """The smallest grid of ``resolution`` anchored at (x_min, y_min) covering the box."""
        if not all(math.isfinite(v) for v in (x_min, y_min, x_max, y_max)):
            raise GpoccError(
                f"bounds must be finite numbers of metres, got {x_min} {y_min} {x_max} {y_max}"
            )
        if not (x_max > x_min and y_max > y_min):
            raise GpoccError(
                f"bounds must satisfy XMIN < XMAX and YMIN < YMAX, got "
                f"{x_min} {y_min} {x_max} {y_max}"
            )
        if not (resolution > 0 and math.isfinite(resolution)):
            raise GpoccError(f"resolution must be a positive number of metres, got {resolution}")
        across = ((x_max - x_min) / resolution, (y_max - y_min) / resolution)
        if not all(math.isfinite(v) and v < 2.0**62 for v in across):
            raise GpoccError(
                f"bounds {x_min} {y_min} {x_max} {y_max} at {resolution} m give more cells "
                f"than can be counted; use a coarser resolution or smaller bounds"
            )
        width = max(1, int(math.ceil(across[0] - CELL_TOLERANCE)))
        height = max(1, int(math.ceil(across[1] - CELL_TOLERANCE)))
        return cls(float(x_min), float(y_min), float(resolution), width, height)

    @property
    def x1(self) -> float:
        """East edge, metres."""
        return self.x0 + self.width * self.resolution

    @property
    def y1(self) -> float:
        """North edge, metres."""
        return self.y0 + self.height * self.resolution

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) metres."""
        return (self.x0, self.y0, self.x1, self.y1)

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) cells."""
        return (self.height, self.width)

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) arrays of cell-centre x and y, metres."""
        xs, ys = self.cell_centres_at(np.arange(self.height), np.arange(self.width))
        return np.meshgrid(xs, ys)

    def cell_centres_at(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre x of ``cols`` and y of ``rows`` (integer arrays), metres; for the
        (K,) cells (rows[k], cols[k]) these are the values of :meth:`cell_centres` there,
        without its (H, W) arrays (a map anchor's query points: 42 against 93 us)."""
        xs = self.x0 + (cols + 0.5) * self.resolution
        ys = self.y0 + (self.height - rows - 0.5) * self.resolution
        return xs, ys

    def window(self, row0: int, col0: int, rows: int, cols: int) -> GridSpec:
        """The sub-grid of ``rows`` x ``cols`` cells whose top-left cell is (row0, col0)."""
        rows = min(rows, self.height - row0)
        cols = min(cols, self.width - col0)
        return GridSpec(
            x0=self.x0 + col0 * self.resolution,
            y0=self.y0 + (self.height - row0 - rows) * self.resolution,
            resolution=self.resolution,
            width=cols,
            height=rows,
        )

    def decimated(self, stride: int) -> GridSpec:
        """The grid of every ``stride``-th row and column, as ``array[::stride, ::stride]``.

        Decimation keeps row 0 (north), so the coarser grid is anchored at the north edge;
        its south edge may lie below this grid's when the height is not a multiple.
        """
        rows, cols = math.ceil(self.height / stride), math.ceil(self.width / stride)
        return GridSpec(self.x0, self.y1 - rows * self.resolution * stride,
                        self.resolution * stride, cols, rows)

    def index_of(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Row and column of each (N, 2) point, and a mask of points inside the grid (a
        point too far for a cell index, or not finite, is outside: row and column -1)."""
        pts = np.asarray(points, dtype=float)
        with np.errstate(over="ignore", invalid="ignore"):
            fcol = np.floor((pts[:, 0] - self.x0) / self.resolution)
            frow = np.floor((pts[:, 1] - self.y0) / self.resolution)
            far = ~((np.abs(fcol) < 2.0**62) & (np.abs(frow) < 2.0**62))  # NaN too
        if far.any():
            fcol[far] = -1.0
            frow[far] = self.height
        col = fcol.astype(np.int64)
        row = self.height - 1 - frow.astype(np.int64)
        inside = (col >= 0) & (col < self.width) & (row >= 0) & (row < self.height)
        return row, col, inside


def geotransform(spec: GridSpec, georef=None) -> tuple[float, float, float, float, float, float]:
    """GDAL geotransform ``(c, a, b, f, d, e)`` of ``spec``: pixel (col, row) corner to CRS.

    ``X = c + a col + b row``, ``Y = f + d col + e row``. Without ``georef`` the CRS is
    the map frame itself (north-up, ``(x0, y1 + ...)``). With one (an object with
    ``easting_m``, ``northing_m``, ``yaw_deg``: the map frame's origin in the CRS and the
    direction of its +x axis, counter-clockwise from east), a map point (x, y) lands at
    ``E = easting + cos(yaw) x - sin(yaw) y``, ``N = northing + sin(yaw) x + cos(yaw) y``;
    for a non-zero yaw the geotransform is rotated, so the raster keeps the map's cells.
    """
    res = float(spec.resolution)
    if georef is None:
        return (float(spec.x0), res, 0.0, float(spec.y1), 0.0, -res)
    yaw = math.radians(float(georef.yaw_deg))
    c, s = math.cos(yaw), math.sin(yaw)
    if abs(s) < 1e-15:  # keep exact zeros: a north-up map stays exactly north-up
        s = 0.0
    # Pixel (col, row) corner in the map frame: x = x0 + col res, y = y1 - row res.
    x, y = float(spec.x0), float(spec.y1)
    east = float(georef.easting_m) + c * x - s * y
    north = float(georef.northing_m) + s * x + c * y
    return (east, c * res, s * res, north, s * res, -c * res)


def georef_metadata(georef) -> dict | None:
    """The ``map.georef`` block for metadata.json (None: local frame in metres)."""
    if georef is None:
        return None
    return {"epsg": georef.epsg, "easting_m": georef.easting_m,
            "northing_m": georef.northing_m, "yaw_deg": georef.yaw_deg}
