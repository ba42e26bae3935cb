"""`gpocc build`: train and map in one process, with the outputs of `gpocc train` followed
by `gpocc map`, and the same refusals (existing --out, bad input) before any work."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.gp.model import kernel_parameters, load_model

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data" / "sample" / "intel_sample.mcap"
SAMPLE_CONFIG = ROOT / "data" / "sample" / "sample.yaml"
RASTERS = ("probability.tif", "variance.tif", "class.tif")
runner = CliRunner()


def read(path: Path) -> np.ndarray:
    with rasterio.open(path) as ds:
        return ds.read(1)


def invoke(*args: str | Path):
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return result


@pytest.fixture(scope="module")
def two_commands(tmp_path_factory) -> Path:
    """`gpocc train` then `gpocc map` on the sample bag, at 0.2 m on two workers."""
    folder = tmp_path_factory.mktemp("two")
    invoke("train", SAMPLE, "--config", SAMPLE_CONFIG, "--out", folder / "model.npz")
    invoke("map", folder / "model.npz", "--resolution", "0.2", "--out", folder / "map",
           "--workers", "2")
    return folder


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("build") / "map"
    result = invoke("build", SAMPLE, "--config", SAMPLE_CONFIG, "--resolution", "0.2",
                    "--out", out, "--workers", "2")
    return out, result.stdout


def test_build_gives_the_model_and_map_of_train_then_map(two_commands: Path, built) -> None:
    out, stdout = built
    trained, kept = load_model(two_commands / "model.npz"), load_model(out / "model.npz")
    for name in ("means", "covariances", "labels", "scan_ids", "pose_factors"):
        assert np.array_equal(getattr(trained.samples, name), getattr(kept.samples, name))
    assert kernel_parameters(trained.kernel) == kernel_parameters(kept.kernel)
    assert trained.noise_variance == kept.noise_variance
    assert (trained.classifier.a, trained.classifier.b) == (kept.classifier.a, kept.classifier.b)
    for raster in RASTERS:
        expected = read(two_commands / "map" / raster)
        got = read(out / raster)
        assert np.array_equal(expected, got, equal_nan=True), raster
    assert (two_commands / "map" / "map.pgm").read_bytes() == (out / "map.pgm").read_bytes()
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["model"] == str(out / "model.npz")
    assert meta["timings_s"]["predict"] > 0
    lines = stdout.splitlines()
    assert f"model: {out / 'model.npz'}" in lines and f"map: {out}" in lines
    assert any(line.startswith("total time: ") for line in lines)


def test_the_kept_model_maps_again_to_the_same_map(built, tmp_path: Path) -> None:
    out, _ = built
    invoke("map", out / "model.npz", "--resolution", "0.2", "--out", tmp_path / "again",
           "--workers", "1")
    assert np.array_equal(read(out / "probability.tif"),
                          read(tmp_path / "again" / "probability.tif"), equal_nan=True)


def test_a_build_folder_given_as_the_model_names_its_model(built, tmp_path: Path) -> None:
    out, _ = built
    for args in (["map", str(out), "--resolution", "0.2", "--out", str(tmp_path / "m")],
                 ["update", str(out), str(SAMPLE), "--out", str(tmp_path / "u.npz")]):
        result = runner.invoke(app, args)
        assert result.exit_code == 2, result.output
        assert f"is a map folder; pass its model, {out / 'model.npz'}" in result.stderr
        assert not any(tmp_path.iterdir())


def test_build_refuses_an_existing_output_before_any_work(tmp_path: Path) -> None:
    out = tmp_path / "map"
    out.mkdir()
    (out / "mine.txt").write_text("not gpocc's")
    result = runner.invoke(app, ["build", str(SAMPLE), "--config", str(SAMPLE_CONFIG),
                                 "--resolution", "0.2", "--out", str(out)])
    assert result.exit_code == 2
    assert result.output.strip().startswith("gpocc build: error: ")
    assert "--force" in result.output and len(result.output.strip().splitlines()) == 1
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt"]


@pytest.mark.parametrize("args, says", [
    (["--resolution", "0"], "--resolution"),
    (["--resolution", "0.2", "--workers", "0"], "--workers"),
    (["--resolution", "0.2", "--seed", "-1"], "seed"),
])
def test_build_refuses_bad_options_with_one_line_and_no_output(
        tmp_path: Path, args: list[str], says: str) -> None:
    out = tmp_path / "map"
    result = runner.invoke(app, ["build", str(SAMPLE), "--config", str(SAMPLE_CONFIG),
                                 "--out", str(out), *args])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("gpocc build: error: ") and says in lines[0]
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_build_of_a_missing_input_leaves_nothing(tmp_path: Path) -> None:
    out = tmp_path / "map"
    result = runner.invoke(app, ["build", str(tmp_path / "nothing.bag"), "--resolution", "0.2",
                                 "--out", str(out)])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "nothing.bag" in lines[0]
    assert list(tmp_path.iterdir()) == []


def test_mapping_a_build_folder_into_itself_keeps_its_model(built, tmp_path: Path) -> None:
    """`gpocc map OUT/model.npz --out OUT --force` replaces the map, not the model."""
    out, _ = built
    folder = tmp_path / "copy"
    invoke("build", SAMPLE, "--config", SAMPLE_CONFIG, "--resolution", "0.4",
           "--out", folder, "--workers", "1")
    model_bytes = (folder / "model.npz").read_bytes()
    invoke("map", folder / "model.npz", "--resolution", "0.2", "--out", folder, "--force",
           "--workers", "1")
    assert (folder / "model.npz").read_bytes() == model_bytes
    meta = json.loads((folder / "metadata.json").read_text())
    assert meta["resolution_m"] == 0.2
    assert meta["model"] == str(folder / "model.npz")
    # the map is the one of the re-mapping: equal to the first build's 0.2 m map
    assert np.array_equal(read(folder / "probability.tif"), read(out / "probability.tif"),
                          equal_nan=True)


def test_build_checks_the_size_of_bounds_before_training(tmp_path: Path) -> None:
    out = tmp_path / "map"
    result = runner.invoke(app, ["build", str(SAMPLE), "--config", str(SAMPLE_CONFIG),
                                 "--resolution", "0.1", "--out", str(out), "--bounds", "0",
                                 "0", "100000", "100000"])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "map.max_cells in the config" in lines[0], result.output
    assert "built" not in result.output and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command", ["grid", "bhm"])
def test_a_baseline_window_without_data_warns_as_map_does(tmp_path: Path, command) -> None:
    result = runner.invoke(app, [command, str(SAMPLE), "--config", str(SAMPLE_CONFIG),
                                 "--resolution", "0.5", "--bounds", "500", "500", "510",
                                 "510", "--out", str(tmp_path / "far")])
    assert result.exit_code == 0, result.output
    assert "warning: every cell of the map is nodata" in result.stderr
    near = runner.invoke(app, [command, str(SAMPLE), "--config", str(SAMPLE_CONFIG),
                               "--resolution", "0.5", "--out", str(tmp_path / "near")])
    assert near.exit_code == 0 and "nodata" not in near.stderr
