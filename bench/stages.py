"""One stage at a time, in this process: building samples, the annealing budget of
hyperparameter learning, and the CPU cost of one map anchor."""

from __future__ import annotations

import dataclasses
import time

from .paths import FREIBURG, INTEL, LOG_CONFIGS
from .registry import Context, Result, Table, benchmark, require


@benchmark("samples", "Building samples")
def samples(ctx: Context) -> Result:
    """`build_samples` on the whole Intel log (910 scans x 180 beams), without thinning
    and with the default 0.15 m thinning, after reading the log once with gpocc's
    reader: samples before and after thinning and wall seconds (best of 3; 1 in a quick
    run)."""
    from gpocc.config import Config, SamplesConfig, SensorConfig, replace
    from gpocc.io.inputs import read_inputs
    from gpocc.samples.beams import build_samples

    require(INTEL)
    started = time.perf_counter()
    (batch,) = read_inputs([INTEL], Config())
    read_s = time.perf_counter() - started
    base = Config(sensors=(SensorConfig(name=batch.sensor),))
    rows, unthinned = [], None
    for thin in (0.0, 0.15):
        config = replace(base, samples=SamplesConfig(free_spacing_m=0.4, thin_cell_m=thin))
        best = float("inf")
        for _ in range(1 if ctx.quick else 3):
            started = time.perf_counter()
            built = build_samples([batch], config)
            best = min(best, time.perf_counter() - started)
        if thin == 0.0:
            unthinned = len(built)
        rows.append([f"{thin:.2f}", str(batch.n_scans), str(unthinned), str(len(built)),
                     f"{best:.2f}"])
    result = Result()
    result.add(Table(("thin_cell_m", "scans", "samples", "kept", "seconds"), rows),
               f"Reading the log took {read_s:.2f} s.")
    return result


@benchmark("anneal-budget", "Annealing budget of hyperparameter learning")
def anneal_budget(ctx: Context) -> Result:
    """Does the global (annealing) stage of hyperparameter learning change the optimum?
    For each log (Intel and Freiburg 079 with their configs; Intel only in a quick run)
    the samples are built once and the hyperparameters learned once per `anneal_maxfun`
    budget (60, 20 the default, 0), everything else as configured: the negative log
    marginal likelihood reached, the likelihood evaluations, the stage's wall time, the
    learned input-noise scale g and label-noise variance. Equal optima at a smaller
    budget mean the evaluations saved were spent for nothing."""
    from gpocc.blas import single_threaded_blas
    from gpocc.config import load_config
    from gpocc.gp.kernels import make_kernel
    from gpocc.gp.train import learn_hyperparameters
    from gpocc.io.inputs import read_inputs
    from gpocc.samples.beams import build_samples

    logs = [INTEL] if ctx.quick else [INTEL, FREIBURG]
    require(*logs)
    rows = []
    with single_threaded_blas():
        for log in logs:
            cfg = load_config(LOG_CONFIGS[log.name])
            built = build_samples(read_inputs([log], cfg), cfg)
            model = cfg.model
            for budget in (60, 20, 0):
                training = dataclasses.replace(model.training, anneal_maxfun=budget)
                started = time.perf_counter()
                fit = learn_hyperparameters(
                    make_kernel(model.kernel, model.hyperparameters),
                    model.hyperparameters.noise_variance, built, model.quadrature_level,
                    training, cfg.seed)
                rows.append([log.name, str(budget), f"{-fit.log_marginal_likelihood:.2f}",
                             str(fit.evaluations), f"{time.perf_counter() - started:.1f}",
                             f"{fit.input_noise_scale:.2f}", f"{fit.noise_variance:.3f}"])
    result = Result()
    result.add(Table(("log", "anneal_maxfun", "-LML", "evaluations", "wall s", "g",
                      "noise variance"), rows))
    return result


@benchmark("anchor-cost", "CPU time of one map anchor")
def anchor_cost(ctx: Context) -> Result:
    """The unit the map's predict stage is made of: one local problem and its
    footprint's queries (`predict_anchor`), in this process with one BLAS thread, on
    the Intel model at 0.1 m. The anchors are laid out as `gpocc map` does (support
    mask included); every k-th of them is predicted (200; 50 in a quick run) after one
    warm-up call. Times the number of anchors, this estimates the predict stage's CPU.
    A second table splits one anchor's CPU into its parts, each timed alone on the same
    anchors: the neighbour look-up, the expected training covariance K (independent
    pairs by the product rule, and what the 4-D rule of same-scan pairs adds), the
    expected cross covariance to the footprint's cells, the Cholesky factor and the
    triangular solve for the variances; `other` is the whole anchor minus the parts. The
    first table gives the whole anchor with the local systems in each
    `model.covariance_precision` (the parts: the model's own, the default)."""
    import dataclasses

    import numpy as np
    from scipy.linalg.blas import dtrsm

    from gpocc.blas import single_threaded_blas
    from gpocc.constants import JITTER
    from gpocc.gp import backends
    from gpocc.gp.local import NeighbourIndex, cholesky_solve, try_cholesky
    from gpocc.gp.model import load_model
    from gpocc.mapping.blend import supported_anchors
    from gpocc.mapping.blocks import Anchor, AnchorLattice, anchor_problems, predict_anchor
    from gpocc.mapping.mapper import whole_map
    from gpocc.mapping.support import model_support

    require(INTEL)
    model = load_model(ctx.intel_model())
    spec = whole_map(model, 0.1)
    lattice = AnchorLattice.of_model(spec, model.config.model)
    rows_, cols = lattice.shape
    every = [Anchor(r, c) for r in range(rows_) for c in range(cols)]
    anchors, _ = supported_anchors(lattice, every, model_support(model).mask(spec,
                                                                             lattice.cells))
    count = 50 if ctx.quick else 200
    chosen = anchors[:: max(1, len(anchors) // count)][:count]
    index = NeighbourIndex(model.samples)
    loops = backends.get(model.backend).loops(model.kernel)
    diagonal = model.noise_variance + JITTER

    def cpu_per_anchor(work) -> float:
        start = time.process_time()
        for item in work:
            item()
        return (time.process_time() - start) / len(work)

    with single_threaded_blas():
        predict_anchor(model, index, lattice, chosen[0])  # compiled loops and caches warm
        by_precision = {}
        for precision in backends.PRECISIONS:
            variant = dataclasses.replace(model, config=dataclasses.replace(
                model.config, model=dataclasses.replace(model.config.model,
                                                        covariance_precision=precision)))
            predict_anchor(variant, index, lattice, chosen[0])
            by_precision[precision] = cpu_per_anchor(
                [lambda a=a, v=variant: predict_anchor(v, index, lattice, a) for a in chosen])
        per_anchor = by_precision[model.config.model.covariance_precision]
        problems = anchor_problems(model, index, lattice, chosen)
        lookup = cpu_per_anchor([lambda a=a: anchor_problems(model, index, lattice, [a])
                                 for a in chosen])
        queries = []
        for anchor, problem in zip(chosen, problems, strict=True):
            block, _ = lattice.footprint(anchor)
            window = spec.window(block.row0, block.col0, block.rows, block.cols)
            wanted = (np.ones((block.rows, block.cols), dtype=bool) if anchor.inside is None
                      else anchor.inside)
            queries.append(np.column_stack(window.cell_centres_at(*np.nonzero(wanted)))
                           - problem.centre)
        none = np.zeros((0, 2))
        independent = [dataclasses.replace(p.samples, pose_factors=None) for p in problems]

        def system(samples, q):
            return lambda: loops.local_systems(model.kernel, [(samples, q)], model.level,
                                               diagonal)

        k_independent = cpu_per_anchor([system(s, none) for s in independent])
        k_full = cpu_per_anchor([system(p.samples, none) for p in problems])
        with_cross = cpu_per_anchor([system(p.samples, q)
                                     for p, q in zip(problems, queries, strict=True)])
        systems = [loops.local_systems(model.kernel, [(p.samples, q)], model.level,
                                       diagonal)[0]
                   for p, q in zip(problems, queries, strict=True)]
        factor = cpu_per_anchor([lambda k=k: try_cholesky(k.copy()) for k, _, _ in systems])
        factors = [try_cholesky(k.copy()) for k, _, _ in systems]

        def solve(chol, cross, prior, labels):
            def run():
                cholesky_solve(chol, labels)
                v = dtrsm(1.0, chol, cross, side=1, lower=1, trans_a=1)
                return prior - np.einsum("ij,ij->i", v, v)
            return run

        solves = cpu_per_anchor([solve(c, cross, prior, p.samples.labels)
                                 for c, (_, cross, prior), p in zip(factors, systems, problems,
                                                                    strict=True)])
    result = Result()
    own = model.config.model.covariance_precision
    result.add(Table(("local systems", "anchors with support", "timed", "CPU ms per anchor",
                      "x anchors: CPU s"),
                     [[f"{precision}{' (this model)' if precision == own else ''}",
                       str(len(anchors)), str(len(chosen)), f"{1e3 * t:.2f}",
                       f"{t * len(anchors):.1f}"] for precision, t in by_precision.items()]))
    n = np.mean([len(p.samples) for p in problems])
    nq = np.mean([len(q) for q in queries])
    parts = [("neighbour look-up", lookup),
             (f"K, independent pairs ({n:.0f} samples)", k_independent),
             ("K, same-scan pairs (4-D rule)", k_full - k_independent),
             (f"cross covariance ({nq:.0f} cells)", with_cross - k_full),
             ("Cholesky factor", factor),
             ("solves: mean and variances", solves)]
    other = per_anchor - sum(t for _, t in parts)
    result.add(Table(("part", "CPU ms per anchor", "share"),
                     [[name, f"{1e3 * t:.3f}", f"{100 * t / per_anchor:.0f}%"]
                      for name, t in [*parts, ("other", other)]]))
    return result


@benchmark("blas-threads", "BLAS threads on small matrices")
def blas_threads(ctx: Context) -> Result:
    """gpocc runs BLAS on one thread per process (`gpocc/blas.py`) and parallelises over
    processes instead. This measures what one thread costs or saves on matrices the size
    of local problems (128 and 256 samples): the Cholesky factor and a triangular solve
    against 333 columns (a block's queries), with the BLAS library's default threads and
    with one; the median of 200 calls (50 in a quick run), so that thread wake-ups and
    contention count."""
    from contextlib import nullcontext

    import numpy as np
    from scipy.linalg import cho_factor, solve_triangular

    from gpocc.blas import single_threaded_blas

    calls = 50 if ctx.quick else 200
    rng = np.random.default_rng(0)
    rows = []
    for n in (128, 256):
        a = rng.standard_normal((n, n))
        spd = a @ a.T + n * np.eye(n)
        rhs = rng.standard_normal((n, 333))
        factor = np.linalg.cholesky(spd)
        timings = []
        for limit in (None, 1):
            with nullcontext() if limit is None else single_threaded_blas():
                chol, solve = [], []
                for _ in range(calls):
                    t0 = time.perf_counter()
                    cho_factor(spd, lower=True)
                    t1 = time.perf_counter()
                    solve_triangular(factor, rhs, lower=True)
                    chol.append(t1 - t0)
                    solve.append(time.perf_counter() - t1)
            timings.append({"chol": np.median(chol), "solve": np.median(solve)})
        rows.append([str(n), f"{1e3 * timings[0]['chol']:.3f}",
                     f"{1e3 * timings[1]['chol']:.3f}", f"{1e3 * timings[0]['solve']:.3f}",
                     f"{1e3 * timings[1]['solve']:.3f}"])
    result = Result()
    result.add(Table(("samples", "Cholesky ms, default threads", "Cholesky ms, 1 thread",
                      "solve (333 columns) ms, default threads", "solve ms, 1 thread"),
                     rows))
    return result


@benchmark("sample-memory", "Memory per training sample")
def sample_memory(ctx: Context) -> Result:
    """Why `gpocc.limits.MAX_SAMPLES_PER_SCAN` bounds what one scan may give: sample
    building pushes a whole scan through the unscented transform at once. Peak traced
    memory (numpy's allocations, `tracemalloc`) of `build_samples` on one scan of 1080
    beams (and 4000 beams in a full run) ending 29 m away, thinning off."""
    import math
    import tracemalloc

    import numpy as np

    from gpocc.config import Config, SamplesConfig, SensorConfig, replace
    from gpocc.io.scans import ScanBatch
    from gpocc.samples.beams import build_samples

    rows = []
    for beams in (1080,) if ctx.quick else (1080, 4000):
        batch = ScanBatch(
            sensor="wide", source="synthetic", stamps=np.zeros(1),
            angles=np.linspace(-math.pi, math.pi, beams, endpoint=False),
            ranges=np.full((1, beams), 29.0), poses=np.zeros((1, 3)),
            pose_covariances=np.diag([1e-3, 1e-3, 1e-4])[None].copy(),
            range_min=0.1, range_max=40.0)
        config = replace(Config(sensors=(SensorConfig(name="wide"),)),
                         samples=SamplesConfig(thin_cell_m=0.0))
        tracemalloc.start()
        built = build_samples([batch], config)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        rows.append([str(beams), str(len(built)), f"{peak / 2**20:.0f}",
                     f"{peak / len(built):.0f}"])
    result = Result()
    result.add(Table(("beams", "samples", "peak traced MiB", "bytes per sample"), rows))
    return result
