"""The OctoMap row of bench/experiment.py: an OctoMap occupancy probability raster.

Needs the ``bench`` extra (pyoctomap). The scans are read with gpocc's reader and beam
rules (:mod:`gpocc.samples.beam_rules`: laser poses with the mount, hits, no-returns), every
scan is inserted as a planar point cloud (z = 0) from its laser pose with OctoMap's own
ray casting and default sensor model (hit 0.7, miss 0.4, clamping 0.12-0.97), no-return
beams as free rays of ``no_return_free_m``; then each cell centre of a reference raster is
looked up: the leaf's occupancy probability, NaN where OctoMap knows nothing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def octomap_probability(inputs: list[Path], config_path: Path, out: Path,
                        like: Path) -> None:
    """Write ``out/probability.tif`` on the grid of the raster ``like``."""
    import pyoctomap

    from gpocc.config import load_config
    from gpocc.io.inputs import read_inputs
    from gpocc.io.rasters import read_raster, write_geotiff
    from gpocc.samples import beam_rules

    config = load_config(config_path)
    _, spec, _ = read_raster(like)
    tree = pyoctomap.OcTree(spec.resolution)
    for batch in read_inputs(inputs, config):
        sensor = beam_rules.sensor_config(batch, config)
        classes = beam_rules.classify_beams(batch.ranges, batch.range_min, batch.range_max)
        lasers = beam_rules.laser_poses(batch.poses, beam_rules.mount_vector(sensor))
        free_m = beam_rules.no_return_free_m(sensor, batch.range_max)
        for s in range(batch.n_scans):
            x, y, yaw = lasers[s]
            origin = np.array([x, y, 0.0])
            bearing = yaw + batch.angles
            for mask, dist, max_range in (
                    (classes.hit[s], batch.ranges[s], -1.0),
                    # max_range short of the points: OctoMap marks the ray free, no hit.
                    (classes.no_return[s], np.full(batch.n_beams, free_m), free_m - 1e-3)):
                if not mask.any() or (max_range != -1.0 and free_m <= 0.0):
                    continue
                d, b = dist[mask], bearing[mask]
                cloud = np.column_stack([x + d * np.cos(b), y + d * np.sin(b),
                                         np.zeros(b.size)])
                tree.insertPointCloud(cloud, origin, max_range=max_range, lazy_eval=True)
    tree.updateInnerOccupancy()
    xs, ys = spec.cell_centres()
    p = np.full(xs.shape, np.nan, dtype=np.float32)
    for index in np.ndindex(xs.shape):
        node = tree.search(np.array([xs[index], ys[index], 0.0]))
        if node is not None:
            p[index] = node.getOccupancy()
    out.mkdir(parents=True, exist_ok=True)
    write_geotiff(out / "probability.tif", p, spec, nodata=np.nan)
