"""The software versions recorded in model files and map folders (provenance)."""

from __future__ import annotations

import platform

import numpy as np
import scipy

import gpocc


def software_versions() -> dict[str, str]:
    """Versions of gpocc, numpy, scipy and Python, by name."""
    return {"gpocc": gpocc.__version__, "numpy": np.__version__, "scipy": scipy.__version__,
            "python": platform.python_version()}
