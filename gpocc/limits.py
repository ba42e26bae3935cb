"""Resource guards: refuse work whose size would exhaust memory, before allocating it.

A raster's cell count is checked against ``map.max_cells`` (default 2e8 cells: the
untiled layers of a grid or truth raster take about 17 bytes a cell, 3.4 GB; a tiled GP
map holds one tile at a time, but its block plan and decimated copies still grow with
the area). The environment variable ``GPOCC_MAX_CELLS`` overrides the config, for
commands that read no config (``simulate``) or a model's embedded config (``map``).
"""

from __future__ import annotations

import math
import os

from gpocc.errors import GpoccError

DEFAULT_MAX_CELLS = 200_000_000
ENV_MAX_CELLS = "GPOCC_MAX_CELLS"

#: Samples one scan may give (hits plus free samples along its beams); a 1080-beam
#: scan at 30 m and 0.4 m spacing gives about 81 000. Sample building holds a scan's
#: sigma points at once (docs/benchmarks.md, 'Memory per training sample', gives the
#: bytes per sample), so this bounds that memory.
MAX_SAMPLES_PER_SCAN = 1_000_000

#: Labelled points ``gpocc split`` may hold out (24 bytes each, plus the random draws).
MAX_HELDOUT_POINTS = 50_000_000


def max_cells(configured: int | None = None) -> int:
    """The cell limit: ``GPOCC_MAX_CELLS`` if set, else ``configured``, else the default."""
    env = os.environ.get(ENV_MAX_CELLS)
    if env is not None and env.strip():
        try:
            value = int(float(env))
        except (ValueError, OverflowError):
            value = 0
        if value <= 0:
            raise GpoccError(
                f"environment variable {ENV_MAX_CELLS}={env!r} must be a positive number of "
                f"cells; unset it or set e.g. {ENV_MAX_CELLS}=400000000"
            )
        return value
    return DEFAULT_MAX_CELLS if configured is None else int(configured)


def check_cells(width: float, height: float, resolution: float, limit: int, what: str,
                fix: str = "use a coarser resolution or smaller bounds",
                configurable: bool = True) -> None:
    """Refuse a ``width`` x ``height`` raster of ``what`` above ``limit`` cells.

    ``width`` and ``height`` may be floats (a size computed before any rounding), so a
    request too large for an integer is refused the same way. ``configurable``: the
    limit came from a config the user can edit (not one embedded in a model file).
    """
    cells = float(width) * float(height)
    if math.isfinite(cells) and cells <= limit:
        return
    size = (f"{width:.0f} x {height:.0f} = {cells:.3g} cells" if math.isfinite(cells)
            else "more cells than can be counted")
    raise GpoccError(
        f"{what} at {resolution:g} m would be {size}, more than the limit of {limit:.3g} "
        f"(about {17 * limit / 1e9:.1f} GB); {fix}, or raise "
        + (f"map.max_cells in the config (or {ENV_MAX_CELLS})" if configurable
           else f"the limit with the environment variable {ENV_MAX_CELLS}")
    )


def check_seed(seed: int | None, option: str = "--seed") -> None:
    """Refuse a seed the random generators reject (they take [0, 2^32))."""
    if seed is not None and not 0 <= seed < 2**32:
        raise GpoccError(f"{option} must be an integer in [0, 2^32), got {seed}")
