"""The classic log-odds occupancy grid: the baseline the GP maps are scored against.

Inverse sensor model (Moravec and Elfes; Thrun, Burgard and Fox, *Probabilistic
Robotics*, ch. 9): every beam adds ``log_odds_free`` to each cell it passes through before
its hit and ``log_odds_occupied`` to the cell of its hit. A beam updates a cell at most
once. Log-odds are clamped to ``[clamp_min, clamp_max]`` after each scan (scans of all
sensors are applied in time order), OctoMap's clamping policy, so that a cell can change
its mind after a long run of one kind of evidence. Unlike OctoMap, which updates a cell at
most once per scan, two beams of one scan may both update a cell before that scan's
clamp, as in the per-beam formulation of *Probabilistic Robotics*.

Beams follow the same rules as the GP's samples (:mod:`gpocc.samples.beam_rules`): REP 117
classes (NaN, ``-inf`` and ranges below ``range_min`` are ignored; a finite
``range_min <= r < range_max`` is a hit; ``+inf`` or ``r >= range_max`` (no return) marks
free space up to ``min(no_return_free_m, range_max)`` and no hit), the laser pose from
the base pose and mount, and the pose covariance that applies.

Rays are traversed exactly (every cell the segment crosses with positive length, like
Amanatides and Woo's walk) but without a per-beam loop: see :func:`ray_cells`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from gpocc.config import Config, GridConfig, SensorConfig
from gpocc.errors import GpoccError
from gpocc.gridspec import GridSpec
from gpocc.io.scans import ScanBatch
from gpocc.samples import beam_rules
from gpocc.samples.unscented import unscented_transform

#: Upper bound on the ray columns (see :func:`ray_cells`) handled in one vectorised step;
#: keeps peak memory near a few hundred MB whatever the log length.
CHUNK_COLUMNS = 2_000_000

#: Spread windows hold at most (2 * SPREAD_MAX_RADIUS + 1)^2 cells per hit; a wider
#: Gaussian is truncated there (and renormalised) to bound the cost.
SPREAD_MAX_RADIUS = 32

#: A spread weight below this share of a hit is dropped (it would not move the cell).
SPREAD_MIN_WEIGHT = 1e-3

# Tolerance, in cells, for a ray that only touches a cell at a corner or along an edge:
# such a cell is not crossed. Far above rounding error (~1e-12 cells), far below any
# meaningful overlap.
_EDGE_EPS = 1e-9

# Chunks of hits for the spread: bounds hits x window cells per step.
_SPREAD_CHUNK_CELLS = 4_000_000
# Sub-columns per cell column in the spread's cell-mass computation.
_SUB = 4


@dataclass(frozen=True, eq=False)
class LogOddsGrid:
    """A log-odds occupancy grid and how often each cell was updated.

    Attributes:
        spec: the raster geometry.
        log_odds: (H, W) float64 clamped log-odds of occupancy; 0 where never updated.
        hit_counts: (H, W) int32, beams whose hit endpoint lies in the cell (with
            ``spread_hits`` the hit's log-odds go to the spread window instead, but the
            count stays with the endpoint cell).
        pass_counts: (H, W) int32, beams that passed through the cell as free space.
        observed: (H, W) bool, cells that received any update (a hit, a pass, or at
            least ``SPREAD_MIN_WEIGHT`` of a spread hit).
    """

    spec: GridSpec
    log_odds: np.ndarray
    hit_counts: np.ndarray
    pass_counts: np.ndarray
    observed: np.ndarray

    @property
    def probability(self) -> np.ndarray:
        """(H, W) float64 p(occupied) = 1 - 1 / (1 + exp(l)); NaN where never observed."""
        p = 0.5 * (1.0 + np.tanh(0.5 * self.log_odds))  # the logistic, without overflow
        return np.where(self.observed, p, np.nan)

    @property
    def variance(self) -> np.ndarray:
        """(H, W) Bernoulli variance p (1 - p) of the cell's occupancy; NaN where unobserved.

        Not comparable with a GP map's latent variance: it says how undecided a cell is
        (0.25 at p = 0.5), not how much evidence it has.
        """
        p = self.probability
        return p * (1.0 - p)


@dataclass(frozen=True, eq=False)
class RayCells:
    """Cells crossed by a set of rays, flattened: one entry per (ray, cell).

    Attributes:
        ray: (M,) int64 index of the ray.
        row: (M,) int64 row (0 = north) of the cell.
        col: (M,) int64 column of the cell.
        is_end: (M,) bool, the cell holding the ray's end point.
    """

    ray: np.ndarray
    row: np.ndarray
    col: np.ndarray
    is_end: np.ndarray


def _clip_long_segments(spec: GridSpec, starts: np.ndarray, ends: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """``starts`` and ``ends`` with every segment longer than the grid's width plus height
    (in cells) cut to the grid and a one-cell border (Liang-Barsky); one that misses it
    becomes a point outside it. The traversal steps through every cell of a segment's
    major axis, inside the grid or not: a small grid at a fine resolution (``--bounds``
    around part of the data) made beams of millions of steps each. Shorter segments are
    left as they are, so a map over its data's bounds traverses exactly as before.

    Args:
        spec: the grid.
        starts: (N, 2) segment starts, metres.
        ends: (N, 2) segment ends, metres.

    Returns:
        ``(starts, ends)``, (N, 2) metres each, new arrays where a segment was cut.
    """
    res = spec.resolution
    d = ends - starts
    long = np.abs(d).max(axis=1) / res > spec.width + spec.height + 4
    if not long.any():
        return starts, ends
    lo = np.array([spec.x0 - res, spec.y0 - res])
    hi = np.array([spec.x0 + (spec.width + 1) * res, spec.y0 + (spec.height + 1) * res])
    p, q = starts[long], d[long]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t_lo = (lo - p) / q
        t_hi = (hi - p) / q
    # Along an axis the segment does not move on, it is inside the slab or never.
    inside_slab = (p >= lo) & (p <= hi)
    t_in = np.where(q != 0, np.minimum(t_lo, t_hi), np.where(inside_slab, -np.inf, np.inf))
    t_out = np.where(q != 0, np.maximum(t_lo, t_hi), np.where(inside_slab, np.inf, -np.inf))
    t_enter, t_leave = t_in.max(axis=1), t_out.min(axis=1)
    enter, leave = np.clip(t_enter, 0.0, 1.0), np.clip(t_leave, 0.0, 1.0)
    misses = t_enter > t_leave
    new_start = np.where((enter > 0)[:, None], p + enter[:, None] * q, p)
    new_end = np.where((leave < 1)[:, None], p + leave[:, None] * q, ends[long])
    outside = lo - 2 * res
    new_start[misses] = outside
    new_end[misses] = outside
    starts, ends = starts.copy(), ends.copy()
    starts[long], ends[long] = new_start, new_end
    return starts, ends


def ray_cells(spec: GridSpec, starts: np.ndarray, ends: np.ndarray) -> RayCells:
    """Every grid cell each segment ``starts[i] -> ends[i]`` crosses, vectorised.

    Exact traversal without a per-ray loop: each ray is split into the columns (rows for
    a ray steeper than 45 degrees) of its major axis; within one column a ray's minor
    coordinate spans at most one cell width, so it crosses one or two cells there, found
    from the minor coordinate where the ray enters and leaves the column. Neighbouring
    columns use the same boundary value, so the cells form one connected 8-neighbour walk
    with no gap and no repetition. A cell touched only at a corner or along an edge
    (overlap below ``1e-9`` cells) is not crossed; the cell of the start point is
    included, and so is the end cell (``floor`` of the end point, as in
    :meth:`GridSpec.index_of`) unless the end lies exactly on its boundary.

    Args:
        spec: the grid.
        starts: (N, 2) segment starts, metres.
        ends: (N, 2) segment ends, metres.

    Returns:
        The crossed cells inside the grid, grouped by ray in ray order; each cell appears
        at most once per ray.
    """
    starts = np.asarray(starts, dtype=float).reshape(-1, 2)
    ends = np.asarray(ends, dtype=float).reshape(-1, 2)
    starts, ends = _clip_long_segments(spec, starts, ends)
    res = spec.resolution
    u0 = (starts[:, 0] - spec.x0) / res
    v0 = (starts[:, 1] - spec.y0) / res
    u1 = (ends[:, 0] - spec.x0) / res
    v1 = (ends[:, 1] - spec.y0) / res
    x_major = np.abs(u1 - u0) >= np.abs(v1 - v0)
    a0, a1 = np.where(x_major, u0, v0), np.where(x_major, u1, v1)
    b0, b1 = np.where(x_major, v0, u0), np.where(x_major, v1, u1)
    da = a1 - a0
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = np.where(da != 0.0, (b1 - b0) / da, 0.0)
    c0 = np.floor(a0).astype(np.int64)
    c1 = np.floor(a1).astype(np.int64)
    forward = c1 >= c0
    step = np.where(forward, 1, -1)
    n_cols = np.abs(c1 - c0) + 1
    first = np.cumsum(n_cols) - n_cols
    last = first + n_cols - 1

    # Column k of a ray is major cell c0 + step * k. A forward ray leaves it at its high
    # edge c + 1, a backward one at its low edge c, where the minor coordinate is
    # b0 + (c0 + forward - a0 + step * k) * slope. Each boundary value is computed once
    # and shared by the two columns it separates, so no cell is missed or repeated.
    ray = np.repeat(np.arange(len(starts), dtype=np.int64), n_cols)
    k = np.arange(ray.size, dtype=np.int64) - first[ray]
    base = b0 + (c0 + forward - a0) * slope
    b_exit = base[ray] + k * (step * slope)[ray]
    b_exit[last] = b1
    b_entry = np.empty_like(b_exit)
    b_entry[1:] = b_exit[:-1]
    b_entry[first] = b0
    lo = np.minimum(b_entry, b_exit)
    hi = np.maximum(b_entry, b_exit, out=b_exit)
    r_lo = np.floor(lo + _EDGE_EPS).astype(np.int64)
    r_hi = np.maximum(r_lo, np.ceil(hi - _EDGE_EPS).astype(np.int64) - 1)
    major = c0[ray] + k * step[ray]
    end_minor = np.floor(b1).astype(np.int64)
    end_lo = np.zeros(ray.size, dtype=bool)
    end_hi = np.zeros(ray.size, dtype=bool)
    end_lo[last] = r_lo[last] == end_minor
    end_hi[last] = r_hi[last] == end_minor

    # Each column's one or two cells, interleaved so the entries stay in ray order.
    two = r_hi > r_lo
    keep = np.stack((np.ones_like(two), two), axis=1)
    counts = 1 + two
    ray = np.repeat(ray, counts)
    major = np.repeat(major, counts)
    minor = np.stack((r_lo, r_hi), axis=1)[keep]
    is_end = np.stack((end_lo, end_hi), axis=1)[keep]
    xm = x_major[ray]
    col = np.where(xm, major, minor)
    row = spec.height - 1 - np.where(xm, minor, major)
    inside = (col >= 0) & (col < spec.width) & (row >= 0) & (row < spec.height)
    if inside.all():
        return RayCells(ray=ray, row=row, col=col, is_end=is_end)
    return RayCells(ray=ray[inside], row=row[inside], col=col[inside], is_end=is_end[inside])


# --------------------------------------------------------------------------- beams


@dataclass(frozen=True, eq=False)
class _Beams:
    """Usable beams of a batch: free length (m) and class, per (scan, beam)."""

    length: np.ndarray  # (S, B) metres; 0 for ignored beams
    is_hit: np.ndarray  # (S, B) bool
    valid: np.ndarray  # (S, B) bool: hit or no-return with a positive free length
    laser: np.ndarray  # (S, 3)


def _classify_beams(batch: ScanBatch, sensor: SensorConfig) -> _Beams:
    ranges = np.asarray(batch.ranges, dtype=float)
    classes = beam_rules.classify_beams(ranges, float(batch.range_min), float(batch.range_max))
    is_hit, no_return = classes.hit, classes.no_return
    limit = beam_rules.no_return_free_m(sensor, batch.range_max)
    length = np.where(is_hit, ranges, np.where(no_return, limit, 0.0))
    length = np.where(np.isfinite(length), length, 0.0)
    valid = is_hit | (no_return & (length > 0.0))
    laser = beam_rules.laser_poses(beam_rules.checked_poses(batch),
                                   beam_rules.mount_vector(sensor))
    return _Beams(length=length, is_hit=is_hit, valid=valid, laser=laser)


def _beam_segments(
    batch: ScanBatch, beams: _Beams, scans: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Segments of the valid beams of ``scans``, in (scan, beam) order.

    Returns:
        (scan position in ``scans`` (n,), beam index (n,), start (n, 2), end (n, 2),
        is_hit (n,)).
    """
    pos, beam = np.nonzero(beams.valid[scans])
    scan = scans[pos]
    laser = beams.laser[scan]
    start = laser[:, :2]
    end = beam_rules.beam_points(laser, np.asarray(batch.angles, dtype=float)[beam],
                                 beams.length[scan, beam])
    return pos, beam, start, end, beams.is_hit[scan, beam]


# --------------------------------------------------------------------------- spread


def _hit_gaussians(
    batch: ScanBatch, sensor: SensorConfig, config: Config, scan: np.ndarray, beam: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Mean (n, 2) and covariance (n, 2, 2) of hit positions, as build_samples makes them.

    The same unscented transform of (range, bearing, x, y, yaw) that gives the GP's
    occupied samples their input covariance.
    """
    n = scan.size
    pose_cov = beam_rules.pose_covariances(batch, sensor, scan)
    mean = np.empty((n, 5))
    mean[:, 0] = np.asarray(batch.ranges, dtype=float)[scan, beam]
    mean[:, 1] = np.asarray(batch.angles, dtype=float)[beam]
    mean[:, 2:] = np.asarray(batch.poses, dtype=float)[scan]
    cov = np.zeros((n, 5, 5))
    cov[:, 0, 0] = sensor.range_variance_m2
    cov[:, 1, 1] = sensor.bearing_variance_rad2
    cov[:, 2:, 2:] = pose_cov
    mount = beam_rules.mount_vector(sensor)
    ut = config.samples.unscented
    y_mean, y_cov, _ = unscented_transform(
        lambda x: beam_rules.beam_endpoint(x, mount), mean, cov, ut.alpha, ut.beta, ut.kappa
    )
    return y_mean, y_cov


def spread_weights(
    spec: GridSpec, means: np.ndarray, covariances: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Share of each Gaussian hit position falling in each nearby cell.

    The share of a cell is the probability mass of ``N(mean, S)`` inside it. Each column
    is cut into 4 sub-columns (1 where y barely depends on x); the mass of a sub-column
    is exact (a difference of normal
    CDFs of x), and the distribution of y given x in it is moment-matched to a normal
    (conditional mean and variance, including the spread of x within the sub-column).
    This is exact for axis-aligned covariances and for covariances much smaller than a
    cell (all mass in the cell holding the mean, as in the plain grid), and within about
    0.001 of a hit per cell for correlated ones (checked against Monte Carlo in the
    tests). The window reaches 3 standard deviations beyond the mean's cell (at most
    ``SPREAD_MAX_RADIUS`` cells); shares are renormalised over it so every hit adds
    exactly its log-odds, and shares below ``SPREAD_MIN_WEIGHT`` are then dropped.

    Args:
        spec: the grid.
        means: (n, 2) metres.
        covariances: (n, 2, 2) m^2.

    Returns:
        (hit index (M,), flat cell index ``row * W + col`` (M,), share (M,)), grouped by
        hit in hit order; cells outside the grid are dropped (their share is lost).
    """
    means = np.asarray(means, dtype=float).reshape(-1, 2)
    res = spec.resolution
    # Work in cell units, v pointing north; a tiny floor keeps degenerate axes finite.
    mu = (means[:, 0] - spec.x0) / res
    mv = (means[:, 1] - spec.y0) / res
    cov = np.asarray(covariances, dtype=float).reshape(-1, 2, 2) / res**2
    suu = cov[:, 0, 0] + 1e-12
    svv = cov[:, 1, 1] + 1e-12
    suv = 0.5 * (cov[:, 0, 1] + cov[:, 1, 0])
    if means.shape[0] == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, np.zeros(0)
    slope = suv / suu
    cond_var = np.maximum(svv - suv * slope, 1e-12)
    cu = np.floor(mu).astype(np.int64)
    cv = np.floor(mv).astype(np.int64)
    sd_max = np.sqrt(np.maximum(suu, svv))
    radius = np.clip(np.ceil(3.0 * sd_max), 1, SPREAD_MAX_RADIUS).astype(np.int64)
    # Sub-columns are needed only where y given x shifts by a good part of its spread
    # across one column; elsewhere a whole column is close enough to normal.
    n_sub = np.where(np.sqrt(cond_var) >= 2.0 * np.abs(slope), 1, _SUB)
    out_hit, out_flat, out_w = [], [], []
    # Hits of one window radius at a time: a few far, blurred hits must not make every
    # hit pay for their large window.
    for rad, sub in np.unique(np.column_stack((radius, n_sub)), axis=0):
        members = np.flatnonzero((radius == rad) & (n_sub == sub))
        offsets = np.arange(-rad, rad + 1)
        per_chunk = max(1, _SPREAD_CHUNK_CELLS // (sub * offsets.size**2))
        for i0 in range(0, members.size, per_chunk):
            h = members[i0:i0 + per_chunk]
            col = cu[h, None] + offsets[None, :]  # (n, K) column index = left edge
            # Sub-columns of width 1/m: x barely varies within one, so y given x there
            # is close to normal.
            left = (col[:, :, None] + np.arange(sub) / sub).reshape(len(h), -1)
            su = np.sqrt(suu[h])[:, None]
            a = (left - mu[h, None]) / su
            b = (left + 1.0 / sub - mu[h, None]) / su
            z = ndtr(b) - ndtr(a)
            ok = z > 1e-15
            zs = np.where(ok, z, 1.0)
            pa, pb = _phi(a), _phi(b)
            # Mean and variance of x given x in the sub-column (truncated normal), cells.
            ratio = (pa - pb) / zs
            u_bar = np.where(ok, mu[h, None] + su * ratio, left + 0.5 / sub)
            u_var = su**2 * (1.0 + (a * pa - b * pb) / zs - ratio**2)
            u_var = np.where(ok, np.clip(u_var, 0.0, 0.25 / sub**2), 1.0 / (12.0 * sub**2))
            v_mean = mv[h, None] + slope[h, None] * (u_bar - mu[h, None])
            v_sd = np.sqrt(cond_var[h, None] + slope[h, None] ** 2 * u_var)
            row_v = cv[h, None] + offsets[None, :]  # (n, K) row index from the south
            edges = np.concatenate((row_v, row_v[:, -1:] + 1), axis=1)  # (n, K + 1)
            cdf = ndtr((edges[:, None, :] - v_mean[:, :, None]) / v_sd[:, :, None])
            w = np.where(ok, z, 0.0)[:, :, None] * np.diff(cdf, axis=2)  # (n, K*m, K)
            w = w.reshape(len(h), offsets.size, sub, offsets.size).sum(axis=2)
            total = w.sum(axis=(1, 2), keepdims=True)
            w /= np.where(total > 0, total, 1.0)
            row = spec.height - 1 - row_v[:, None, :]
            colb = np.broadcast_to(col[:, :, None], w.shape)
            row = np.broadcast_to(row, w.shape)
            keep = (w >= SPREAD_MIN_WEIGHT) & (row >= 0) & (row < spec.height)
            keep &= (colb >= 0) & (colb < spec.width)
            out_hit.append(np.broadcast_to(h[:, None, None], w.shape)[keep])
            out_flat.append(row[keep] * spec.width + colb[keep])
            out_w.append(w[keep])
    hit = np.concatenate(out_hit)
    order = np.argsort(hit, kind="stable")
    return hit[order], np.concatenate(out_flat)[order], np.concatenate(out_w)[order]


def _phi(x: np.ndarray) -> np.ndarray:
    """Standard normal density."""
    return np.exp(-0.5 * x * x) / math.sqrt(2.0 * math.pi)


# --------------------------------------------------------------------------- the grid


@dataclass(frozen=True, eq=False)
class _Updates:
    """One batch's updates for a run of its scans, each kind grouped by scan position."""

    free_flat: np.ndarray
    free_bounds: np.ndarray  # (n_scans + 1,) slice bounds into free_flat per scan position
    hit_flat: np.ndarray
    hit_bounds: np.ndarray
    hit_delta: np.ndarray  # log-odds added with each hit entry
    end_flat: np.ndarray  # the cell of every hit endpoint inside the grid (for counts)


def _batch_updates(
    batch: ScanBatch,
    sensor: SensorConfig,
    beams: _Beams,
    scans: np.ndarray,
    config: Config,
    spec: GridSpec,
) -> _Updates:
    grid = config.grid
    n_scans = scans.size
    pos, beam, start, end, is_hit = _beam_segments(batch, beams, scans)
    cells = ray_cells(spec, start, end)
    free = ~(cells.is_end & is_hit[cells.ray])
    free_flat = cells.row[free] * spec.width + cells.col[free]
    free_bounds = np.searchsorted(pos[cells.ray[free]], np.arange(n_scans + 1))

    hit_pos = pos[is_hit]
    row, col, inside = spec.index_of(end[is_hit])
    end_flat = (row * spec.width + col)[inside]
    if grid.spread_hits:
        mean, cov = _hit_gaussians(batch, sensor, config, scans[hit_pos], beam[is_hit])
        hit_idx, hit_flat, share = spread_weights(spec, mean, cov)
        hit_delta = grid.log_odds_occupied * share
        hit_bounds = np.searchsorted(hit_pos[hit_idx], np.arange(n_scans + 1))
    else:
        hit_flat = end_flat
        hit_delta = np.full(hit_flat.size, grid.log_odds_occupied)
        hit_bounds = np.searchsorted(hit_pos[inside], np.arange(n_scans + 1))
    return _Updates(free_flat, free_bounds, hit_flat, hit_bounds, hit_delta, end_flat)


def _scan_chunks(
    batches: list[ScanBatch], beams: list[_Beams], spec: GridSpec
) -> Iterator[list[tuple[int, int]]]:
    """All (batch, scan) pairs in time order, in runs of about CHUNK_COLUMNS ray columns."""
    keys = [(b, s) for b, batch in enumerate(batches) for s in range(batch.n_scans)]
    stamps = np.concatenate([np.asarray(b.stamps, dtype=float) for b in batches])
    # Columns per beam: about its length in cells, plus the start and end cells.
    cost = np.concatenate(
        [np.where(bm.valid, bm.length / spec.resolution + 2.0, 0.0).sum(axis=1) for bm in beams]
    )
    order = np.argsort(stamps, kind="stable")
    chunk: list[tuple[int, int]] = []
    total = 0.0
    for i in order:
        if chunk and total + cost[i] > CHUNK_COLUMNS:
            yield chunk
            chunk, total = [], 0.0
        chunk.append(keys[i])
        total += cost[i]
    if chunk:
        yield chunk


def occupancy_grid(batches: list[ScanBatch], config: Config, spec: GridSpec) -> LogOddsGrid:
    """Build the clamped log-odds grid of all scans of all sensors on ``spec``.

    See the module docstring for the sensor model. With ``config.grid.spread_hits`` each
    hit's ``log_odds_occupied`` is shared among nearby cells in proportion to the hit's
    2-D Gaussian position (the unscented transform of range, bearing and pose noise that
    gives the GP's occupied samples their covariance; see :func:`spread_weights`); the
    free updates along the beam are unchanged.

    Args:
        batches: the readers' output.
        config: ``grid``, ``sensors`` (noise, mount, no-return length) and
            ``samples.unscented`` (for ``spread_hits``) are used.
        spec: the raster to fill; beams are clipped to it.

    Raises:
        GpoccError: no scans, non-finite poses, or bad clamp limits.
    """
    grid_cfg: GridConfig = config.grid
    if not grid_cfg.clamp_min < 0.0 < grid_cfg.clamp_max:
        raise GpoccError(
            f"config key 'grid': clamp_min < 0 < clamp_max is required, got "
            f"{grid_cfg.clamp_min}, {grid_cfg.clamp_max}"
        )
    if not batches or sum(b.n_scans for b in batches) == 0:
        raise GpoccError("no scans to build a grid from; check the input files")
    sensors = [beam_rules.sensor_config(b, config) for b in batches]
    beams = [_classify_beams(b, s) for b, s in zip(batches, sensors, strict=True)]
    n_cells = spec.width * spec.height
    log_odds = np.zeros(n_cells)
    hits = np.zeros(n_cells, dtype=np.int32)
    passes = np.zeros(n_cells, dtype=np.int32)
    observed = np.zeros(n_cells, dtype=bool)
    lo, hi = grid_cfg.clamp_min, grid_cfg.clamp_max

    for chunk in _scan_chunks(batches, beams, spec):
        keys = np.asarray(chunk, dtype=np.int64)
        updates: dict[int, _Updates] = {}
        local: dict[int, np.ndarray] = {}
        for b in np.unique(keys[:, 0]):
            scans = keys[keys[:, 0] == b, 1]
            updates[int(b)] = _batch_updates(batches[b], sensors[b], beams[b], scans,
                                             config, spec)
            local[int(b)] = np.cumsum(keys[:, 0] == b) - 1
        for i, (b, _) in enumerate(chunk):
            u = updates[b]
            j = local[b][i]
            free = u.free_flat[u.free_bounds[j]:u.free_bounds[j + 1]]
            h0, h1 = u.hit_bounds[j], u.hit_bounds[j + 1]
            hit = u.hit_flat[h0:h1]
            np.add.at(log_odds, free, grid_cfg.log_odds_free)
            np.add.at(log_odds, hit, u.hit_delta[h0:h1])
            touched = np.concatenate((free, hit))
            log_odds[touched] = np.clip(log_odds[touched], lo, hi)
            observed[touched] = True
        for u in updates.values():
            passes += np.bincount(u.free_flat, minlength=n_cells).astype(np.int32)
            hits += np.bincount(u.end_flat, minlength=n_cells).astype(np.int32)
            observed[u.end_flat] = True

    shape = spec.shape
    return LogOddsGrid(
        spec=spec,
        log_odds=log_odds.reshape(shape),
        hit_counts=hits.reshape(shape),
        pass_counts=passes.reshape(shape),
        observed=observed.reshape(shape),
    )


def observed_extent(batches: list[ScanBatch], config: Config) -> tuple[float, float, float, float]:
    """(x_min, y_min, x_max, y_max) metres of laser origins, hits and no-return free ends.

    Raises:
        GpoccError: no usable beam in any batch.
    """
    lo = np.full(2, np.inf)
    hi = np.full(2, -np.inf)
    for batch in batches:
        beams = _classify_beams(batch, beam_rules.sensor_config(batch, config))
        scans = np.flatnonzero(beams.valid.any(axis=1))
        if scans.size == 0:
            continue
        _, _, start, end, _ = _beam_segments(batch, beams, scans)
        for pts in (start, end):
            lo = np.minimum(lo, pts.min(axis=0))
            hi = np.maximum(hi, pts.max(axis=0))
    if not np.all(np.isfinite(lo)):
        raise GpoccError(
            "no usable beam in the inputs (every range is NaN, too close, or no-return with "
            "no_return_free_m 0); check the sensors' range_min_m / range_max_m"
        )
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def default_grid_spec(
    batches: list[ScanBatch],
    config: Config,
    resolution: float,
    bounds: tuple[float, float, float, float] | None = None,
) -> GridSpec:
    """``bounds`` if given, else :func:`observed_extent` plus ``config.map.margin_m``."""
    if bounds is not None:
        return GridSpec.from_bounds(*bounds, resolution)
    x0, y0, x1, y1 = observed_extent(batches, config)
    m = config.map.margin_m
    return GridSpec.from_bounds(x0 - m, y0 - m, x1 + m, y1 + m, resolution)
