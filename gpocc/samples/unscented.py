"""Scaled unscented transform (Julier 2002; van der Merwe 2004), batched over many inputs.

Every function works on a stack of ``N`` independent Gaussians at once: means ``(N, n)``,
covariances ``(N, n, n)``. The sigma points of the scaled transform are
``mean``, ``mean +- sqrt(n + lambda) * S[:, j]`` for the columns of any ``S`` with
``S S^T = cov``, where ``lambda = alpha^2 (n + kappa) - n``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

# A pivot below this fraction of its diagonal entry means the matrix is (numerically)
# singular; such matrices take the eigendecomposition route instead.
_PIVOT_RTOL = 1e-10


def _batched_cholesky(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower Cholesky factors of a stack ``(N, n, n)`` and a mask of the ones that worked.

    Written out column by column (vectorised over N) because ``np.linalg.cholesky``
    rejects the whole stack when one matrix is singular, and the callers need to know
    which ones.
    """
    n_items, n, _ = cov.shape
    lower = np.zeros_like(cov)
    ok = np.ones(n_items, dtype=bool)
    diag = np.einsum("kii->ki", cov)
    for j in range(n):
        row = lower[:, j, :j]
        pivot = diag[:, j] - np.einsum("ki,ki->k", row, row)
        good = pivot > _PIVOT_RTOL * np.abs(diag[:, j])
        good &= pivot > 0.0
        ok &= good
        root = np.sqrt(np.where(good, pivot, 1.0))
        lower[:, j, j] = root
        if j + 1 < n:
            below = cov[:, j + 1 :, j] - np.einsum("kri,ki->kr", lower[:, j + 1 :, :j], row)
            lower[:, j + 1 :, j] = below / root[:, None]
    return lower, ok


def matrix_sqrt(cov: np.ndarray) -> np.ndarray:
    """A square root ``S`` with ``S @ S.T == cov`` for a stack of PSD matrices.

    Cholesky where the matrix is positive definite; otherwise (singular, or slightly
    indefinite from rounding) ``V diag(sqrt(max(w, 0)))`` from ``eigh``, which is exact
    for singular PSD matrices and the nearest PSD root for slightly indefinite ones.

    Args:
        cov: (N, n, n) or (n, n) symmetric positive semi-definite.

    Returns:
        Same shape as ``cov``.
    """
    cov = np.asarray(cov, dtype=float)
    single = cov.ndim == 2
    stack = cov[None] if single else cov
    stack = 0.5 * (stack + np.swapaxes(stack, -1, -2))
    root, ok = _batched_cholesky(stack)
    if not ok.all():
        bad = ~ok
        w, v = np.linalg.eigh(stack[bad])
        root[bad] = v * np.sqrt(np.clip(w, 0.0, None))[:, None, :]
    return root[0] if single else root


def ut_weights(n: int, alpha: float, beta: float, kappa: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance weights ``(2n+1,)`` of the scaled unscented transform."""
    c = alpha**2 * (n + kappa)
    if not c > 0.0:
        raise ValueError(f"alpha^2 (n + kappa) must be positive, got {c}")
    lam = c - n
    wm = np.full(2 * n + 1, 0.5 / c)
    wc = wm.copy()
    wm[0] = lam / c
    wc[0] = lam / c + (1.0 - alpha**2 + beta)
    return wm, wc


def sigma_points(
    mean: np.ndarray,
    cov: np.ndarray,
    alpha: float,
    beta: float,
    kappa: float,
    *,
    sqrt_cov: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sigma points and weights of the scaled unscented transform.

    Args:
        mean: (N, n).
        cov: (N, n, n) positive semi-definite (singular allowed).
        alpha, beta, kappa: spread, prior knowledge (2 is optimal for Gaussians) and
            secondary scaling.
        sqrt_cov: optional (N, n, n) ``S`` with ``S S^T = cov`` when the caller knows a
            cheaper or structured one; computed with :func:`matrix_sqrt` otherwise.

    Returns:
        points (N, 2n+1, n): the mean first, then ``mean + gamma S[:, j]`` for j < n, then
        ``mean - gamma S[:, j]``, with ``gamma = sqrt(alpha^2 (n + kappa))``;
        wm (2n+1,) mean weights; wc (2n+1,) covariance weights.
    """
    mean = np.asarray(mean, dtype=float)
    n = mean.shape[-1]
    wm, wc = ut_weights(n, alpha, beta, kappa)
    root = matrix_sqrt(cov) if sqrt_cov is None else np.asarray(sqrt_cov, dtype=float)
    gamma = np.sqrt(alpha**2 * (n + kappa))
    offsets = gamma * np.swapaxes(root, -1, -2)  # row j = gamma * column j of S
    points = np.empty(mean.shape[:-1] + (2 * n + 1, n))
    points[..., 0, :] = mean
    points[..., 1 : n + 1, :] = mean[..., None, :] + offsets
    points[..., n + 1 :, :] = mean[..., None, :] - offsets
    return points, wm, wc


def unscented_transform(
    fn: Callable[[np.ndarray], np.ndarray],
    mean: np.ndarray,
    cov: np.ndarray,
    alpha: float,
    beta: float,
    kappa: float,
    *,
    sqrt_cov: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gaussian approximation of ``fn(x)`` for ``x ~ N(mean, cov)``, batched.

    Args:
        fn: vectorised map from (..., n) to (..., m).
        mean: (N, n).
        cov: (N, n, n).
        alpha, beta, kappa: see :func:`sigma_points`.
        sqrt_cov: optional precomputed square root of ``cov``.

    Returns:
        y_mean (N, m); y_cov (N, m, m), symmetric; cross (N, n, m) = Cov(x, fn(x)).
    """
    mean = np.asarray(mean, dtype=float)
    points, wm, wc = sigma_points(mean, cov, alpha, beta, kappa, sqrt_cov=sqrt_cov)
    y = np.asarray(fn(points), dtype=float)
    y_mean = np.einsum("k,nkm->nm", wm, y)
    dy = y - y_mean[:, None, :]
    dx = points - mean[:, None, :]
    weighted = np.swapaxes(dy * wc[:, None], -1, -2)  # (N, m, K)
    y_cov = weighted @ dy
    y_cov = 0.5 * (y_cov + np.swapaxes(y_cov, -1, -2))
    cross = np.swapaxes(dx * wc[:, None], -1, -2) @ dy
    return y_mean, y_cov, cross
