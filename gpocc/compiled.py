"""The compiled loops of ``gpocc/_kernels.c``, loaded with ctypes.

``pip install`` (``make install``) builds them as the extension ``gpocc._kernels``. ctypes
releases the GIL for every call, so threads run them in parallel. Each wrapper checks
what C cannot: dtypes, C order, shapes, and that output arrays are writable float64 in C
order. Loading the library takes about a millisecond; numba, which they replace, cost
0.5-0.9 s of every process's start (measured in commit b5aee9e, which replaced it).
"""

from __future__ import annotations

import ctypes
import importlib.util
from pathlib import Path

import numpy as np

_P = ctypes.c_void_p
_I = ctypes.c_int64
_D = ctypes.c_double
_B = ctypes.c_int

#: name -> (argument types, return type) of every exported loop.
_SIGNATURES: dict[str, tuple[list, object]] = {
    "gpocc_kernels_compiler": ([], ctypes.c_char_p),
    "gpocc_asin_array": ([_P, _I, _P], None),
    "gpocc_gaussian_nodes_2d": ([_P, _P, _I, _P, _I, _P], None),
    "gpocc_nn_matrix": ([_P, _P, _P, _I, _D, _P], ctypes.c_int),
    "gpocc_nn_matrix_uniform": ([_P, _P, _I, _I, _D, _P], ctypes.c_int),
    "gpocc_nn_matrix_gradient": ([_P, _P, _P, _I, _D, _P, _P, _B], ctypes.c_int),
    "gpocc_nn_cross": ([_P, _I, _P, _P, _P, _I, _D, _P], ctypes.c_int),
    "gpocc_nn_cross_uniform": ([_P, _I, _P, _P, _I, _I, _D, _P], None),
    "gpocc_cholesky_psd4": ([_P, _I, _P], None),
    "gpocc_correlated_nodes": ([_P, _P, _P, _P, _P, _I, _P, _I, _D, _P], None),
    "gpocc_nn_same_scan_pairs": ([_P, _P, _P, _P, _P, _I, _P, _P, _I, _P, _D, _D, _P, _B, _B],
                                 ctypes.c_int),
    "gpocc_correlated_pairs": ([_P, _P, _P, _I, _D, _D, _P, _P], ctypes.c_int64),
    "gpocc_nn_local_system": ([_P, _P, _P, _P, _I, _P, _I, _P, _P, _I, _P, _P, _I, _P, _D,
                               _D, _B, _D, _D, _P, _P, _P], ctypes.c_int),
    "gpocc_beam_unscented": ([_P, _P, _P, _D, _P, _I, _P, _P, _P, _P, _P, _P, _D, _P, _P, _P],
                             None),
    "gpocc_mark_segments": ([_P, _P, _I, _P, _I, _I], None),
}


def built_library() -> Path:
    """The built extension ``gpocc._kernels`` (a shared library)."""
    spec = importlib.util.find_spec("gpocc._kernels")
    if spec is None or not spec.origin:
        raise ImportError("gpocc's compiled loops (gpocc/_kernels.c) are not built: run "
                          "'make install' (or 'pip install -e .') with a C compiler")
    return Path(spec.origin)


def load(library: Path, source: Path | None = None) -> ctypes.CDLL:
    """Open ``library`` and declare its loops' signatures. A ``source`` (the C file of a
    source checkout) newer than the library means stale loops: ImportError."""
    if source is not None and source.exists() \
            and source.stat().st_mtime > library.stat().st_mtime:
        raise ImportError(f"{library.name} is older than {source.name}: rebuild it with "
                          "'make install'")
    lib = ctypes.CDLL(str(library))
    for name, (argtypes, restype) in _SIGNATURES.items():
        function = getattr(lib, name)
        function.argtypes = argtypes
        function.restype = restype
    return lib


_lib = load(built_library(), Path(__file__).with_name("_kernels.c"))


def compiler() -> str:
    """The compiler that built the loops, e.g. ``gcc 12.2.0`` (provenance)."""
    return _lib.gpocc_kernels_compiler().decode()


def _in(array: np.ndarray, dtype: type = np.float64) -> np.ndarray:
    """``array`` as C-ordered ``dtype`` (a copy only if needed)."""
    return np.ascontiguousarray(array, dtype=dtype)


def _out(array: np.ndarray, shape: tuple[int, ...]) -> int:
    """The address of an output array, which must be writable C-ordered float64 of
    ``shape``: C writes through it, so a wrong one would corrupt memory silently."""
    if (array.dtype != np.float64 or not array.flags.c_contiguous
            or not array.flags.writeable or array.shape != shape):
        raise ValueError(f"output must be writable C-ordered float64 of shape {shape}, "
                         f"got {array.dtype} {array.shape}")
    return array.ctypes.data


def _check(status: int) -> None:
    if status < 0:
        raise MemoryError("out of memory in gpocc's compiled loops")


def _points(u: np.ndarray, weights: np.ndarray, starts: np.ndarray) -> int:
    """N of point-major nodes: ``u`` (3, M), ``weights`` (M,), ``starts`` (N + 1,)
    non-decreasing from 0 to M (C indexes with them)."""
    total = u.shape[1] if u.ndim == 2 else -1
    if (u.ndim != 2 or u.shape[0] != 3 or weights.shape != (total,) or starts.ndim != 1
            or starts.shape[0] < 1 or starts[0] != 0 or starts[-1] != total
            or np.any(np.diff(starts) < 0)):
        raise ValueError("u (3, M), weights (M,) and starts (N + 1,) from 0 to M expected")
    return starts.shape[0] - 1


def _uniform_points(u: np.ndarray, weights: np.ndarray) -> int:
    """N of node-major nodes sharing one rule: ``u`` (3, L N), ``weights`` (L,)."""
    size = weights.shape[0]
    if u.ndim != 2 or u.shape[0] != 3 or weights.ndim != 1 or size == 0 or u.shape[1] % size:
        raise ValueError("u (3, L N) and weights (L,) expected")
    return u.shape[1] // size


def _queries(q: np.ndarray) -> int:
    if q.ndim != 2 or q.shape[0] != 3:
        raise ValueError(f"scaled queries (3, Q) expected, got {q.shape}")
    return q.shape[1]


def _pairs(n: int, i: np.ndarray, j: np.ndarray) -> int:
    """P of pair indices ``i``, ``j`` (P,) into N points."""
    if i.ndim != 1 or i.shape != j.shape:
        raise ValueError("pair indices i and j must both be (P,)")
    if i.size and (min(i.min(), j.min()) < 0 or max(i.max(), j.max()) >= n):
        raise ValueError("pair index out of range of the points")
    return i.shape[0]


def asin_array(x: np.ndarray) -> np.ndarray:
    """The compiled branch-free arcsin, elementwise over (M,) values in [-1, 1]."""
    x = _in(x)
    out = np.empty_like(x)
    _lib.gpocc_asin_array(x.ctypes.data, x.size, out.ctypes.data)
    return out


def gaussian_nodes_2d(means: np.ndarray, covariances: np.ndarray, unit: np.ndarray
                      ) -> np.ndarray:
    """(2, N L) nodes ``mean_i + R_i unit_k`` of N 2-D Gaussians ((N, 2) means, (N, 2, 2)
    covariances, (L, 2) unit nodes), point-major (node k of point i in column i L + k)."""
    means, covariances, unit = _in(means), _in(covariances), _in(unit)
    n, size = means.shape[0], unit.shape[0]
    if covariances.shape != (n, 2, 2) or means.shape != (n, 2) or unit.shape != (size, 2):
        raise ValueError("means (N, 2), covariances (N, 2, 2) and unit (L, 2) expected")
    out = np.empty((2, n * size))
    _lib.gpocc_gaussian_nodes_2d(means.ctypes.data, covariances.ctypes.data, n,
                                 unit.ctypes.data, size, out.ctypes.data)
    return out


def nn_matrix(u: np.ndarray, weights: np.ndarray, starts: np.ndarray, scale: float,
              out: np.ndarray) -> None:
    """out (N, N): E k(x_i, x_j) off the diagonal (diagonal untouched) from scaled nodes
    ``u`` (3, M), per-node ``weights`` (M,) and node offsets ``starts`` (N + 1,)."""
    u, weights, starts = _in(u), _in(weights), _in(starts, np.int64)
    n = _points(u, weights, starts)
    _check(_lib.gpocc_nn_matrix(u.ctypes.data, weights.ctypes.data, starts.ctypes.data, n,
                                scale, _out(out, (n, n))))


def nn_matrix_uniform(u: np.ndarray, weights: np.ndarray, scale: float, out: np.ndarray
                      ) -> None:
    """:func:`nn_matrix` for N points sharing one rule of L nodes: ``u`` (3, L N)
    node-major, ``weights`` (L,)."""
    u, weights = _in(u), _in(weights)
    size = weights.shape[0]
    n = _uniform_points(u, weights)
    _check(_lib.gpocc_nn_matrix_uniform(u.ctypes.data, weights.ctypes.data, size, n, scale,
                                        _out(out, (n, n))))


def nn_matrix_gradient(u: np.ndarray, weights: np.ndarray, starts: np.ndarray, scale: float,
                       out: np.ndarray, offsets: np.ndarray, with_scale: bool) -> None:
    """out (4 or 5, N, N): the expected kernel and its derivatives in log(s, bias, wx, wy)
    (and with ``with_scale`` in log g, from ``offsets`` (2, M)), off the diagonal."""
    u, weights, starts, offsets = _in(u), _in(weights), _in(starts, np.int64), _in(offsets)
    n = _points(u, weights, starts)
    count = 5 if with_scale else 4
    if out.ndim != 3 or out.shape[0] < count:
        raise ValueError(f"out needs {count} rows, got shape {out.shape}")
    if with_scale and offsets.shape != (2, u.shape[1]):
        raise ValueError("offsets (2, M) expected")
    _check(_lib.gpocc_nn_matrix_gradient(
        u.ctypes.data, weights.ctypes.data, starts.ctypes.data, n, scale,
        _out(out, (out.shape[0], n, n)), offsets.ctypes.data, bool(with_scale)))


def nn_cross(q: np.ndarray, u: np.ndarray, weights: np.ndarray, starts: np.ndarray,
             scale: float, out: np.ndarray) -> None:
    """out (Q, N) = E k(query_r, x_i) for exact queries with scaled rows ``q`` (3, Q)."""
    q, u, weights, starts = _in(q), _in(u), _in(weights), _in(starts, np.int64)
    n, nq = _points(u, weights, starts), _queries(q)
    _check(_lib.gpocc_nn_cross(q.ctypes.data, nq, u.ctypes.data, weights.ctypes.data,
                               starts.ctypes.data, n, scale, _out(out, (nq, n))))


def nn_cross_uniform(q: np.ndarray, u: np.ndarray, weights: np.ndarray, scale: float,
                     out: np.ndarray) -> None:
    """:func:`nn_cross` when all N points share one rule of L nodes (``u`` (3, L N)
    node-major, ``weights`` (L,))."""
    q, u, weights = _in(q), _in(u), _in(weights)
    size = weights.shape[0]
    n, nq = _uniform_points(u, weights), _queries(q)
    _lib.gpocc_nn_cross_uniform(q.ctypes.data, nq, u.ctypes.data, weights.ctypes.data, size,
                                n, scale, _out(out, (nq, n)))


def cholesky_psd4(s: np.ndarray) -> np.ndarray:
    """Lower-triangular R (4, 4, P) with R R' = s for P symmetric PSD 4 x 4 matrices
    ``s`` (4, 4, P), pair-minor; a pivot below 1e-10 of the largest diagonal entry gives a
    zero column."""
    s = _in(s)
    if s.ndim != 3 or s.shape[:2] != (4, 4):
        raise ValueError(f"s (4, 4, P) expected, got {s.shape}")
    out = np.zeros_like(s)
    _lib.gpocc_cholesky_psd4(s.ctypes.data, s.shape[2], out.ctypes.data)
    return out


def _check_points(means: np.ndarray, covariances: np.ndarray, pose_factors: np.ndarray
                  ) -> None:
    n = means.shape[0]
    if means.shape != (n, 2) or covariances.shape != (n, 2, 2) or pose_factors.shape != (n, 2, 3):
        raise ValueError("means (N, 2), covariances (N, 2, 2) and pose_factors (N, 2, 3) "
                         "expected")


def correlated_nodes(means: np.ndarray, covariances: np.ndarray, pose_factors: np.ndarray,
                     i: np.ndarray, j: np.ndarray, unit: np.ndarray,
                     input_scale: float = 1.0) -> np.ndarray:
    """(4, P L) nodes of the joint 4-D rule of each same-scan pair (x_i then x_j),
    pair-major, from ``unit`` (L, 4); the joint covariance times ``input_scale``."""
    means, covariances, pose_factors = _in(means), _in(covariances), _in(pose_factors)
    i, j, unit = _in(i, np.int64), _in(j, np.int64), _in(unit)
    _check_points(means, covariances, pose_factors)
    pairs, size = _pairs(means.shape[0], i, j), unit.shape[0]
    if unit.shape != (size, 4):
        raise ValueError("unit (L, 4) expected")
    out = np.empty((4, pairs * size))
    _lib.gpocc_correlated_nodes(means.ctypes.data, covariances.ctypes.data,
                                pose_factors.ctypes.data, i.ctypes.data, j.ctypes.data, pairs,
                                unit.ctypes.data, size, input_scale, out.ctypes.data)
    return out


def nn_same_scan_pairs(means: np.ndarray, covariances: np.ndarray, pose_factors: np.ndarray,
                       i: np.ndarray, j: np.ndarray, unit: np.ndarray, weights: np.ndarray,
                       root: np.ndarray, scale: float, input_scale: float, out: np.ndarray,
                       with_gradient: bool, with_scale: bool) -> None:
    """out[:, p]: the expected kernel (row 0; rows 1-3 its derivatives with
    ``with_gradient``, row 4 the derivative in log g with ``with_scale``) of same-scan pair
    (i[p], j[p]) under its joint 4-D rule (``unit`` (L, 4), ``weights`` (L,))."""
    means, covariances, pose_factors = _in(means), _in(covariances), _in(pose_factors)
    i, j = _in(i, np.int64), _in(j, np.int64)
    unit, weights, root = _in(unit), _in(weights), _in(root)
    _check_points(means, covariances, pose_factors)
    pairs = _pairs(means.shape[0], i, j)
    if unit.shape != (weights.shape[0], 4) or root.shape != (3,):
        raise ValueError("unit (L, 4), weights (L,) and root (3,) expected")
    rows = (5 if with_scale else 4) if with_gradient else 1
    if out.ndim != 2 or out.shape[0] < rows:
        raise ValueError(f"out needs {rows} rows, got shape {out.shape}")
    _check(_lib.gpocc_nn_same_scan_pairs(
        means.ctypes.data, covariances.ctypes.data, pose_factors.ctypes.data, i.ctypes.data,
        j.ctypes.data, pairs, unit.ctypes.data, weights.ctypes.data, weights.shape[0],
        root.ctypes.data, scale, input_scale, _out(out, (out.shape[0], pairs)),
        bool(with_gradient), bool(with_scale)))


def correlated_pairs(covariances: np.ndarray, scan_ids: np.ndarray, pose_factors: np.ndarray,
                     pose_share_min: float, zero_variance: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The same-scan pairs (i, j), (P,) each with i < j in row-major order, of points whose
    pose share of the covariance trace exceeds ``pose_share_min`` and whose covariance has
    an entry above ``zero_variance`` (``gpocc.gp.expected.same_scan_pairs``' rule)."""
    covariances, pose_factors = _in(covariances), _in(pose_factors)
    scan_ids = _in(scan_ids, np.int64)
    n = covariances.shape[0]
    if covariances.shape != (n, 2, 2) or scan_ids.shape != (n,) or pose_factors.shape != (n, 2, 3):
        raise ValueError("covariances (N, 2, 2), scan_ids (N,) and pose_factors (N, 2, 3) "
                         "expected")
    args = (covariances.ctypes.data, scan_ids.ctypes.data, pose_factors.ctypes.data, n,
            pose_share_min, zero_variance)
    count = _lib.gpocc_correlated_pairs(*args, None, None)
    _check(count)
    first = np.empty(count, dtype=np.intp)
    second = np.empty(count, dtype=np.intp)
    _check(_lib.gpocc_correlated_pairs(*args, first.ctypes.data, second.ctypes.data))
    return first, second


def nn_local_system(means: np.ndarray, covariances: np.ndarray, scan_ids: np.ndarray,
                    pose_factors: np.ndarray, queries: np.ndarray, unit: np.ndarray,
                    weights: np.ndarray, unit4: np.ndarray, weights4: np.ndarray,
                    root: np.ndarray, scale: float, diagonal: float, correlated: bool,
                    pose_share_min: float, zero_variance: float, k_out: np.ndarray,
                    cross_out: np.ndarray, prior_out: np.ndarray) -> None:
    """Every covariance one local GP problem needs (N points sharing one 2-D rule):
    k_out (N, N) the expected training matrix plus ``diagonal`` on its diagonal,
    cross_out (Q, N) the cross-covariances of the exact (Q, 2) ``queries``, prior_out
    (Q,) k(q, q). See ``gpocc.gp.expected.expected_local_system``."""
    means, covariances, pose_factors = _in(means), _in(covariances), _in(pose_factors)
    scan_ids, queries = _in(scan_ids, np.int64), _in(queries)
    unit, weights, unit4, weights4, root = (_in(unit), _in(weights), _in(unit4),
                                            _in(weights4), _in(root))
    n, nq = means.shape[0], queries.shape[0]
    _check_points(means, covariances, pose_factors)
    if (scan_ids.shape != (n,) or queries.shape != (nq, 2) or root.shape != (3,)
            or unit.shape != (weights.shape[0], 2) or unit4.shape != (weights4.shape[0], 4)):
        raise ValueError("scan_ids (N,), queries (Q, 2), root (3,), unit (L, 2) with weights "
                         "(L,) and unit4 (L4, 4) with weights4 (L4,) expected")
    _check(_lib.gpocc_nn_local_system(
        means.ctypes.data, covariances.ctypes.data, scan_ids.ctypes.data,
        pose_factors.ctypes.data, n, queries.ctypes.data, nq, unit.ctypes.data,
        weights.ctypes.data, weights.shape[0], unit4.ctypes.data, weights4.ctypes.data,
        weights4.shape[0], root.ctypes.data, scale, diagonal, bool(correlated),
        pose_share_min, zero_variance, _out(k_out, (n, n)), _out(cross_out, (nq, n)),
        _out(prior_out, (nq,))))


def beam_unscented(distances: np.ndarray, bearings: np.ndarray, range_sd: np.ndarray,
                   bearing_sd: float, scans: np.ndarray, poses: np.ndarray,
                   pose_roots: np.ndarray, pose_maps: np.ndarray, mount: np.ndarray,
                   wm: np.ndarray, wc: np.ndarray, gamma: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The unscented transform of N beam samples: means (N, 2), covariances (N, 2, 2) and
    pose factors (N, 2, 3). See ``gpocc.samples.beam_unscented.beam_unscented``."""
    distances, bearings, range_sd = _in(distances), _in(bearings), _in(range_sd)
    scans = _in(scans, np.int64)
    poses, pose_roots, pose_maps = _in(poses), _in(pose_roots), _in(pose_maps)
    mount, wm, wc = _in(mount), _in(wm), _in(wc)
    n = distances.shape[0]
    if not (bearings.shape == range_sd.shape == scans.shape == (n,)):
        raise ValueError("distances, bearings, range_sd and scans must all be (N,)")
    if n and (scans.min() < 0 or scans.max() >= poses.shape[0]):
        raise ValueError("scan index out of range of the poses")
    s = poses.shape[0]
    if pose_roots.shape != (s, 3, 3) or pose_maps.shape != (s, 3, 3) or poses.shape != (s, 3):
        raise ValueError("poses (S, 3), pose_roots and pose_maps (S, 3, 3) expected")
    if wm.shape != (11,) or wc.shape != (11,) or mount.shape != (3,):
        raise ValueError("wm, wc (11,) and mount (3,) expected")
    means = np.empty((n, 2))
    covariances = np.empty((n, 2, 2))
    factors = np.empty((n, 2, 3))
    _lib.gpocc_beam_unscented(
        distances.ctypes.data, bearings.ctypes.data, range_sd.ctypes.data, bearing_sd,
        scans.ctypes.data, n, poses.ctypes.data, pose_roots.ctypes.data, pose_maps.ctypes.data,
        mount.ctypes.data, wm.ctypes.data, wc.ctypes.data, gamma, means.ctypes.data,
        covariances.ctypes.data, factors.ctypes.data)
    return means, covariances, factors


def mark_segments(start: np.ndarray, end: np.ndarray, covered: np.ndarray) -> None:
    """Set the cells of ``covered`` (H, W) bool that hold a point every cell along each
    segment ``start -> end`` (N, 2, cell units from the raster's corner), or its end."""
    start, end = _in(start), _in(end)
    if (covered.dtype != np.bool_ or not covered.flags.c_contiguous
            or not covered.flags.writeable or covered.ndim != 2):
        raise ValueError("covered must be a writable C-ordered (H, W) bool array")
    if start.shape != end.shape or start.ndim != 2 or start.shape[1] != 2:
        raise ValueError("start and end must be (N, 2)")
    height, width = covered.shape
    if height == 0 or width == 0:
        return
    _lib.gpocc_mark_segments(start.ctypes.data, end.ctypes.data, start.shape[0],
                             covered.ctypes.data, height, width)
