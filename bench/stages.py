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
    warm-up call. Times the number of anchors, this estimates the predict stage's CPU."""
    from gpocc.blas import single_threaded_blas
    from gpocc.gp.local import NeighbourIndex
    from gpocc.gp.model import load_model
    from gpocc.mapping.blend import supported_anchors
    from gpocc.mapping.blocks import Anchor, AnchorLattice, predict_anchor
    from gpocc.mapping.mapper import default_spec
    from gpocc.mapping.support import model_support

    require(INTEL)
    model = load_model(ctx.intel_model())
    spec = default_spec(model, 0.1, model.config.map.margin_m)
    lattice = AnchorLattice.of_model(spec, model.config.model)
    rows_, cols = lattice.shape
    every = [Anchor(r, c) for r in range(rows_) for c in range(cols)]
    anchors, _ = supported_anchors(lattice, every, model_support(model).mask(spec,
                                                                             lattice.cells))
    count = 50 if ctx.quick else 200
    chosen = anchors[:: max(1, len(anchors) // count)][:count]
    index = NeighbourIndex(model.samples)
    with single_threaded_blas():
        predict_anchor(model, index, lattice, chosen[0])  # compiled loops and caches warm
        start = time.process_time()
        for anchor in chosen:
            predict_anchor(model, index, lattice, anchor)
        per_anchor = (time.process_time() - start) / len(chosen)
    result = Result()
    result.add(Table(("anchors with support", "timed", "CPU ms per anchor",
                      "x anchors: CPU s"),
                     [[str(len(anchors)), str(len(chosen)), f"{1e3 * per_anchor:.2f}",
                       f"{per_anchor * len(anchors):.1f}"]]))
    return result
