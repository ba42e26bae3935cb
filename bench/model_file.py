"""Model files: their size and the time to write and load them, as ``gpocc`` writes them
(format 6) and with every array written whole and deflated (format 5's layout and writer).

Registered as the benchmark ``model-file`` (``python -m bench.run_bench --only model-file``).
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np

from .paths import INTEL
from .registry import Context, Result, Table, benchmark, require

#: Writes and loads of each file whose median the table gives.
REPEATS = 5


def write_whole(model, path: Path) -> None:
    """``model`` as format 5 wrote it: every array (the samples' own included) deflated
    at level 1, with :func:`gpocc.gp.model.write_model`'s metadata at format version 5."""
    from gpocc.gp.model import model_arrays, model_metadata, write_archive

    write_archive(path, {**model_metadata(model), "format_version": 5}, model_arrays(model))


def _median_seconds(fn, *args, repeats: int = REPEATS) -> float:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        fn(*args)
        times.append(time.perf_counter() - started)
    return statistics.median(times)


@benchmark("model-file", "Model files: size, write and load time")
def model_file(ctx: Context) -> Result:
    """The model of the whole Intel log (`configs/carmen_intel.yaml`) and the model of 16
    buildings of the city (`growth`'s build of 4 x 4 buildings at 0.1 m, no config; left
    out in a quick run): file size and median wall seconds of 5 writes and loads in this
    process, as `gpocc` writes it (format 6: the samples as their rows of the growth pool,
    positions, covariances and calibration points stored without compression) and with
    every array written whole and deflated at level 1 (format 5's layout and writer).
    Both files load the same arrays (checked)."""
    from gpocc.gp.model import load_model, model_arrays, write_model

    require(INTEL)
    models = [("Intel", ctx.intel_model())]
    if not ctx.quick:
        from .city import build_site

        models.append(("16 buildings", build_site(ctx, 4, 0.1).out / "model.npz"))
    rows = []
    for name, source in models:
        model = load_model(source)
        reference = model_arrays(model)
        for layout, writer in (("format 6 (gpocc)", write_model),
                               ("format 5 (all arrays whole, deflated)", write_whole)):
            path = ctx.work / f"model-file-{len(rows)}.npz"
            write_s = _median_seconds(writer, model, path)
            load_s = _median_seconds(load_model, path)
            loaded = model_arrays(load_model(path))
            if loaded.keys() != reference.keys() or not all(
                    np.array_equal(loaded[k], reference[k]) for k in reference):
                raise RuntimeError(f"{name}: the {layout} file loads other arrays")
            rows.append([name, f"{len(model.samples)}", layout,
                         f"{path.stat().st_size / 1e6:.1f}", f"{write_s:.2f}", f"{load_s:.2f}"])
    result = Result()
    result.add(Table(("model", "samples", "layout", "file MB", "write s", "load s"), rows))
    return result
