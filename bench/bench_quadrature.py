"""Quadrature level vs accuracy and time of the expected-kernel matrix.

A synthetic local problem shaped like real ones: N samples within ~2 m of the origin from a
dozen scans whose sensors stand 1-8 m away, with per-scan pose errors (so samples of one scan
are correlated) and range/bearing noise; sqrt(trace S) spans about 0.05-0.3 m. The NN
kernel (weight variance 4 /m^2) is compared with its level-10 result; the SE kernel
(length scale 0.5 m) with Girard's closed form, which is exact for both independent and
correlated pairs. Run: ``python bench/bench_quadrature.py [--n 200] [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from gpocc.gp.expected import (
    expected_kernel_matrix,
    expected_se_closed_form_pairs,
)
from gpocc.gp.kernels import NeuralNetworkKernel, SquaredExponentialKernel


def make_problem(n: int, seed: int):
    """(means, covariances, scan_ids, pose_factors) of a realistic local problem."""
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


def timed(fn, repeat: int) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--levels", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6, 8])
    args = parser.parse_args()

    means, covs, scan_ids, factors = make_problem(args.n, args.seed)
    sqrt_trace = np.sqrt(np.trace(covs, axis1=1, axis2=2))
    i, j = np.triu_indices(args.n, 1)
    same = scan_ids[i] == scan_ids[j]
    print(f"N={args.n}  scans={len(np.unique(scan_ids))}  correlated pairs={same.sum()}  "
          f"sqrt(trace S) {sqrt_trace.min():.3f}-{sqrt_trace.max():.3f} m "
          f"(median {np.median(sqrt_trace):.3f})")
    kw = dict(scan_ids=scan_ids, pose_factors=factors)

    nn = NeuralNetworkKernel(1.0, 1.0, (4.0, 4.0))
    se = SquaredExponentialKernel(1.0, (0.5, 0.5))
    t_ref, ref = timed(lambda: expected_kernel_matrix(nn, means, covs, 10, **kw), 1)
    cross = np.where(same[:, None, None], factors[i] @ factors[j].transpose(0, 2, 1), 0.0)
    exact = expected_se_closed_form_pairs(se, means[i], covs[i], means[j], covs[j], cross)
    print(f"NN reference: level 10, {t_ref:.2f} s.  SE reference: Girard closed form.")
    print("max |error| over entries: 'indep' = pairs from different scans, 'corr' = same scan")
    header = (f"{'level':>5} {'NN K ms':>8} {'NN K+dK ms':>10} {'NN indep':>9} {'NN corr':>9} "
              f"{'NN diag':>9} {'NN rel F':>9} {'SE K ms':>8} {'SE indep':>9} {'SE corr':>9}")
    print(header)
    print("-" * len(header))
    scale = np.linalg.norm(ref)
    for level in args.levels:
        t_k, k = timed(lambda lv=level: expected_kernel_matrix(nn, means, covs, lv, **kw),
                       args.repeat)
        t_g, _ = timed(lambda lv=level: expected_kernel_matrix(
            nn, means, covs, lv, with_gradient=True, **kw), args.repeat)
        err = np.abs(k - ref)[i, j]
        t_se, kse = timed(lambda lv=level: expected_kernel_matrix(se, means, covs, lv, **kw),
                          args.repeat)
        err_se = np.abs(kse[i, j] - exact)
        print(f"{level:>5} {1e3 * t_k:>8.1f} {1e3 * t_g:>10.1f} {err[~same].max():>9.2e} "
              f"{err[same].max():>9.2e} {np.abs(np.diag(k) - np.diag(ref)).max():>9.2e} "
              f"{np.linalg.norm(k - ref) / scale:>9.2e} {1e3 * t_se:>8.1f} "
              f"{err_se[~same].max():>9.2e} {err_se[same].max():>9.2e}")
    t0, _ = timed(lambda: expected_kernel_matrix(nn, means, np.zeros_like(covs), 3), args.repeat)
    print(f"no input noise (plain kernel): NN K {1e3 * t0:.1f} ms")


if __name__ == "__main__":
    main()
