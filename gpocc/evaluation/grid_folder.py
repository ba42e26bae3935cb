"""Writing a log-odds grid as a map folder, so ``gpocc evaluate`` compares it like a map."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gpocc.config import Config
from gpocc.evaluation.grid import LogOddsGrid
from gpocc.gp.classify import NO_DATA, class_counts, classify
from gpocc.io.mapserver import write_map_server
from gpocc.io.rasters import BERNOULLI_VARIANCE_BAND, CLASS_BAND, PROBABILITY_BAND, write_geotiff
from gpocc.mapping.render import preview_factor, render_preview


def write_grid_folder(out_dir: Path, grid: LogOddsGrid, config: Config) -> dict[str, int]:
    """Write the map-folder layers of ``grid`` into ``out_dir``; return the class counts.

    Files: ``probability.tif`` and ``variance.tif`` (float32, NaN no data; the variance
    is the Bernoulli ``p (1 - p)``), ``class.tif`` (uint8 0 free, 1 occupied, 2 unsure,
    255 no data), ``map.yaml`` + ``map.pgm`` and ``preview.png``.
    """
    spec = grid.spec
    georef = config.map.georef
    occupied, free = config.classify.occupied, config.classify.free
    probability = grid.probability.astype(np.float32)
    variance = grid.variance.astype(np.float32)
    classes = classify(probability, occupied, free)
    write_geotiff(out_dir / "probability.tif", probability, spec, nodata=np.nan, georef=georef,
                  band=PROBABILITY_BAND)
    write_geotiff(out_dir / "variance.tif", variance, spec, nodata=np.nan, georef=georef,
                  band=BERNOULLI_VARIANCE_BAND)
    write_geotiff(out_dir / "class.tif", classes, spec, nodata=NO_DATA, georef=georef,
                  band=CLASS_BAND)
    write_map_server(out_dir / "map.yaml", probability, spec, occupied, free,
                     config.map.max_pgm_pixels)
    stride = preview_factor(spec.shape)
    render_preview(out_dir / "preview.png", probability[::stride, ::stride],
                   variance[::stride, ::stride], spec.decimated(stride),
                   title="log-odds occupancy grid")
    return class_counts(classes)
