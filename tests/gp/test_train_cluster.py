"""`gpocc train --scheduler` / `gpocc build --scheduler`: training on a Dask cluster.

The oracle is the local run: the likelihood patches and the classifier's predictions are
computed by the same functions on the cluster's workers and summed in the same order, so
the model file must hold exactly the same numbers.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.io.rasters import read_raster

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data" / "sample" / "intel_sample.mcap"
SAMPLE_CONFIG = ROOT / "data" / "sample" / "sample.yaml"
runner = CliRunner()


def _train(out: Path, *extra: str) -> None:
    result = runner.invoke(app, ["train", "--quiet", str(SAMPLE), "--config",
                                 str(SAMPLE_CONFIG), "--out", str(out), *extra])
    assert result.exit_code == 0, result.output


def _arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


def _assert_same_model(local: Path, cluster: Path) -> None:
    a, b = _arrays(local), _arrays(cluster)
    assert a.keys() == b.keys()
    for key in a:
        if key == "metadata":  # holds the stages' wall seconds
            continue
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    # The metadata's learned values (hyperparameters, classifier, likelihood) too.
    meta_a, meta_b = (json.loads(m["metadata"].tobytes()) for m in (a, b))
    for meta in (meta_a, meta_b):
        meta["training"].pop("timings_s")
    assert meta_a == meta_b


@pytest.fixture(scope="module")
def local_model(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("local") / "model.npz"
    _train(out)
    return out


def test_train_on_a_local_cluster_gives_the_local_model(local_model, tmp_path):
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, host="127.0.0.1",
                      dashboard_address=None, processes=True) as cluster:
        out = tmp_path / "cluster.npz"
        _train(out, "--scheduler", cluster.scheduler_address)
        # The workers computed the likelihood patches and the classifier's predictions.
        ran = set(cluster.scheduler.task_prefixes)
        assert {"patch_negative_log_likelihood", "patch_holdout_predictions"} <= ran, ran
    _assert_same_model(local_model, out)


def test_scoring_from_several_starts_on_a_local_cluster_gives_the_local_model(tmp_path):
    # Fisher scoring's Fisher information travels back from the workers with the gradient.
    import yaml
    from distributed import LocalCluster

    config = yaml.safe_load(SAMPLE_CONFIG.read_text())
    config.setdefault("model", {}).setdefault("training", {}).update(
        {"local_search": "scoring", "local_starts": 2})
    job = tmp_path / "job.yaml"
    job.write_text(yaml.safe_dump(config))

    def train(out: Path, *extra: str) -> None:
        result = runner.invoke(app, ["train", "--quiet", str(SAMPLE), "--config", str(job),
                                     "--out", str(out), *extra])
        assert result.exit_code == 0, result.output

    train(tmp_path / "local.npz")
    with LocalCluster(n_workers=2, threads_per_worker=1, host="127.0.0.1",
                      dashboard_address=None, processes=True) as cluster:
        train(tmp_path / "cluster.npz", "--scheduler", cluster.scheduler_address)
    _assert_same_model(tmp_path / "local.npz", tmp_path / "cluster.npz")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_for_workers(address: str, count: int, deadline_s: float = 60.0) -> None:
    from distributed import Client

    with Client(address, timeout="30s") as client:
        client.wait_for_workers(count, timeout=deadline_s)


@pytest.mark.skipif(shutil.which("dask", path=str(Path(sys.executable).parent)) is None,
                    reason="the dask command-line tools are not installed")
def test_build_on_dask_scheduler_and_worker_processes(local_model, tmp_path, monkeypatch):
    """`dask scheduler` and two `dask worker` processes, as a user starts them; the build
    connects to the scheduler once, for training and the map both, and makes the local
    build's map."""
    import distributed

    clients: list[str] = []

    class CountedClient(distributed.Client):
        def __init__(self, address, *args, **kwargs):
            clients.append(address)
            super().__init__(address, *args, **kwargs)

    bindir = Path(sys.executable).parent
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    procs = [subprocess.Popen(
        [str(bindir / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port),
         "--dashboard-address", ":0", "--no-show"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)]
    try:
        time.sleep(0.5)
        procs += [subprocess.Popen(
            [str(bindir / "dask"), "worker", address, "--nthreads", "1", "--nworkers", "1",
             "--no-dashboard", "--host", "127.0.0.1"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env) for _ in range(2)]
        _wait_for_workers(address, 2)
        out = tmp_path / "built"
        monkeypatch.setattr(distributed, "Client", CountedClient)
        result = runner.invoke(app, ["build", "--quiet", str(SAMPLE), "--config",
                                     str(SAMPLE_CONFIG), "--resolution", "0.2", "--out",
                                     str(out), "--scheduler", address])
        monkeypatch.undo()
        assert result.exit_code == 0, result.output
        assert clients == [address]
        _assert_same_model(local_model, out / "model.npz")
        local = tmp_path / "built-locally"
        result = runner.invoke(app, ["build", "--quiet", str(SAMPLE), "--config",
                                     str(SAMPLE_CONFIG), "--resolution", "0.2", "--out",
                                     str(local)])
        assert result.exit_code == 0, result.output
        for raster in ("probability.tif", "variance.tif", "class.tif"):
            (a, spec_a, _), (b, spec_b, _) = (read_raster(f / raster) for f in (local, out))
            np.testing.assert_array_equal(a, b, err_msg=raster)
            assert spec_a == spec_b
    finally:
        for proc in reversed(procs):
            proc.terminate()
        for proc in procs:
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()


def test_train_with_an_unreachable_scheduler_is_one_error_line(tmp_path):
    port = _free_port()  # nothing listens there
    out = tmp_path / "model.npz"
    result = runner.invoke(app, ["train", str(SAMPLE), "--config", str(SAMPLE_CONFIG),
                                 "--out", str(out), "--scheduler", f"tcp://127.0.0.1:{port}"])
    assert result.exit_code != 0
    assert "Traceback" not in result.output
    assert f"127.0.0.1:{port}" in result.output
    assert not out.exists()


def test_build_with_an_unreachable_scheduler_is_one_error_line_and_no_folder(tmp_path):
    port = _free_port()  # nothing listens there
    out = tmp_path / "built"
    result = runner.invoke(app, ["build", str(SAMPLE), "--config", str(SAMPLE_CONFIG),
                                 "--resolution", "0.2", "--out", str(out),
                                 "--scheduler", f"tcp://127.0.0.1:{port}"])
    assert result.exit_code != 0
    assert "Traceback" not in result.output
    assert f"--scheduler tcp://127.0.0.1:{port}" in result.output
    assert not out.exists()
