"""Fingerprints of what gpocc computes, for checking that a change alters no result."""

from __future__ import annotations

import hashlib

import numpy as np

from .harness import gpocc
from .paths import FREIBURG, FREIBURG_CONFIG, INTEL
from .registry import Context, Result, Table, benchmark, require


def digest(*arrays: np.ndarray) -> str:
    """The first 16 hex digits of the SHA-256 of the arrays' dtypes, shapes and bytes."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


@benchmark("fingerprints", "Fingerprints of samples, grid, model and map")
def fingerprints(ctx: Context) -> Result:
    """SHA-256 digests of the Freiburg 079 training samples and log-odds grid (0.1 m), of
    the Intel model's arrays and learned parameters, and of the decoded rasters of its map
    at 0.1 m. Two pages with equal digests computed the same results bit for bit; a
    change that should not alter results (a refactor, a speed-up) keeps them."""
    from gpocc.baselines.grid import default_grid_spec, occupancy_grid
    from gpocc.config import load_config
    from gpocc.gp.model import load_model, model_arrays
    from gpocc.io.inputs import read_inputs
    from gpocc.io.rasters import read_raster
    from gpocc.samples.beams import build_samples

    require(FREIBURG, INTEL)
    rows = []
    cfg = load_config(FREIBURG_CONFIG)
    batches = read_inputs([FREIBURG], cfg)
    s = build_samples(batches, cfg)
    spec = default_grid_spec(batches, cfg, 0.1)
    grid = occupancy_grid(batches, cfg, spec)
    rows.append(["Freiburg samples", f"{len(s)} samples",
                 digest(s.means, s.covariances, s.labels, s.scan_ids, s.pose_factors)])
    rows.append(["Freiburg grid", f"{spec.width} x {spec.height}",
                 digest(grid.log_odds, np.array(spec.bounds))])
    model_path = ctx.intel_model()
    model = load_model(model_path)
    # The model's arrays as loaded, in format 5's layout and name order (whatever layout
    # the file stores them in): equal digests, equal models.
    stored = model_arrays(model)
    arrays = [stored[k] for k in sorted(stored)]
    rows.append(["Intel model arrays", f"{len(model.samples)} samples", digest(*arrays)])
    learned = np.array([*np.asarray(model.kernel.theta, float), model.noise_variance,
                        model.input_noise_scale, model.classifier.offset,
                        model.classifier.extra_variance, model.classifier.temperature])
    lml = model.training.get("log_marginal_likelihood", float("nan"))
    rows.append(["Intel learned parameters", f"LML {lml:.6f}", digest(learned)])
    out = ctx.work / "fingerprint-map"
    gpocc("map", model_path, "--resolution", "0.1", "--out", out, "--force")
    for layer in ("probability", "variance", "class"):
        values, layer_spec, _ = read_raster(out / f"{layer}.tif")
        rows.append([f"Intel map {layer}", f"{layer_spec.width} x {layer_spec.height}",
                     digest(values)])
    result = Result()
    result.add(Table(("what", "size", "digest"), rows))
    return result
