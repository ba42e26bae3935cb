"""A corpus of bad inputs run through the real CLI (``python -m gpocc`` in a subprocess).

Each case must give: a non-zero exit, exactly one stderr line with ``error:`` that names
the file at fault, no traceback, and nothing left at ``--out`` (no temporaries either).
Classes (issue 13): unbounded sizes, OS errors, tampered model files, config edge cases
(races and signals need two processes or a signal: tests/cli/test_faults.py).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from gpocc.config import Config, ModelConfig, TrainingConfig
from gpocc.gp.model import build_model, save_model
from gpocc.io.bags import write_bag
from gpocc.io.scans import ScanBatch
from gpocc.samples.coverage import sample_coverage
from gpocc.samples.sampleset import SampleSet


def _room() -> SampleSet:
    rng = np.random.default_rng(1)
    t = np.linspace(0, 1, 30, endpoint=False)
    walls = np.vstack([np.column_stack([-2 + 4 * t, np.full_like(t, s)]) for s in (-1.5, 1.5)])
    free = rng.uniform([-1.8, -1.3], [1.8, 1.3], size=(80, 2))
    means = np.vstack([walls, free])
    n = len(means)
    return SampleSet(means, np.einsum("n,ij->nij", np.full(n, 0.001), np.eye(2)),
                     np.concatenate([np.ones(len(walls)), -np.ones(len(free))]),
                     np.arange(n, dtype=np.int64), np.zeros((n, 2, 3)),
                     np.zeros(n, dtype=np.int16))


def _batch(ranges: float, range_max: float) -> ScanBatch:
    n_scans, n_beams = 3, 8
    return ScanBatch(
        sensor="robot", source="memory", stamps=np.arange(n_scans) * 0.1 + 100.0,
        angles=np.linspace(-1.0, 1.0, n_beams), ranges=np.full((n_scans, n_beams), ranges),
        poses=np.zeros((n_scans, 3)),
        pose_covariances=np.broadcast_to(np.diag([1e-3, 1e-3, 1e-4]), (n_scans, 3, 3)).copy(),
        range_min=0.1, range_max=range_max,
    )


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> Path:
    """The inputs the cases refer to by name."""
    root = tmp_path_factory.mktemp("corpus")
    room = _room()
    model = build_model(room, Config(model=ModelConfig(
        neighbours=40, training=TrainingConfig(learn=False, patches=1, patch_size=30))),
        coverage=sample_coverage(room.means))
    save_model(model, root / "good.npz")
    write_bag(root / "far.mcap", [_batch(1e6, 1e7)], [("/scan", "/pose")], "mcap")
    write_bag(root / "huge.mcap", [_batch(1e20, 1e30)], [("/scan", "/pose")], "mcap")
    write_bag(root / "ok.mcap", [_batch(3.0, 30.0)], [("/scan", "/pose")], "mcap")
    (root / "binary.yaml").write_bytes(bytes(range(256)) * 4)
    (root / "seed_float.yaml").write_text("seed: 1e23\n")
    (root / "huge_margin.yaml").write_text("map:\n  margin_m: 1.0e+9\n")
    (root / "seed_huge.yaml").write_text("seed: 100000000000000000000000\n")
    np.save(root / "bare_array.npy", np.zeros(3))
    (root / "bare_array.npy").rename(root / "bare_array.npz")  # np.load gives an array
    (root / "a_file").write_text("not a folder\n")
    (root / "user_dir").mkdir()
    os.mkfifo(root / "fifo")  # no writer: reading it would block for ever
    (root / "ragged_cov.yaml").write_text(
        "sensors:\n  - name: a\n    pose_covariance: [[0.01, 0, 0], [0, 0.01], [0, 0, 0.001]]\n")
    (root / "box_0.yaml").write_text("model:\n  training:\n    log_bounds_width: 0\n")
    (root / "box_1000.yaml").write_text("model:\n  training:\n    log_bounds_width: 1000\n")
    (root / "alpha_huge.yaml").write_text("samples:\n  unscented: {alpha: 1.0e+300}\n")
    (root / "signal_huge.yaml").write_text(
        "model:\n  hyperparameters:\n    signal_variance: 1.0e+300\n")
    # ROBOTLASER1: type start fov res max_range accuracy mode n r.. m rem.. laser pose,
    # robot pose, tv rv, safety x2, turn axis, ipc stamp, host, logger stamp.
    line = ("ROBOTLASER1 0 {start} 3.14 {res} 81.9 0.01 0 5 1 1 1 1 1 0 "
            "0 0 0 0 0 0 0 0 0.1 0.1 0.1 {t} host {t}\n")
    (root / "angles_nan.log").write_text(
        "".join(line.format(start=-1.57, res="nan", t=100 + i) for i in range(5)))
    # A second laser's fan from line 4 on, 2 rad round: no one layout holds both.
    (root / "angles_change.log").write_text(
        "".join(line.format(start=-1.57 if i < 3 else 0.5, res=0.01, t=100 + i)
                for i in range(5)))
    (root / "neighbours_huge.yaml").write_text("model:\n  neighbours: 100000\n")
    with np.load(root / "good.npz") as data:  # metadata nested deeper than json recurses
        arrays = {k: data[k] for k in data.files}
    arrays["metadata"] = np.frombuffer(b"[" * 100000 + b"]" * 100000, np.uint8)
    np.savez(root / "deep_json.npz", **arrays)
    (root / "user_dir" / "notes.txt").write_text("mine\n")
    for name, edit in TAMPERING.items():
        _tamper(root / "good.npz", root / f"{name}.npz", edit)
    return root


def _tamper(src: Path, dst: Path, edit: Callable[[dict, dict], None]) -> None:
    with np.load(src) as data:
        arrays = dict(data)
    meta = json.loads(bytes(arrays.pop("metadata")).decode())
    edit(meta, arrays)
    np.savez(dst, metadata=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays)


def _set(path: str, value) -> Callable[[dict, dict], None]:
    def edit(meta: dict, arrays: dict) -> None:
        *parents, last = path.split(".")
        node = meta
        for key in parents:
            node = node[key]
        if value is _DELETE:
            del node[last]
        else:
            node[last] = value
    return edit


def _arrays(fn: Callable[[dict], None]) -> Callable[[dict, dict], None]:
    return lambda meta, arrays: fn(arrays)


_DELETE = object()

TAMPERING: dict[str, Callable[[dict, dict], None]] = {
    "no_kernel": _set("kernel", _DELETE),
    "unknown_parameter": _set("kernel.smoothness", 2.0),
    "nan_hyperparameter": _set("kernel.signal_variance", math.nan),
    "empty_classifier": _set("classifier", {}),
    "bad_kernel_name": _set("kernel_name", "rbf"),
    "lengths_disagree": _arrays(lambda a: a.update(labels=a["labels"][:-3])),
    "nan_means": _arrays(lambda a: a["means"].__setitem__((0, 0), np.nan)),
    "zero_samples": _arrays(lambda a: a.update({k: v[:0] for k, v in a.items()})),
    "one_d_means": _arrays(lambda a: a.update(means=a["means"][:, 0])),
    "text_labels": _arrays(lambda a: a.update(labels=np.array(["x"] * len(a["labels"])))),
    "missing_array": _arrays(lambda a: a.pop("pose_factors")),
    "huge_extent": _arrays(lambda a: a.update(means=a["means"] * 5e6)),
    # The coverage raster behind the nodata mask is model data like any other.
    "coverage_nan_cell": _set("coverage.cell_m", math.nan),
    "coverage_negative_cell": _set("coverage.cell_m", -0.2),
    "coverage_huge_shape": _set("coverage.shape", [100000, 100000]),
    "coverage_truncated_bits": _arrays(lambda a: a.update(coverage=a["coverage"][:1])),
    "coverage_bits_missing": _arrays(lambda a: a.pop("coverage")),
}

# (case id, argv with {root} placeholders, what the error line must name (parts separated
# by a backquote), the --out that must not appear)
CASES = [
    # Unbounded sizes
    ("map-fine-resolution", ["map", "{root}/good.npz", "--resolution", "0.00002",
                             "--out", "{root}/out"], "good.npz", "out"),
    ("map-huge-bounds", ["map", "{root}/good.npz", "--resolution", "0.1", "--bounds",
                         "-1e7", "-1e7", "1e7", "1e7", "--out", "{root}/out"], "good.npz", "out"),
    ("map-tiny-resolution", ["map", "{root}/good.npz", "--resolution", "1e-300",
                             "--out", "{root}/out"], "1e-300", "out"),
    ("map-model-spans-1e7-m", ["map", "{root}/huge_extent.npz", "--resolution", "0.1",
                               "--out", "{root}/out"], "huge_extent.npz", "out"),
    ("simulate-fine-resolution", ["simulate", "--resolution", "1e-5", "--out", "{root}/out"],
     "truth raster", "out"),
    ("split-free-per-beam", ["split", "{root}/ok.mcap", "--every", "2", "--free-per-beam",
                             "100000000", "--out", "{root}/out"], "ok.mcap", "out"),
    ("train-ranges-1e6", ["train", "{root}/far.mcap", "--out", "{root}/out.npz"],
     "far.mcap", "out.npz"),
    ("train-ranges-1e20", ["train", "{root}/huge.mcap", "--out", "{root}/out.npz"],
     "huge.mcap", "out.npz"),
    ("grid-huge-bounds", ["grid", "{root}/ok.mcap", "--resolution", "0.001", "--bounds",
                          "-1e4", "-1e4", "1e4", "1e4", "--out", "{root}/out"], "grid", "out"),
    # A malformed address (no port) is refused by Dask with a ValueError.
    ("map-scheduler-no-port", ["map", "{root}/good.npz", "--resolution", "0.3",
                               "--scheduler", "not-an-address", "--out", "{root}/out"],
     "not-an-address", "out"),
    # OS errors
    ("map-out-under-a-file", ["map", "{root}/good.npz", "--resolution", "0.3",
                              "--out", "{root}/a_file/out"], "a_file", "a_file/out"),
    ("train-out-existing-dir-force", ["train", "{root}/ok.mcap", "--out", "{root}/user_dir",
                                      "--force"], "user_dir", None),
    ("map-force-over-user-files", ["map", "{root}/good.npz", "--resolution", "0.3",
                                   "--out", "{root}/user_dir", "--force"], "user_dir", None),
    # Config edge cases
    ("config-binary", ["train", "{root}/ok.mcap", "--config", "{root}/binary.yaml",
                       "--out", "{root}/out.npz"], "binary.yaml", "out.npz"),
    ("config-seed-1e23", ["train", "{root}/ok.mcap", "--config", "{root}/seed_float.yaml",
                          "--out", "{root}/out.npz"], "seed_float.yaml", "out.npz"),
    # A margin of 1e9 m passed validation and failed only after training, naming the size.
    ("config-huge-margin", ["build", "{root}/ok.mcap", "--config", "{root}/huge_margin.yaml",
                            "--resolution", "0.3", "--out", "{root}/out"],
     "huge_margin.yaml`map.margin_m", "out"),
    ("config-seed-huge", ["train", "{root}/ok.mcap", "--config", "{root}/seed_huge.yaml",
                          "--out", "{root}/out.npz"], "seed_huge.yaml", "out.npz"),
    ("train-negative-seed", ["train", "{root}/ok.mcap", "--seed", "-1",
                             "--out", "{root}/out.npz"], "--seed", "out.npz"),
    ("map-npy-as-model", ["map", "{root}/bare_array.npz", "--resolution", "0.3",
                          "--out", "{root}/out"], "bare_array.npz`gpocc train", "out"),
    ("info-npy-as-model", ["info", "{root}/bare_array.npz"], "bare_array.npz`gpocc train",
     None),
    ("config-is-a-folder", ["train", "{root}/ok.mcap", "--config", "{root}/user_dir",
                            "--out", "{root}/out.npz"], "user_dir", "out.npz"),
    # Config values that passed validation and failed later with a traceback
    ("config-ragged-covariance", ["config", "{root}/ragged_cov.yaml"],
     "ragged_cov.yaml`pose_covariance", None),
    ("config-box-width-0", ["train", "{root}/ok.mcap", "--config", "{root}/box_0.yaml",
                            "--out", "{root}/out.npz"], "box_0.yaml`log_bounds_width", "out.npz"),
    # e^-1000 is 0: the error named signal_variance, which the file does not set.
    ("config-box-width-1000", ["config", "{root}/box_1000.yaml"],
     "box_1000.yaml`log_bounds_width", None),
    ("config-unscented-alpha-1e300", ["train", "{root}/ok.mcap", "--config",
                                      "{root}/alpha_huge.yaml", "--out", "{root}/out.npz"],
     "alpha_huge.yaml`alpha", "out.npz"),
    ("config-signal-variance-1e300", ["config", "{root}/signal_huge.yaml"],
     "signal_huge.yaml`signal_variance", None),
    ("map-resolution-1e39", ["map", "{root}/good.npz", "--resolution", "1e39",
                             "--out", "{root}/out"], "--resolution", "out"),
    ("split-every-2-to-the-63", ["split", "{root}/ok.mcap", "--every", str(2**63),
                                 "--out", "{root}/out"], "ok.mcap`holds out no scan", "out"),
    ("train-robotlaser-nan-resolution", ["train", "{root}/angles_nan.log",
                                         "--out", "{root}/out.npz"], "angles_nan.log`line 1",
     "out.npz"),
    # Each line states its bearings: the first line's were used for every scan. Fans that
    # change are placed on one layout (gpocc.io.layouts) unless they cannot be one laser's.
    ("train-robotlaser-layout-changes", ["train", "{root}/angles_change.log",
                                         "--out", "{root}/out.npz"],
     "angles_change.log`do not fit one layout", "out.npz"),
    # Local problems of the whole model: minutes per block instead of an error.
    ("config-neighbours-100000", ["config", "{root}/neighbours_huge.yaml"],
     "neighbours_huge.yaml`model.neighbours", None),
    ("map-model-deep-json", ["map", "{root}/deep_json.npz", "--resolution", "0.3",
                             "--out", "{root}/out"], "deep_json.npz`gpocc train", "out"),
    ("train-same-input-twice", ["train", "{root}/ok.mcap", "{root}/./ok.mcap",
                                "--out", "{root}/out.npz"], "ok.mcap`given twice", "out.npz"),
    ("info-same-input-twice", ["info", "{root}/ok.mcap", "{root}/./ok.mcap"],
     "ok.mcap`given twice", None),
    ("update-keep-with-refine", ["update", "{root}/good.npz", "{root}/ok.mcap", "--keep",
                                 "--refine-iterations", "3", "--out", "{root}/out.npz"],
     "--refine-iterations`--keep does not run", "out.npz"),
    ("update-relearn-with-refine", ["update", "{root}/good.npz", "{root}/ok.mcap",
                                    "--relearn", "--refine-iterations", "3", "--out",
                                    "{root}/out.npz"],
     "--refine-iterations`--relearn does not run", "out.npz"),
    # Paths that are not regular files: a pipe blocks a read, and is read only once
    ("train-input-pipe", ["train", "{root}/fifo", "--out", "{root}/out.npz"],
     "fifo`not a regular file", "out.npz"),
    ("update-input-pipe", ["update", "{root}/good.npz", "{root}/fifo", "--out",
                           "{root}/out.npz"], "fifo`not a regular file", "out.npz"),
    ("info-input-pipe", ["info", "{root}/fifo"], "fifo`not a regular file", None),
    ("map-model-pipe", ["map", "{root}/fifo", "--resolution", "0.3", "--out", "{root}/out"],
     "fifo`not a regular file", "out"),
    ("map-model-folder", ["map", "{root}/user_dir", "--resolution", "0.3", "--out",
                          "{root}/out"], "user_dir`is a folder", "out"),
    ("config-pipe", ["train", "{root}/ok.mcap", "--config", "{root}/fifo",
                     "--out", "{root}/out.npz"], "fifo`not a regular file", "out.npz"),
] + [
    # Tampered model files ("huge_extent" is valid data: the size guard handles it above)
    (f"model-{name}", ["map", f"{{root}}/{name}.npz", "--resolution", "0.3",
                       "--out", "{root}/out"], f"{name}.npz`re-create it with `gpocc train", "out")
    for name in TAMPERING if name != "huge_extent"
]


@pytest.mark.parametrize("argv, names, out", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_clean_error(corpus, argv, names, out):
    args = [a.replace("{root}", str(corpus)) for a in argv]
    before = sorted(p.name for p in corpus.iterdir())
    run = subprocess.run([sys.executable, "-m", "gpocc", *args], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode != 0, run.stdout + run.stderr
    assert "Traceback" not in run.stderr, run.stderr
    errors = [line for line in run.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1, run.stderr
    for name in names.split("`"):  # the file, and for model files the fix
        assert name in errors[0], errors[0]
    if out is not None:
        assert not (corpus / out).exists()
    # Nothing new beside the inputs: no output, no temporary, no claim file.
    assert sorted(p.name for p in corpus.iterdir()) == before
    assert (corpus / "user_dir" / "notes.txt").read_text() == "mine\n"
