"""The compiled loops of ``gpocc/_kernels.c``, loaded with ctypes.

``pip install`` (``make install``) builds them as the extension ``gpocc._kernels``. ctypes
releases the GIL for every call, so threads run them in parallel. Each loop is declared
once, as a C prototype in :data:`DECLARATIONS` (a test checks it against the C file);
the ctypes signature and a keyword-argument binding (:class:`_Function`) that checks
every array's dtype, C order, writability and finiteness are made from it, and each
wrapper below checks the shapes C indexes with. Loading the library takes about a
millisecond; numba, which they replace, cost 0.5-0.9 s of every process's start
(measured in commit b5aee9e, which replaced it).
"""

from __future__ import annotations

import ctypes
import importlib.util
import re
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from gpocc.errors import CompiledLoopsUnavailable

#: Every exported loop of ``gpocc/_kernels.c``, as C prototypes: the one declaration the
#: ctypes signatures and the argument checks are made from (tests/gp/test_compiled.py checks
#: it against the C source's definitions). A ``const`` pointer is an input (C order, its
#: dtype, finite: see :class:`_Function`), any other pointer an output (also writable).
DECLARATIONS = """
const char *gpocc_kernels_compiler(void);
void gpocc_asin_array(const double *x, i64 n, double *out);
void gpocc_gaussian_nodes_2d(const double *means, const double *cov, i64 n,
                             const double *unit, i64 size, double *out);
int gpocc_nn_matrix(const double *u, const double *weights, const i64 *starts, i64 n,
                    double scale, double *out);
int gpocc_nn_matrix_uniform(const double *u, const double *weights, i64 size, i64 n,
                            double scale, double *out);
int gpocc_nn_matrix_gradient(const double *u, const double *weights, const i64 *starts, i64 n,
                             double scale, double *out, const double *offsets, int with_scale);
int gpocc_nn_cross(const double *q, i64 nq, const double *u, const double *weights,
                   const i64 *starts, i64 n, double scale, double *out);
void gpocc_nn_cross_uniform(const double *q, i64 nq, const double *u, const double *weights,
                            i64 size, i64 n, double scale, double *out);
void gpocc_cholesky_psd4(const double *s, i64 pairs, double *out);
void gpocc_correlated_nodes(const double *means, const double *cov, const double *pf,
                            const i64 *first, const i64 *second, i64 pairs,
                            const double *unit, i64 size, double input_scale, double *nodes);
int gpocc_nn_same_scan_pairs(const double *means, const double *cov, const double *pf,
                             const i64 *first, const i64 *second, i64 pairs,
                             const double *unit, const double *weights, i64 size,
                             const double *root, double scale, double input_scale,
                             double *out, int with_gradient, int with_scale);
i64 gpocc_correlated_pairs(const double *cov, const i64 *scan_ids, const double *pf, i64 n,
                           double pose_share_min, double zero_variance, i64 *first,
                           i64 *second);
int gpocc_nn_local_system(const double *means, const double *cov, const i64 *scan_ids,
                          const double *pf, i64 n, const double *queries, i64 nq,
                          const double *unit, const double *weights, i64 size,
                          const double *unit4, const double *weights4, i64 size4,
                          const double *root, double scale, double diagonal, int correlated,
                          double pose_share_min, double zero_variance, int single,
                          double *k_out, double *cross_out, double *prior_out);
void gpocc_beam_unscented(const double *dist, const double *bearing, const double *range_sd,
                          double bearing_sd, const i64 *scan, i64 n, const double *poses,
                          const double *pose_root, const double *pose_map,
                          const double *mount, const double *wm, const double *wc,
                          double gamma, double *means, double *covariances, double *factors);
void gpocc_mark_segments(const double *start, const double *end, i64 n,
                         unsigned char *covered, i64 height, i64 width);
i64 gpocc_thin_groups(const i64 *keys, const float *trace, i64 n, i64 *group_keys,
                      i64 *group_counts, i64 *kept);
i64 gpocc_parse_rows(const unsigned char *text, i64 per_line, i64 lines, double *out);
"""

#: Pointer arguments the C code accepts as NULL (count-only mode).
NULLABLE = {("gpocc_correlated_pairs", "first"), ("gpocc_correlated_pairs", "second")}

#: C scalar type -> ctypes type; C pointee type -> the numpy dtypes accepted for it.
_SCALARS = {"i64": ctypes.c_int64, "int": ctypes.c_int, "double": ctypes.c_double,
            "void": None}
_POINTEES = {"double": (np.dtype(np.float64),), "float": (np.dtype(np.float32),),
             "i64": (np.dtype(np.int64),),
             "unsigned char": (np.dtype(np.uint8), np.dtype(np.bool_))}


@dataclass(frozen=True)
class Parameter:
    """One C parameter: ``const double *u`` is Parameter("u", "double", True, True)."""

    name: str
    ctype: str
    pointer: bool
    const: bool


@dataclass(frozen=True)
class Prototype:
    """One C function: its return type (``const char *`` as ``char*``) and parameters."""

    name: str
    returns: str
    parameters: tuple[Parameter, ...]


def _parameter(text: str) -> Parameter:
    words = text.replace("*", " * ").replace("restrict", " ").split()
    name = words.pop()
    const = "const" in words
    pointer = "*" in words
    ctype = " ".join(w for w in words if w not in ("const", "*"))
    return Parameter(name, ctype, pointer, const)


def parse_prototypes(text: str, definitions: bool = False) -> dict[str, Prototype]:
    """The ``gpocc_*`` functions of C ``text`` by name: its declarations (``...);``, the
    form of :data:`DECLARATIONS`), or with ``definitions`` its exported definitions
    (``EXPORT [CLONES] ... ) {``, the form of ``_kernels.c``). ``restrict`` is ignored;
    a return type stays on its function's first line."""
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    head = r"^EXPORT[ \t]+(?:CLONES[ \t]+)?" if definitions else r"^"
    tail = r"\{" if definitions else r";"
    pattern = head + r"([\w \t]+?\**)[ \t]*\b(gpocc_\w+)\s*\(([^)]*)\)\s*" + tail
    found = {}
    for match in re.finditer(pattern, text, flags=re.M):
        returns, name, params = match.groups()
        returns = " ".join(returns.replace("*", " * ").split()).replace(" *", "*")
        returns = returns.removeprefix("const ")
        params = " ".join(params.split())
        parameters = () if params in ("", "void") else tuple(
            _parameter(p) for p in params.split(","))
        found[name] = Prototype(name, returns, parameters)
    return found


def _restype(returns: str):
    return ctypes.c_char_p if returns == "char*" else _SCALARS[returns]


#: Loops whose every call comes from :mod:`gpocc.gp.expected` and its backends, which
#: refuse non-finite means, covariances, pose factors and queries before any loop runs
#: (their other inputs derive from those and from kernel parameters that are checked
#: positive and finite): they are called per local problem, and a finiteness pass over
#: each of their arrays cost more than the check of the data once (3% of a map anchor).
#: Every other loop's float inputs are checked finite here.
FINITE_UPSTREAM = frozenset({
    "gpocc_gaussian_nodes_2d", "gpocc_nn_matrix", "gpocc_nn_matrix_uniform",
    "gpocc_nn_matrix_gradient", "gpocc_nn_cross", "gpocc_nn_cross_uniform",
    "gpocc_nn_same_scan_pairs", "gpocc_correlated_pairs", "gpocc_nn_local_system",
})


class _Function:
    """A loop of the library, called with keyword arguments named as in C: each array is
    checked against its declared pointee type (dtype, C order; outputs writable; float
    inputs finite unless :data:`FINITE_UPSTREAM`) and passed by address, each scalar
    converted by ctypes.

    ``setup.py`` compiles with -ffinite-math-only, under which the compiler may assume
    that no value is NaN or infinite: the branch-free arcsin's clip and selects, and
    every comparison, could then give any result for one. So no NaN may reach a loop:
    it raises ValueError here or upstream (tests/gp/test_compiled.py)."""

    def __init__(self, library: ctypes.CDLL, prototype: Prototype) -> None:
        self.name = prototype.name
        self._function = getattr(library, prototype.name)
        self._function.argtypes = [ctypes.c_void_p if p.pointer else _SCALARS[p.ctype]
                                   for p in prototype.parameters]
        self._function.restype = _restype(prototype.returns)
        check_finite = prototype.name not in FINITE_UPSTREAM
        # (name, accepted dtypes or None for a scalar, output, finite, nullable)
        self._plan = tuple(
            (p.name, _POINTEES[p.ctype] if p.pointer else None, p.pointer and not p.const,
             check_finite and p.pointer and p.const and p.ctype == "double",
             (prototype.name, p.name) in NULLABLE)
            for p in prototype.parameters)

    def __call__(self, **arguments):
        if len(arguments) != len(self._plan):
            raise TypeError(f"{self.name} takes {[p[0] for p in self._plan]}, "
                            f"got {sorted(arguments)}")
        values = []
        for name, dtypes, output, finite, nullable in self._plan:
            try:
                value = arguments[name]
            except KeyError:
                raise TypeError(f"{self.name}: missing argument {name!r}") from None
            if dtypes is None:
                values.append(value)
                continue
            if value is None and nullable:
                values.append(None)
                continue
            if (not isinstance(value, np.ndarray) or value.dtype not in dtypes
                    or not value.flags.c_contiguous):
                raise ValueError(f"{self.name}: {name} must be a C-ordered {dtypes[0]} "
                                 f"array, got {getattr(value, 'dtype', type(value).__name__)}")
            if output and not value.flags.writeable:
                raise ValueError(f"{self.name}: output {name} must be writable")
            if finite and not np.isfinite(value).all():
                raise ValueError(f"{self.name}: {name} holds NaN or infinity")
            values.append(value.ctypes.data)
        return self._function(*values)


def built_library() -> Path:
    """The built extension ``gpocc._kernels`` (a shared library)."""
    spec = importlib.util.find_spec("gpocc._kernels")
    if spec is None or not spec.origin:
        raise CompiledLoopsUnavailable(
            "gpocc's compiled loops (gpocc/_kernels.c) are not built: run 'make install' (or "
            "'pip install -e .') with a C compiler")
    return Path(spec.origin)


def load(library: Path, source: Path | None = None) -> ctypes.CDLL:
    """Open ``library`` and declare its loops' signatures (:data:`DECLARATIONS`). A
    ``source`` (the C file of a source checkout) newer than the library means stale
    loops: ImportError."""
    if source is not None and source.exists() \
            and source.stat().st_mtime > library.stat().st_mtime:
        raise CompiledLoopsUnavailable(f"{library} is older than {source.name}: rebuild it "
                                       "with 'make install'")
    lib = ctypes.CDLL(str(library))
    for prototype in parse_prototypes(DECLARATIONS).values():
        try:
            function = getattr(lib, prototype.name)
        except AttributeError:  # built from an older source (copied keeping its mtime)
            raise CompiledLoopsUnavailable(f"{library} lacks {prototype.name}, so it was "
                                           "built from older source: rebuild it with "
                                           "'make install'") from None
        function.argtypes = [ctypes.c_void_p if p.pointer else _SCALARS[p.ctype]
                             for p in prototype.parameters]
        function.restype = _restype(prototype.returns)
    return lib


def bind(library: ctypes.CDLL) -> SimpleNamespace:
    """Every loop of :data:`DECLARATIONS` as a checked keyword-argument function
    (:class:`_Function`), named without the ``gpocc_`` prefix."""
    return SimpleNamespace(**{name.removeprefix("gpocc_"): _Function(library, prototype)
                              for name, prototype in parse_prototypes(DECLARATIONS).items()})


_lib = load(built_library(), Path(__file__).with_name("_kernels.c"))
_c = bind(_lib)


def compiler() -> str:
    """The compiler that built the loops, e.g. ``gcc 12.2.0`` (provenance)."""
    return _c.kernels_compiler().decode()


def _in(array: np.ndarray, dtype: type = np.float64) -> np.ndarray:
    """``array`` as C-ordered ``dtype`` (a copy only if needed)."""
    return np.ascontiguousarray(array, dtype=dtype)


def _out(array: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """An output array, which must be writable C-ordered float64 of ``shape``: C writes
    through it, so a wrong one would corrupt memory silently."""
    if (array.dtype != np.float64 or not array.flags.c_contiguous
            or not array.flags.writeable or array.shape != shape):
        raise ValueError(f"output must be writable C-ordered float64 of shape {shape}, "
                         f"got {array.dtype} {array.shape}")
    return array


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
    _c.asin_array(x=x, n=x.size, out=out)
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
    _c.gaussian_nodes_2d(means=means, cov=covariances, n=n, unit=unit, size=size, out=out)
    return out


def nn_matrix(u: np.ndarray, weights: np.ndarray, starts: np.ndarray, scale: float,
              out: np.ndarray) -> None:
    """out (N, N): E k(x_i, x_j) off the diagonal (diagonal untouched) from scaled nodes
    ``u`` (3, M), per-node ``weights`` (M,) and node offsets ``starts`` (N + 1,)."""
    u, weights, starts = _in(u), _in(weights), _in(starts, np.int64)
    n = _points(u, weights, starts)
    _check(_c.nn_matrix(u=u, weights=weights, starts=starts, n=n, scale=scale,
                        out=_out(out, (n, n))))


def nn_matrix_uniform(u: np.ndarray, weights: np.ndarray, scale: float, out: np.ndarray
                      ) -> None:
    """:func:`nn_matrix` for N points sharing one rule of L nodes: ``u`` (3, L N)
    node-major, ``weights`` (L,)."""
    u, weights = _in(u), _in(weights)
    size = weights.shape[0]
    n = _uniform_points(u, weights)
    _check(_c.nn_matrix_uniform(u=u, weights=weights, size=size, n=n, scale=scale,
                                out=_out(out, (n, n))))


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
    _check(_c.nn_matrix_gradient(
        u=u, weights=weights, starts=starts, n=n, scale=scale,
        out=_out(out, (out.shape[0], n, n)), offsets=offsets, with_scale=bool(with_scale)))


def nn_cross(q: np.ndarray, u: np.ndarray, weights: np.ndarray, starts: np.ndarray,
             scale: float, out: np.ndarray) -> None:
    """out (Q, N) = E k(query_r, x_i) for exact queries with scaled rows ``q`` (3, Q)."""
    q, u, weights, starts = _in(q), _in(u), _in(weights), _in(starts, np.int64)
    n, nq = _points(u, weights, starts), _queries(q)
    _check(_c.nn_cross(q=q, nq=nq, u=u, weights=weights, starts=starts, n=n, scale=scale,
                       out=_out(out, (nq, n))))


def nn_cross_uniform(q: np.ndarray, u: np.ndarray, weights: np.ndarray, scale: float,
                     out: np.ndarray) -> None:
    """:func:`nn_cross` when all N points share one rule of L nodes (``u`` (3, L N)
    node-major, ``weights`` (L,))."""
    q, u, weights = _in(q), _in(u), _in(weights)
    size = weights.shape[0]
    n, nq = _uniform_points(u, weights), _queries(q)
    _c.nn_cross_uniform(q=q, nq=nq, u=u, weights=weights, size=size, n=n, scale=scale,
                        out=_out(out, (nq, n)))


def cholesky_psd4(s: np.ndarray) -> np.ndarray:
    """Lower-triangular R (4, 4, P) with R R' = s for P symmetric PSD 4 x 4 matrices
    ``s`` (4, 4, P), pair-minor; a pivot below 1e-10 of the largest diagonal entry gives a
    zero column."""
    s = _in(s)
    if s.ndim != 3 or s.shape[:2] != (4, 4):
        raise ValueError(f"s (4, 4, P) expected, got {s.shape}")
    out = np.zeros_like(s)
    _c.cholesky_psd4(s=s, pairs=s.shape[2], out=out)
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
    _c.correlated_nodes(means=means, cov=covariances, pf=pose_factors, first=i, second=j,
                        pairs=pairs, unit=unit, size=size, input_scale=input_scale,
                        nodes=out)
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
    _check(_c.nn_same_scan_pairs(
        means=means, cov=covariances, pf=pose_factors, first=i, second=j, pairs=pairs,
        unit=unit, weights=weights, size=weights.shape[0], root=root, scale=scale,
        input_scale=input_scale, out=_out(out, (out.shape[0], pairs)),
        with_gradient=bool(with_gradient), with_scale=bool(with_scale)))


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
    args = {"cov": covariances, "scan_ids": scan_ids, "pf": pose_factors, "n": n,
            "pose_share_min": pose_share_min, "zero_variance": zero_variance}
    count = _c.correlated_pairs(**args, first=None, second=None)
    _check(count)
    first = np.empty(count, dtype=np.intp)
    second = np.empty(count, dtype=np.intp)
    _check(_c.correlated_pairs(**args, first=first, second=second))
    return first, second


def nn_local_system(means: np.ndarray, covariances: np.ndarray, scan_ids: np.ndarray,
                    pose_factors: np.ndarray, queries: np.ndarray, unit: np.ndarray,
                    weights: np.ndarray, unit4: np.ndarray, weights4: np.ndarray,
                    root: np.ndarray, scale: float, diagonal: float, correlated: bool,
                    pose_share_min: float, zero_variance: float, single: bool,
                    k_out: np.ndarray, cross_out: np.ndarray, prior_out: np.ndarray) -> None:
    """Every covariance one local GP problem needs (N points sharing one 2-D rule):
    k_out (N, N) the expected training matrix plus ``diagonal`` on its diagonal,
    cross_out (Q, N) the cross-covariances of the exact (Q, 2) ``queries``, prior_out
    (Q,) k(q, q); with ``single`` the product-rule part of k_out and cross_out in single
    precision. See ``gpocc.gp.expected.expected_local_system``."""
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
    _check(_c.nn_local_system(
        means=means, cov=covariances, scan_ids=scan_ids, pf=pose_factors, n=n,
        queries=queries, nq=nq, unit=unit, weights=weights, size=weights.shape[0],
        unit4=unit4, weights4=weights4, size4=weights4.shape[0], root=root, scale=scale,
        diagonal=diagonal, correlated=bool(correlated), pose_share_min=pose_share_min,
        zero_variance=zero_variance, single=bool(single), k_out=_out(k_out, (n, n)),
        cross_out=_out(cross_out, (nq, n)), prior_out=_out(prior_out, (nq,))))


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
    _c.beam_unscented(
        dist=distances, bearing=bearings, range_sd=range_sd, bearing_sd=bearing_sd,
        scan=scans, n=n, poses=poses, pose_root=pose_roots, pose_map=pose_maps, mount=mount,
        wm=wm, wc=wc, gamma=gamma, means=means, covariances=covariances, factors=factors)
    return means, covariances, factors


def thin_groups(keys: np.ndarray, trace: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each distinct key of ``keys`` (N,) int64, in the order of its first sample:
    the key, its number of samples, and the index of its sample with the smallest
    ``trace`` (N,) float32 (the earliest of those that have it): three (G,) int64
    arrays. ``trace`` must be finite (the loops assume it; not checked here)."""
    keys = np.ascontiguousarray(keys, dtype=np.int64)
    trace = np.ascontiguousarray(trace, dtype=np.float32)
    n = keys.shape[0]
    if keys.ndim != 1 or trace.shape != (n,):
        raise ValueError("keys and trace must both be (N,)")
    group_keys, counts, kept = (np.empty(n, np.int64) for _ in range(3))
    groups = _c.thin_groups(keys=keys, trace=trace, n=n, group_keys=group_keys,
                            group_counts=counts, kept=kept)
    if groups < 0:
        raise MemoryError("thinning's hash table")
    return group_keys[:groups], counts[:groups], kept[:groups]


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
    _c.mark_segments(start=start, end=end, n=start.shape[0], covered=covered, height=height,
                     width=width)


def parse_rows(text: bytes, per_line: int, lines: int) -> np.ndarray | None:
    """The numbers of ASCII ``text`` as (lines, per_line) float64, or None.

    ``text`` holds ``lines`` lines (split by newlines), each of exactly ``per_line``
    whitespace-separated numbers; each becomes the double Python's ``float`` reads from
    its token (correctly rounded, as C's ``strtod``). None if a line holds another count
    or a token that is not a plain decimal, inf or nan (hex floats, ``1e``, ``1,5``),
    text after the last line, or a NUL: the caller then reads it token by token, which
    names the culprit.
    """
    if per_line <= 0 or lines < 0:
        raise ValueError("per_line must be positive and lines at least 0")
    # A token is at least one character and a blank: more numbers than that cannot be in
    # the text (and would ask for a vast array); C stops at a NUL, so none may be inside.
    if per_line * lines > len(text) // 2 + 1 or b"\0" in text:
        return None
    buffer = np.frombuffer(text + b"\0", dtype=np.uint8)
    out = np.empty((lines, per_line))
    bad = _c.parse_rows(text=buffer, per_line=per_line, lines=lines, out=out)
    return out if bad < 0 else None
