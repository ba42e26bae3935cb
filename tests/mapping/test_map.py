"""Model files and `gpocc map`: values, resolutions, tiling, executors, atomic output."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import rasterio
from blendweights import trapezoid
from modelfiles import read_model_file, write_model_file
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.config import Config, ModelConfig, TrainingConfig
from gpocc.errors import GpoccError
from gpocc.gp.local import NeighbourIndex, predict_local
from gpocc.gp.model import FORMAT_VERSION, build_model, load_model, save_model
from gpocc.gridspec import GridSpec
from gpocc.io.mapserver import read_map_server
from gpocc.samples.sampleset import SampleSet

runner = CliRunner()


def room_samples(seed: int = 0) -> SampleSet:
    """Samples of a 4 x 3 m room seen from its middle: walls occupied, inside free."""
    rng = np.random.default_rng(seed)
    walls = []
    for t in np.linspace(0, 1, 60, endpoint=False):
        walls += [(-2 + 4 * t, -1.5), (-2 + 4 * t, 1.5)]
    for t in np.linspace(0, 1, 45, endpoint=False):
        walls += [(-2, -1.5 + 3 * t), (2, -1.5 + 3 * t)]
    walls = np.array(walls)
    free = rng.uniform([-1.8, -1.3], [1.8, 1.3], size=(300, 2))
    means = np.vstack([walls, free])
    n = len(means)
    labels = np.concatenate([np.ones(len(walls)), -np.ones(len(free))])
    covs = np.einsum("n,ij->nij", rng.uniform(0.0005, 0.004, n), np.eye(2))
    scan_ids = rng.integers(0, 30, n)
    pose_factors = rng.normal(0.0, 0.01, (n, 2, 3))
    return SampleSet(means, covs, labels, scan_ids, pose_factors, np.zeros(n, dtype=np.int16))


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    config = Config(model=ModelConfig(
        neighbours=120, block_size_m=0.6,
        training=TrainingConfig(patches=3, patch_size=80, anneal_maxfun=10, lbfgs_maxiter=10),
    ))
    model = build_model(room_samples(), config)
    path = tmp_path_factory.mktemp("model") / "model.npz"
    save_model(model, path)
    return path


def test_model_round_trip(model_path):
    model = load_model(model_path)
    # Hand-made samples carry no label-noise factors: the model says its labels weigh once
    # each, whatever the default (Config() asks for count weights).
    assert Config().samples.label_weights == "count"
    assert model.config.samples.label_weights == "none" and model.samples.noise_factors is None
    again = model_path.with_name("again.npz")
    save_model(model, again)
    other = load_model(again)
    assert other.kernel == model.kernel
    assert other.classifier == model.classifier
    assert other.config == model.config
    np.testing.assert_array_equal(other.samples.covariances, model.samples.covariances)
    np.testing.assert_array_equal(other.samples.pose_factors, model.samples.pose_factors)


def test_model_learns_the_room(model_path):
    model = load_model(model_path)
    index = NeighbourIndex(model.samples)
    inside = np.array([[0.0, 0.0], [0.8, 0.5]])
    wall = np.array([[0.0, 1.5], [2.0, 0.3]])
    for pts, sign in ((inside, -1), (wall, 1)):
        for p in pts:
            pred = predict_local(model.kernel, model.noise_variance,
                                 index.problem(p, 120), p[None], model.level)
            prob = model.classifier.probability(pred.mean, pred.variance)[0]
            assert (prob - 0.5) * sign > 0.1


def test_newer_or_corrupt_model_file_is_a_clear_error(model_path, tmp_path):
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(model_path.read_bytes()[:500])
    newer = tmp_path / "newer.npz"
    arrays, meta = read_model_file(model_path)
    meta["format_version"] = FORMAT_VERSION + 1
    write_model_file(newer, arrays, meta)
    for path, words in ((corrupt, "corrupt"), (newer, "newer")):
        result = runner.invoke(app, ["map", str(path), "--resolution", "0.2",
                                     "--out", str(tmp_path / "m")])
        assert result.exit_code != 0
        assert words in result.output
        assert "Traceback" not in result.output
        assert not (tmp_path / "m").exists()


def run_map(model_path, out, *extra):
    result = runner.invoke(app, ["map", str(model_path), "--out", str(out), *extra])
    assert result.exit_code == 0, result.output
    return out


@pytest.mark.parametrize("overlap", [1.0, 0.4])
def test_map_values_match_the_model_and_files_are_complete(model_path, tmp_path, overlap):
    if overlap != 1.0:  # the same model, mapped with another blend overlap
        arrays, meta = read_model_file(model_path)
        meta["config"]["model"]["blend_overlap"] = overlap
        model_path = tmp_path / "model.npz"
        write_model_file(model_path, arrays, meta)
    out = run_map(model_path, tmp_path / "map", "--resolution", "0.1", "--workers", "1")
    for name in ("probability.tif", "variance.tif", "class.tif", "map.yaml", "map.pgm",
                 "preview.png", "metadata.json"):
        assert (out / name).is_file(), name
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["blend_overlap"] == overlap  # as used: 6-cell blocks allow down to 1/3
    assert meta["anchor_spacing_m"] == 0.6  # block_size_m 0.6 at 0.1 m, as written
    timings = meta["timings_s"]
    assert set(timings) == {"map", "predict", "write", "finish"}
    assert timings["predict"] + timings["write"] + timings["finish"] <= timings["map"] + 0.002
    model = load_model(model_path)
    with rasterio.open(out / "probability.tif") as ds:
        prob = ds.read(1)
        transform = ds.transform
    with rasterio.open(out / "class.tif") as ds:
        classes = ds.read(1)
    # Re-predict a few cells directly from the model: the blend of the local problems
    # centred on the (up to) four block centres around the cell, with the trapezoid
    # weights of the blend overlap (bilinear at 1; clamped at the map's edges).
    index = NeighbourIndex(model.samples)
    cells = 6  # block_size_m 0.6 / 0.1
    n_rows, n_cols = -(-prob.shape[0] // cells), -(-prob.shape[1] // cells)
    # Blocks are 6 cells: (26, 21) lies within 0.1 blocks of its block's centre, where at
    # overlap 0.4 its own anchor alone counts; (24, 20) lies in the blended band.
    for row, col in ((3, 4), (20, 30), (35, 10), (9, 9), (26, 21), (24, 20)):
        x, y = transform @ (col + 0.5, row + 0.5)
        u = np.clip((row + 0.5) / cells - 0.5, 0, n_rows - 1)
        v = np.clip((col + 0.5) / cells - 0.5, 0, n_cols - 1)
        mix_w, mix_mu, mix_var = [], [], []
        for i in {int(np.floor(u)), int(np.ceil(u))}:
            for j in {int(np.floor(v)), int(np.ceil(v))}:
                w = trapezoid(abs(u - i), overlap) * trapezoid(abs(v - j), overlap)
                cx, cy = transform @ (j * cells + cells / 2, i * cells + cells / 2)
                pred = predict_local(
                    model.kernel, model.noise_variance,
                    index.problem(np.array([cx, cy]), model.config.model.neighbours),
                    np.array([[x, y]]), model.level)
                mix_w.append(w)
                mix_mu.append(pred.mean[0])
                mix_var.append(pred.variance[0])
        w, mu, var = np.array(mix_w), np.array(mix_mu), np.array(mix_var)
        assert w.sum() == pytest.approx(1.0)
        mean = np.sum(w * mu)
        variance = np.sum(w * var)
        expected = model.classifier.probability(mean, variance)
        assert prob[row, col] == pytest.approx(expected, abs=1e-6)
    spec_classes, spec = read_map_server(out / "map.yaml")
    np.testing.assert_array_equal(spec_classes == 1, classes == 1)
    np.testing.assert_array_equal(spec_classes == 0, classes == 0)
    assert spec.x0 == pytest.approx(transform.c)


def test_existing_output_needs_force(model_path, tmp_path):
    out = run_map(model_path, tmp_path / "map", "--resolution", "0.3")
    result = runner.invoke(app, ["map", str(model_path), "--resolution", "0.3", "--out", str(out)])
    assert result.exit_code != 0 and "--force" in result.output
    run_map(model_path, out, "--resolution", "0.3", "--force")


def test_two_resolutions_agree(model_path, tmp_path):
    bounds = ["--bounds", "-2.4", "-1.8", "2.4", "1.8"]
    coarse = run_map(model_path, tmp_path / "c", "--resolution", "0.2", *bounds)
    fine = run_map(model_path, tmp_path / "f", "--resolution", "0.1", *bounds)
    with rasterio.open(coarse / "probability.tif") as ds:
        pc = ds.read(1)
    with rasterio.open(fine / "probability.tif") as ds:
        pf = ds.read(1)
    # Average each 2 x 2 group of fine cells onto the coarse cell that contains them.
    pf2 = pf.reshape(pc.shape[0], 2, pc.shape[1], 2).mean(axis=(1, 3))
    assert np.mean(np.abs(pf2 - pc)) < 0.03
    assert np.mean((pf2 > 0.5) == (pc > 0.5)) > 0.95


def test_parallel_tiled_and_dask_outputs_identical_to_serial(model_path, tmp_path):
    serial = run_map(model_path, tmp_path / "s", "--resolution", "0.1", "--workers", "1")
    parallel = run_map(model_path, tmp_path / "p", "--resolution", "0.1", "--workers", "2")
    with rasterio.open(serial / "probability.tif") as ds:
        reference = ds.read(1)
    with rasterio.open(parallel / "probability.tif") as ds:
        np.testing.assert_array_equal(ds.read(1), reference)

    # A tiny tile size forces the tiled layout: tiles + VRT, same values.
    model = load_model(model_path)
    tiled_model = dataclasses.replace(model, config=dataclasses.replace(
        model.config, map=dataclasses.replace(model.config.map, tile_pixels=12)))
    tiled_path = tmp_path / "tiled.npz"
    save_model(tiled_model, tiled_path)
    tiled = run_map(tiled_path, tmp_path / "t", "--resolution", "0.1", "--workers", "2")
    assert (tiled / "probability.vrt").is_file()
    assert len(list((tiled / "tiles" / "probability").glob("*.tif"))) > 1
    with rasterio.open(tiled / "probability.vrt") as ds:
        np.testing.assert_array_equal(ds.read(1), reference)

    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, host="127.0.0.1",
                      dashboard_address=None, processes=True) as cluster:
        dask_out = run_map(model_path, tmp_path / "d", "--resolution", "0.1",
                           "--scheduler", cluster.scheduler_address)
    with rasterio.open(dask_out / "probability.tif") as ds:
        np.testing.assert_array_equal(ds.read(1), reference)


def test_workers_warm_up_on_the_model_and_a_failed_warm_up_is_harmless(
        model_path, tmp_path, monkeypatch):
    """The warm-up predicts from a real neighbourhood (it builds the worker's index); if it
    fails, the pool must not restart its workers forever: the map is still made, equal to
    the serial one."""
    from gpocc.mapping import executors

    model = load_model(model_path)
    executors._worker_state.clear()
    executors.warm_up(model)
    assert executors._worker_state["model"] is model
    assert isinstance(executors._worker_state["index"], NeighbourIndex)

    def broken(model):
        raise RuntimeError("warm-up failed")

    monkeypatch.setattr(executors, "warm_up", broken)  # forked workers inherit it
    parallel = run_map(model_path, tmp_path / "p", "--resolution", "0.2", "--workers", "2")
    serial = run_map(model_path, tmp_path / "s", "--resolution", "0.2", "--workers", "1")
    with rasterio.open(parallel / "probability.tif") as a, \
            rasterio.open(serial / "probability.tif") as b:
        np.testing.assert_array_equal(a.read(1), b.read(1))


def test_executor_starts_no_more_processes_than_chunks_of_anchors(model_path):
    from gpocc.mapping import executors

    model = load_model(model_path)
    with executors.anchor_executor(model, workers=50, anchors=10) as executor:
        assert executor.local_workers and executor._pool._processes == 2  # 8 + 2 anchors
    with executors.anchor_executor(model, workers=50, anchors=8) as executor:
        assert not executor.local_workers  # one chunk: in this process


def test_anchors_are_queued_for_the_pool_before_the_caller_does_its_own_work(model_path):
    # predict_tile's while_running (where the map loads its GeoTIFF writer) must run once
    # the tile's anchors are queued for the pool, not before, and must not change the
    # tile.
    from gpocc.mapping import executors
    from gpocc.mapping.blend import predict_tile
    from gpocc.mapping.blocks import AnchorLattice

    model = load_model(model_path)
    spec = GridSpec.from_bounds(-1.0, -1.0, 1.5, 0.5, 0.1)
    lattice = AnchorLattice.of_model(spec, model.config.model)
    seen = []
    with executors.anchor_executor(model, workers=2, anchors=100) as executor:
        assert executor.local_workers

        def while_running():
            seen.append(len(executor._pool._cache))  # jobs handed to the pool

        layers = predict_tile(model, lattice, 0, 0, spec, None, executor=executor,
                              while_running=while_running)
    plain = predict_tile(model, lattice, 0, 0, spec, None)
    assert seen == [1]
    np.testing.assert_array_equal(layers.mean, plain.mean)
    np.testing.assert_array_equal(layers.variance, plain.variance)


@pytest.mark.parametrize("workers", [1, 2])
def test_side_work_runs_once_even_when_the_first_tile_has_no_anchors(model_path, tmp_path,
                                                                     workers):
    from gpocc.mapping.mapper import make_map

    model = load_model(model_path)
    model = dataclasses.replace(model, config=dataclasses.replace(
        model.config, map=dataclasses.replace(model.config.map, tile_pixels=12)))
    # The north-west tile lies beyond every beam's reach: no anchors there.
    spec = GridSpec.from_bounds(-2.5, -2.0, 6.0, 6.0, 0.1)
    calls = []
    summary = make_map(model, spec, tmp_path, workers=workers,
                       while_running=lambda: calls.append(1))
    assert summary.tiles > 1 and calls == [1]
    with rasterio.open(tmp_path / "probability.vrt") as ds:
        first = ds.read(1, window=((0, 12), (0, 12)))
    assert np.isnan(first).all()  # the first tile really had nothing to compute


@pytest.mark.parametrize("side", ["while_running", "while_writing"])
def test_a_failure_beside_the_workers_leaves_no_output_and_no_process(model_path, tmp_path,
                                                                      side):
    import multiprocessing

    from gpocc.io.atomic import atomic_directory
    from gpocc.mapping.mapper import make_map

    model = load_model(model_path)
    spec = GridSpec.from_bounds(-1.0, -1.0, 1.5, 0.5, 0.1)

    def disk_full():
        raise OSError(28, "No space left on device")

    # atomic_directory turns the OS error into gpocc's one-line error.
    with pytest.raises(GpoccError, match="(?i)no space left on device"), \
            atomic_directory(tmp_path / "map") as folder:
        make_map(model, spec, folder, workers=2, **{side: disk_full})
    assert list(tmp_path.iterdir()) == []  # neither the map nor its temporary folder
    assert multiprocessing.active_children() == []


@pytest.mark.parametrize("tile_pixels", [12, 4096])
def test_writing_side_work_runs_once_on_a_thread_after_the_last_anchor(model_path, tmp_path,
                                                                        tile_pixels):
    # gpocc build writes its model file there: beside the map's own files, after every
    # anchor is in (no busy worker to slow down), before make_map returns.
    import threading

    from gpocc.mapping.mapper import block_count, make_map

    model = load_model(model_path)
    model = dataclasses.replace(model, config=dataclasses.replace(
        model.config, map=dataclasses.replace(model.config.map, tile_pixels=tile_pixels)))
    spec = GridSpec.from_bounds(-2.5, -2.0, 6.0, 6.0, 0.1)
    done, calls = [], []

    def while_writing():
        calls.append((threading.current_thread() is threading.main_thread(), sum(done)))

    summary = make_map(model, spec, tmp_path, workers=2, progress=done.append,
                       while_writing=while_writing)
    assert (summary.tiles > 1) == (tile_pixels == 12)
    assert calls == [(False, block_count(model, spec))]


def test_bounds_and_grid_geometry(model_path, tmp_path):
    out = run_map(model_path, tmp_path / "b", "--resolution", "0.25",
                  "--bounds", "-1", "-1", "1.5", "0.5")
    with rasterio.open(out / "variance.tif") as ds:
        expected = GridSpec.from_bounds(-1, -1, 1.5, 0.5, 0.25)
        assert (ds.width, ds.height) == (expected.width, expected.height)
        assert ds.bounds.left == pytest.approx(-1) and ds.bounds.top == pytest.approx(0.5)
        assert np.all(ds.read(1) >= 0)


def test_cells_far_from_every_sample_are_nodata_and_unknown_to_map_server(model_path, tmp_path):
    # The room's samples span about 4 x 3 m around the origin; 6 m away there is no data.
    # This model has no beams, so its support is the cells holding a sample.
    out = run_map(model_path, tmp_path / "far", "--resolution", "0.2",
                  "--bounds", "-2.2", "-1.8", "9.8", "1.8")
    with rasterio.open(out / "class.tif") as ds:
        classes = ds.read(1)
        transform = ds.transform
    with rasterio.open(out / "probability.tif") as ds:
        prob = ds.read(1)
    with rasterio.open(out / "variance.tif") as ds:
        variance = ds.read(1)
    xs = np.array([(transform @ (c + 0.5, 0.5))[0] for c in range(classes.shape[1])])
    far = xs > 2.0 + 1.5 + 0.2
    assert np.all(classes[:, far] == 255)
    assert np.all(np.isnan(prob[:, far])) and np.all(np.isnan(variance[:, far]))
    assert np.any(classes[:, xs < 1.5] == 0) and np.any(classes[:, xs < 2.5] == 1)
    server_classes, _ = read_map_server(out / "map.yaml")
    assert np.all(server_classes[:, far] == 2)


def test_map_server_is_full_resolution_when_preview_is_decimated_or_map_tiled(
        model_path, tmp_path, monkeypatch):
    # Force a decimated preview (stride 3) and, below, a tiled map: map.pgm must still
    # have one pixel per map cell, equal to class.tif's decided cells.
    import gpocc.mapping.folder as folder

    monkeypatch.setattr(folder, "MAX_PREVIEW_PIXELS", 20)
    out = run_map(model_path, tmp_path / "dec", "--resolution", "0.1", "--workers", "1",
                  "--bounds", "-2.4", "-1.7", "2.4", "1.8")
    with rasterio.open(out / "class.tif") as ds:
        classes = ds.read(1)
        bounds = ds.bounds
    server, spec = read_map_server(out / "map.yaml")
    assert spec.resolution == pytest.approx(0.1)
    assert (spec.x0, spec.y0, spec.y1) == pytest.approx((bounds.left, bounds.bottom, bounds.top))
    np.testing.assert_array_equal(server == 1, classes == 1)
    np.testing.assert_array_equal(server == 0, classes == 0)

    model = load_model(model_path)
    tiled_model = dataclasses.replace(model, config=dataclasses.replace(
        model.config, map=dataclasses.replace(model.config.map, tile_pixels=12)))
    tiled_path = tmp_path / "tiled.npz"
    save_model(tiled_model, tiled_path)
    tiled = run_map(tiled_path, tmp_path / "t", "--resolution", "0.1", "--workers", "1",
                    "--bounds", "-2.4", "-1.7", "2.4", "1.8")
    assert (tiled / "class.vrt").is_file()
    tiled_server, tiled_spec = read_map_server(tiled / "map.yaml")
    assert tiled_spec == spec
    np.testing.assert_array_equal(tiled_server, server)


def test_map_server_size_limit_is_an_explicit_error(model_path, tmp_path):
    model = load_model(model_path)
    limited = dataclasses.replace(model, config=dataclasses.replace(
        model.config, map=dataclasses.replace(model.config.map, max_pgm_pixels=30)))
    path = tmp_path / "limited.npz"
    save_model(limited, path)
    out = tmp_path / "lim"
    result = runner.invoke(app, ["map", str(path), "--resolution", "0.1", "--out", str(out)])
    assert result.exit_code != 0
    assert "map.max_pgm_pixels" in result.output and "coarser resolution" in result.output
    assert not out.exists()
    run_map(path, out, "--resolution", "0.2", "--bounds", "-2.4", "-1.7", "2.4", "1.8")


def test_georeferenced_map_folder_is_cog_and_lands_where_the_robot_was(model_path, tmp_path):
    import math

    from rio_cogeo.cogeo import cog_validate

    from gpocc.config import GeorefConfig

    georef = GeorefConfig(epsg=32633, easting_m=389_000.25, northing_m=5_819_500.5,
                          yaw_deg=30.0)
    model = load_model(model_path)
    placed = dataclasses.replace(model, config=dataclasses.replace(
        model.config, map=dataclasses.replace(model.config.map, georef=georef)))
    path = tmp_path / "placed.npz"
    save_model(placed, path)
    out = run_map(path, tmp_path / "geo", "--resolution", "0.1",
                  "--bounds", "-2.4", "-1.7", "2.4", "1.8")
    yaw = math.radians(30.0)
    for name in ("probability", "variance", "class"):
        valid, errors, warnings = cog_validate(str(out / f"{name}.tif"), strict=True)
        assert valid, (name, errors, warnings)
        with rasterio.open(out / f"{name}.tif") as ds:
            assert ds.crs.to_epsg() == 32633
            # The map frame's (xmin, ymax) corner, rotated by yaw and moved to the origin.
            x, y = -2.4, -1.7 + ds.height * 0.1
            expected = (georef.easting_m + math.cos(yaw) * x - math.sin(yaw) * y,
                        georef.northing_m + math.sin(yaw) * x + math.cos(yaw) * y)
            assert ds.transform @ (0, 0) == pytest.approx(expected, abs=1e-6)
            assert ds.read_masks(1).all()  # inside the samples' extent every cell has data
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["georef"]["epsg"] == 32633 and meta["georef"]["yaw_deg"] == 30.0
    # map.yaml stays in the map frame (Nav2 works there).
    _, spec = read_map_server(out / "map.yaml")
    assert (spec.x0, spec.y0) == pytest.approx((-2.4, -1.7))


def test_nav2_reads_the_map_folders_pgm_as_its_class_layer_cell_for_cell(model_path, tmp_path):
    # The whole folder as Nav2 sees it: map.yaml + map.pgm loaded by the test's own
    # transliteration of Nav2's map_io (not gpocc's reader), each class.tif cell looked
    # up in Nav2's grid by its centre through GDAL's geotransform. Bounds off the cell
    # lattice and past the data's reach, so every class (and no data) is present.
    from tests.io.test_io_mapserver import nav2_load_map

    out = run_map(model_path, tmp_path / "nav2", "--resolution", "0.1",
                  "--bounds", "-2.45", "-1.75", "4.05", "1.85")
    with rasterio.open(out / "class.tif") as ds:
        classes = ds.read(1)
        transform, bounds = ds.transform, ds.bounds
    assert set(np.unique(classes)) == {0, 1, 2, 255}
    data, resolution, origin = nav2_load_map(out / "map.yaml")
    assert data.shape == classes.shape
    assert resolution == pytest.approx(transform.a)
    # origin: the pose of the lower-left corner of the lower-left pixel, no rotation.
    assert origin == pytest.approx([bounds.left, bounds.bottom, 0.0], abs=1e-9)
    rows, cols = np.mgrid[0:classes.shape[0], 0:classes.shape[1]]
    xs, ys = transform @ (cols + 0.5, rows + 0.5)
    nav_col = np.floor((xs - origin[0]) / resolution).astype(int)
    nav_row = np.floor((ys - origin[1]) / resolution).astype(int)  # row 0 is south
    loaded = data[nav_row, nav_col]
    expected = np.where(classes == 1, 100, np.where(classes == 0, 0, -1))
    np.testing.assert_array_equal(loaded, expected)


def test_stdout_and_metadata_state_what_the_files_hold(model_path, tmp_path):
    # The numbers a user reads (stdout, metadata.json) against the rasters as GDAL
    # reads them: size, bounds, resolution and the class counts.
    import ast
    import re

    out = tmp_path / "said"
    result = runner.invoke(app, ["map", str(model_path), "--out", str(out), "--resolution",
                                 "0.2", "--bounds", "-2.45", "-1.75", "4.05", "1.85"])
    assert result.exit_code == 0, result.output
    with rasterio.open(out / "class.tif") as ds:
        classes = ds.read(1)
        b, res = ds.bounds, ds.res
    counts = {"free": int((classes == 0).sum()), "occupied": int((classes == 1).sum()),
              "unsure": int((classes == 2).sum())}
    assert (classes == 255).any() and min(counts.values()) > 0
    cells = re.search(r"^cells: (\d+) x (\d+) at ([\d.]+) m, bounds (\(.*\))$", result.stdout,
                      re.M)
    assert cells, result.stdout
    assert (int(cells[1]), int(cells[2])) == (ds.width, ds.height)
    assert float(cells[3]) == res[0] == res[1]
    assert ast.literal_eval(cells[4]) == pytest.approx((b.left, b.bottom, b.right, b.top))
    said = re.search(r"^classes: (\d+) occupied, (\d+) free, (\d+) unsure$", result.stdout,
                     re.M)
    assert said and [int(v) for v in said.groups()] == [
        counts["occupied"], counts["free"], counts["unsure"]]
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["class_counts"] == counts
    assert meta["size_cells"] == [ds.width, ds.height] and meta["resolution_m"] == res[0]
    assert meta["bounds_m"] == pytest.approx([b.left, b.bottom, b.right, b.top])


def test_a_map_that_misses_the_data_says_so_on_stderr(model_path, tmp_path):
    # Bounds 20 m from the room: every cell is nodata, which stdout shows only as zero
    # class counts; stderr names the cause and the data's extent.
    result = runner.invoke(app, ["map", str(model_path), "--out", str(tmp_path / "away"),
                                 "--resolution", "0.2", "--bounds", "20", "20", "24", "23"])
    assert result.exit_code == 0, result.output
    with rasterio.open(tmp_path / "away" / "class.tif") as ds:
        assert np.all(ds.read(1) == 255)
    warning = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert len(warning) == 1 and "every cell of the map is nodata" in warning[0]
    assert "check --bounds" in warning[0] and "x -2.0 .. 2.0 m" in warning[0]
    # A map that holds data says nothing of the kind.
    result = runner.invoke(app, ["map", str(model_path), "--out", str(tmp_path / "near"),
                                 "--resolution", "0.2", "--bounds", "-1", "-1", "1", "1"])
    assert result.exit_code == 0, result.output
    assert "warning:" not in result.stderr


def test_more_workers_than_cores_are_capped_with_a_note(model_path, tmp_path, monkeypatch):
    """``--workers 100000`` must not start a process per chunk of anchors: the map runs
    on the usable cores (here made 2), says so, and equals the serial map."""
    import gpocc.commands.map as map_command
    from gpocc.mapping import executors

    monkeypatch.setattr(map_command, "default_workers", lambda: 2)
    started = []
    real_pool = executors.worker_pool

    def counting_pool(workers, *args):
        started.append(workers)
        return real_pool(workers, *args)

    monkeypatch.setattr(executors, "worker_pool", counting_pool)
    result = runner.invoke(app, ["map", str(model_path), "--out", str(tmp_path / "many"),
                                 "--resolution", "0.2", "--workers", "100000"])
    assert result.exit_code == 0, result.output
    assert "note: --workers 100000 is more than the 2 core(s) this process may use; " \
        "using 2" in result.stderr
    assert started == [2]
    assert json.loads((tmp_path / "many" / "metadata.json").read_text())["workers"] == 2
    serial = run_map(model_path, tmp_path / "one", "--resolution", "0.2", "--workers", "1")
    with rasterio.open(serial / "probability.tif") as a, \
            rasterio.open(tmp_path / "many" / "probability.tif") as b:
        np.testing.assert_array_equal(a.read(1), b.read(1))


def test_the_writing_thread_is_waited_for_through_further_interrupts():
    # On the way out of an interrupted map the folder's clean-up must not race the thread
    # still writing into it: a second Ctrl-C (here: an alarm raising KeyboardInterrupt
    # twice) must not end the wait early.
    import signal
    import threading
    import time
    from concurrent.futures import ThreadPoolExecutor

    from gpocc.mapping.mapper import _wait_through_interrupts

    release = threading.Event()
    interrupts = []

    def interrupt(signum, frame):
        interrupts.append(time.monotonic())
        if len(interrupts) == 2:
            release.set()
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGALRM, interrupt)
    try:
        with ThreadPoolExecutor(1) as pool:
            future = pool.submit(release.wait)
            signal.setitimer(signal.ITIMER_REAL, 0.05, 0.05)
            _wait_through_interrupts(future)
            signal.setitimer(signal.ITIMER_REAL, 0)
            assert future.done() and len(interrupts) >= 2
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def test_tiles_are_written_in_order_off_the_main_thread_and_a_failure_leaves_nothing(
        model_path, tmp_path, monkeypatch):
    # A tiled map writes each tile on a thread while the workers compute the next one.
    import multiprocessing
    import threading

    from gpocc.io.atomic import atomic_directory
    from gpocc.mapping import folder as folder_module
    from gpocc.mapping.mapper import make_map

    model = load_model(model_path)
    model = dataclasses.replace(model, config=dataclasses.replace(
        model.config, map=dataclasses.replace(model.config.map, tile_pixels=12)))
    spec = GridSpec.from_bounds(-2.5, -2.0, 6.0, 6.0, 0.1)
    real_add = folder_module.MapFolder.add
    added = []

    def add(self, row0, col0, *args, **kwargs):
        added.append((row0, col0, threading.current_thread() is threading.main_thread()))
        return real_add(self, row0, col0, *args, **kwargs)

    monkeypatch.setattr(folder_module.MapFolder, "add", add)
    summary = make_map(model, spec, tmp_path / "ok", workers=2)
    assert summary.tiles > 2
    assert len(added) == summary.tiles  # every tile, once
    order = [(r, c) for r, c, _ in added]
    assert order == sorted(order)  # row-major, as the tiles are laid out
    assert not any(on_main for _, _, on_main in added)

    def disk_full(self, row0, col0, *args, **kwargs):
        if row0 or col0:  # the first tile is written, a later one fails
            raise OSError(28, "No space left on device")
        return real_add(self, row0, col0, *args, **kwargs)

    monkeypatch.setattr(folder_module.MapFolder, "add", disk_full)
    out = tmp_path / "failed"
    out.mkdir()
    with pytest.raises(GpoccError, match="(?i)no space left on device"), \
            atomic_directory(out / "map") as folder:
        make_map(model, spec, folder, workers=2)
    assert list(out.iterdir()) == []
    assert multiprocessing.active_children() == []


def test_a_failed_export_stops_the_map_once_the_other_exports_are_done(model_path, tmp_path,
                                                                       monkeypatch):
    # The map_server, scale map, map.mcap and preview exports are written side by side:
    # one failing is the map's error, and the folder goes only when none is writing.
    import threading
    import time

    from gpocc.io.atomic import atomic_directory
    from gpocc.mapping import folder as folder_module
    from gpocc.mapping.mapper import make_map

    model = load_model(model_path)
    spec = GridSpec.from_bounds(-1.0, -1.0, 1.5, 0.5, 0.1)
    real_mcap = folder_module.MapFolder._write_mcap
    mcap_done = threading.Event()

    def slow_mcap(self):
        time.sleep(0.3)  # still writing when the scale map fails
        real_mcap(self)
        mcap_done.set()

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(folder_module.MapFolder, "_write_mcap", slow_mcap)
    monkeypatch.setattr(folder_module, "write_scale_map", disk_full)
    with pytest.raises(GpoccError, match="(?i)no space left on device"), \
            atomic_directory(tmp_path / "map") as folder:
        make_map(model, spec, folder, workers=1)
    assert mcap_done.is_set()
    assert list(tmp_path.iterdir()) == []


def _read_layers(folder) -> tuple[dict[str, np.ndarray], rasterio.coords.BoundingBox]:
    layers = {}
    for name in ("probability", "variance", "class"):
        path = folder / f"{name}.tif"
        with rasterio.open(path if path.exists() else folder / f"{name}.vrt") as ds:
            layers[name], bounds = ds.read(1), ds.bounds
    return layers, bounds


@pytest.mark.parametrize("limit,tile_pixels", [(1.5, 4096), (0.4, 12)])
def test_windows_on_the_whole_maps_cells_are_its_crops_and_join_without_seams(
        model_path, tmp_path, limit, tile_pixels):
    # The model's whole map; windows of it at offsets that are not whole anchor blocks
    # (6 cells of 0.1 m) must hold exactly its values: a window maps with the whole map's
    # local problems, not a lattice of its own. A small support limit leaves nodata cells
    # and skipped anchors; small tiles start off the blocks.
    arrays, meta = read_model_file(model_path)
    meta["config"]["map"].update(max_beam_distance_m=limit, tile_pixels=tile_pixels)
    model_path = tmp_path / "model.npz"
    write_model_file(model_path, arrays, meta)
    whole_folder = run_map(model_path, tmp_path / "whole", "--resolution", "0.1")
    whole, wb = _read_layers(whole_folder)
    assert np.isfinite(whole["probability"]).sum() > 500
    assert (limit > 1) or np.isnan(whole["probability"]).sum() > 500

    def window(name, row0, col0, rows, cols):
        x0, top = wb.left + col0 * 0.1, wb.top - row0 * 0.1
        folder = run_map(model_path, tmp_path / name, "--resolution", "0.1", "--bounds",
                         repr(x0), repr(top - rows * 0.1), repr(x0 + cols * 0.1), repr(top))
        layers, bounds = _read_layers(folder)
        assert layers["probability"].shape == (rows, cols)
        assert bounds.left == pytest.approx(x0, abs=1e-9)
        assert bounds.top == pytest.approx(top, abs=1e-9)
        return layers

    height, width = whole["probability"].shape
    split = width // 2 + 1  # not a multiple of the block
    west = window("west", 7, 3, height - 11, split - 3)
    assert np.isfinite(west["probability"]).sum() > 200
    east = window("east", 7, split, height - 11, width - split - 2)
    for name in whole:
        joined = np.hstack([west[name], east[name]])
        np.testing.assert_array_equal(joined, whole[name][7:height - 4, 3:width - 2])


@pytest.mark.parametrize("side", ["north-west", "south-east"])
def test_windows_beyond_the_whole_map_keep_its_anchors_and_join(model_path, tmp_path, side):
    # A wide support limit: the cells beyond the whole map's edges have values too.
    arrays, meta = read_model_file(model_path)
    meta["config"]["map"]["max_beam_distance_m"] = 5.0
    model_path = tmp_path / "model.npz"
    write_model_file(model_path, arrays, meta)
    whole_folder = run_map(model_path, tmp_path / "whole", "--resolution", "0.1")
    whole, wb = _read_layers(whole_folder)
    origin = np.array(json.loads((whole_folder / "metadata.json").read_text())
                      ["anchor_origin_m"])
    spacing = 0.6  # the fixture's block_size_m: 6 cells
    height, width = whole["probability"].shape

    def window(name, row0, col0, rows, cols):
        x0, top = wb.left + col0 * 0.1, wb.top - row0 * 0.1
        folder = run_map(model_path, tmp_path / name, "--resolution", "0.1", "--bounds",
                         repr(x0), repr(top - rows * 0.1), repr(x0 + cols * 0.1), repr(top))
        moved = (np.array(json.loads((folder / "metadata.json").read_text())
                          ["anchor_origin_m"]) - origin) / spacing
        np.testing.assert_allclose(moved, np.round(moved), atol=1e-9)  # the same anchors
        return _read_layers(folder)[0]

    # c reaches 12 cells beyond the whole map's edges on one side; a and b split it, and
    # d reaches less far (6 cells) beyond. (Whole blocks beyond: a lattice grown by just
    # that much would put the clamped edge band inside them.)
    if side == "north-west":
        row0, col0, rows, cols, split = -12, -12, height // 2 + 12, width // 2 + 12, 20
        d = window("d", row0 + 6, col0 + 6, rows - 6, cols - 6)
        d_at = (slice(6, None), slice(6, None))
    else:
        row0, col0 = height // 2, 7
        rows, cols, split = height - row0 + 12, width - col0 + 12, 23
        d = window("d", row0, col0, rows - 6, cols - 6)
        d_at = (slice(0, rows - 6), slice(0, cols - 6))
    c = window("c", row0, col0, rows, cols)
    a = window("a", row0, col0, rows, split)
    b = window("b", row0, col0 + split, rows, cols - split)
    assert np.isfinite(c["probability"]).all()
    for name in c:
        np.testing.assert_array_equal(np.hstack([a[name], b[name]]), c[name])  # no seam
        np.testing.assert_array_equal(d[name], c[name][d_at])  # nor where a window ends
    # Inside the whole map, more than half a spacing from its edges: the whole map's values.
    r_lo, r_hi = max(row0, 3), min(row0 + rows, height - 3)
    c_lo, c_hi = max(col0, 3), min(col0 + cols, width - 3)
    for name in c:
        np.testing.assert_array_equal(c[name][r_lo - row0:r_hi - row0, c_lo - col0:c_hi - col0],
                                      whole[name][r_lo:r_hi, c_lo:c_hi])


def test_lattice_frame_against_brute_force():
    from gpocc.mapping.mapper import lattice_frame

    whole = GridSpec(-3.217, -2.481, 0.1, 57, 43)
    cells = 6
    rng = np.random.default_rng(4)
    for _ in range(200):
        col0, row0 = rng.integers(-40, 70, 2)
        width, height = rng.integers(1, 60, 2)
        shift = rng.uniform(-0.45, 0.45, 2) * (rng.random() < 0.5)
        x0 = whole.x0 + (col0 + shift[0]) * 0.1
        top = whole.y1 - (row0 + shift[1]) * 0.1
        spec = GridSpec(x0, top - height * 0.1, 0.1, int(width), int(height))
        placed = lattice_frame(whole, spec, cells)
        frame, r, c = placed.grid, placed.row0, placed.col0
        # The window is frame's cells [r, r + height) x [c, c + width), centre for centre.
        rows, cols = np.arange(spec.height), np.arange(spec.width)
        np.testing.assert_allclose(frame.cell_centres_at(rows + r, cols + c)[0],
                                   spec.cell_centres_at(rows, cols)[0], atol=1e-9)
        np.testing.assert_allclose(frame.cell_centres_at(rows + r, cols + c)[1],
                                   spec.cell_centres_at(rows, cols)[1], atol=1e-9)
        assert 0 <= r and r + height <= frame.height and 0 <= c and c + width <= frame.width
        # The lattice's corner moved by whole blocks plus the shift onto spec's cells,
        # which is less than half a cell.
        blocks = np.array([(whole.x0 - frame.x0) / 0.1, (frame.y1 - whole.y1) / 0.1])
        off_cells = blocks - np.round(blocks)
        assert np.all(np.abs(off_cells) < 0.5 + 1e-9)
        np.testing.assert_allclose(off_cells, -shift * np.array([1, 1]), atol=1e-6)
        assert np.all(np.round(blocks) % cells == 0) and np.all(np.round(blocks) >= 0)
        if not shift.any() and col0 >= 0 and row0 >= 0 and col0 + width <= whole.width \
                and row0 + height <= whole.height:
            assert frame == whole and (r, c) == (row0, col0)


def test_block_count_is_the_anchors_whose_block_corner_is_in_the_map(model_path):
    from gpocc.mapping.blocks import block_cells
    from gpocc.mapping.mapper import block_count, default_spec, map_frame

    model = load_model(model_path)
    whole = default_spec(model, 0.1, model.config.map.margin_m)
    cells = block_cells(model.config.model.block_size_m, 0.1)
    for bounds in [whole.bounds, (-1.03, -0.7, 1.5, 1.1), (whole.x0 - 2, -1, 0.3, whole.y1 + 2)]:
        spec = GridSpec.from_bounds(*bounds, 0.1)
        placed = map_frame(model, spec)
        frame, r, c = placed.grid, placed.row0, placed.col0
        brute = sum(r <= row < r + spec.height and c <= col < c + spec.width
                    for row in range(0, frame.height, cells)
                    for col in range(0, frame.width, cells))
        assert block_count(model, spec) == brute


def test_a_coarser_map_samples_the_same_local_problems(model_path, tmp_path):
    # The fixture's anchors are 0.6 m apart: 6 cells of 0.1 m, 2 of 0.3 m. Maps of the
    # model at 0.3 m (its whole extent, or a window) have the 0.1 m map's anchors, and each
    # 0.3 m cell centre is the centre of a 0.1 m cell: the maps agree there.
    fine_folder = run_map(model_path, tmp_path / "fine", "--resolution", "0.1")
    fine, fb = _read_layers(fine_folder)
    origin = json.loads((fine_folder / "metadata.json").read_text())["anchor_origin_m"]
    whole = run_map(model_path, tmp_path / "whole", "--resolution", "0.3")
    window = run_map(model_path, tmp_path / "window", "--resolution", "0.3", "--bounds",
                     repr(fb.left + 0.3), repr(fb.top - 3.6), repr(fb.left + 3.9),
                     repr(fb.top - 0.6))
    for folder in (whole, window):
        coarse, cb = _read_layers(folder)
        rows, cols = np.nonzero(np.isfinite(coarse["probability"]))
        assert rows.size > 40
        x = cb.left + (cols + 0.5) * 0.3
        y = cb.top - (rows + 0.5) * 0.3
        fine_cols = np.floor((x - fb.left) / 0.1).astype(int)
        fine_rows = np.floor((fb.top - y) / 0.1).astype(int)
        np.testing.assert_allclose(fb.left + (fine_cols + 0.5) * 0.1, x, atol=1e-9)
        np.testing.assert_allclose(fb.top - (fine_rows + 0.5) * 0.1, y, atol=1e-9)
        np.testing.assert_allclose(coarse["probability"][rows, cols],
                                   fine["probability"][fine_rows, fine_cols], rtol=0,
                                   atol=1e-5)
        moved = (np.subtract(json.loads((folder / "metadata.json").read_text())
                             ["anchor_origin_m"], origin)) / 0.6
        np.testing.assert_allclose(moved, np.round(moved), atol=1e-9)


def test_progress_counts_block_count_on_windows_off_the_blocks(model_path, tmp_path):
    from gpocc.mapping.mapper import block_count, make_map

    model = load_model(model_path)
    for k, bounds in enumerate([(-1.73, -1.41, 1.12, 0.93), (-4.1, -3.3, -1.2, 2.9)]):
        spec = GridSpec.from_bounds(*bounds, 0.1)
        done: list[int] = []
        make_map(model, spec, tmp_path / str(k), workers=1, progress=done.append)
        assert sum(done) == block_count(model, spec) > 0


def test_bounds_within_round_off_of_the_cells_map_the_same_cells(model_path):
    # Bounds a nanometre off the whole map's cells (printed or computed with round-off)
    # give the exact bounds' grid and its place on the lattice: no extra column that
    # would cross the whole map's edge and grow the lattice.
    from gpocc.mapping.mapper import map_frame, whole_map

    model = load_model(model_path)
    whole = whole_map(model, 0.1)
    exact = (whole.x0 + 2.0, whole.y0 + 0.5, whole.x1, whole.y1 - 0.3)
    exact_spec = GridSpec.from_bounds(*exact, 0.1)
    exact_frame = map_frame(model, exact_spec)
    assert exact_frame.grid == whole
    for off in (-1e-9, 1e-9, -1e-8, 1e-8):  # metres: the box widened or narrowed
        spec = GridSpec.from_bounds(exact[0] - off, exact[1] - off, exact[2] + off,
                                    exact[3] + off, 0.1)
        assert (spec.width, spec.height) == (exact_spec.width, exact_spec.height)
        frame = map_frame(model, spec)
        assert (frame.grid, frame.row0, frame.col0) == (whole, exact_frame.row0,
                                                        exact_frame.col0)


@pytest.mark.parametrize("resolution_m", [0.1, 0.15])
def test_models_with_one_anchor_origin_share_their_anchors(tmp_path, resolution_m):
    # Two models of different extents (a room and its west half), both pinned to one
    # anchor origin: their maps' lattices coincide (origins a whole number of blocks
    # apart), and the whole map starts on that lattice; also when map.resolution_m (0.15)
    # does not divide the block and the maps are made at one that does.
    from gpocc.config import MapConfig

    origin = (-0.37, 1.93)
    samples = room_samples(3)
    half = samples.subset(np.flatnonzero(samples.means[:, 0] < 0.3))
    origins = []
    for k, s in enumerate((samples, half)):
        config = Config(model=ModelConfig(neighbours=60, block_size_m=0.5, training=TrainingConfig(
            patches=2, patch_size=60, anneal_maxfun=5, lbfgs_maxiter=5)),
            map=MapConfig(resolution_m=resolution_m, anchor_origin_m=origin))
        path = tmp_path / f"m{k}.npz"
        save_model(build_model(s, config), path)
        folder = run_map(path, tmp_path / f"map{k}", "--resolution", "0.1")
        meta = json.loads((folder / "metadata.json").read_text())
        origins.append(meta["anchor_origin_m"])
        x0, _, _, y1 = meta["bounds_m"]
        lo = s.means.min(axis=0) - 1.0
        assert x0 <= lo[0] + 1e-9 and y1 >= s.means[:, 1].max() + 1.0 - 1e-9
    for o in origins:
        steps = (np.array(o) - origin) / 0.5
        np.testing.assert_allclose(steps, np.round(steps), atol=1e-9)
