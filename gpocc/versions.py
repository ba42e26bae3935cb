"""The software versions recorded in model files and map folders (provenance)."""

from __future__ import annotations

import platform

import numpy as np
import scipy

import gpocc


def software_versions(rasters: bool = True) -> dict[str, str]:
    """Versions of gpocc, numpy, scipy, the compiler of gpocc's compiled loops (``kernels``,
    e.g. ``gcc 12.2.0``) and Python, by name;
    with ``rasters`` also rasterio and GDAL (every GeoTIFF byte of a map folder). A model
    file writes no raster, and importing rasterio only to read its version cost 0.5 s of
    every ``gpocc train``."""
    from gpocc import compiled

    versions = {"gpocc": gpocc.__version__, "numpy": np.__version__,
                "scipy": scipy.__version__, "kernels": compiled.compiler()}
    if rasters:
        import rasterio

        versions.update(rasterio=rasterio.__version__, gdal=rasterio.__gdal_version__)
    return {**versions, "python": platform.python_version()}


def model_versions() -> dict[str, str]:
    """:func:`software_versions` of a model file (no raster libraries)."""
    return software_versions(rasters=False)
