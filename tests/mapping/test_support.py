"""The data's support (nodata far from every beam) and seam-free blending of local problems.

Oracles: brute-force point-to-segment distances, the beam end points of the unscented
model's own ``beam_endpoint``, and per-cell local GP predictions.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gpocc.config import Config, ModelConfig, MountConfig, SensorConfig, TrainingConfig
from gpocc.gp.local import NeighbourIndex, predict_local
from gpocc.gp.model import build_model, load_model, save_model
from gpocc.gridspec import GridSpec
from gpocc.io.scans import ScanBatch
from gpocc.mapping import support as support_module
from gpocc.mapping.blend import predict_tile
from gpocc.mapping.blocks import Anchor, AnchorLattice
from gpocc.mapping.support import Support
from gpocc.samples.beam_rules import beam_endpoint
from gpocc.samples.beams import build_samples
from gpocc.samples.coverage import beam_coverage, beam_segments, coverage_of_segments


def segment_distance(points: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """(P,) brute force: distance from each point to the nearest of the segments."""
    d = end - start
    length2 = np.maximum(np.einsum("ij,ij->i", d, d), 1e-300)
    rel = points[:, None, :] - start[None, :, :]
    t = np.clip(np.einsum("pij,ij->pi", rel, d) / length2, 0.0, 1.0)
    nearest = start[None] + t[..., None] * d[None]
    return np.min(np.linalg.norm(points[:, None, :] - nearest, axis=-1), axis=1)


def room_batch(n_scans: int = 12, n_beams: int = 120) -> ScanBatch:
    """A robot driving along a 6 x 4 m room whose east wall has a 1 m doorway.

    Beams through the doorway see nothing (no return, +inf). Ranges are exact ray-box
    intersections.
    """
    angles = np.linspace(-np.pi, np.pi, n_beams, endpoint=False)
    xs = np.linspace(-2.0, 2.0, n_scans)
    poses = np.column_stack([xs, 0.3 * np.sin(xs), 0.1 * xs])
    ranges = np.empty((n_scans, n_beams))
    for s, (x, y, yaw) in enumerate(poses):
        phi = yaw + angles
        c, si = np.cos(phi), np.sin(phi)
        with np.errstate(divide="ignore", invalid="ignore"):
            tx = np.where(c > 0, (3.0 - x) / c, np.where(c < 0, (-3.0 - x) / c, np.inf))
            ty = np.where(si > 0, (2.0 - y) / si, np.where(si < 0, (-2.0 - y) / si, np.inf))
        r = np.minimum(tx, ty)
        hit_y = y + tx * si
        through_door = (tx < ty) & (c > 0) & (np.abs(hit_y) < 0.5)
        ranges[s] = np.where(through_door, np.inf, r)
    return ScanBatch(
        sensor="robot", source="room", stamps=np.arange(n_scans, dtype=float),
        angles=angles, ranges=ranges, poses=poses,
        pose_covariances=np.broadcast_to(np.diag([1e-4, 1e-4, 1e-5]), (n_scans, 3, 3)).copy(),
        range_min=0.05, range_max=20.0,
    )


def room_config(**map_changes) -> Config:
    config = Config(
        sensors=(SensorConfig(name="robot", no_return_free_m=3.0),),
        model=ModelConfig(neighbours=100, block_size_m=0.8, training=TrainingConfig(
            patches=3, patch_size=80, anneal_maxfun=8, lbfgs_maxiter=8)),
    )
    return dataclasses.replace(config, map=dataclasses.replace(config.map, **map_changes))


def test_beam_segments_match_the_unscented_beam_model():
    batch = room_batch(3, 40)
    mount = MountConfig(x_m=0.2, y_m=-0.1, yaw_deg=10.0)
    sensor = SensorConfig(name="robot", no_return_free_m=3.0, mount=mount)
    config = Config(sensors=(sensor,))
    start, end = beam_segments(batch, sensor, config)
    scan, beam = np.nonzero(np.isfinite(batch.ranges) | np.isinf(batch.ranges))
    r = np.where(np.isinf(batch.ranges[scan, beam]), 3.0, batch.ranges[scan, beam])
    inputs = np.column_stack([r, batch.angles[beam], batch.poses[scan]])
    m = np.array([0.2, -0.1, np.deg2rad(10.0)])
    np.testing.assert_allclose(end, beam_endpoint(inputs, m), atol=1e-12)
    zero = inputs.copy()
    zero[:, 0] = 0.0
    np.testing.assert_allclose(start, beam_endpoint(zero, m), atol=1e-12)
    assert np.any(np.isinf(batch.ranges))  # the doorway's no-return beams are included


def test_coverage_of_several_logs_is_the_raster_of_all_their_beams():
    """Batches far apart, marked one at a time on one raster, give the raster of all
    their beams' segments at once (same corner, same cells)."""
    config = room_config()
    sensor = config.sensors[0]
    batches = [room_batch(4, 60)]
    moved = room_batch(3, 50)
    batches.append(dataclasses.replace(moved, poses=moved.poses + [25.0, -13.0, 0.5]))
    segments = [beam_segments(b, sensor, config) for b in batches]
    whole = coverage_of_segments(np.concatenate([s for s, _ in segments]),
                                 np.concatenate([e for _, e in segments]))
    got = beam_coverage(batches, config)
    assert (got.x0, got.y0, got.cell_m, got.step_m) == (whole.x0, whole.y0, whole.cell_m,
                                                        whole.step_m)
    np.testing.assert_array_equal(got.covered, whole.covered)
    assert got.covered.shape[1] > 25.0 / got.cell_m  # one raster spans both


def test_coverage_distance_is_within_its_bound_of_the_exact_beam_distance():
    rng = np.random.default_rng(3)
    start = rng.uniform(-3, 3, (40, 2))
    end = start + rng.normal(0, 2.0, (40, 2))
    coverage = coverage_of_segments(start, end, 0.2)
    support = Support(coverage, 0.0)
    points = rng.uniform(-6, 6, (3000, 2))
    exact = segment_distance(points, start, end)
    approx, _ = support._tree.query(points)
    error = np.abs(approx - exact)
    assert error.max() <= coverage.error_m
    # The bound is not loose by an order of magnitude.
    assert error.max() > 0.3 * coverage.error_m


@pytest.mark.parametrize("batch", [1 << 20, 7])  # 7: many look-up batches, one cut mid-row
def test_support_mask_equals_per_cell_distances(monkeypatch, batch):
    monkeypatch.setattr(support_module, "_LOOKUP_BATCH", batch)
    rng = np.random.default_rng(4)
    start = rng.uniform(-2, 2, (15, 2))
    end = start + rng.normal(0, 1.5, (15, 2))
    support = Support(coverage_of_segments(start, end, 0.2), 1.0)
    spec = GridSpec.from_bounds(-5, -4, 5, 4.5, 0.1)
    xs, ys = spec.cell_centres()
    pts = np.column_stack([xs.ravel(), ys.ravel()])
    direct = support.within(pts).reshape(spec.shape)
    np.testing.assert_array_equal(support.mask(spec, 7), direct)
    assert 0.1 < direct.mean() < 0.9


@pytest.fixture(scope="module")
def room_model():
    batch = room_batch()
    config = room_config()
    samples = build_samples([batch], config)
    return build_model(samples, config, coverage=beam_coverage([batch], config)), batch


def test_model_file_keeps_the_coverage(room_model, tmp_path):
    model, _ = room_model
    path = tmp_path / "m.npz"
    save_model(model, path)
    again = load_model(path).coverage
    np.testing.assert_array_equal(again.covered, model.coverage.covered)
    assert (again.x0, again.y0, again.cell_m) == (model.coverage.x0, model.coverage.y0,
                                                   model.coverage.cell_m)


def test_cells_far_from_every_beam_are_nodata(room_model, tmp_path):
    # Issue 10's target, measured as stated: of the cells more than 2 m from any beam
    # (brute-force distance to every beam segment), >= 99% have p nodata or in
    # [0.35, 0.65] and >= 95% are nodata in class.tif; map.pgm shows them unknown.
    import rasterio

    from gpocc.io.mapserver import read_map_server
    from gpocc.mapping.mapper import make_map

    model, batch = room_model
    spec = GridSpec.from_bounds(-8, -6, 10, 6, 0.25)
    out = tmp_path / "map"
    out.mkdir()
    make_map(model, spec, out)
    with rasterio.open(out / "probability.tif") as ds:
        p = ds.read(1)
    with rasterio.open(out / "variance.tif") as ds:
        var = ds.read(1)
    with rasterio.open(out / "class.tif") as ds:
        classes = ds.read(1)
    server, _ = read_map_server(out / "map.yaml")
    start, end = beam_segments(batch, model.config.sensors[0], model.config)
    xs, ys = spec.cell_centres()
    distance = segment_distance(np.column_stack([xs.ravel(), ys.ravel()]), start,
                                end).reshape(spec.shape)
    far = distance > 2.0
    assert far.sum() > 1000
    ok = np.isnan(p[far]) | ((p[far] >= 0.35) & (p[far] <= 0.65))
    assert ok.mean() >= 0.99
    assert np.mean(classes[far] == 255) >= 0.95
    assert np.all(server[far] == 2)
    # Nodata exactly where the configured distance says, up to the coverage's bound.
    limit, bound = model.config.map.max_beam_distance_m, model.coverage.error_m
    assert np.all(np.isnan(p[distance > limit + bound]))
    assert np.all(np.isnan(var[distance > limit + bound]))
    near = distance < limit - bound
    assert np.all(np.isfinite(p[near])) and np.all(classes[near] != 255)


def test_skipped_problems_and_unmasked_map_agree_inside_the_support(room_model):
    # Skipping local problems and cells outside the support must not change any supported
    # cell.
    model, _ = room_model
    spec = GridSpec.from_bounds(-6, -4.5, 6, 4.5, 0.25)
    lattice = AnchorLattice.of_model(spec, model.config.model)
    masked = predict_tile(model, lattice, 0, 0, spec, Support(model.coverage, 1.5))
    full = predict_tile(model, lattice, 0, 0, spec, None)
    inside = np.isfinite(masked.probability)
    assert masked.anchors < full.anchors
    # Masked anchors predict only their supported cells: fewer queries per triangular
    # solve, so round-off (not the value) may differ.
    np.testing.assert_allclose(masked.probability[inside], full.probability[inside],
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(masked.variance[inside], full.variance[inside],
                               rtol=1e-12, atol=0)


def test_mask_pieces_are_bit_for_bit_the_whole_mask_on_aligned_grids():
    # A map grid aligned with the coverage grid puts many cells exactly at the distance
    # limit; a piece computed from its own sub-grid's origin put some of them on the
    # other side (last-bit differences in the cell centres). Oracle: the whole mask.
    from gpocc.samples.coverage import Coverage

    rng = np.random.default_rng(3)
    for _ in range(40):
        coverage = Coverage(0.0, 0.0, 0.1, 0.05, rng.random((40, 40)) < 0.02)
        support = Support(coverage, float(rng.choice([0.3, 0.5, 1.0, 1.5])))
        spec = GridSpec.from_bounds(-1.0, -1.0, 5.0, 5.0, float(rng.choice([0.05, 0.1, 0.2])))
        cells = int(rng.integers(3, 12))
        whole = support.mask(spec, cells)
        r0, c0 = int(rng.integers(0, 3)) * cells, int(rng.integers(0, 3)) * cells
        c1 = int(rng.integers(c0, spec.width + 1))
        pieces, row = [], r0
        while row < spec.height:
            stop = min(spec.height, row + int(rng.integers(1, 5)) * cells)
            pieces.append(support.mask(spec, cells, rows=(row, stop), cols=(c0, c1)))
            row = stop
        np.testing.assert_array_equal(np.vstack(pieces), whole[r0:, c0:c1])
    with pytest.raises(ValueError, match="multiple of 4"):
        support.mask(spec, 4, rows=(2, 8))


@pytest.mark.parametrize("workers", [1, 2])
def test_anchors_laid_out_in_bands_give_the_one_band_map(room_model, monkeypatch, workers):
    # predict_tile lays out (support mask, supported anchors) and queues one band of
    # lattice rows at a time; the mask is built from pieces. Oracle: one band and one
    # Support.mask call over the whole window.
    from gpocc.mapping import blend
    from gpocc.mapping.executors import anchor_executor

    model, _ = room_model
    spec = GridSpec.from_bounds(-6, -4.5, 6, 4.5, 0.25)
    lattice = AnchorLattice.of_model(spec, model.config.model)
    support = Support(model.coverage, 1.5)
    layers = {}
    for rows in (1, 3, 10_000):
        monkeypatch.setattr(blend, "BAND_ROWS", rows)
        with anchor_executor(model, workers) as executor:
            layers[rows] = predict_tile(model, lattice, 0, 0, spec, support,
                                        executor=executor)
    one = layers[10_000]
    np.testing.assert_array_equal(np.isnan(one.probability),
                                  ~support.mask(spec, lattice.cells))
    for rows in (1, 3):
        assert layers[rows].anchors == one.anchors
        for name in ("mean", "variance", "probability", "unsure"):
            np.testing.assert_array_equal(getattr(layers[rows], name), getattr(one, name))


def jumps_at_and_inside_block_boundaries(values: np.ndarray, cells: int):
    """Max |difference| of adjacent cells across block boundaries and within blocks."""
    diff = np.abs(np.diff(values))
    at_boundary = (np.arange(1, len(values)) % cells) == 0
    return diff[at_boundary].max(), diff[~at_boundary].max()


@pytest.fixture(scope="module")
def room_tile(room_model):
    """The room at 0.05 m (0.8 m blocks of 16 cells), blended, without a support mask."""
    model, _ = room_model
    spec = GridSpec.from_bounds(-2.4, -3.2, 2.4, 3.2, 0.05)
    lattice = AnchorLattice.of_model(spec, model.config.model)
    return lattice, predict_tile(model, lattice, 0, 0, spec, None)


# Rows: 16 lies 0.4 m behind the north wall, where p is between 0.9 and 0.98 (inside the
# room p saturates at 0); 64 runs through the free inside of the room.
@pytest.mark.parametrize(("layer", "row"), [("probability", 16), ("mean", 64),
                                            ("variance", 64), ("variance", 16)])
def test_no_seams_between_blocks(room_model, room_tile, layer, row):
    # Along a row crossing block boundaries: the largest jump between adjacent cells at a
    # block boundary is no larger than inside blocks, nor than the largest jump of a
    # brute-force per-cell oracle (each cell predicted from the neighbours of its own
    # centre); the one-problem-per-block scheme this replaces fails the first check.
    model, _ = room_model
    lattice, tile = room_tile
    cells = lattice.cells
    blended = getattr(tile, layer)[row]
    at, inside = jumps_at_and_inside_block_boundaries(blended, cells)
    assert at <= inside

    index = NeighbourIndex(model.samples)
    xs, ys = lattice.spec.cell_centres()
    pts = np.column_stack([xs[row], ys[row]])
    k = model.config.model.neighbours

    def predict(centre, point):
        pred = predict_local(model.kernel, model.noise_variance, index.problem(centre, k),
                             point[None], model.level)
        if layer == "probability":
            return model.classifier.probability(pred.mean, pred.variance)[0]
        return getattr(pred, layer)[0]

    oracle = np.array([predict(p, p) for p in pts])
    assert at <= np.abs(np.diff(oracle)).max()
    if layer == "variance":
        # Whether the old scheme's variance jumps at these rows depends on the learned
        # hyperparameters (it did before thinning broke ties in single precision, and
        # no longer does); its mean and probability do, which shows the check bites.
        return
    per_block = np.array([predict(lattice.centre(Anchor(row // cells, c // cells)), p)
                          for c, p in enumerate(pts)])
    old_at, old_inside = jumps_at_and_inside_block_boundaries(per_block, cells)
    assert old_at > old_inside


@pytest.mark.parametrize("seed", [0, 1])
def test_supported_anchors_are_those_whose_footprint_holds_a_supported_cell(seed):
    """Against slicing each anchor's footprint out of the mask: the same anchors kept
    (with their footprint's mask) and skipped, for a sparse mask, offsets and partly
    covered lattice rows."""
    from gpocc.mapping.blend import supported_anchors

    rng = np.random.default_rng(seed)
    spec = GridSpec(-3.0, -2.0, 0.1, 97, 83)  # width, height: blocks cut at the edges
    lattice = AnchorLattice(spec, 8, 0.5 + 0.5 * seed)
    rows, cols = lattice.shape
    row0, col0 = 8, 16  # the mask starts on block boundaries, as a tile's does
    mask = np.zeros((spec.height - row0, spec.width - col0), dtype=bool)
    mask[rng.random(mask.shape) < 0.004] = True
    anchors = [Anchor(r, c) for r in range(2, rows) for c in range(3, cols)]
    kept, skipped = supported_anchors(lattice, anchors, mask, row0, col0)
    want_kept, want_skipped = [], []
    for a in anchors:
        fp = lattice.footprint_block(a)
        inside = mask[fp.row0 - row0:fp.row0 + fp.rows - row0,
                      fp.col0 - col0:fp.col0 + fp.cols - col0]
        (want_kept if inside.any() else want_skipped).append((a, inside))
    assert [(a.row, a.col) for a in skipped] == [(a.row, a.col) for a, _ in want_skipped]
    assert [(a.row, a.col) for a in kept] == [(a.row, a.col) for a, _ in want_kept]
    for got, (_, inside) in zip(kept, want_kept, strict=True):
        np.testing.assert_array_equal(got.inside, inside)
    assert want_kept and want_skipped  # both kinds occur
