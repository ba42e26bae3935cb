"""The compiled loops' loader and the checks their ctypes wrappers make before C runs.

Their values are checked elsewhere against independent references: the expected kernels
against the numpy path (tests/gp/test_expected.py), the beam transform against the generic
unscented transform and Monte Carlo (tests/samples/test_beam_unscented.py); here the coverage
loop against a plain-Python walk along each segment.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

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


def test_the_declarations_match_the_c_definitions():
    """compiled.DECLARATIONS, from which every ctypes signature and argument check is
    made, against the exported definitions of gpocc/_kernels.c: the same functions with
    the same parameter names, types and constness."""
    source = Path(compiled.__file__).with_name("_kernels.c")
    if not source.exists():
        pytest.skip("an installed copy without its C source")
    defined = compiled.parse_prototypes(source.read_text(), definitions=True)
    declared = compiled.parse_prototypes(compiled.DECLARATIONS)
    assert len(defined) == 17
    assert declared == defined
    # The parser sees what it should: a pointer output, a const input, a scalar.
    params = {p.name: p for p in declared["gpocc_nn_matrix"].parameters}
    assert params["out"] == compiled.Parameter("out", "double", True, False)
    assert params["starts"] == compiled.Parameter("starts", "i64", True, True)
    assert params["n"] == compiled.Parameter("n", "i64", False, False)
    assert declared["gpocc_kernels_compiler"].returns == "char*"


def test_the_binding_checks_names_dtypes_and_outputs():
    x = np.linspace(-1.0, 1.0, 7)
    out = np.empty(7)
    bound = compiled._c.asin_array
    bound(x=x, n=7, out=out)
    np.testing.assert_allclose(out, np.arcsin(x), rtol=0, atol=1e-15)
    with pytest.raises(TypeError, match="missing argument 'out'"):
        bound(x=x, n=7, output=out)
    with pytest.raises(ValueError, match="x must be a C-ordered float64"):
        bound(x=x.astype(np.float32), n=7, out=out)
    with pytest.raises(ValueError, match="x must be a C-ordered float64"):
        bound(x=np.linspace(-1, 1, 14)[::2], n=7, out=out)
    out.setflags(write=False)
    with pytest.raises(ValueError, match="output out must be writable"):
        bound(x=x, n=7, out=out)


def _nan_at(array: np.ndarray, value: float = np.nan) -> np.ndarray:
    array = np.array(array, dtype=np.float64)
    array.flat[array.size // 2] = value
    return array


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_no_nan_reaches_the_loops_compiled_with_finite_math_only(value):
    """setup.py's -ffinite-math-only lets the compiler assume no NaN or infinity: each is
    refused with a ValueError before a loop runs, by the wrapper or, for the per-problem
    loops of compiled.FINITE_UPSTREAM, by gpocc.gp.expected's entry points."""
    from gpocc.gp import expected as ex
    from gpocc.gp.kernels import NeuralNetworkKernel

    # Loops that check here: every float input.
    with pytest.raises(ValueError, match="NaN or infinity"):
        compiled.asin_array(_nan_at(np.zeros(9), value))
    with pytest.raises(ValueError, match="NaN or infinity"):
        compiled.cholesky_psd4(_nan_at(np.tile(np.eye(4)[:, :, None], (1, 1, 3)), value))
    with pytest.raises(ValueError, match="NaN or infinity"):
        compiled.mark_segments(_nan_at(np.zeros((4, 2)), value), np.ones((4, 2)),
                               np.zeros((3, 3), dtype=bool))
    # The per-problem loops: their data is checked where it enters.
    rng = np.random.default_rng(3)
    n = 12
    means, covs = rng.normal(size=(n, 2)), np.tile(np.eye(2) * 0.01, (n, 1, 1))
    scans, factors = np.arange(n) // 4, rng.normal(size=(n, 2, 3)) * 0.05
    queries = rng.normal(size=(5, 2))
    kernel = NeuralNetworkKernel(1.0, 2.0, (3.0, 4.0))
    for bad in ("means", "covs", "factors", "queries"):
        args = {"means": means, "covs": covs, "factors": factors, "queries": queries}
        args[bad] = _nan_at(args[bad], value)
        with pytest.raises(ValueError, match="finite"):
            ex.expected_local_system(kernel, args["means"], args["covs"], args["queries"], 2,
                                     0.1, scan_ids=scans, pose_factors=args["factors"],
                                     backend="compiled")
        if bad != "queries":
            with pytest.raises(ValueError, match="finite"):
                ex.expected_kernel_matrix(kernel, args["means"], args["covs"], 2,
                                          scan_ids=scans, pose_factors=args["factors"],
                                          with_gradient=True, backend="compiled")
        if bad in ("means", "covs", "queries"):
            with pytest.raises(ValueError, match="finite"):
                ex.expected_kernel_cross(kernel, args["queries"], args["means"],
                                         args["covs"], 2, backend="compiled")


def test_a_stale_library_is_one_error_line_at_the_command_line(tmp_path):
    # A copy of the package whose C source is newer than its built library: every command
    # says so in one line (status 2) instead of an ImportError traceback.
    package = Path(compiled.__file__).parent
    copy = tmp_path / "gpocc"
    shutil.copytree(package, copy, ignore=shutil.ignore_patterns("__pycache__"))
    library = next(copy.glob("_kernels*.so"))
    os.utime(library, (1_000_000, 1_000_000))
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    for argv in (["info", str(tmp_path / "missing.log")],
                 ["map", str(tmp_path / "m.npz"), "--resolution", "1", "--out", "m"]):
        result = subprocess.run([sys.executable, "-m", "gpocc", *argv], env=env, cwd=tmp_path,
                                capture_output=True, text=True, timeout=120)
        assert result.returncode == 2, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and "older than _kernels.c" in lines[0], result.stderr
        assert "make install" in lines[0] and "Traceback" not in result.stderr


def test_a_library_that_lacks_a_declared_loop_is_refused(monkeypatch):
    # Built from older source but newer on disk (copied keeping its mtime): the missing
    # symbol is an install problem in one line, not an AttributeError.
    from gpocc.errors import CompiledLoopsUnavailable

    monkeypatch.setattr(compiled, "DECLARATIONS",
                        compiled.DECLARATIONS + "void gpocc_not_built(void);\n")
    with pytest.raises(CompiledLoopsUnavailable, match="lacks gpocc_not_built.*make install"):
        compiled.load(compiled.built_library())
