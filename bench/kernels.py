"""Expected kernels: the compiled loops against the numpy quadrature on real
neighbourhoods, and the quadrature level's accuracy and time on a synthetic problem."""

from __future__ import annotations

import time

import numpy as np

from .paths import INTEL
from .registry import Context, Result, Table, benchmark, require


def _cold_cache() -> None:
    """Empty the expected kernels' node-set cache, so that no backend reuses another's."""
    from gpocc.gp import expected as ex

    ex._NODE_CACHE.clear()


@benchmark("expected-kernels", "Expected kernels: compiled loops against numpy")
def expected_kernels(ctx: Context) -> Result:
    """Process (CPU) time per local problem, on one BLAS thread, of the expected training
    covariance K, of K with its gradients dK (what training evaluates) and of the cross
    covariance to 100 queries, through the `compiled` and the `numpy` backends
    (`model.backend`), with their largest difference. The problems are
    `model.neighbours` samples around random samples of the Intel model (20 problems; 5
    in a quick run)."""
    from gpocc.blas import single_threaded_blas
    from gpocc.gp import expected as ex
    from gpocc.gp.local import NeighbourIndex
    from gpocc.gp.model import load_model

    require(INTEL)
    model = load_model(ctx.intel_model())
    kernel, samples, level = model.kernel, model.samples, model.level
    neighbours = model.config.model.neighbours
    index = NeighbourIndex(samples)
    rng = np.random.default_rng(0)
    count = 5 if ctx.quick else 20
    problems = [index.problem(samples.means[rng.integers(len(samples))], neighbours).samples
                for _ in range(count)]
    queries = rng.uniform(-0.5, 0.5, (100, 2))
    pairs = np.mean([ex.same_scan_pairs(p.covariances, p.scan_ids, p.pose_factors)[0].size
                     for p in problems])

    def run(what: str, backend: str) -> list[np.ndarray]:
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

    rows = []
    with single_threaded_blas():
        for what in ("K", "K+dK", "cross"):
            times, results = {}, {}
            for backend in ("numpy", "compiled"):
                _cold_cache()
                run(what, backend)  # warm up (not timed)
                _cold_cache()
                start = time.process_time()
                results[backend] = run(what, backend)
                times[backend] = 1e3 * (time.process_time() - start) / len(problems)
            diff = max(float(np.abs(a - b).max())
                       for a, b in zip(results["numpy"], results["compiled"], strict=True))
            rows.append([what, f"{times['numpy']:.2f}", f"{times['compiled']:.2f}",
                         f"{times['numpy'] / times['compiled']:.1f}x", f"{diff:.1e}"])
    result = Result()
    result.add(Table(("matrix", "numpy ms", "compiled ms", "speed-up", "max abs difference"),
                     rows),
               f"{len(problems)} problems of {neighbours} samples, quadrature level {level}, "
               f"{pairs:.0f} same-scan pairs each on average.")
    return result


def synthetic_problem(n: int, seed: int):
    """(means, covariances, scan_ids, pose_factors) of a local problem shaped like real
    ones: ``n`` samples within ~1 m of the origin from a dozen scans whose sensors stand
    1-8 m away, with per-scan pose errors (so samples of one scan are correlated) and
    range/bearing noise; sqrt(trace S) spans about 0.05-0.3 m."""
    rng = np.random.default_rng(seed)
    scans = 12
    scan_ids = rng.integers(0, scans, n)
    means = rng.uniform(-1.0, 1.0, (n, 2))
    angle = rng.uniform(0, 2 * np.pi, scans)
    dist = rng.uniform(1.0, 8.0, scans)
    sensor = np.stack([dist * np.cos(angle), dist * np.sin(angle)], axis=1)[scan_ids]
    trans_sd = rng.uniform(0.03, 0.15, scans)[scan_ids]
    yaw_sd = np.deg2rad(rng.uniform(0.3, 1.5, scans))[scan_ids]
    beam = means - sensor
    r = np.linalg.norm(beam, axis=1)
    # Pose factor: translation moves the point 1:1, yaw moves it along the lever arm.
    factors = np.zeros((n, 2, 3))
    factors[:, 0, 0] = factors[:, 1, 1] = trans_sd
    factors[:, 0, 2] = -beam[:, 1] * yaw_sd
    factors[:, 1, 2] = beam[:, 0] * yaw_sd
    along = beam / r[:, None]
    across = np.stack([-along[:, 1], along[:, 0]], axis=1)
    noise = (0.02**2 * np.einsum("ni,nj->nij", along, along)
             + ((r * np.deg2rad(0.1)) ** 2)[:, None, None]
             * np.einsum("ni,nj->nij", across, across))
    covs = factors @ factors.transpose(0, 2, 1) + noise
    return means, covs, scan_ids, factors


def _best_of(fn, repeat: int) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


@benchmark("quadrature", "Expected-kernel quadrature: level against accuracy and time")
def quadrature(ctx: Context) -> Result:
    """The expected-kernel matrix of a synthetic local problem of 200 samples (100 in a
    quick run; see `bench/kernels.py: synthetic_problem`) at each Gauss-Hermite level: the
    NN kernel (weight variance 4 /m^2) against its level-10 result, the SE kernel (length
    scale 0.5 m) against Girard's closed form, which is exact for independent and
    correlated (same-scan) pairs. Times are the best of 3 wall-clock runs."""
    from gpocc.gp.expected import expected_kernel_matrix, expected_se_closed_form_pairs
    from gpocc.gp.kernels import NeuralNetworkKernel, SquaredExponentialKernel

    n = 100 if ctx.quick else 200
    levels = (1, 2, 3) if ctx.quick else (1, 2, 3, 4, 5, 6, 8)
    repeat = 3
    means, covs, scan_ids, factors = synthetic_problem(n, 0)
    i, j = np.triu_indices(n, 1)
    same = scan_ids[i] == scan_ids[j]
    kw = dict(scan_ids=scan_ids, pose_factors=factors)
    nn = NeuralNetworkKernel(1.0, 1.0, (4.0, 4.0))
    se = SquaredExponentialKernel(1.0, (0.5, 0.5))
    _, ref = _best_of(lambda: expected_kernel_matrix(nn, means, covs, 10, **kw), 1)
    cross = np.where(same[:, None, None], factors[i] @ factors[j].transpose(0, 2, 1), 0.0)
    exact = expected_se_closed_form_pairs(se, means[i], covs[i], means[j], covs[j], cross)
    scale = np.linalg.norm(ref)
    rows = []
    for level in levels:
        t_k, k = _best_of(lambda lv=level: expected_kernel_matrix(nn, means, covs, lv, **kw),
                          repeat)
        t_g, _ = _best_of(lambda lv=level: expected_kernel_matrix(
            nn, means, covs, lv, with_gradient=True, **kw), repeat)
        err = np.abs(k - ref)[i, j]
        t_se, kse = _best_of(
            lambda lv=level: expected_kernel_matrix(se, means, covs, lv, **kw), repeat)
        err_se = np.abs(kse[i, j] - exact)
        rows.append([str(level), f"{1e3 * t_k:.1f}", f"{1e3 * t_g:.1f}",
                     f"{err[~same].max():.1e}", f"{err[same].max():.1e}",
                     f"{np.linalg.norm(k - ref) / scale:.1e}", f"{1e3 * t_se:.1f}",
                     f"{err_se[~same].max():.1e}", f"{err_se[same].max():.1e}"])
    result = Result()
    result.add(Table(("level", "NN K ms", "NN K+dK ms", "NN error, other scans",
                      "NN error, same scan", "NN relative Frobenius", "SE K ms",
                      "SE error, other scans", "SE error, same scan"), rows),
               f"{n} samples, {int(same.sum())} same-scan pairs; errors are the largest "
               "absolute difference over the matrix's entries.")
    return result
