"""Hyperparameter learning: maximise the log marginal likelihood of local patches.

Inference is local, so the likelihood is too: the sum over a few spatially spread
neighbourhoods ("patches") of the exact GP log marginal likelihood, each patch centred
at the origin like an inference problem. The expected-kernel matrices and their analytic
gradients come from Gauss-Hermite quadrature whose nodes do not depend on the
hyperparameters. Optimisation: ``scipy.optimize.dual_annealing`` (global, bounded,
seeded) and then L-BFGS-B (or Fisher scoring, ``local_search: scoring``) from its best
point, and from its next best distinct points with ``local_starts`` above 1. With
``learn_input_noise_scale`` a scale g on every input covariance
(:mod:`gpocc.gp.inputscale`) is learned with them.
Given a ``warm_start`` (the values of a model of part of the samples, ``gpocc update``), the
annealing is skipped and Fisher scoring (:mod:`gpocc.gp.refine`; L-BFGS-B where the loops
give no dK/dlog g) starts there: the optimum of a set of patches mostly does not depend
on where the search starts (Freiburg: four annealing seeds and budgets 20 and 60 reach
one optimum), so the refinement usually lands where learning from the initial values
does; where the annealing's best point lies in another basin, it does not
(docs/benchmarks.md, ``update-cost`` and ``local-search``).
"""

from __future__ import annotations

import contextlib
import functools
import math
from collections.abc import Callable, Iterator
from concurrent.futures import Executor
from dataclasses import dataclass
from multiprocessing.pool import Pool
from typing import Any

import numpy as np

from gpocc.config import ModelConfig, TrainingConfig
from gpocc.errors import GpoccError
from gpocc.gp import backends
from gpocc.gp.expected import same_scan_pairs, supports_scale_gradient
from gpocc.gp.inputscale import LOG_SCALE_STEP, scale_input_noise
from gpocc.gp.kernels import Kernel, axis_pairs, learned_names
from gpocc.gp.local import LocalProblem, NeighbourIndex, PatchLikelihood
from gpocc.gp.refine import TOLERANCE as _SCORING_TOLERANCE
from gpocc.gp.refine import fisher_scoring
from gpocc.parallel import default_workers, wait_for, worker_pool
from gpocc.progress import log
from gpocc.samples.sampleset import SampleSet

#: Value of hyperparameters whose training covariance is not positive definite.
_REJECTED = 1e10


@dataclass(frozen=True)
class TrainingResult:
    """Learned hyperparameters and how they were found.

    Attributes:
        kernel: the kernel with learned hyperparameters.
        noise_variance: learned label-noise variance.
        log_marginal_likelihood: at the learned values, summed over patches (nats).
        initial_log_marginal_likelihood: at the initial values (nats).
        evaluations: likelihood evaluations spent.
        patches: number of patches and samples per patch.
        input_noise_scale: learned scale g of the input covariances (1: not learned).
        warm_started: the search refined a ``warm_start`` (else it started from the
            initial values).
    """

    kernel: Kernel
    noise_variance: float
    log_marginal_likelihood: float
    initial_log_marginal_likelihood: float
    evaluations: int
    patches: tuple[int, int]
    input_noise_scale: float = 1.0
    warm_started: bool = False


def farthest_point_indices(points: np.ndarray, count: int,
                           rng: np.random.Generator) -> list[int]:
    """Indices of ``count`` of the (N, 2) ``points`` spread over them: greedy
    farthest-point sampling from a random start (one draw of ``rng``)."""
    chosen = [int(rng.integers(len(points)))]
    distance = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(1, min(count, len(points))):
        nxt = int(np.argmax(distance))
        chosen.append(nxt)
        distance = np.minimum(distance, np.linalg.norm(points - points[nxt], axis=1))
    return chosen


def spread_patch_centres(means: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` sample positions spread over the data (greedy farthest-point from a random start).

    Spatial stratification makes the patches see walls, open space and corners rather
    than one dense corridor, which a purely random choice tends to do.
    """
    n = len(means)
    candidates = means[rng.choice(n, size=min(n, max(50 * count, 500)), replace=False)]
    return candidates[farthest_point_indices(candidates, count, rng)]


def patch_count(samples: SampleSet, config: TrainingConfig) -> int:
    """How many patches learning draws: ``config.patches``, or ``patches_per_sensor``
    per sensor with samples where that is more (a site of many separate buildings, each
    its own sensor, gets patches on all of them instead of ten at the site's edges,
    where farthest-point spreading puts them)."""
    sensors = np.unique(samples.sensor_ids).size
    return max(config.patches, config.patches_per_sensor * sensors)


def make_patches(samples: SampleSet, config: TrainingConfig, seed: int,
                 index: NeighbourIndex | None = None) -> list[LocalProblem]:
    """Training patches: :func:`patch_count` neighbourhoods of ``config.patch_size``
    samples. ``index``: a :class:`NeighbourIndex` of samples with the same means, whose
    tree is used instead of building one.

    ``config.patch_centres``: ``hits`` spreads the centres over the occupied samples, so
    that every patch holds a boundary (over all samples when there are fewer hits than
    patches); ``samples`` spreads them over all samples. ``config.patch_offset_m`` then
    moves each centre by a tent-distributed offset per axis (see
    :class:`gpocc.config.TrainingConfig`; unset: the default ``model.block_size_m``, so
    give :attr:`gpocc.config.ModelConfig.effective_training` for another). The Platt
    classifier is fitted on patches made the same way (gpocc.gp.model).
    """
    if len(samples) < 10:
        raise GpoccError(
            f"only {len(samples)} training samples: too few to learn hyperparameters; "
            "check the inputs' ranges or lower samples.free_spacing_m"
        )
    rng = np.random.default_rng(seed)
    index = NeighbourIndex(samples) if index is None else index.over(samples)
    hits = samples.labels > 0
    centre_pool = samples.means
    count = patch_count(samples, config)
    if config.patch_centres == "hits" and hits.sum() >= count:
        centre_pool = samples.means[hits]
    centres = spread_patch_centres(centre_pool, count, rng)
    # Unset: resolved by the one rule, here under the default block size.
    offset_m = ModelConfig(training=config).effective_training.patch_offset_m
    if offset_m > 0:
        # Where a map cell lies from the anchors that predict it: a tent, the sum of two
        # uniform draws.
        half = offset_m / 2
        centres = (centres + rng.uniform(-half, half, centres.shape)
                   + rng.uniform(-half, half, centres.shape))
    return [index.problem(c, config.patch_size) for c in centres]


def _patch_negative_log_likelihood(
    kernel: Kernel, noise: float, patch: LocalProblem, **options
) -> PatchLikelihood | None:
    """One patch's -LML and its gradient (:func:`_patch_negative_log_likelihoods`)."""
    return next(_patch_negative_log_likelihoods(kernel, noise, [patch], **options))


def _patch_negative_log_likelihoods(
    kernel: Kernel, noise: float, patches: list[LocalProblem], *, level: int,
    with_gradient: bool, input_scale: float = 1.0, scale_gradient: bool = False,
    backend: str = "auto", scale_part: str = "all", with_fisher: bool = False,
) -> Iterator[PatchLikelihood | None]:
    """Each patch's -LML and its gradient in log-parameters (with ``scale_gradient``, then
    in log g; with ``with_fisher``, its Fisher information too), or None where K is not a
    covariance, in patch order: one batch for the backend
    (``KernelLoops.patch_likelihoods``). ``scale_part``: what ``input_scale`` scales
    (:func:`gpocc.gp.inputscale.scale_input_noise`); the loops scale whole covariances
    themselves, so a pose-only scale is applied to the samples first."""
    chosen = backends.get(backend)
    samples = [p.samples for p in patches]
    if scale_part != "all":
        if scale_gradient:
            raise ValueError("the loops give d/dlog g for a scale of whole covariances only")
        samples = [scale_input_noise(s, input_scale, scale_part) for s in samples]
        input_scale = 1.0
    return chosen.loops(kernel).patch_likelihoods(
        kernel, noise, samples, level, with_gradient=with_gradient,
        input_scale=input_scale, scale_gradient=scale_gradient, backend=chosen,
        with_fisher=with_fisher)


# The patches of a training worker process, installed once when its pool starts
# (:class:`ResidentPatches`), so that each task carries the hyperparameters only.
_worker_patches: list[LocalProblem] = []


def _install_patches(patches: list[LocalProblem]) -> None:
    _worker_patches[:] = patches


def _resident_patch_negative_log_likelihood(kernel: Kernel, noise: float, index: int,
                                            **options) -> PatchLikelihood | None:
    return _patch_negative_log_likelihood(kernel, noise, _worker_patches[index], **options)


@dataclass(frozen=True)
class ResidentPatches:
    """A process pool whose workers already hold ``patches`` (:func:`resident_patch_pool`).

    Sending a patch with every task (16 kB pickled, ten per evaluation) cost a quarter of
    a value-only evaluation on 2 workers; resident patches leave the hyperparameters as
    the only payload.
    """

    pool: Pool
    patches: tuple[LocalProblem, ...]
    #: Patch indices, most expensive first: handing out the longest tasks first keeps
    #: both workers busy to the end (an all-one-scan patch cost three others before the
    #: same-scan rule was compiled better, and still costs twice as much).
    order: tuple[int, ...]


def _patch_cost(patch: LocalProblem, level: int) -> float:
    """Relative cost of a patch's likelihood: its pairs, plus its same-scan pairs (a 4-D
    rule each) at 1.7 pairs apiece (Intel patches, values and gradients: 1.6-1.8). A
    level-1 rule puts every point at its mean and has no same-scan work."""
    s = patch.samples
    n = len(s)
    same_scan, _ = same_scan_pairs(s.covariances, s.scan_ids, s.pose_factors)
    return n * (n - 1) / 2 + (1.7 * same_scan.shape[0] if level > 1 else 0.0)


@contextlib.contextmanager
def resident_patch_pool(patches: list[LocalProblem], workers: int, level: int):
    """A :class:`ResidentPatches` pool of ``workers`` processes holding ``patches``
    (``level``: the quadrature level they will be evaluated at, for the costs)."""
    order = _costliest_first(patches, level)
    with worker_pool(workers, _install_patches, (list(patches),)) as pool:
        yield ResidentPatches(pool, tuple(patches), order)


@dataclass(frozen=True)
class ClusterPatches:
    """The workers of a Dask cluster holding ``patches`` (:func:`cluster_patches`): each
    evaluation sends the hyperparameters and a reference to each patch, one task per
    patch, most expensive first, as :class:`ResidentPatches` does locally."""

    client: Any
    futures: tuple[Any, ...]
    patches: tuple[LocalProblem, ...]
    order: tuple[int, ...]


def _costliest_first(patches: list[LocalProblem], level: int) -> tuple[int, ...]:
    costs = [_patch_cost(p, level) for p in patches]
    return tuple(sorted(range(len(patches)), key=lambda i: -costs[i]))


def cluster_patches(client: Any, patches: list[LocalProblem], level: int) -> ClusterPatches:
    """:class:`ClusterPatches`: ``patches`` sent once to every worker of ``client``."""
    futures = client.scatter(list(patches), broadcast=True)
    return ClusterPatches(client, tuple(futures), tuple(patches),
                          _costliest_first(patches, level))


def _held_by(pool: ResidentPatches | ClusterPatches, patches: list[LocalProblem]) -> None:
    if len(pool.patches) != len(patches) or any(
            held is not patch for held, patch in zip(pool.patches, patches, strict=True)):
        raise ValueError("the pool holds other patches than those to evaluate")


def _patch_terms(
    arguments: tuple[Kernel, float], patches: list[LocalProblem],
    executor: Executor | Pool | ResidentPatches | ClusterPatches | None, options: dict,
) -> list[PatchLikelihood | None]:
    """Each patch's :class:`PatchLikelihood` (None: not a covariance) in patch order,
    evaluated by ``executor`` (:func:`negative_log_likelihood`)."""
    # Partials of module-level functions, so that worker processes can receive them.
    # One patch per task: patches differ in cost (3-12 ms), and Pool.map's default chunks of
    # two left one worker idle (gradient evaluations about 9% slower on 2 workers).
    if isinstance(executor, ResidentPatches | ClusterPatches):
        _held_by(executor, patches)
        if isinstance(executor, ResidentPatches):
            one = functools.partial(_resident_patch_negative_log_likelihood, *arguments,
                                    **options)
            by_cost = wait_for(executor.pool,
                               executor.pool.map_async(one, executor.order, chunksize=1))
        else:
            client = executor.client
            by_cost = client.gather([
                client.submit(_patch_negative_log_likelihood, *arguments,
                              executor.futures[index], pure=False, **options)
                for index in executor.order])
        terms: list[PatchLikelihood | None] = [None] * len(patches)
        for index, term in zip(executor.order, by_cost, strict=True):
            terms[index] = term
        return terms
    one = functools.partial(_patch_negative_log_likelihood, *arguments, **options)
    return (list(executor.map(one, patches, chunksize=1)) if executor is not None
            else list(_patch_negative_log_likelihoods(*arguments, patches, **options)))


def negative_log_likelihood(
    params: np.ndarray, kernel, patches: list[LocalProblem], level: int,
    with_gradient: bool = True,
    executor: Executor | Pool | ResidentPatches | ClusterPatches | None = None,
    input_scale: float = 1.0, scale_gradient: bool = False, backend: str = "auto",
    scale_part: str = "all",
) -> tuple[float, np.ndarray]:
    """Negative log marginal likelihood over patches and its gradient in log-parameters.

    ``params`` = ``[kernel.theta..., log noise_variance]``. Without ``with_gradient`` the
    gradient is returned as zeros (and not computed: the global stage needs values only).
    ``executor`` (a ``multiprocessing`` pool or a ``concurrent.futures`` executor: a
    ``map`` that takes ``chunksize``; a :class:`ResidentPatches` pool or the
    :class:`ClusterPatches` of a Dask cluster holding these ``patches``) evaluates the
    patches concurrently; the sum is taken in patch order, so
    the result does not depend on it.
    ``input_scale``: g of :mod:`gpocc.gp.inputscale` (the patches' inputs as stated: 1);
    ``scale_gradient`` (with gradients): the gradient gains d/dlog g.
    ``backend``: ``model.backend`` (:mod:`gpocc.gp.backends`). ``scale_part``: what g
    scales (:func:`gpocc.gp.inputscale.scale_input_noise`).
    """
    arguments = (kernel.with_theta(params[:-1]), math.exp(params[-1]))
    options = {"level": level, "with_gradient": with_gradient, "input_scale": input_scale,
               "scale_gradient": scale_gradient and with_gradient, "backend": backend,
               "scale_part": scale_part}
    terms = _patch_terms(arguments, patches, executor, options)
    value = 0.0
    grad = np.zeros(len(params) + (1 if scale_gradient else 0))
    for term in terms:
        if term is None:  # not a valid covariance: reject these hyperparameters
            return _REJECTED, np.zeros_like(grad)
        value += term[0]
        if term[1] is not None:
            grad += term[1]
    return float(value), grad


def likelihood_with_fisher(
    params: np.ndarray, kernel, patches: list[LocalProblem], level: int,
    executor: Executor | Pool | ResidentPatches | ClusterPatches | None = None,
    with_scale: bool = False, backend: str = "auto",
) -> tuple[float, np.ndarray, np.ndarray] | None:
    """The -LML over patches, its gradient (P,) and its Fisher information (P, P), all in
    ``params`` = ``[kernel.theta..., log noise_variance(, log g)]`` (``with_scale``: g of
    :mod:`gpocc.gp.inputscale` on whole covariances, which needs
    :func:`~gpocc.gp.expected.supports_scale_gradient`); None where K is not a
    covariance. ``executor``: as :func:`negative_log_likelihood`'s."""
    if with_scale:
        kernel_params, input_scale = params[:-1], math.exp(params[-1])
    else:
        kernel_params, input_scale = params, 1.0
    arguments = (kernel.with_theta(kernel_params[:-1]), math.exp(kernel_params[-1]))
    options = {"level": level, "with_gradient": True, "input_scale": input_scale,
               "scale_gradient": with_scale, "backend": backend, "with_fisher": True}
    value, grad, fisher = 0.0, np.zeros(len(params)), np.zeros((len(params), len(params)))
    for term in _patch_terms(arguments, patches, executor, options):
        if term is None:
            return None
        value += term.value
        grad += term.gradient
        fisher += term.fisher
    return value, grad, fisher


def negative_log_likelihood_with_scale(
    params: np.ndarray, kernel, patches: list[LocalProblem], level: int,
    with_gradient: bool = True,
    executor: Executor | Pool | ResidentPatches | ClusterPatches | None = None,
    backend: str = "auto", scale_part: str = "all",
) -> tuple[float, np.ndarray]:
    """:func:`negative_log_likelihood` with the patches' input noise scaled by g.

    ``params`` = ``[kernel.theta..., log noise_variance, log g]``. The derivative in
    ``log g`` is analytic for the compiled NN kernel (every quadrature node moves away
    from its mean as sqrt(g)); for other kernels it is a central difference of two
    value-only evaluations, step :data:`LOG_SCALE_STEP`. At ``log g = 0`` the value and
    the other derivatives are exactly those of the unscaled likelihood. ``scale_part``:
    what g scales (:func:`gpocc.gp.inputscale.scale_input_noise`); a pose-only scale
    always takes the central difference.
    """
    log_g = float(params[-1])

    def at(log_scale: float, gradient: bool, scale_gradient: bool = False
           ) -> tuple[float, np.ndarray]:
        return negative_log_likelihood(params[:-1], kernel, patches, level,
                                       with_gradient=gradient, executor=executor,
                                       input_scale=math.exp(log_scale),
                                       scale_gradient=scale_gradient, backend=backend,
                                       scale_part=scale_part)

    if with_gradient and scale_part == "all" and supports_scale_gradient(kernel, backend):
        return at(log_g, True, scale_gradient=True)
    value, grad = at(log_g, with_gradient)
    if not with_gradient or value >= _REJECTED:
        return value, np.append(grad, 0.0)
    up, down = at(log_g + LOG_SCALE_STEP, False)[0], at(log_g - LOG_SCALE_STEP, False)[0]
    if up < _REJECTED and down < _REJECTED:
        slope = (up - down) / (2.0 * LOG_SCALE_STEP)
    elif up < _REJECTED:  # one side is not a valid covariance: one-sided difference
        slope = (up - value) / LOG_SCALE_STEP
    elif down < _REJECTED:
        slope = (value - down) / LOG_SCALE_STEP
    else:
        slope = 0.0
    return value, np.append(grad, slope)


def learn_hyperparameters(
    kernel: Kernel, noise_variance: float, samples: SampleSet, level: int,
    config: TrainingConfig,
    seed: int, on_evaluation: Callable[[int], None] | None = None,
    workers: int | None = None, backend: str = "auto", client: Any = None,
    warm_start: TrainingResult | None = None, refine_iterations: int | None = None,
    index: NeighbourIndex | None = None,
) -> TrainingResult:
    """Maximise the patch log marginal likelihood; see the module docstring.

    ``kernel`` and ``noise_variance`` are the initial values (the centre of the search
    box). ``warm_start``: learned values (kernel, label noise, input-noise scale) to refine
    with L-BFGS-B alone instead of annealing from the initial values; a start outside the
    box is moved onto it, and one that fits the patches worse than the initial values
    (or whose covariance is not positive definite) falls back to the full search, which
    then gives the result of learning without a start. ``refine_iterations``: at most
    this many steps from a ``warm_start`` it refines (Fisher scoring steps, one
    evaluation each; L-BFGS-B iterations for loops without dK/dlog g; default
    ``config.lbfgs_maxiter``). ``index``: for :func:`make_patches`.

    ``on_evaluation(1)`` is called after every likelihood evaluation (progress display).
    ``workers`` processes (default: every usable core; 1: none) evaluate the patches
    concurrently, or the workers of the Dask cluster of ``client`` (a
    ``distributed.Client``, :func:`gpocc.parallel.dask_client`); the result does not
    depend on which, nor on their number. ``backend``: ``model.backend``
    (:mod:`gpocc.gp.backends`).
    """
    patches = make_patches(samples, config, seed, index)
    # g only matters (and is only learned) when some input has a covariance.
    learn_scale = config.learn_input_noise_scale and bool(samples.covariances.any())
    objective = (functools.partial(negative_log_likelihood_with_scale,
                                   scale_part=config.input_noise_scale_part)
                 if learn_scale else negative_log_likelihood)
    # Processes, not threads: much of a patch's work is numpy glue that holds the GIL
    # (threads gave 1.4x on 2 cores). The workers receive the patches once.
    workers = min(len(patches), workers or default_workers())
    if client is not None:
        holder = contextlib.nullcontext(cluster_patches(client, patches, level))
    elif workers > 1:
        holder = resident_patch_pool(patches, workers, level)
    else:
        holder = contextlib.nullcontext()
    with holder as pool:

        def negative_log_likelihood_counted(
            params: np.ndarray, *args: object, with_gradient: bool = True
        ) -> tuple[float, np.ndarray]:
            result = objective(params, *args, with_gradient=with_gradient, executor=pool,
                               backend=backend)
            if on_evaluation is not None:
                on_evaluation(1)
            return result

        def fisher_counted(params: np.ndarray) -> tuple[float, np.ndarray, np.ndarray] | None:
            result = likelihood_with_fisher(params, kernel, patches, level, executor=pool,
                                            with_scale=learn_scale, backend=backend)
            if on_evaluation is not None:
                on_evaluation(1)
            return result

        # Scoring needs dK/dlog g from the loops (whole covariances).
        scoring = (warm_start is not None or config.local_search == "scoring") and (
            not learn_scale or (config.input_noise_scale_part == "all"
                                and supports_scale_gradient(kernel, backend)))
        return _optimise(kernel, noise_variance, patches, level, config, seed,
                         negative_log_likelihood_counted, learn_scale, warm_start,
                         refine_iterations, fisher_counted if scoring else None)


def load_optimiser() -> None:
    """Import scipy.optimize now (0.1-0.2 s), for a caller with a core to spare before
    :func:`learn_hyperparameters` (``gpocc train`` builds its samples meanwhile). Imported
    at the learner's start, it kept both freshly forked workers idle."""
    import scipy.optimize  # noqa: F401


def search_bounds(theta: np.ndarray, noise_variance: float, config: TrainingConfig,
                  learn_scale: bool) -> list[tuple[float, float]]:
    """The optimiser's box in its parameters (all natural logs): the kernel's ``theta``
    and the label-noise variance each within ``log_bounds_width`` of their initial
    values, the noise kept at or above ``min_noise_variance`` (its box at least one unit
    wide), then log g in ``[min_input_noise_scale, max_input_noise_scale]`` when
    ``learn_scale``. :mod:`gpocc.gp.bounds` checks learned values against the same box."""
    width = config.log_bounds_width
    x0 = [*np.asarray(theta, dtype=float), math.log(noise_variance)]
    bounds = [(v - width, v + width) for v in x0]
    floor = math.log(config.min_noise_variance)
    lo, hi = bounds[-1]
    bounds[-1] = (max(lo, floor), max(hi, floor + 1.0))
    if learn_scale:
        bounds.append((math.log(config.min_input_noise_scale),
                       math.log(config.max_input_noise_scale)))
    return bounds


def _optimise(kernel: Kernel, noise_variance: float, patches: list[LocalProblem], level: int,
              config: TrainingConfig, seed: int,
              negative_log_likelihood_counted: Callable[..., tuple[float, np.ndarray]],
              learn_scale: bool = False, warm_start: TrainingResult | None = None,
              refine_iterations: int | None = None,
              fisher: Callable[[np.ndarray], tuple[float, np.ndarray, np.ndarray] | None]
              | None = None) -> TrainingResult:
    """Global annealing on values, then ``config.local_starts`` local searches on values
    and gradients from its best distinct points: L-BFGS-B, or Fisher scoring
    (:mod:`gpocc.gp.refine`) with ``config.local_search: scoring`` given ``fisher``
    (params -> value, gradient, Fisher information). From a valid ``warm_start``, one
    local search alone: Fisher scoring given ``fisher``, else L-BFGS-B."""
    # Imported here: a map loads models through this module but never learns.
    from scipy.optimize import dual_annealing, minimize

    x0 = np.append(kernel.theta, math.log(noise_variance))
    noise_at = x0.shape[0] - 1  # then log g when it is learned, starting at g = 1
    if learn_scale:
        x0 = np.append(x0, 0.0)
    # Its value only: every search below computes the gradients it uses itself.
    initial, _ = negative_log_likelihood_counted(x0, kernel, patches, level,
                                                 with_gradient=False)
    evaluations = 1
    # Every value held (model.training.fixed) leaves nothing to search: as learn: false.
    nothing_free = set(learned_names(kernel)) <= set(config.fixed) and not learn_scale
    if not config.learn or nothing_free:
        return TrainingResult(kernel, noise_variance, -initial, -initial, evaluations,
                              (len(patches), len(patches[0].samples)))
    bounds = search_bounds(kernel.theta, noise_variance, config, learn_scale)
    start = min(max(x0[noise_at], bounds[noise_at][0]), bounds[noise_at][1])

    def value_only(p: np.ndarray) -> float:
        return negative_log_likelihood_counted(p, kernel, patches, level,
                                               with_gradient=False)[0]

    # Only a start below the noise floor moves; otherwise its value is already known.
    best_value = initial if start == x0[noise_at] else None
    x0[noise_at] = start
    if best_value is None:
        best_value = value_only(x0)
        evaluations += 1
    best = x0
    # ``config.fixed`` values stay at their start: the optimisers see the others only.
    free = np.ones(x0.shape[0], dtype=bool)
    names = learned_names(kernel)
    free[[names.index(n) for n in config.fixed]] = False
    # ``config.isotropic``: each per-axis pair is one value, its y following its x.
    tied = axis_pairs(kernel) if config.isotropic else ()
    for _, y in tied:
        free[y] = False
    free_bounds = [b for b, f in zip(bounds, free, strict=True) if f]
    # d(all parameters)/d(free ones): a tied second moves with its first.
    columns = np.flatnonzero(free)
    jacobian = np.zeros((free.shape[0], columns.shape[0]))
    jacobian[columns, np.arange(columns.shape[0])] = 1.0
    for x, y in tied:
        jacobian[y, np.searchsorted(columns, x)] = 1.0

    def lift(p: np.ndarray) -> np.ndarray:
        full = x0.copy()
        full[free] = p
        for x, y in tied:
            full[y] = full[x]
        return full

    # The annealing's valid points, for further local starts.
    visited: list[tuple[float, np.ndarray]] = []

    def value_only_free(p: np.ndarray) -> float:
        point = lift(p)
        value = value_only(point)
        if value < _REJECTED:
            visited.append((value, point))
        return value

    def objective_free(p: np.ndarray, *args: object) -> tuple[float, np.ndarray]:
        value, grad = negative_log_likelihood_counted(lift(p), *args)
        return value, jacobian.T @ grad

    from_start = False
    if warm_start is not None:
        given = np.append(warm_start.kernel.theta, math.log(warm_start.noise_variance))
        if learn_scale:
            given = np.append(given, math.log(warm_start.input_noise_scale))
        given = np.clip(given, [lo for lo, _ in bounds], [hi for _, hi in bounds])
        # A model learned with one value per axis, refined isotropic: each pair starts
        # at its geometric mean, the nearest tied point in the logs, not at its x.
        for x, y in tied:
            given[x] = 0.5 * (given[x] + given[y])
        given = lift(given[free])
        if fisher is not None:
            first = fisher(given)
            given_value = _REJECTED if first is None else first[0]
        else:
            given_value = value_only(given)
        evaluations += 1
        # A start worse than the initial values (a model of few logs that learned a kernel
        # far too smooth for the walls) is dropped: the search is then learning's own.
        from_start = given_value < best_value
        if from_start:
            best, best_value = given, given_value
    if config.anneal_maxfun > 0 and not from_start:
        annealed = dual_annealing(
            value_only_free, free_bounds, maxfun=config.anneal_maxfun, seed=seed,
            x0=x0[free], no_local_search=True,
        )
        evaluations += int(annealed.nfev)
        if annealed.fun < initial:
            best, best_value = lift(annealed.x), float(annealed.fun)
    iterations = (refine_iterations if from_start and refine_iterations is not None
                  else config.lbfgs_maxiter)
    scoring = fisher is not None and (from_start or config.local_search == "scoring")
    starts = [best] if from_start else distinct_starts(best, visited, config.local_starts)
    final, final_value = best, best_value
    # Whether the search that gave the result stopped at its budget short of converging
    # (said once, of the kept result: another start's stop changes nothing the model has).
    final_unconverged = False
    for point in starts:
        converged = True
        if scoring:
            found, found_value, spent, converged = _score_from(
                point[free], first if from_start else None, fisher, jacobian, lift,
                free_bounds, iterations)
        else:
            refined = minimize(
                objective_free, point[free], args=(kernel, patches, level), jac=True,
                method="L-BFGS-B", bounds=free_bounds, options={"maxiter": iterations},
            )
            found, found_value, spent = lift(refined.x), float(refined.fun), int(refined.nfev)
        evaluations += spent
        if found_value <= final_value:
            final, final_value, final_unconverged = found, found_value, not converged
    if final_unconverged:
        budget = ("--refine-iterations" if from_start and refine_iterations is not None
                  else "model.training.lbfgs_maxiter")
        log(f"Fisher scoring stopped after {iterations} steps, its budget, with more "
            f"than {_SCORING_TOLERANCE} nats still to gain; {budget} raises it")
    return TrainingResult(
        kernel=kernel.with_theta(final[:noise_at]),
        noise_variance=float(math.exp(final[noise_at])),
        input_noise_scale=float(math.exp(final[-1])) if learn_scale else 1.0,
        log_marginal_likelihood=-final_value,
        initial_log_marginal_likelihood=-initial,
        evaluations=evaluations,
        patches=(len(patches), len(patches[0].samples)),
        warm_started=from_start,
    )


#: Local starts after the annealing's best differ from each earlier start by at least
#: this much (natural log) in some parameter: a factor e.
START_SEPARATION = 1.0


def distinct_starts(best: np.ndarray, visited: list[tuple[float, np.ndarray]],
                    count: int) -> list[np.ndarray]:
    """Up to ``count`` local starts: ``best``, then the lowest-valued ``visited`` points
    (value, (P,) parameters) at least :data:`START_SEPARATION` from every start so far
    in some parameter."""
    starts = [best]
    for _, point in sorted(visited, key=lambda v: v[0]):
        if len(starts) >= count:
            break
        if all(np.abs(point - s).max() >= START_SEPARATION for s in starts):
            starts.append(point)
    return starts


def _score_from(
    start: np.ndarray, first: tuple[float, np.ndarray, np.ndarray] | None,
    fisher: Callable[[np.ndarray], tuple[float, np.ndarray, np.ndarray] | None],
    jacobian: np.ndarray, lift: Callable[[np.ndarray], np.ndarray],
    free_bounds: list[tuple[float, float]], max_evaluations: int,
) -> tuple[np.ndarray, float, int, bool]:
    """Fisher scoring from ``start`` (the free parameters; ``first`` = ``fisher`` at
    ``lift(start)``, or None: evaluated here), where ``lift`` maps free parameters to all
    and ``jacobian`` (all, free) is its derivative: all the refined parameters, their
    value, the evaluations spent after ``first`` and whether it converged before its
    budget ran out."""
    def reduced(evaluation: tuple[float, np.ndarray, np.ndarray]
                ) -> tuple[float, np.ndarray, np.ndarray]:
        value, grad, information = evaluation
        return value, jacobian.T @ grad, jacobian.T @ information @ jacobian

    def evaluate(p: np.ndarray) -> tuple[float, np.ndarray, np.ndarray] | None:
        evaluation = fisher(lift(p))
        return None if evaluation is None else reduced(evaluation)

    lower = np.array([lo for lo, _ in free_bounds])
    upper = np.array([hi for _, hi in free_bounds])
    refined = fisher_scoring(evaluate, start, lower, upper, max(1, max_evaluations),
                             start=None if first is None else reduced(first))
    return lift(refined.x), refined.value, refined.evaluations, refined.converged
