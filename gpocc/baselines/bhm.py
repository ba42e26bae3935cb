"""Bayesian Hilbert maps: variational logistic regression on local kernel features.

Written here from the paper (R. Senanayake and F. Ramos, "Bayesian Hilbert Maps for
Dynamic Continuous Occupancy Mapping", CoRL 2017), as a peer the GP maps are scored
against. The model:

* Features ``phi(x) = (k(x, z_1), ..., k(x, z_M), 1)``: squared-exponential kernels
  ``k(x, z) = exp(-gamma |x - z|^2)`` against a square lattice of inducing points ``z``,
  and a bias. Each kernel is cut to zero beyond ``REACH_SIGMAS / sqrt(gamma)`` (where it
  is below 1.3e-4), so the feature matrix is sparse (``scipy.sparse``).
* Likelihood ``p(y = 1 | x, w) = sigmoid(w . phi(x))``, prior ``w ~ N(0, I / p0)``.
* Posterior: a fully factorised Gaussian ``q(w) = prod_d N(mu_d, s_d)``, found by EM on
  the Jaakkola-Jordan bound ``log sigmoid(a) >= log sigmoid(xi) + (a - xi) / 2 -
  lambda(xi) (a^2 - xi^2)``, ``lambda(xi) = tanh(xi / 2) / (4 xi)``, with one
  variational parameter ``xi_n`` per training point. E-step: with ``A = p0 I + 2 Phi^T
  diag(lambda(xi)) Phi`` and ``b = Phi^T (y - 1/2)``, ``1 / s_d = A_dd`` and ``A mu =
  b`` (:func:`e_step`: the exact optimum of the bound over factorised Gaussians, so EM
  never lowers the bound). The paper's diagonal shortcut ``mu_d = b_d / A_dd``
  (``bhm.mean_update: diagonal``) is the same where no two features overlap; where they
  do it counts each point once per feature and the weights run away (held-out AUC 0.50
  on Intel). M-step: ``xi_n^2 = E_q[(w . phi_n)^2] = (mu . phi_n)^2 + sum_d s_d
  phi_nd^2``.
* Prediction: the logit ``a = w . phi(x)`` has mean ``mu . phi`` and variance ``sum_d
  s_d phi_d^2`` (the variance layer), and ``p(occupied) = sigmoid(mean / sqrt(1 + pi
  var / 8))`` (MacKay's probit approximation).

Training points follow the beam rules every method shares (:mod:`gpocc.samples.beam_rules`:
REP 117 classes, mounts, the free extent of no-return beams) and the GP's scan and beam
strides. EM runs in batch over all of them: the paper also gives a sequential form (one
scan at a time, the last posterior as the next prior) for online and dynamic maps; on a
finished log the batch form sets every point's ``xi`` from the final posterior. A
weight ``c`` on a training point raises its likelihood to the power ``c``, which is how
points counted per cell and label (``bhm.sample_cell_m``) stand for that many repeated
points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import cg, spsolve
from scipy.special import expit

from gpocc.blas import single_threaded_blas
from gpocc.config import BHMConfig, Config
from gpocc.errors import GpoccError
from gpocc.gridspec import GridSpec
from gpocc.io.scans import ScanBatch
from gpocc.samples import beam_rules

#: A feature is cut to zero beyond this many ``gamma^-1/2`` from its inducing point.
REACH_SIGMAS = 3.0

#: Raw training points generated per step before they are counted into cells.
CHUNK_POINTS = 2_000_000

#: Training points or map cells whose features are built in one step.
FEATURE_CHUNK = 100_000

#: (point, candidate inducing point) pairs examined in one step (bounds temporaries to
#: about 30 MB each).
FEATURE_PAIRS = 4_000_000

#: Relative residual and iteration cap of the conjugate gradients of the coupled E-step.
CG_RTOL = 1e-5
CG_MAXITER = 10_000

#: Cell indices of counted training points stay below this (keys must fit in int64).
_MAX_CELL_INDEX = 2**29


@dataclass(frozen=True, eq=False)
class TrainingPoints:
    """Labelled points of the beams.

    Attributes:
        points: (N, 2) metres, map frame.
        labels: (N,) float, +1 occupied (a hit), -1 free (along a beam).
        weights: (N,) float, how many raw points each stands for (>= 1).
    """

    points: np.ndarray
    labels: np.ndarray
    weights: np.ndarray

    def __len__(self) -> int:
        return int(self.labels.size)


@dataclass(frozen=True)
class InducingGrid:
    """The square lattice of inducing points ``(x0 + i spacing, y0 + j spacing)``,
    ``0 <= i < nx``, ``0 <= j < ny``; weight ``j * nx + i`` belongs to point (i, j)."""

    x0: float
    y0: float
    spacing: float
    nx: int
    ny: int

    @property
    def size(self) -> int:
        return self.nx * self.ny

    def points(self) -> np.ndarray:
        """(nx * ny, 2) metres, in weight order."""
        j, i = np.divmod(np.arange(self.size), self.nx)
        return np.column_stack((self.x0 + i * self.spacing, self.y0 + j * self.spacing))


@dataclass(frozen=True, eq=False)
class Posterior:
    """The factorised Gaussian posterior of the weights and how EM got there.

    Attributes:
        mean: (M + 1,) posterior means; the last entry is the bias weight.
        variance: (M + 1,) posterior variances.
        xi: (N,) the Jaakkola-Jordan parameters the last E-step used.
        bounds: (iterations,) the variational lower bound on the log evidence after each
            E-step (:func:`evidence_bound`).
    """

    mean: np.ndarray
    variance: np.ndarray
    xi: np.ndarray
    bounds: np.ndarray


@dataclass(frozen=True, eq=False)
class BHMModel:
    """A fitted Bayesian Hilbert map.

    Attributes:
        grid: the inducing points.
        gamma: kernel width, 1/m^2.
        posterior: the weights' posterior.
        n_points: training points (after counting into cells); n_raw: raw points.
    """

    grid: InducingGrid
    gamma: float
    posterior: Posterior
    n_points: int
    n_raw: int


# --------------------------------------------------------------------------- data


def training_points(batches: list[ScanBatch], config: Config) -> TrainingPoints:
    """The labelled points of every beam of ``batches``.

    A hit at range ``r`` gives an occupied point at ``r`` and free points at ``d = k *
    bhm.free_spacing_m`` (k = 1, 2, ...) while ``d <= r - bhm.hit_gap_m``; a no-return
    beam gives free points up to ``min(no_return_free_m, range_max)``; invalid readings
    give nothing (:func:`gpocc.samples.beam_rules.classify_beams`). Scans and beams follow
    ``samples.scan_stride`` and ``samples.beam_stride``, as the GP's samples do. With
    ``bhm.sample_cell_m > 0`` points are counted per label in squares of that side and
    each count becomes one point at the mean of its points with that weight.

    Raises:
        GpoccError: no batches, non-finite poses, or no usable beam at all.
    """
    cfg = config.bhm
    parts: list[TrainingPoints] = []
    for batch in batches:
        sensor = beam_rules.sensor_config(batch, config)
        scans = np.arange(0, batch.n_scans, config.samples.scan_stride)
        beams = np.arange(0, batch.n_beams, config.samples.beam_stride)
        ranges = np.asarray(batch.ranges, dtype=float)[np.ix_(scans, beams)]
        bearings = np.asarray(batch.angles, dtype=float)[beams]
        lasers = beam_rules.laser_poses(beam_rules.checked_poses(batch, scans),
                                        beam_rules.mount_vector(sensor))
        classes = beam_rules.classify_beams(ranges, float(batch.range_min),
                                            float(batch.range_max))
        free_end = np.where(classes.hit, ranges - cfg.hit_gap_m,
                            np.where(classes.no_return,
                                     beam_rules.no_return_free_m(sensor, batch.range_max), 0.0))
        free_end = np.where(np.isfinite(free_end), np.maximum(free_end, 0.0), 0.0)
        # A tiny slack keeps a point that lies exactly on the limit (2.0 / 0.4 = 4.999...).
        n_free = np.floor(free_end / cfg.free_spacing_m + 1e-9).astype(np.int64)
        per_scan = classes.hit.sum(axis=1) + n_free.sum(axis=1)
        start = 0
        while start < scans.size:
            stop = start + max(1, int(np.searchsorted(
                np.cumsum(per_scan[start:]), CHUNK_POINTS, side="right")))
            s = slice(start, stop)
            parts.append(_count_cells(
                _beam_points(lasers[s], bearings, ranges[s], classes.hit[s], n_free[s],
                             cfg.free_spacing_m), cfg.sample_cell_m))
            start = stop
    points = _merge(parts, cfg.sample_cell_m)
    if len(points) == 0:
        raise GpoccError(
            "no usable beam in the inputs (every range is NaN, too close, or no-return with "
            "no_return_free_m 0); check the sensors' range_min_m / range_max_m")
    return points


def _beam_points(lasers: np.ndarray, bearings: np.ndarray, ranges: np.ndarray,
                 is_hit: np.ndarray, n_free: np.ndarray, spacing: float) -> TrainingPoints:
    """Hits then free points of scans with laser poses (S, 3), ranges (S, B)."""
    hs, hb = np.nonzero(is_hit)
    hits = beam_rules.beam_points(lasers[hs], bearings[hb], ranges[hs, hb])
    counts = n_free.ravel()
    flat = np.repeat(np.arange(counts.size), counts)
    k = np.arange(flat.size) - np.repeat(np.cumsum(counts) - counts, counts) + 1
    fs, fb = np.divmod(flat, bearings.size)
    free = beam_rules.beam_points(lasers[fs], bearings[fb], k * spacing)
    return TrainingPoints(points=np.concatenate((hits, free)).reshape(-1, 2),
                          labels=np.concatenate((np.ones(hs.size), -np.ones(fs.size))),
                          weights=np.ones(hs.size + fs.size))


def _count_cells(pts: TrainingPoints, cell_m: float) -> TrainingPoints:
    """Points counted per (label, cell of side ``cell_m``): one weighted point at the
    weighted mean of each group; groups in ascending key order. ``cell_m <= 0``: as is."""
    if cell_m <= 0 or len(pts) == 0:
        return pts
    cells = np.floor(pts.points / cell_m)
    if np.abs(cells).max() >= _MAX_CELL_INDEX:
        raise GpoccError(
            f"training points lie more than {_MAX_CELL_INDEX * cell_m:.3g} m from the map "
            f"origin; check the poses' units or raise bhm.sample_cell_m")
    c = cells.astype(np.int64) + _MAX_CELL_INDEX
    keys = (((c[:, 0] << 30) | c[:, 1]) << 1) | (pts.labels > 0)
    unique, inverse = np.unique(keys, return_inverse=True)
    weight = np.bincount(inverse, weights=pts.weights, minlength=unique.size)
    xy = np.column_stack([np.bincount(inverse, weights=pts.weights * pts.points[:, i],
                                      minlength=unique.size) for i in (0, 1)])
    return TrainingPoints(points=xy / weight[:, None],
                          labels=np.where(unique & 1, 1.0, -1.0), weights=weight)


def _merge(parts: list[TrainingPoints], cell_m: float) -> TrainingPoints:
    if not parts:
        return TrainingPoints(np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    merged = TrainingPoints(points=np.concatenate([p.points for p in parts]),
                            labels=np.concatenate([p.labels for p in parts]),
                            weights=np.concatenate([p.weights for p in parts]))
    return _count_cells(merged, cell_m) if len(parts) > 1 else merged


# --------------------------------------------------------------------------- features


def reach_m(gamma: float) -> float:
    """Distance, metres, beyond which a feature of width ``gamma`` (1/m^2) is zero."""
    return REACH_SIGMAS / math.sqrt(gamma)


def inducing_grid(points: np.ndarray, spacing: float, gamma: float) -> InducingGrid:
    """The lattice, aligned to multiples of ``spacing``, covering the (N, 2) points plus
    one feature reach on every side (farther inducing points would see no point)."""
    reach = reach_m(gamma)
    lo = np.floor((points.min(axis=0) - reach) / spacing) * spacing
    n = np.floor((points.max(axis=0) + reach - lo) / spacing).astype(np.int64) + 1
    return InducingGrid(float(lo[0]), float(lo[1]), float(spacing), int(n[0]), int(n[1]))


def features(points: np.ndarray, grid: InducingGrid, gamma: float) -> sp.csr_matrix:
    """(N, M + 1) sparse feature matrix of (N, 2) points: ``exp(-gamma d^2)`` to each
    inducing point within :func:`reach_m` (column ``j * nx + i``), then the bias (1)."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    reach = reach_m(gamma)
    k = int(math.ceil(reach / grid.spacing)) + 1
    oi, oj = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1))
    oi, oj = oi.ravel(), oj.ravel()
    blocks = []
    step = max(1, min(FEATURE_CHUNK, FEATURE_PAIRS // oi.size))
    for lo in range(0, max(len(pts), 1), step):
        p = pts[lo:lo + step]
        ci = np.rint((p[:, 0] - grid.x0) / grid.spacing).astype(np.int64)
        cj = np.rint((p[:, 1] - grid.y0) / grid.spacing).astype(np.int64)
        i = ci[:, None] + oi[None, :]
        j = cj[:, None] + oj[None, :]
        dx = p[:, 0:1] - (grid.x0 + i * grid.spacing)
        dy = p[:, 1:2] - (grid.y0 + j * grid.spacing)
        d2 = dx * dx + dy * dy
        keep = (d2 <= reach * reach) & (i >= 0) & (i < grid.nx) & (j >= 0) & (j < grid.ny)
        rows = np.repeat(np.arange(len(p)), keep.sum(axis=1))
        cols = (j * grid.nx + i)[keep]
        vals = np.exp(-gamma * d2[keep])
        # The bias column, one per point.
        rows = np.concatenate((rows, np.arange(len(p))))
        cols = np.concatenate((cols, np.full(len(p), grid.size)))
        vals = np.concatenate((vals, np.ones(len(p))))
        blocks.append(sp.csr_matrix((vals, (rows, cols)), shape=(len(p), grid.size + 1)))
    return sp.vstack(blocks, format="csr") if len(blocks) > 1 else blocks[0]


# --------------------------------------------------------------------------- learning


def jj_lambda(xi: np.ndarray) -> np.ndarray:
    """Jaakkola-Jordan ``lambda(xi) = tanh(xi / 2) / (4 xi)`` (1/8 at 0), elementwise."""
    xi = np.abs(np.asarray(xi, dtype=float))
    small = xi < 1e-4
    safe = np.where(small, 1.0, xi)
    return np.where(small, 0.125 - xi * xi / 96.0, np.tanh(safe / 2.0) / (4.0 * safe))


def e_step(phi: sp.csr_matrix, phi2: sp.csr_matrix, labels: np.ndarray, weights: np.ndarray,
           xi: np.ndarray, prior_precision: float, coupled: bool = True,
           start: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The factorised posterior (means (M+1,), variances (M+1,)) for fixed ``xi`` (N,).

    With ``A = p0 I + 2 Phi^T diag(c lambda(xi)) Phi`` and ``b = Phi^T (c y / 2)`` (point
    weights ``c``, labels ``y = +-1``, so ``y / 2 = t - 1/2`` for ``t`` in {0, 1}), the
    bound is ``-m^T A m / 2 + b^T m - sum_d A_dd s_d / 2 + sum_d log(s_d) / 2`` plus
    terms free of ``q``; its maximiser over factorised Gaussians has ``s_d = 1 / A_dd``
    and ``A m = b`` (``coupled``: conjugate gradients preconditioned by ``diag(A)``, from
    ``start``, to a relative residual of ``CG_RTOL``; a sparse LU if that fails). Not
    ``coupled``: the paper's
    diagonal shortcut ``m_d = b_d / A_dd``, which treats every weight as if it alone
    explained its points; exact when no two features overlap, overconfident when they
    do. ``phi2`` is ``phi`` squared elementwise.
    """
    cl = weights * jj_lambda(xi)
    diag = prior_precision + 2.0 * (phi2.T @ cl)
    b = phi.T @ (weights * labels * 0.5)
    if not coupled:
        return b / diag, 1.0 / diag
    a = phi.T.tocsr().multiply(2.0 * cl) @ phi
    a = (a + prior_precision * sp.identity(a.shape[0], format="csr")).tocsr()
    mean, info = cg(a, b, x0=start, rtol=CG_RTOL, maxiter=CG_MAXITER,
                    M=sp.diags(1.0 / diag))
    if info != 0:
        mean = spsolve(a.tocsc(), b)
    return np.asarray(mean, dtype=float), 1.0 / diag


def m_step(phi: sp.csr_matrix, phi2: sp.csr_matrix, mean: np.ndarray,
           variance: np.ndarray) -> np.ndarray:
    """The optimal ``xi`` (N,): ``sqrt(E_q[a_n^2])`` for the logits ``a_n = w . phi_n``."""
    return np.sqrt((phi @ mean) ** 2 + phi2 @ variance)


def evidence_bound(phi: sp.csr_matrix, phi2: sp.csr_matrix, labels: np.ndarray,
                   weights: np.ndarray, mean: np.ndarray, variance: np.ndarray,
                   xi: np.ndarray, prior_precision: float) -> float:
    """The variational lower bound on the log evidence ``log p(labels)``.

    ``sum_n c_n E_q[JJ bound of log sigmoid(y_n a_n)] - KL(q || prior)`` for the
    factorised ``q``, point weights ``c_n`` and labels ``y_n = +-1``; it never exceeds
    the exact log evidence, and equals the expected log-likelihood bound at the ``xi``
    given.
    """
    a_mean = phi @ mean
    a_sq = a_mean**2 + phi2 @ variance
    lam = jj_lambda(xi)
    log_sig = -np.logaddexp(0.0, -xi)
    data = np.sum(weights * (log_sig + 0.5 * (labels * a_mean - xi) - lam * (a_sq - xi * xi)))
    p0 = prior_precision
    kl = 0.5 * np.sum(p0 * variance + p0 * mean**2 - 1.0 - np.log(p0 * variance))
    return float(data - kl)


def variational_em(phi: sp.csr_matrix, labels: np.ndarray, weights: np.ndarray,
                   prior_precision: float, iterations: int, coupled: bool = True) -> Posterior:
    """EM from the prior: ``xi`` from ``q`` = prior, then ``iterations`` x (E-step, and
    an M-step between E-steps)."""
    phi = sp.csr_matrix(phi)
    phi2 = phi.multiply(phi).tocsr()
    labels = np.asarray(labels, dtype=float)
    weights = np.asarray(weights, dtype=float)
    n_w = phi.shape[1]
    mean = np.zeros(n_w)
    variance = np.full(n_w, 1.0 / prior_precision)
    xi = m_step(phi, phi2, mean, variance)
    bounds = []
    for it in range(iterations):
        mean, variance = e_step(phi, phi2, labels, weights, xi, prior_precision, coupled,
                                start=mean)
        bounds.append(evidence_bound(phi, phi2, labels, weights, mean, variance, xi,
                                     prior_precision))
        if it < iterations - 1:
            xi = m_step(phi, phi2, mean, variance)
    return Posterior(mean=mean, variance=variance, xi=xi, bounds=np.asarray(bounds))


def fit_bhm(points: TrainingPoints, cfg: BHMConfig) -> BHMModel:
    """Fit the map to the labelled points with ``cfg``'s features, prior and EM passes."""
    if len(points) == 0:
        raise GpoccError("no training points to fit the Bayesian Hilbert map to")
    grid = inducing_grid(points.points, cfg.inducing_spacing_m, cfg.gamma)
    phi = features(points.points, grid, cfg.gamma)
    # The conjugate gradients' vectors hold one entry per weight (tens of thousands):
    # BLAS threads only wake and wait there (on Intel, 4 of 7 s with them; gpocc.blas).
    with single_threaded_blas():
        posterior = variational_em(phi, points.labels, points.weights, cfg.prior_precision,
                                   cfg.em_iterations, cfg.mean_update == "coupled")
    return BHMModel(grid=grid, gamma=cfg.gamma, posterior=posterior, n_points=len(points),
                    n_raw=int(round(points.weights.sum())))


# --------------------------------------------------------------------------- prediction


def predict(model: BHMModel, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """p(occupied) and the logit's variance at (N, 2) points, each (N,).

    ``p = sigmoid(m / sqrt(1 + pi v / 8))`` with the logit's posterior mean ``m`` and
    variance ``v``.
    """
    phi = features(points, model.grid, model.gamma)
    m = phi @ model.posterior.mean
    v = phi.multiply(phi) @ model.posterior.variance
    return expit(m / np.sqrt(1.0 + math.pi * v / 8.0)), v


def predict_grid(model: BHMModel, spec: GridSpec,
                 inside: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) float32 probability and logit variance of ``spec``'s cells; NaN where
    ``inside`` (H, W) bool is False (nodata, not computed)."""
    prob = np.full(spec.shape, np.nan, dtype=np.float32)
    var = np.full(spec.shape, np.nan, dtype=np.float32)
    rows, cols = np.nonzero(np.ones(spec.shape, dtype=bool) if inside is None else inside)
    for lo in range(0, rows.size, FEATURE_CHUNK):
        r, c = rows[lo:lo + FEATURE_CHUNK], cols[lo:lo + FEATURE_CHUNK]
        xs, ys = spec.cell_centres_at(r, c)
        p, v = predict(model, np.column_stack((xs, ys)))
        prob[r, c] = p
        var[r, c] = v
    return prob, var
