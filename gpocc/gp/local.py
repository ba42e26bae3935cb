"""Local GP inference: each block of queries is predicted from its nearest training samples.

The neural-network kernel is not translation invariant, so every local problem is moved
to the origin (its centre subtracted from queries and sample means) exactly as during
hyperparameter learning. Training-to-training covariances are expected kernels over the
samples' input distributions (correlated within a scan); queries are exact points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
from scipy.linalg.blas import dtrsm
from scipy.linalg.lapack import dpotrf, dpotrs
from scipy.spatial import cKDTree

from gpocc.constants import JITTER
from gpocc.errors import GpoccError
from gpocc.gp import backends
from gpocc.gp.expected import expected_kernel_cross, expected_kernel_matrix
from gpocc.gp.kernels import Kernel
from gpocc.samples.sampleset import SampleSet

_LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class LocalProblem:
    """One local GP: a neighbourhood of samples, moved so that ``centre`` is the origin.

    Attributes:
        centre: (2,) metres, map frame.
        samples: the neighbourhood, means already centred (metres, local frame).
        index: (M,) indices of the neighbourhood in the full sample set.
    """

    centre: np.ndarray
    samples: SampleSet
    index: np.ndarray


@dataclass(frozen=True)
class Prediction:
    """Latent GP prediction at queries: mean, variance and prior variance (Q,) of f(x*)."""

    mean: np.ndarray
    variance: np.ndarray
    prior_variance: np.ndarray


class NeighbourIndex:
    """Nearest-neighbour look-up of training samples by their mean position."""

    def __init__(self, samples: SampleSet, tree: cKDTree | None = None,
                 rows: np.ndarray | None = None) -> None:
        """``rows``: (R,) ascending indices of the only samples looked up (None: all),
        the index of ``samples.subset(rows)`` without copying the samples (a city's
        held-out classifier points: a second); ``tree``: a tree of their means already
        built (:meth:`over`)."""
        self.samples = samples
        self.rows = rows
        if tree is None:
            tree = cKDTree(samples.means if rows is None else samples.means[rows])
        self._tree = tree

    def over(self, samples: SampleSet) -> NeighbourIndex:
        """This index for ``samples`` with the same means (the same samples with other
        covariances, say scaled by the input-noise scale g), sharing its tree: a city's
        1.7 M samples take 0.5 s to index.

        Raises:
            ValueError: ``samples`` has other means.
        """
        if samples.means is not self.samples.means and not np.array_equal(
                samples.means, self.samples.means):
            raise ValueError("samples with other means need an index of their own")
        return NeighbourIndex(samples, self._tree, self.rows)

    def problem(self, centre: np.ndarray, neighbours: int) -> LocalProblem:
        """The ``neighbours`` samples nearest ``centre`` (2,), centred at it."""
        return self.problems(np.asarray(centre, dtype=float)[None, :], neighbours)[0]

    def problems(self, centres: np.ndarray, neighbours: int) -> list[LocalProblem]:
        """:meth:`problem` of each of the (K, 2) ``centres``, from one look-up (a look-up
        of 128 neighbours costs 67 us alone and 21 us per centre in eights)."""
        centres = np.asarray(centres, dtype=float).reshape(-1, 2)
        k = min(neighbours, self._tree.n)
        if len(centres) == 0:
            return []
        _, indices = self._tree.query(centres, k=k)
        indices = np.sort(np.asarray(indices).reshape(len(centres), k), axis=1)
        if self.rows is not None:  # ascending rows keep each neighbourhood's order
            indices = self.rows[indices]
        return [centred_problem(self.samples, index, centre)
                for index, centre in zip(indices, centres, strict=True)]


def centred_problem(samples: SampleSet, index: np.ndarray, centre: np.ndarray) -> LocalProblem:
    """The local problem of ``samples[index]`` with ``centre`` (2,) moved to the origin."""
    subset = samples.subset(index)
    local = replace(subset, means=subset.means - centre, sensor_names=())
    return LocalProblem(centre=centre, samples=local, index=index)


def _lower_cholesky(matrix: np.ndarray) -> np.ndarray | None:
    """LAPACK's lower factor of ``matrix`` (upper triangle zero), or None if it is not
    numerically positive definite or not finite. Straight ``dpotrf``:
    ``np.linalg.cholesky``'s checks and error handling cost twice the factorisation of a
    128 x 128 map problem. LAPACK passes NaN through with success; a NaN factor is
    refused here, so it takes the same road as an indefinite matrix (rejected in
    training, an error in prediction) instead of reaching a likelihood or a map."""
    factor, info = dpotrf(matrix, lower=1, clean=1)
    if info != 0 or not np.isfinite(np.diagonal(factor)).all():
        return None
    return factor


def cholesky_solve(chol: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``K^-1 rhs`` from the lower Cholesky factor of K (``rhs`` (M,) or (M, R))."""
    solution, info = dpotrs(chol, rhs, lower=1)
    if info != 0:  # only for malformed arguments, never for values
        raise ValueError(f"dpotrs failed (info {info})")
    return solution


def try_cholesky(matrix: np.ndarray, jitter: bool = True) -> np.ndarray | None:
    """Lower Cholesky factor of a label covariance, or None: the one place where a failed
    factorisation becomes a decision.

    ``jitter=True`` (prediction, classifier fitting: the hyperparameters are fixed, a
    factor is needed): add diagonal jitter (1e-10 .. 1e-4 of the mean diagonal) only when
    the matrix is numerically indefinite. Correlated same-scan entries come from a 4-D
    quadrature and are not guaranteed to keep the expected-kernel matrix exactly positive
    definite when the learned label noise is tiny; a relative jitter of at most 1e-4 is
    far below any label noise. None then means even that failed
    (:func:`factor_training_covariance` falls back to independent inputs).

    ``jitter=False`` (hyperparameter learning): None at once, and the learner rejects the
    hyperparameters; a jittered likelihood would score a matrix the model cannot have.
    """
    factor = _lower_cholesky(matrix)
    if factor is not None or not jitter:
        return factor
    scale = float(np.mean(np.diag(matrix)))
    eye = np.eye(matrix.shape[0])
    for exponent in range(-10, -3):
        factor = _lower_cholesky(matrix + (scale * 10.0**exponent) * eye)
        if factor is not None:
            return factor
    return None


def training_covariance(
    kernel: Kernel, noise_variance: float, samples: SampleSet, level: int,
    correlated: bool = True, backend: str = "auto",
) -> np.ndarray:
    """(M, M) covariance of the training labels: expected kernel plus label noise.

    ``correlated=False`` treats every pair as independent (no 4-D same-scan rule).
    ``backend``: ``model.backend`` (:mod:`gpocc.gp.backends`), as in every function here.
    """
    k = expected_kernel_matrix(
        kernel,
        samples.means,
        samples.covariances,
        level,
        scan_ids=samples.scan_ids if correlated else None,
        pose_factors=samples.pose_factors if correlated else None,
        backend=backend,
    )
    # Through a writable view of the diagonal: the same sums as fancy indexing, without
    # building index arrays on every local problem.
    np.einsum("ii->i", k)[:] += samples.label_noise(noise_variance) + JITTER
    return k


def factor_training_covariance(
    kernel: Kernel, noise_variance: float, samples: SampleSet, level: int,
    backend: str = "auto",
) -> np.ndarray:
    """Lower Cholesky factor of the label covariance of ``samples``.

    The product rule over independent inputs always gives a positive semi-definite
    matrix (a Gram matrix of expected features) but the 4-D rule of correlated pairs
    need not, when inputs are broad compared with the kernel's scale and the quadrature
    level is low. If even jitter cannot save it, the problem falls back to independent
    inputs, which is exactly positive definite.
    """
    chol = try_cholesky(training_covariance(kernel, noise_variance, samples, level,
                                            backend=backend))
    if chol is None:
        chol = try_cholesky(training_covariance(kernel, noise_variance, samples, level,
                                                correlated=False, backend=backend))
    if chol is None:
        raise GpoccError(
            "the training covariance of a local problem is not positive definite; raise "
            "model.hyperparameters.noise_variance or model.quadrature_level"
        )
    return chol


def predict_local(
    kernel: Kernel, noise_variance: float, problem: LocalProblem, queries: np.ndarray,
    level: int, backend: str = "auto",
) -> Prediction:
    """GP predictive mean and variance at (Q, 2) map-frame queries from one local problem."""
    return predict_locals(kernel, noise_variance, [problem], [queries], level, backend)[0]


def _local_systems(kernel: Kernel, backend: backends.Backend,
                   batch: list[tuple[SampleSet, np.ndarray]], level: int, diagonal: float
                   ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray] | None]:
    """The backend's one-pass covariances of a batch of (samples, local queries)."""
    return backend.loops(kernel).local_systems(kernel, batch, level, diagonal)


def predict_locals(
    kernel: Kernel, noise_variance: float, problems: list[LocalProblem],
    queries: list[np.ndarray], level: int, backend: str = "auto",
) -> list[Prediction]:
    """:func:`predict_local` of each problem at its (Q_k, 2) map-frame queries: the
    backend computes the covariances of the whole batch in one call
    (``KernelLoops.local_systems``), then each problem is solved."""
    backend = backends.get(backend)
    local_queries = [np.asarray(q, dtype=float) - p.centre
                     for p, q in zip(problems, queries, strict=True)]
    live = [k for k, p in enumerate(problems) if len(p.samples)]
    systems = _local_systems(kernel, backend,
                             [(problems[k].samples, local_queries[k]) for k in live], level,
                             noise_variance + JITTER) if live else []
    by_problem = dict(zip(live, systems, strict=True))
    return [_predict(kernel, noise_variance, problem, local, level, by_problem.get(k), backend)
            for k, (problem, local) in enumerate(zip(problems, local_queries, strict=True))]


def _predict(kernel: Kernel, noise_variance: float, problem: LocalProblem,
             local_queries: np.ndarray, level: int,
             system: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
             backend: backends.Backend) -> Prediction:
    """One problem's prediction at its centred queries from its one-pass ``system``, or
    (None) from the separate calls."""
    samples = problem.samples
    if len(samples) == 0:
        prior = kernel.diag(local_queries)
        return Prediction(mean=np.zeros(len(local_queries)), variance=prior, prior_variance=prior)
    chol = None
    if system is not None:
        k, k_cross, prior = system
        if samples.noise_factors is not None:  # the system's diagonal has the base noise
            np.einsum("ii->i", k)[:] += noise_variance * (samples.noise_factors - 1.0)
        chol = try_cholesky(k)
    if chol is None:  # no one-pass system, or the fallbacks of factor_training_covariance
        chol = factor_training_covariance(kernel, noise_variance, samples, level, backend)
    if system is None:
        k_cross = expected_kernel_cross(
            kernel, local_queries, samples.means, samples.covariances, level, backend=backend
        )
        prior = kernel.diag(local_queries)
    alpha = cholesky_solve(chol, samples.labels)
    mean = k_cross @ alpha
    # v = k_cross L^-T (Q, M) from the right, in k_cross's own row-major layout: half
    # the time of solving L v' = k_cross' (no transposed copies).
    v = dtrsm(1.0, chol, k_cross, side=1, lower=1, trans_a=1)
    variance = prior - np.einsum("ij,ij->i", v, v)
    return Prediction(mean=mean, variance=np.maximum(variance, 0.0), prior_variance=prior)


def predict_full(kernel: Kernel, noise_variance: float, samples: SampleSet, queries: np.ndarray,
                 level: int, backend: str = "auto") -> Prediction:
    """The exact (non-local) GP prediction from every sample; the oracle for small problems."""
    problem = LocalProblem(centre=np.zeros(2), samples=samples, index=np.arange(len(samples)))
    return predict_local(kernel, noise_variance, problem, queries, level, backend)


class PatchLikelihood(NamedTuple):
    """A training patch's -LML (nats), its gradient (P,) in log-parameters (None: not
    asked for) and its Fisher information (P, P) in the same parameters (None: not asked
    for)."""

    value: float
    gradient: np.ndarray | None
    fisher: np.ndarray | None = None


def negative_log_likelihood(
    kernel: Kernel, noise: float, samples: SampleSet, level: int, *, with_gradient: bool,
    input_scale: float = 1.0, scale_gradient: bool = False, backend: str = "auto",
    with_fisher: bool = False,
) -> PatchLikelihood | None:
    """One local problem's (a training patch's) -LML and its gradient in log-parameters
    ``[kernel.theta..., log noise]`` (with ``scale_gradient``, then in log g); None if K
    is not a covariance. The generic form of ``KernelLoops.patch_likelihoods``.

    ``with_fisher`` (with ``with_gradient``): also the Fisher information of the labels'
    Gaussian in the same parameters, ``F_pq = 1/2 tr(K^-1 dK_p K^-1 dK_q)`` (Rasmussen
    and Williams, eq. 5.9's expected Hessian): the curvature a refinement's scoring steps
    use (:mod:`gpocc.gp.refine`).
    """
    s = samples
    if with_fisher and not with_gradient:
        raise ValueError("the Fisher information needs the gradients' dK")
    if with_gradient:
        cov, dcov = expected_kernel_matrix(
            kernel, s.means, s.covariances, level, scan_ids=s.scan_ids,
            pose_factors=s.pose_factors, with_gradient=True, input_scale=input_scale,
            with_scale_gradient=scale_gradient, backend=backend,
        )
    else:
        cov = expected_kernel_matrix(
            kernel, s.means, s.covariances, level, scan_ids=s.scan_ids,
            pose_factors=s.pose_factors, input_scale=input_scale, backend=backend,
        )
    label_noise = s.label_noise(noise)
    np.einsum("ii->i", cov)[:] += label_noise + JITTER
    chol = try_cholesky(cov, jitter=False)
    if chol is None:
        return None
    alpha = cholesky_solve(chol, s.labels)
    value = 0.5 * s.labels @ alpha + np.log(np.diag(chol)).sum() + 0.5 * len(s) * _LOG_2PI
    if not with_gradient:
        return PatchLikelihood(float(value), None)
    inverse = cholesky_solve(chol, np.eye(len(s)))
    inner = inverse - np.outer(alpha, alpha)
    nkernel = len(kernel.theta)
    grad = np.empty(nkernel + (2 if scale_gradient else 1))
    # d(-LML)/d theta = 1/2 tr((K^-1 - alpha alpha^T) dK/d theta)
    grad[:nkernel] = 0.5 * np.einsum("ij,pij->p", inner, dcov[:nkernel])
    grad[nkernel] = (0.5 * noise * np.trace(inner) if s.noise_factors is None
                     else 0.5 * float(np.diagonal(inner) @ label_noise))
    if scale_gradient:
        grad[nkernel + 1] = 0.5 * np.einsum("ij,ij->", inner, dcov[nkernel])
    if not with_fisher:
        return PatchLikelihood(float(value), grad)
    # dK/dlog noise is diag(label noise): K^-1 dK scales K^-1's columns.
    products = [inverse @ dcov[p] for p in range(nkernel)]
    products.append(inverse * np.broadcast_to(label_noise, (len(s),))[None, :])
    if scale_gradient:
        products.append(inverse @ dcov[nkernel])
    flat = np.stack(products).reshape(len(products), -1)
    transposed = np.stack([w.T for w in products]).reshape(len(products), -1)
    # tr(A B) = sum_ij A_ij B_ji
    fisher = 0.5 * flat @ transposed.T
    return PatchLikelihood(float(value), grad, 0.5 * (fisher + fisher.T))


def leave_one_out(chol: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form leave-one-out predictive mean and variance (M,) of a GP.

    ``mu_i = y_i - [K^-1 y]_i / [K^-1]_ii`` and ``var_i = 1 / [K^-1]_ii`` (Rasmussen and
    Williams, eq. 5.12), with ``chol`` the lower Cholesky factor of the label covariance
    including noise.
    """
    inverse = cholesky_solve(chol, np.eye(len(labels)))
    alpha = inverse @ labels
    diag = np.diag(inverse)
    return labels - alpha / diag, 1.0 / diag
