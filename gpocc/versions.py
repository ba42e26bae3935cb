"""The software versions recorded in model files and map folders (provenance)."""

from __future__ import annotations

import platform

import numpy as np
import scipy

import gpocc


def software_versions() -> dict[str, str]:
    """Versions of gpocc, numpy, scipy, numba (the expected kernels), rasterio and GDAL
    (every GeoTIFF byte) and Python, by name."""
    import numba
    import rasterio

    return {"gpocc": gpocc.__version__, "numpy": np.__version__, "scipy": scipy.__version__,
            "numba": numba.__version__, "rasterio": rasterio.__version__,
            "gdal": rasterio.__gdal_version__, "python": platform.python_version()}
