"""Compiled (C) against numpy expected NN kernels on real Intel neighbourhoods.

Run ``.venv/bin/python bench/bench_fused.py [MODEL.npz]``. Takes 20 neighbourhoods of
``model.neighbours`` samples (160) around random samples of a trained Intel model (or
trains nothing and uses ``configs/carmen_intel.yaml``'s samples with the model's default
kernel when no model is given), and reports the process (CPU) time per problem of the
expected training covariance K, of K with its gradients dK (what training evaluates), and
of the cross covariance to 100 queries, for both paths, with their largest difference.
Process time, not wall time, so that a busy machine distorts it less; one BLAS thread.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from gpocc.blas import single_threaded_blas
from gpocc.gp import expected as ex
from gpocc.gp.local import NeighbourIndex
from gpocc.gp.model import load_model

ROOT = Path(__file__).resolve().parents[1]
CARMEN = Path(os.environ.get("GPOCC_CARMEN_DIR", ROOT.parent / "shared" / "data" / "carmen"))


def _problems(model_path: str | None):
    if model_path:
        model = load_model(model_path)
        return model.kernel, model.samples, model.level, model.config.model.neighbours
    from gpocc.config import load_config
    from gpocc.gp.kernels import make_kernel
    from gpocc.io.inputs import read_inputs
    from gpocc.samples.beams import build_samples

    config = load_config(ROOT / "configs" / "carmen_intel.yaml")
    samples = build_samples(read_inputs([CARMEN / "intel.gfs.log"], config), config)
    kernel = make_kernel(config.model.kernel, config.model.hyperparameters)
    return kernel, samples, config.model.quadrature_level, config.model.neighbours


def main() -> None:
    kernel, samples, level, neighbours = _problems(sys.argv[1] if len(sys.argv) > 1 else None)
    index = NeighbourIndex(samples)
    rng = np.random.default_rng(0)
    problems = [index.problem(samples.means[rng.integers(len(samples))], neighbours).samples
                for _ in range(20)]
    queries = rng.uniform(-0.5, 0.5, (100, 2))
    pairs = np.mean([ex.same_scan_pairs(p.covariances, p.scan_ids, p.pose_factors)[0].size
                     for p in problems])

    def run(what: str, backend: str):
        out = []
        for p in problems:
            if what == "cross":
                out.append(ex.expected_kernel_cross(kernel, queries, p.means, p.covariances,
                                                    level, backend=backend))
                continue
            r = ex.expected_kernel_matrix(kernel, p.means, p.covariances, level,
                                          scan_ids=p.scan_ids, pose_factors=p.pose_factors,
                                          with_gradient=what == "K+dK", backend=backend)
            out.append(r[1] if what == "K+dK" else r)
        return out

    print(f"{len(problems)} problems of {neighbours} samples, level {level}, "
          f"{pairs:.0f} same-scan pairs each on average")
    print(f"{'':6} {'numpy ms':>9} {'C ms':>9} {'speed-up':>9} {'max |diff|':>11}")
    with single_threaded_blas():
        for what in ("K", "K+dK", "cross"):
            times, results = {}, {}
            for fused in (False, True):
                backend = "compiled" if fused else "numpy"
                ex._NODE_CACHE.clear()
                run(what, backend)  # compile / warm up (not timed)
                ex._NODE_CACHE.clear()
                start = time.process_time()
                results[fused] = run(what, backend)
                times[fused] = 1e3 * (time.process_time() - start) / len(problems)
            diff = max(float(np.abs(a - b).max())
                       for a, b in zip(results[False], results[True], strict=True))
            print(f"{what:6} {times[False]:9.2f} {times[True]:9.2f} "
                  f"{times[False] / times[True]:8.1f}x {diff:11.1e}")


if __name__ == "__main__":
    main()
