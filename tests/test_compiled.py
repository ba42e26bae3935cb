"""The compiled loops' loader and the checks their ctypes wrappers make before C runs.

Their values are checked elsewhere against independent references: the expected kernels
against the numpy path (tests/test_expected.py), the beam transform against the generic
unscented transform and Monte Carlo (tests/test_beam_unscented.py); here the coverage
loop against a plain-Python walk along each segment.
"""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from gpocc import compiled


def test_a_library_older_than_its_source_is_refused(tmp_path):
    library = tmp_path / "kernels.so"
    shutil.copy(compiled.built_library(), library)
    source = tmp_path / "kernels.c"
    source.write_text("/* changed */\n")
    os.utime(library, (1_000_000, 1_000_000))
    with pytest.raises(ImportError, match="older than kernels.c"):
        compiled.load(library, source)
    os.utime(source, (1_000, 1_000))
    assert compiled.load(library, source).gpocc_kernels_compiler()


def test_provenance_names_the_compiler():
    assert compiled.compiler().split()[0] in {"gcc", "clang"}


@pytest.mark.parametrize("bad", [
    np.empty((5, 5), dtype=np.float32),          # wrong dtype
    np.empty((5, 6)),                            # wrong shape
    np.empty((5, 10))[:, ::2],                   # not contiguous
])
def test_outputs_that_c_cannot_write_safely_are_refused(bad):
    rng = np.random.default_rng(1)
    u = rng.normal(size=(3, 20)) * 0.1
    weights = np.full(20, 0.25)
    starts = np.arange(0, 24, 4)
    with pytest.raises(ValueError, match="output must be"):
        compiled.nn_matrix(u, weights, starts, 1.0, bad)
    readonly = np.empty((5, 5))
    readonly.setflags(write=False)
    with pytest.raises(ValueError, match="output must be"):
        compiled.nn_matrix(u, weights, starts, 1.0, readonly)


def test_inconsistent_node_layouts_are_refused():
    u = np.zeros((3, 20))
    out = np.empty((5, 5))
    with pytest.raises(ValueError, match="starts"):
        compiled.nn_matrix(u, np.ones(20), np.array([0, 4, 8, 12, 16, 24]), 1.0, out)
    with pytest.raises(ValueError, match="weights"):
        compiled.nn_matrix(u, np.ones(19), np.arange(0, 24, 4), 1.0, out)
    with pytest.raises(ValueError, match="pair index"):
        compiled.correlated_nodes(np.zeros((3, 2)), np.zeros((3, 2, 2)), np.zeros((3, 2, 3)),
                                  np.array([0]), np.array([3]), np.zeros((16, 4)))
    with pytest.raises(ValueError, match="scan index"):
        compiled.beam_unscented(np.ones(2), np.zeros(2), np.ones(2), 0.1, np.array([0, 5]),
                                np.zeros((2, 3)), np.zeros((2, 3, 3)), np.zeros((2, 3, 3)),
                                np.zeros(3), np.ones(11), np.ones(11), 1.0)


def _walk(start, end, covered):
    """The coverage rule in plain Python: a point every cell along the segment, and its
    end, each marking the cell it falls in (clamped to the raster)."""
    height, width = covered.shape
    for (sx, sy), (ex, ey) in zip(start, end, strict=True):
        length = float(np.hypot(ex - sx, ey - sy))
        ux, uy = (ex - sx) / max(length, 1e-12), (ey - sy) / max(length, 1e-12)
        for k in range(int(np.floor(length)) + 2):
            t = min(float(k), length)
            col = min(max(int(sx + t * ux), 0), width - 1)
            row = min(max(int(sy + t * uy), 0), height - 1)
            covered[row, col] = True


def test_coverage_loop_marks_the_cells_of_a_walk_along_each_segment():
    rng = np.random.default_rng(5)
    start = rng.uniform(0.0, 40.0, (300, 2))
    end = start + rng.normal(scale=8.0, size=(300, 2))
    end = np.clip(end, 0.0, 45.0)
    end[:5] = start[:5]  # zero-length segments mark their one cell
    got, want = np.zeros((46, 47), bool), np.zeros((46, 47), bool)
    compiled.mark_segments(start, end, got)
    _walk(start, end, want)
    np.testing.assert_array_equal(got, want)
    assert 300 < want.sum() < want.size
