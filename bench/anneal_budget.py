"""Does the global (annealing) stage of hyperparameter learning change the optimum?

Run ``.venv/bin/python bench/anneal_budget.py [--budgets 60,20,0] BAG:CONFIG ...``. For
each input (a log and its config, e.g. the worlds and splits that ``make experiment``
writes under ``out/experiment``) the samples are built once and the hyperparameters
learned once per ``anneal_maxfun`` budget, with everything else as configured. Prints
per budget the log marginal likelihood reached, the likelihood evaluations it took, the
stage's wall time, the learned input-noise scale g and label-noise variance: equal
optima at a smaller budget mean the evaluations saved were spent for nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

from gpocc.blas import single_threaded_blas
from gpocc.config import load_config
from gpocc.gp.kernels import make_kernel
from gpocc.gp.train import learn_hyperparameters
from gpocc.io.inputs import read_inputs
from gpocc.samples.beams import build_samples


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("cases", nargs="+", help="BAG:CONFIG pairs")
    parser.add_argument("--budgets", default="60,20,0",
                        help="comma-separated anneal_maxfun values (default 60,20,0)")
    args = parser.parse_args()
    budgets = [int(b) for b in args.budgets.split(",")]
    single_threaded_blas()
    print("| input | " + " | ".join(f"anneal {b}: -LML, evaluations, s, g, noise"
                                      for b in budgets) + " |")
    print("|---|" + "---|" * len(budgets))
    for case in args.cases:
        bag, config_path = (Path(p) for p in case.split(":"))
        cfg = load_config(config_path)
        samples = build_samples(read_inputs([bag], cfg), cfg)
        model = cfg.model
        cells = []
        for budget in budgets:
            training = dataclasses.replace(model.training, anneal_maxfun=budget)
            started = time.perf_counter()
            result = learn_hyperparameters(
                make_kernel(model.kernel, model.hyperparameters),
                model.hyperparameters.noise_variance, samples, model.quadrature_level,
                training, cfg.seed)
            cells.append(f"{-result.log_marginal_likelihood:.2f}, {result.evaluations}, "
                         f"{time.perf_counter() - started:.1f}, "
                         f"{result.input_noise_scale:.2f}, {result.noise_variance:.3f}")
        print(f"| {bag} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
