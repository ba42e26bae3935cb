"""The method paper's real-data claim: a map before loop closure is more uncertain and blurrier.

Data: ``intel_poses_odom_vs_corrected.txt`` (one row per FLASER line of intel.gfs.log:
raw wheel odometry and GMapping-corrected poses).

* After loop closure: the corrected poses with the Intel config's small covariance
  (3 cm, 0.5 deg).
* Before loop closure: a localiser that is corrected every ``CORRECTION_M`` metres of
  travel and dead-reckons in between: pose(t) = corrected(t_c) composed with the
  odometry increment from t_c to t, t_c the last correction. Its covariance grows
  linearly with the distance d travelled since t_c, ``diag(k_xy d, k_xy d, k_yaw d)``,
  with k_xy and k_yaw fitted to the log itself (mean squared dead-reckoning error per
  metre against the corrected poses), so the covariance is honest on average.

Both are written as MCAP bags with per-scan covariances and mapped with the same GP
(input noise on). Reported per map over the cells both cover: mean latent variance,
mean binary entropy of p (blur: a sharp map is near 0 or 1), share of cells with p in
[0.35, 0.65], and the mean gradient magnitude of p (edge sharpness, 1/m).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .paths import INTEL_CONFIG

CORRECTION_M = 10.0


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SE(2) composition a (+) b of (N, 3) poses."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack((a[:, 0] + c * b[:, 0] - s * b[:, 1],
                            a[:, 1] + s * b[:, 0] + c * b[:, 1],
                            np.angle(np.exp(1j * (a[:, 2] + b[:, 2])))))


def inverse(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack((-c * a[:, 0] - s * a[:, 1], s * a[:, 0] - c * a[:, 1], -a[:, 2]))


def before_loop_closure(odom: np.ndarray, corrected: np.ndarray,
                        every_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Dead-reckoned poses (S, 3) reset to the corrected pose every ``every_m`` metres,
    and the distance (S,) travelled since the last reset."""
    step = np.linalg.norm(np.diff(odom[:, :2], axis=0), axis=1)
    travelled = np.concatenate(([0.0], np.cumsum(step)))
    anchor = np.floor(travelled / every_m).astype(int)
    first = np.searchsorted(anchor, anchor, side="left")  # index of each segment's start
    increment = compose(inverse(odom[first]), odom)
    return compose(corrected[first], increment), travelled - travelled[first]


def map_stats(folder: Path, mask: np.ndarray | None = None) -> tuple[dict, np.ndarray]:
    from gpocc.io.rasters import read_raster

    p, spec, _ = read_raster(folder / "probability.tif")
    v, _, _ = read_raster(folder / "variance.tif")
    p, v = p.astype(float), v.astype(float)
    ok = np.isfinite(p) & np.isfinite(v)
    if mask is not None:
        ok &= mask
    q = np.clip(p, 1e-9, 1 - 1e-9)
    entropy = -(q * np.log2(q) + (1 - q) * np.log2(1 - q))
    gy, gx = np.gradient(np.where(np.isfinite(p), p, 0.5), spec.resolution)
    grad = np.hypot(gx, gy)
    return {"cells": int(ok.sum()), "mean_variance": float(v[ok].mean()),
            "mean_entropy_bits": float(entropy[ok].mean()),
            "unsure_share": float(((p[ok] >= 0.35) & (p[ok] <= 0.65)).mean()),
            "mean_gradient_per_m": float(grad[ok].mean())}, ok


def figure(path: Path, folders: dict[str, Path]) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from gpocc.io.rasters import read_raster

    fig = Figure(figsize=(12, 11), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 2)
    for col, (name, folder) in enumerate(folders.items()):
        p, spec, _ = read_raster(folder / "probability.tif")
        v, _, _ = read_raster(folder / "variance.tif")
        x0, y0, x1, y1 = spec.bounds
        for row, (layer, cmap, title) in enumerate(((p, "gray_r", "p(occupied)"),
                                                    (v, "viridis", "latent variance"))):
            ax = axes[row, col]
            im = ax.imshow(layer, extent=(x0, x1, y0, y1), cmap=cmap,
                           vmin=0 if row == 0 else None, vmax=1 if row == 0 else None)
            ax.set_title(f"{name}: {title}")
            fig.colorbar(im, ax=ax, shrink=0.7)
    fig.savefig(path, format="png")


def loop_closure_experiment(work: Path, carmen: Path, gpocc: Callable[..., str]) -> str:
    import yaml

    from gpocc.config import load_config
    from gpocc.io.bags import write_bag
    from gpocc.io.inputs import read_inputs

    log, table = carmen / "intel.gfs.log", carmen / "intel_poses_odom_vs_corrected.txt"
    if not (log.is_file() and table.is_file()):
        return f"skipped: {log} or {table} missing"
    work.mkdir(parents=True, exist_ok=True)
    rows = np.loadtxt(table, comments="#")
    odom, corrected = rows[:, 2:5], rows[:, 5:8]
    config = load_config(INTEL_CONFIG)
    (batch,) = read_inputs([log], config)
    if batch.n_scans != len(rows) or not np.allclose(batch.poses[:, :2], corrected[:, :2],
                                                     atol=1e-3):
        return "skipped: the pose table does not match intel.gfs.log line by line"
    before, since = before_loop_closure(odom, corrected, CORRECTION_M)
    err = before - corrected
    err[:, 2] = np.angle(np.exp(1j * err[:, 2]))
    moving = since > 0.5
    k_xy = float(np.mean((err[moving, 0] ** 2 + err[moving, 1] ** 2) / 2 / since[moving]))
    k_yaw = float(np.mean(err[moving, 2] ** 2 / since[moving]))
    sensor = config.sensors[0]
    after_cov = np.broadcast_to(sensor.pose_covariance_matrix, (batch.n_scans, 3, 3))
    before_cov = after_cov + np.einsum("s,ij->sij", since, np.diag([k_xy, k_xy, k_yaw]))
    cfg = yaml.safe_load((INTEL_CONFIG).read_text())
    entry = cfg["sensors"][0]
    entry.pop("inputs", None)
    entry.update(scan_topic="/intel/scan", pose_topic="/intel/pose",
                 override_pose_covariance=False)
    cfg_path = work / "intel-bag.yaml"
    cfg_path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    stats, folders = {}, {}
    for name, poses, cov in (("after loop closure", corrected, after_cov),
                             ("before loop closure", before, before_cov)):
        slug = name.split()[0]
        bag = work / f"{slug}.mcap"
        b = dataclasses.replace(batch, poses=poses.copy(), pose_covariances=np.array(cov),
                                has_pose_covariance=True)
        write_bag(bag, [b], [("/intel/scan", "/intel/pose")], "mcap", force=True)
        gpocc("train", bag, "--config", cfg_path, "--out", work / f"{slug}.npz", "--force")
        folders[name] = work / slug
    # The same window for both maps: the corrected map's.
    gpocc("map", work / "after.npz", "--resolution", "0.1", "--out", work / "after", "--force")
    from gpocc.io.rasters import read_raster

    _, spec, _ = read_raster(work / "after" / "probability.tif")
    bounds = [f"{v:.3f}" for v in spec.bounds]
    gpocc("map", work / "before.npz", "--resolution", "0.1", "--out", work / "before",
          "--force", "--bounds", *bounds)
    _, both_a = map_stats(folders["after loop closure"])
    _, both_b = map_stats(folders["before loop closure"])
    common = both_a & both_b
    for name, folder in folders.items():
        stats[name], _ = map_stats(folder, common)
    figure(work / "loop_closure.png", folders)
    lines = [f"Dead-reckoning drift fitted on the log: k_xy = {k_xy:.4g} m^2/m, "
             f"k_yaw = {k_yaw:.4g} rad^2/m (correction every {CORRECTION_M:g} m; largest "
             f"position error {np.hypot(err[:, 0], err[:, 1]).max():.2f} m).", "",
             "| poses | cells | mean latent variance | mean entropy (bits) | "
             "p in [0.35, 0.65] | mean gradient of p (1/m) |", "|---|---|---|---|---|---|"]
    for name, s in stats.items():
        lines.append(f"| {name} | {s['cells']} | {s['mean_variance']:.4f} | "
                     f"{s['mean_entropy_bits']:.3f} | {100 * s['unsure_share']:.1f}% | "
                     f"{s['mean_gradient_per_m']:.3f} |")
    lines += ["", f"Figure: {work / 'loop_closure.png'}"]
    return "\n".join(lines)


def near_data_stats(work: Path, names: list[str], within_m: float = 0.3) -> dict[str, dict]:
    """map_stats of each map folder ``work/<name>`` over the cells within ``within_m`` of
    a training sample of ``work/after.npz`` and covered by every map, plus the mean
    latent variance relative to the model's mean prior variance over a 1 m block
    (latent variances of models with different signal variances are not comparable)."""
    from scipy.spatial import cKDTree

    from gpocc.gp.model import load_model
    from gpocc.io.rasters import read_raster

    after = load_model(work / "after.npz")
    p, spec, _ = read_raster(work / names[0] / "probability.tif")
    rows, cols = np.indices(p.shape)
    x0, _, _, y1 = spec.bounds
    xy = np.column_stack((x0 + (cols.ravel() + 0.5) * spec.resolution,
                          y1 - (rows.ravel() + 0.5) * spec.resolution))
    distance, _ = cKDTree(after.samples.means).query(xy)
    common = (distance < within_m).reshape(p.shape)
    for name in names:
        common &= map_stats(work / name)[1]
    offsets = np.linspace(-0.5, 0.5, 21)
    block = np.array([(a, b) for a in offsets for b in offsets])
    out = {}
    for name in names:
        stats, _ = map_stats(work / name, common)
        prior = float(load_model(work / f"{name}.npz").kernel.diag(block).mean())
        stats["mean_variance_over_prior"] = stats["mean_variance"] / prior
        out[name] = stats
    return out


if __name__ == "__main__":
    import sys

    folder = Path(sys.argv[1])
    for map_name, values in near_data_stats(folder, sys.argv[2:]).items():
        print(map_name, {k: round(v, 4) for k, v in values.items()})
