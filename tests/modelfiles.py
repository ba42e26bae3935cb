"""Reading and rewriting a saved model file's arrays and JSON metadata, for tests that
make old, newer or damaged files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def read_model_file(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    """The file's arrays and its decoded metadata, the samples as their own arrays (as
    files of every format hold them when they are not rows of the growth pool, and all
    files before format 6 do) even where the file stores their rows of the pool."""
    with np.load(path) as data:
        arrays = dict(data)
    if "sample_index" in arrays:
        from gpocc.gp.model import load_model
        from gpocc.gp.modelfile import ARRAY_LAYOUT

        samples = load_model(path).samples
        del arrays["sample_index"]
        arrays.update({name: getattr(samples, name) for name in ARRAY_LAYOUT})
    return arrays, json.loads(bytes(arrays["metadata"]).decode())


def write_model_file(path: Path, arrays: dict[str, np.ndarray], meta: dict) -> None:
    """Write ``arrays`` with ``meta`` as their metadata to ``path``."""
    arrays = {**arrays, "metadata": np.frombuffer(json.dumps(meta).encode(), np.uint8)}
    np.savez(path, **arrays)
