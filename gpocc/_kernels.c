/* gpocc's compiled loops: the expected neural-network kernel (quadrature and arcsin
 * fused), the unscented transform of beam samples and the beam-coverage raster.
 *
 * Plain C over C-contiguous float64 / int64 arrays, called through ctypes
 * (gpocc/compiled.py), which releases the GIL for every call. They replace numba
 * kernels whose import and first call cost 0.5-0.9 s of every command's start (numba's
 * typing and lowering registries load on the first call in each process); loading
 * this library takes about a millisecond. The loops, their order of summation and
 * their formulas are those of the numba versions they replaced (commit b5aee9e);
 * docs/benchmarks.md, 'Expected kernels: compiled loops against numpy', compares them
 * with the numpy quadrature.
 *
 * Each exported loop is compiled twice (GCC's target_clones on x86-64): for x86-64-v3
 * (AVX2 and FMA: with setup.py's -ffp-contract=fast, a * b + c becomes one fused
 * multiply-add, one rounding instead of two; -std=c11 alone would forbid that, and the
 * loops took 25% longer) and for the baseline (no FMA: its results may differ from the
 * other clone's in the last bits); the loader picks the clone the CPU runs.
 * setup.py compiles with -ffinite-math-only -fno-signed-zeros -fno-math-errno
 * -fno-trapping-math (where the compiler accepts them): no input here is NaN or
 * infinite (gpocc/compiled.py refuses them, or for the per-problem loops
 * gpocc.gp.expected does, before any loop runs), and without them GCC will not turn the
 * branch-free arcsin's selects and the clip to [-1, 1] into vector min/max and blends,
 * which halves the speed. No reassociation and no approximate division or square root.
 *
 * The exported functions' prototypes are declared once more, for ctypes, in
 * gpocc/compiled.py (DECLARATIONS); tests/gp/test_compiled.py checks that they match.
 *
 * A map's local systems may run their product-rule and cross-covariance sums in single
 * precision (model.covariance_precision): converted here, inputs and outputs float64.
 *
 * Array layouts (row-major, as numpy's C order):
 *   u (3, M): scaled nodes, coordinate-major (z = u_a . u_b is the kernel's arcsin
 *   argument); weights (M,) per-node quadrature weights; starts (N + 1,) node offsets of
 *   each point; "uniform" loops: every point shares one rule of L nodes, node-major
 *   (node k of point i in column k N + i) and weights (L,).
 *   ``scale`` is signal_variance * 2 / pi.
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
#define CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define CLONES
#endif
#if defined(_MSC_VER)
#define EXPORT __declspec(dllexport)
#else
#define EXPORT __attribute__((visibility("default")))
#endif

typedef int64_t i64;

/* fdlibm e_asin.c coefficients: asin(x) = x + x R(x^2) on [0, 0.5], R = P/Q. */
#define PS0 1.66666666666666657415e-01
#define PS1 -3.25565818622400915405e-01
#define PS2 2.01212532134862925881e-01
#define PS3 -4.00555345006794114027e-02
#define PS4 7.91534994289814532176e-04
#define PS5 3.47933107596021167570e-05
#define QS1 -2.40339491173441421878e00
#define QS2 2.02094576023350569471e00
#define QS3 -6.88283971605453293030e-01
#define QS4 7.70381505559019352791e-02
#define PIO2_HI 1.57079632679489655800e00
#define PIO2_LO 6.12323399573676603587e-17

/* arcsin(x) for |x| <= 1, branch-free so that loops calling it vectorise: both of
 * fdlibm's ranges, then a select (<= 2 ulp from numpy.arcsin). |x| >= 0.5 uses
 * asin(x) = pi/2 - 2 asin(sqrt((1 - x) / 2)). */
static inline double asin_fast(double x)
{
    double ax = fabs(x);
    int big = ax >= 0.5;
    double t = big ? 0.5 * (1.0 - ax) : ax * ax;
    double p = t * (PS0 + t * (PS1 + t * (PS2 + t * (PS3 + t * (PS4 + t * PS5)))));
    double q = 1.0 + t * (QS1 + t * (QS2 + t * (QS3 + t * QS4)));
    double r = p / q;
    double s = sqrt(t);
    double v = big ? PIO2_HI - (2.0 * (s + s * r) - PIO2_LO) : ax + ax * r;
    return x >= 0.0 ? v : -v;
}

/* Rounding only: |z| < 1 exactly (Cauchy-Schwarz on normalised rows). */
static inline double clip1(double z)
{
    z = z < 1.0 ? z : 1.0;
    return z > -1.0 ? z : -1.0;
}

/* fdlibm e_asinf.c (FreeBSD) coefficients: asin(x) = x + x R(x^2) on [0, 0.5] in
 * single precision. */
#define PS0F 1.6666586697e-01f
#define PS1F -4.2743422091e-02f
#define PS2F -8.6563630030e-03f
#define QS1F -7.0662963390e-01f
#define PIO2F 1.5707963268e+00f

/* arcsin(z) in single precision for z = u . v of two scaled rows, branch-free as
 * asin_fast. ``far`` is (1 - |z|) / 2 computed without cancellation
 * (:c:func:`half_gap`): near |z| = 1, where the arcsine is steepest, (1 - |z|) / 2
 * formed from a single-precision z would lose most of its digits. */
static inline float asin_single(float z, float far)
{
    float az = fabsf(z);
    int big = az >= 0.5f;
    float t = big ? far : az * az;
    float p = t * (PS0F + t * (PS1F + t * PS2F));
    float q = 1.0f + t * QS1F;
    float r = p / q;
    float s = sqrtf(t);
    float v = big ? PIO2F - 2.0f * (s + s * r) : az + az * r;
    return z >= 0.0f ? v : -v;
}

/* (1 - |u . v|) / 2 for scaled rows u, v with gaps e_u = 1 - |u|^2, e_v = 1 - |v|^2:
 * 1 -+ u . v = (|u -+ v|^2 + e_u + e_v) / 2, a sum of non-negative terms. */
static inline float half_gap(float z, float u0, float u1, float u2, float eu, float v0,
                             float v1, float v2, float ev)
{
    float sv = z >= 0.0f ? 1.0f : -1.0f;
    float d0 = u0 - sv * v0, d1 = u1 - sv * v1, d2 = u2 - sv * v2;
    return 0.25f * (d0 * d0 + d1 * d1 + d2 * d2 + eu + ev);
}

/* u = (1, x, y) sqrt(2 S) / sqrt(1 + 2 (1, x, y)' S (1, x, y)) and the normaliser. */
static inline void scaled_row(double x, double y, const double *root, double *u0, double *u1,
                              double *u2, double *inv)
{
    double a1 = x * root[1];
    double a2 = y * root[2];
    double n = 1.0 / sqrt(a1 * a1 + a2 * a2 + (1.0 + root[0] * root[0]));
    *u0 = n * root[0];
    *u1 = a1 * n;
    *u2 = a2 * n;
    *inv = n;
}

/* dz/dtheta_c = u_c v_c - z (u_c^2 + v_c^2) / 2 (theta_c the log of S_c); hz = z / 2. */
static inline double dz(double ua, double ub, double hz)
{
    return ua * ub - hz * (ua * ua + ub * ub);
}

/* dz/dlog g of the input-noise scale g (gpocc.gp.expected's gradient in log g). */
static inline double dz_scale(double a1, double a2, double b1, double b2, double z,
                              double da1, double da2, double db1, double db2)
{
    return 0.5 * ((b1 - z * a1) * da1 + (b2 - z * a2) * da2
                  + (a1 - z * b1) * db1 + (a2 - z * b2) * db2);
}

EXPORT const char *gpocc_kernels_compiler(void)
{
#if defined(__clang__)
    return "clang " __clang_version__;
#elif defined(__GNUC__)
    return "gcc " __VERSION__;
#else
    return "unknown";
#endif
}

EXPORT CLONES void gpocc_asin_array(const double *restrict x, i64 n, double *restrict out)
{
    for (i64 m = 0; m < n; m++)
        out[m] = asin_fast(x[m]);
}

/* (2, N L) nodes mean_i + R_i unit_k of N 2-D Gaussians, point-major; R_i the closed-form
 * root of gpocc.gp.expected._sqrt_psd2 (same formulas, same order). */
EXPORT void gpocc_gaussian_nodes_2d(const double *restrict means, const double *restrict cov,
                                    i64 n, const double *restrict unit, i64 size,
                                    double *restrict out)
{
    i64 total = n * size;
    for (i64 i = 0; i < n; i++) {
        const double *c = cov + 4 * i;
        double a = c[0], d = c[3];
        double b = 0.5 * (c[1] + c[2]);
        double half = 0.5 * (a - d);
        double radius = hypot(half, b);
        double high = 0.5 * (a + d) + radius;
        high = high > 0.0 ? high : 0.0;
        double low = high > 0.0 ? (a * d - b * b) / high : 0.0;
        if (low < 1e-13 * high)
            low = 0.0;
        double angle = 0.5 * atan2(b, half);
        double cs = cos(angle), sn = sin(angle);
        double root_low = sqrt(low), root_high = sqrt(high);
        double r00 = -sn * root_low, r01 = cs * root_high;
        double r10 = cs * root_low, r11 = sn * root_high;
        double mx = means[2 * i], my = means[2 * i + 1];
        for (i64 k = 0; k < size; k++) {
            out[i * size + k] = mx + (r00 * unit[2 * k] + r01 * unit[2 * k + 1]);
            out[total + i * size + k] = my + (r10 * unit[2 * k] + r11 * unit[2 * k + 1]);
        }
    }
}

/* out[i, j] = out[j, i] = E k(x_i, x_j) for i < j (product rule); diagonal untouched.
 * Point i's nodes are summed into one row against every later node, then reduced per
 * point j once. Returns -1 if out of memory. */
EXPORT CLONES int gpocc_nn_matrix(const double *restrict u, const double *restrict weights,
                                  const i64 *restrict starts, i64 n, double scale,
                                  double *restrict out)
{
    i64 total = starts[n];
    double *restrict acc = malloc((size_t)(total > 0 ? total : 1) * sizeof(double));
    if (!acc)
        return -1;
    for (i64 i = 0; i < n; i++) {
        i64 b0 = starts[i + 1];
        i64 later = total - b0;
        const double *restrict u0 = u + b0;
        const double *restrict u1 = u + total + b0;
        const double *restrict u2 = u + 2 * total + b0;
        const double *restrict wb = weights + b0;
        for (i64 b = 0; b < later; b++)
            acc[b] = 0.0;
        for (i64 a = starts[i]; a < b0; a++) {
            double x0 = u[a], x1 = u[total + a], x2 = u[2 * total + a];
            double wa = weights[a] * scale;
            for (i64 b = 0; b < later; b++)
                acc[b] += wa * asin_fast(clip1(x0 * u0[b] + x1 * u1[b] + x2 * u2[b]));
        }
        for (i64 j = i + 1; j < n; j++) {
            double value = 0.0;
            for (i64 b = starts[j] - b0; b < starts[j + 1] - b0; b++)
                value += acc[b] * wb[b];
            out[i * n + j] = value;
            out[j * n + i] = value;
        }
    }
    free(acc);
    return 0;
}

/* gpocc_nn_matrix for N points sharing one rule of L nodes (u (3, L N) node-major,
 * weights (L,)); both triangles written, diagonal untouched. At level 2 (L = 4) point
 * i's four nodes are held in registers through each contiguous pass. With ``first``
 * (N,), row i leaves out its entries i < j < first[i] in whole vectors of four (so up to
 * three of them are still computed): the caller writes them, and their mirrors, after
 * this returns (same-scan pairs); the lower triangle then holds copies of whatever was
 * there. */
static CLONES int nn_matrix_uniform_from(const double *restrict u,
                                         const double *restrict weights, i64 size, i64 n,
                                         double scale, const i64 *restrict first,
                                         double *restrict out)
{
    i64 total = size * n;
    double *restrict acc = malloc((size_t)(total > 0 ? total : 1) * sizeof(double));
    if (!acc)
        return -1;
    const double *U0 = u, *U1 = u + total, *U2 = u + 2 * total;
    for (i64 i = 0; i < n; i++) {
        /* Whole vectors of the pass only (4 lanes): which entries the pass leaves to its
         * scalar remainder must not change, nor then their last bits. */
        i64 from = first ? i + 1 + ((first[i] - i - 1) & ~(i64)3) : i + 1;
        if (size == 4) {
            double p0 = U0[i], p1 = U1[i], p2 = U2[i];
            double q0 = U0[n + i], q1 = U1[n + i], q2 = U2[n + i];
            double r0 = U0[2 * n + i], r1 = U1[2 * n + i], r2 = U2[2 * n + i];
            double s0 = U0[3 * n + i], s1 = U1[3 * n + i], s2 = U2[3 * n + i];
            double wp = weights[0] * scale, wq = weights[1] * scale;
            double wr = weights[2] * scale, ws = weights[3] * scale;
            for (i64 slot = 0; slot < 4; slot++) {
                i64 lo = slot * n + from;
                const double *restrict v0 = U0 + lo;
                const double *restrict v1 = U1 + lo;
                const double *restrict v2 = U2 + lo;
                double *restrict row = acc + slot * n + from;
                for (i64 j = 0; j < n - from; j++) {
                    double y0 = v0[j], y1 = v1[j], y2 = v2[j];
                    double t = 0.0;
                    t += wp * asin_fast(clip1(p0 * y0 + p1 * y1 + p2 * y2));
                    t += wq * asin_fast(clip1(q0 * y0 + q1 * y1 + q2 * y2));
                    t += wr * asin_fast(clip1(r0 * y0 + r1 * y1 + r2 * y2));
                    t += ws * asin_fast(clip1(s0 * y0 + s1 * y1 + s2 * y2));
                    row[j] = t;
                }
            }
        } else {
            for (i64 slot = 0; slot < size; slot++)
                for (i64 j = from; j < n; j++)
                    acc[slot * n + j] = 0.0;
            for (i64 k = 0; k < size; k++) {
                double x0 = U0[k * n + i], x1 = U1[k * n + i], x2 = U2[k * n + i];
                double wa = weights[k] * scale;
                for (i64 slot = 0; slot < size; slot++) {
                    i64 lo = slot * n + from;
                    const double *restrict v0 = U0 + lo;
                    const double *restrict v1 = U1 + lo;
                    const double *restrict v2 = U2 + lo;
                    double *restrict row = acc + slot * n + from;
                    for (i64 j = 0; j < n - from; j++)
                        row[j] += wa * asin_fast(clip1(x0 * v0[j] + x1 * v1[j] + x2 * v2[j]));
                }
            }
        }
        for (i64 j = from; j < n; j++) {
            double value = 0.0;
            for (i64 slot = 0; slot < size; slot++)
                value += acc[slot * n + j] * weights[slot];
            out[i * n + j] = value;
        }
    }
    for (i64 i = 0; i < n; i++) /* the lower triangle once, row by row */
        for (i64 j = 0; j < i; j++)
            out[i * n + j] = out[j * n + i];
    free(acc);
    return 0;
}

EXPORT int gpocc_nn_matrix_uniform(const double *restrict u, const double *restrict weights,
                                   i64 size, i64 n, double scale, double *restrict out)
{
    return nn_matrix_uniform_from(u, weights, size, n, scale, NULL, out);
}

/* out[:, i, j] = out[:, j, i] = E dk(x_i, x_j)/dtheta, theta = log(s, bias, wx, wy), for
 * i < j; out[0] is the expected kernel itself; with with_scale out[4] is the derivative
 * in log g from offsets (2, M), each node's scaled offset from its point's mean.
 * Diagonal untouched. */
EXPORT CLONES int gpocc_nn_matrix_gradient(const double *restrict u,
                                           const double *restrict weights,
                                           const i64 *restrict starts, i64 n, double scale,
                                           double *restrict out,
                                           const double *restrict offsets, int with_scale)
{
    i64 total = starts[n];
    i64 count = with_scale ? 5 : 4;
    double *restrict acc = malloc((size_t)(total > 0 ? count * total : 1) * sizeof(double));
    if (!acc)
        return -1;
    double *restrict a0 = acc, *restrict a1 = acc + total, *restrict a2 = acc + 2 * total;
    double *restrict a3 = acc + 3 * total, *restrict a4 = acc + 4 * total;
    for (i64 i = 0; i < n; i++) {
        i64 b0 = starts[i + 1];
        i64 later = total - b0;
        const double *restrict u0 = u + b0;
        const double *restrict u1 = u + total + b0;
        const double *restrict u2 = u + 2 * total + b0;
        for (i64 p = 0; p < count; p++)
            for (i64 b = 0; b < later; b++)
                acc[p * total + b] = 0.0;
        for (i64 a = starts[i]; a < b0; a++) {
            double x0 = u[a], x1 = u[total + a], x2 = u[2 * total + a];
            double wa = weights[a] * scale;
            for (i64 b = 0; b < later; b++) {
                double y0 = u0[b], y1 = u1[b], y2 = u2[b];
                double z = clip1(x0 * y0 + x1 * y1 + x2 * y2);
                double wg = wa / sqrt(1.0 - z * z); /* dk/dz = 1 / sqrt(1 - z^2) */
                double hz = 0.5 * z;
                a0[b] += wa * asin_fast(z);
                a1[b] += wg * dz(x0, y0, hz);
                a2[b] += wg * dz(x1, y1, hz);
                a3[b] += wg * dz(x2, y2, hz);
            }
            if (with_scale) { /* a loop of its own keeps the one above free of branches */
                double da1 = offsets[a], da2 = offsets[total + a];
                const double *restrict o1 = offsets + b0;
                const double *restrict o2 = offsets + total + b0;
                for (i64 b = 0; b < later; b++) {
                    double y0 = u0[b], y1 = u1[b], y2 = u2[b];
                    double z = clip1(x0 * y0 + x1 * y1 + x2 * y2);
                    a4[b] += wa / sqrt(1.0 - z * z)
                             * dz_scale(x1, x2, y1, y2, z, da1, da2, o1[b], o2[b]);
                }
            }
        }
        for (i64 j = i + 1; j < n; j++) {
            for (i64 p = 0; p < count; p++) {
                double value = 0.0;
                for (i64 b = starts[j] - b0; b < starts[j + 1] - b0; b++)
                    value += acc[p * total + b] * weights[b0 + b];
                out[(p * n + i) * n + j] = value;
                out[(p * n + j) * n + i] = value;
            }
        }
    }
    free(acc);
    return 0;
}

/* out[r, i] = E k(query_r, x_i) for exact queries with scaled rows q (3, Q). */
EXPORT CLONES int gpocc_nn_cross(const double *restrict q, i64 nq, const double *restrict u,
                                 const double *restrict weights, const i64 *restrict starts,
                                 i64 n, double scale, double *restrict out)
{
    i64 total = starts[n];
    double *restrict row = malloc((size_t)(total > 0 ? total : 1) * sizeof(double));
    if (!row)
        return -1;
    const double *restrict u0 = u, *restrict u1 = u + total, *restrict u2 = u + 2 * total;
    for (i64 r = 0; r < nq; r++) {
        double x0 = q[r], x1 = q[nq + r], x2 = q[2 * nq + r];
        for (i64 b = 0; b < total; b++)
            row[b] = weights[b] * asin_fast(clip1(x0 * u0[b] + x1 * u1[b] + x2 * u2[b]));
        for (i64 i = 0; i < n; i++) {
            double acc = 0.0;
            for (i64 b = starts[i]; b < starts[i + 1]; b++)
                acc += row[b];
            out[r * n + i] = scale * acc;
        }
    }
    free(row);
    return 0;
}

/* gpocc_nn_cross when all N points share one rule of L nodes (u (3, L N) node-major,
 * weights (L,)): each node's loop runs over the points with nothing to reduce after. */
EXPORT CLONES void gpocc_nn_cross_uniform(const double *restrict q, i64 nq,
                                          const double *restrict u,
                                          const double *restrict weights, i64 size, i64 n,
                                          double scale, double *restrict out)
{
    i64 total = size * n;
    const double *U0 = u, *U1 = u + total, *U2 = u + 2 * total;
    if (size == 4) { /* level 2, the default: the four nodes summed in registers */
        double w0 = weights[0], w1 = weights[1], w2 = weights[2], w3 = weights[3];
        const double *restrict a0 = U0, *restrict a1 = U1, *restrict a2 = U2;
        const double *restrict b0 = U0 + n, *restrict b1 = U1 + n, *restrict b2 = U2 + n;
        const double *restrict c0 = U0 + 2 * n, *restrict c1 = U1 + 2 * n;
        const double *restrict c2 = U2 + 2 * n;
        const double *restrict d0 = U0 + 3 * n, *restrict d1 = U1 + 3 * n;
        const double *restrict d2 = U2 + 3 * n;
        for (i64 r = 0; r < nq; r++) {
            double x0 = q[r], x1 = q[nq + r], x2 = q[2 * nq + r];
            double *restrict row = out + r * n;
            for (i64 i = 0; i < n; i++)
                row[i] = scale * (w0 * asin_fast(clip1(x0 * a0[i] + x1 * a1[i] + x2 * a2[i]))
                                  + w1 * asin_fast(clip1(x0 * b0[i] + x1 * b1[i] + x2 * b2[i]))
                                  + w2 * asin_fast(clip1(x0 * c0[i] + x1 * c1[i] + x2 * c2[i]))
                                  + w3 * asin_fast(clip1(x0 * d0[i] + x1 * d1[i] + x2 * d2[i])));
        }
        return;
    }
    for (i64 r = 0; r < nq; r++) {
        double x0 = q[r], x1 = q[nq + r], x2 = q[2 * nq + r];
        double *restrict row = out + r * n;
        for (i64 i = 0; i < n; i++)
            row[i] = 0.0;
        for (i64 k = 0; k < size; k++) {
            double wk = weights[k];
            const double *restrict v0 = U0 + k * n;
            const double *restrict v1 = U1 + k * n;
            const double *restrict v2 = U2 + k * n;
            for (i64 i = 0; i < n; i++)
                row[i] += wk * asin_fast(clip1(x0 * v0[i] + x1 * v1[i] + x2 * v2[i]));
        }
        for (i64 i = 0; i < n; i++)
            row[i] *= scale;
    }
}

/* ------------------------------------------------------------------ same-scan pairs */

/* The parts of cholesky4's first two columns that only its leading 2 x 2 block decides
 * (a00, a10, a11 in its order): sqrt(a00), a10 / sqrt(a00), a11 - that squared and its
 * square root; each is used only where cholesky4 computes the same. */
struct leading_block {
    double l00, l10, d11, l11;
};

static inline struct leading_block leading_block(double a00, double a10, double a11)
{
    struct leading_block c = {0.0, 0.0, a11, 0.0};
    if (a00 > 0.0) {
        c.l00 = sqrt(a00);
        c.l10 = a10 / c.l00;
        c.d11 = a11 - c.l10 * c.l10;
    }
    if (c.d11 > 0.0)
        c.l11 = sqrt(c.d11);
    return c;
}

/* The lower Cholesky factor l (l00, l10, l11, l20, l21, l22, l30, l31, l32, l33) of one
 * symmetric positive semi-definite 4 x 4 matrix given by its lower triangle a (same
 * order). A pivot below 1e-10 of the largest diagonal entry is rounding noise of a
 * singular matrix: its column is zero. cholesky4_led takes its leading block's parts
 * from ``lead`` (leading_block of a's first three entries; NULL: computed here). */
static inline void cholesky4_led(const double *a, const struct leading_block *lead,
                                 double *l)
{
    double a00 = a[0], a10 = a[1], a11 = a[2], a20 = a[3], a21 = a[4], a22 = a[5];
    double a30 = a[6], a31 = a[7], a32 = a[8], a33 = a[9];
    double m01 = a00 > a11 ? a00 : a11, m23 = a22 > a33 ? a22 : a33;
    double tiny = 1e-10 * (m01 > m23 ? m01 : m23);
    double l00 = 0, l10 = 0, l20 = 0, l30 = 0, l11 = 0, l21 = 0, l31 = 0, l22 = 0, l32 = 0;
    double l33 = 0;
    int led = lead != NULL && a00 > tiny; /* then a00 > 0: lead's first column is set */
    if (a00 > tiny) {
        l00 = led ? lead->l00 : sqrt(a00);
        l10 = led ? lead->l10 : a10 / l00;
        l20 = a20 / l00;
        l30 = a30 / l00;
    }
    double d = led ? lead->d11 : a11 - l10 * l10;
    if (d > tiny) {
        l11 = led ? lead->l11 : sqrt(d);
        l21 = (a21 - l20 * l10) / l11;
        l31 = (a31 - l30 * l10) / l11;
    }
    d = a22 - l20 * l20 - l21 * l21;
    if (d > tiny) {
        l22 = sqrt(d);
        l32 = (a32 - l30 * l20 - l31 * l21) / l22;
    }
    d = a33 - l30 * l30 - l31 * l31 - l32 * l32;
    if (d > tiny)
        l33 = sqrt(d);
    l[0] = l00; l[1] = l10; l[2] = l11; l[3] = l20; l[4] = l21;
    l[5] = l22; l[6] = l30; l[7] = l31; l[8] = l32; l[9] = l33;
}

static inline void cholesky4(const double *a, double *l)
{
    cholesky4_led(a, NULL, l);
}

/* Lower-triangular R (4, 4, P) with R R' = s for P symmetric PSD matrices s (4, 4, P),
 * pair-minor (off-diagonal entries symmetrised). out must be zeroed by the caller. */
EXPORT void gpocc_cholesky_psd4(const double *restrict s, i64 pairs, double *restrict out)
{
#define S(r, c) s[((r) * 4 + (c)) * pairs + m]
#define O(r, c) out[((r) * 4 + (c)) * pairs + m]
    for (i64 m = 0; m < pairs; m++) {
        double a[10] = {S(0, 0), 0.5 * (S(1, 0) + S(0, 1)), S(1, 1),
                        0.5 * (S(2, 0) + S(0, 2)), 0.5 * (S(2, 1) + S(1, 2)), S(2, 2),
                        0.5 * (S(3, 0) + S(0, 3)), 0.5 * (S(3, 1) + S(1, 3)),
                        0.5 * (S(3, 2) + S(2, 3)), S(3, 3)};
        double l[10];
        cholesky4(a, l);
        O(0, 0) = l[0];
        O(1, 0) = l[1]; O(1, 1) = l[2];
        O(2, 0) = l[3]; O(2, 1) = l[4]; O(2, 2) = l[5];
        O(3, 0) = l[6]; O(3, 1) = l[7]; O(3, 2) = l[8]; O(3, 3) = l[9];
    }
#undef S
#undef O
}

/* Cov(x_a[r], x_b[c]) = (A_a A_b')[r, c] of two points of one scan; pf (N, 2, 3). */
static inline double pose_cross(const double *pf, i64 a, i64 b, int r, int c)
{
    const double *x = pf + (a * 2 + r) * 3, *y = pf + (b * 2 + c) * 3;
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2];
}

#define FACTOR_CHUNK 32

/* (4, P L) nodes of the joint 4-D rule of each pair (x_i then x_j), pair-major: the
 * joint covariance [[S_i, A_i A_j'], [A_j A_i', S_j]] times input_scale, its root
 * cholesky4 (times the scale's square root); nodes mean + R unit_k (unit (L, 4)). */
EXPORT void gpocc_correlated_nodes(const double *restrict means, const double *restrict cov,
                                   const double *restrict pf, const i64 *restrict first,
                                   const i64 *restrict second, i64 pairs,
                                   const double *restrict unit, i64 size, double input_scale,
                                   double *restrict nodes)
{
    double root_scale = sqrt(input_scale);
    i64 total = pairs * size;
    double *n0 = nodes, *n1 = nodes + total, *n2 = nodes + 2 * total, *n3 = nodes + 3 * total;
    /* Pairs come by first point (row-major): its block is factored once per run. */
    struct leading_block lead = {0.0, 0.0, 0.0, 0.0};
    i64 led = -1;
    /* The factors of FACTOR_CHUNK pairs, then their nodes: the factorisations' chains of
     * divisions and square roots overlap when no node loop stands between them. */
    double roots[FACTOR_CHUNK][10];
    for (i64 lo = 0; lo < pairs; lo += FACTOR_CHUNK) {
        i64 hi = lo + FACTOR_CHUNK < pairs ? lo + FACTOR_CHUNK : pairs;
        for (i64 p = lo; p < hi; p++) {
            i64 a = first[p], b = second[p];
            const double *ca = cov + 4 * a, *cb = cov + 4 * b;
            double joint[10] = {ca[0], 0.5 * (ca[2] + ca[1]), ca[3],
                                pose_cross(pf, a, b, 0, 0), pose_cross(pf, a, b, 1, 0), cb[0],
                                pose_cross(pf, a, b, 0, 1), pose_cross(pf, a, b, 1, 1),
                                0.5 * (cb[2] + cb[1]), cb[3]};
            if (a != led) {
                lead = leading_block(joint[0], joint[1], joint[2]);
                led = a;
            }
            double *l = roots[p - lo];
            cholesky4_led(joint, &lead, l);
            for (int k = 0; k < 10; k++)
                l[k] *= root_scale;
        }
        for (i64 p = lo; p < hi; p++) {
            const double *l = roots[p - lo];
            i64 a = first[p], b = second[p];
            double ma0 = means[2 * a], ma1 = means[2 * a + 1];
            double mb0 = means[2 * b], mb1 = means[2 * b + 1];
            i64 base = p * size;
            for (i64 m = 0; m < size; m++) {
                const double *e = unit + 4 * m;
                n0[base + m] = ma0 + l[0] * e[0];
                n1[base + m] = ma1 + (l[1] * e[0] + l[2] * e[1]);
                n2[base + m] = mb0 + (l[3] * e[0] + l[4] * e[1] + l[5] * e[2]);
                n3[base + m] = mb1 + (l[6] * e[0] + l[7] * e[1] + l[8] * e[2] + l[9] * e[3]);
            }
        }
    }
}

/* out[r, p] (row stride ld) = scale * sum_k w_k (k, dk/dtheta)(a_pk, b_pk) over each of
 * the batch's pairs' L nodes (nodes (4, total), total = pairs L); rows (count, total) and
 * offsets (4, total) are scratch; centres (4, pairs) the two means of each pair. Point a's
 * coordinates are the same over each run of ``group`` nodes of a pair (1: no such runs;
 * :func:`a_side_group`). */
static CLONES void node_pairs(const double *restrict nodes, i64 total,
                              const double *restrict weights, i64 size, i64 group,
                              const double *restrict root, double scale, double *out, i64 ld,
                              int with_gradient, const double *restrict centres,
                              i64 centres_ld, int with_scale, double *restrict rows,
                              double *restrict offsets)
{
    i64 count = with_gradient ? (with_scale ? 5 : 4) : 1;
    const double *restrict n0 = nodes, *restrict n1 = nodes + total;
    const double *restrict n2 = nodes + 2 * total, *restrict n3 = nodes + 3 * total;
    double a0, a1, a2, ia, b0, b1, b2, ib;
    if (!with_gradient) {
        double *restrict values = rows;
        /* Point a's part of a node repeats over ``group`` consecutive nodes: its scaled
         * row is computed once per group (a quarter of them at level 2). */
        double *restrict s0 = offsets, *restrict s1 = offsets + total;
        double *restrict s2 = offsets + 2 * total;
        for (i64 g = 0; g < total; g += group) {
            scaled_row(n0[g], n1[g], root, &a0, &a1, &a2, &ia);
            for (i64 k = g; k < g + group; k++) {
                s0[k] = a0;
                s1[k] = a1;
                s2[k] = a2;
            }
        }
        for (i64 m = 0; m < total; m++) { /* vectorised over every node of every pair */
            scaled_row(n2[m], n3[m], root, &b0, &b1, &b2, &ib);
            values[m] = asin_fast(clip1(s0[m] * b0 + s1[m] * b1 + s2[m] * b2));
        }
    } else {
        double *restrict r0 = rows, *restrict r1 = rows + total;
        double *restrict r2 = rows + 2 * total, *restrict r3 = rows + 3 * total;
        for (i64 m = 0; m < total; m++) {
            scaled_row(n0[m], n1[m], root, &a0, &a1, &a2, &ia);
            scaled_row(n2[m], n3[m], root, &b0, &b1, &b2, &ib);
            double z = clip1(a0 * b0 + a1 * b1 + a2 * b2);
            double slope = 1.0 / sqrt(1.0 - z * z); /* dk/dz */
            double hz = 0.5 * z;
            r0[m] = asin_fast(z);
            r1[m] = slope * dz(a0, b0, hz);
            r2[m] = slope * dz(a1, b1, hz);
            r3[m] = slope * dz(a2, b2, hz);
        }
        if (with_scale) {
            /* Each node's offset from its pair's means, so that the loop below is flat. */
            double *restrict d0 = offsets, *restrict d1 = offsets + total;
            double *restrict d2 = offsets + 2 * total, *restrict d3 = offsets + 3 * total;
            for (i64 p = 0; p < total / size; p++) {
                for (i64 m = p * size; m < (p + 1) * size; m++) {
                    d0[m] = n0[m] - centres[p];
                    d1[m] = n1[m] - centres[centres_ld + p];
                    d2[m] = n2[m] - centres[2 * centres_ld + p];
                    d3[m] = n3[m] - centres[3 * centres_ld + p];
                }
            }
            double *restrict r4 = rows + 4 * total;
            for (i64 m = 0; m < total; m++) {
                scaled_row(n0[m], n1[m], root, &a0, &a1, &a2, &ia);
                scaled_row(n2[m], n3[m], root, &b0, &b1, &b2, &ib);
                double z = clip1(a0 * b0 + a1 * b1 + a2 * b2);
                r4[m] = dz_scale(a1, a2, b1, b2, z, root[1] * d0[m] * ia, root[2] * d1[m] * ia,
                                 root[1] * d2[m] * ib, root[2] * d3[m] * ib)
                        / sqrt(1.0 - z * z);
            }
        }
    }
    for (i64 p = 0; p < total / size; p++) {
        for (i64 r = 0; r < count; r++) {
            double acc = 0.0;
            for (i64 k = 0; k < size; k++)
                acc += weights[k] * rows[r * total + p * size + k];
            out[r * ld + p] = scale * acc;
        }
    }
}

/* The runs of a 4-D rule's nodes (unit (L, 4)) over which the first point's two unit
 * coordinates stay the same: the rule's square root for gpocc.gp.expected's tensor
 * rules (the first coordinates vary slowest), 1 for a rule without such runs. */
static i64 a_side_group(const double *unit, i64 size)
{
    i64 group = 1;
    while ((group + 1) * (group + 1) <= size)
        group++;
    if (group * group != size)
        return 1;
    for (i64 m = 0; m < size; m++) {
        const double *first = unit + 4 * (m - m % group), *e = unit + 4 * m;
        if (e[0] != first[0] || e[1] != first[1])
            return 1;
    }
    return group;
}

/* Pairs per batch of gpocc_nn_same_scan_pairs: their nodes (4 x 16 float64 per pair at
 * level 2) stay in cache. */
#define PAIR_BATCH 256

/* out[:, p] (out (rows, P)): the expected kernel (and gradients, and with with_scale the
 * derivative in log g) of same-scan pair (first[p], second[p]) under its joint 4-D rule
 * (unit (L, 4), weights (L,)). Returns -1 if out of memory. */
EXPORT int gpocc_nn_same_scan_pairs(const double *restrict means, const double *restrict cov,
                                    const double *restrict pf, const i64 *restrict first,
                                    const i64 *restrict second, i64 pairs,
                                    const double *restrict unit, const double *restrict weights,
                                    i64 size, const double *restrict root, double scale,
                                    double input_scale, double *out, int with_gradient,
                                    int with_scale)
{
    i64 batch_nodes = (i64)PAIR_BATCH * size;
    double *nodes = malloc((size_t)(4 * batch_nodes) * sizeof(double));
    double *rows = malloc((size_t)(5 * batch_nodes) * sizeof(double));
    double *offsets = malloc((size_t)(4 * batch_nodes) * sizeof(double));
    double centres[4 * PAIR_BATCH];
    if (!nodes || !rows || !offsets) {
        free(nodes);
        free(rows);
        free(offsets);
        return -1;
    }
    i64 group = a_side_group(unit, size);
    for (i64 lo = 0; lo < pairs; lo += PAIR_BATCH) {
        i64 hi = lo + PAIR_BATCH < pairs ? lo + PAIR_BATCH : pairs;
        i64 count = hi - lo;
        gpocc_correlated_nodes(means, cov, pf, first + lo, second + lo, count, unit, size,
                               input_scale, nodes);
        if (with_scale) {
            for (i64 p = 0; p < count; p++) {
                centres[p] = means[2 * first[lo + p]];
                centres[PAIR_BATCH + p] = means[2 * first[lo + p] + 1];
                centres[2 * PAIR_BATCH + p] = means[2 * second[lo + p]];
                centres[3 * PAIR_BATCH + p] = means[2 * second[lo + p] + 1];
            }
        }
        node_pairs(nodes, count * size, weights, size, group, root, scale, out + lo, pairs,
                   with_gradient, centres, PAIR_BATCH, with_scale, rows, offsets);
    }
    free(nodes);
    free(rows);
    free(offsets);
    return 0;
}

static int pair_is_live(const double *cov, const double *pf, i64 a, double pose_share_min,
                        double zero_variance)
{
    double pose_part = 0.0;
    for (int k = 0; k < 6; k++)
        pose_part += pf[6 * a + k] * pf[6 * a + k];
    const double *c = cov + 4 * a;
    double trace = c[0] + c[3];
    double biggest = fabs(c[0]);
    for (int k = 1; k < 4; k++)
        biggest = fabs(c[k]) > biggest ? fabs(c[k]) : biggest;
    return pose_part > pose_share_min * trace && biggest > zero_variance;
}

/* The same-scan pairs (i < j, row-major order) of gpocc.gp.expected.same_scan_pairs:
 * both points carry a pose share above pose_share_min of their trace and a covariance
 * entry above zero_variance. With first == NULL only counts them; otherwise writes them
 * (first and second hold the count). Returns the count, or -1 if out of memory. */
EXPORT i64 gpocc_correlated_pairs(const double *restrict cov, const i64 *restrict scan_ids,
                                  const double *restrict pf, i64 n, double pose_share_min,
                                  double zero_variance, i64 *restrict first,
                                  i64 *restrict second)
{
    unsigned char *live = malloc((size_t)(n > 0 ? n : 1));
    if (!live)
        return -1;
    for (i64 a = 0; a < n; a++)
        live[a] = (unsigned char)pair_is_live(cov, pf, a, pose_share_min, zero_variance);
    i64 k = 0;
    for (i64 a = 0; a < n; a++) {
        if (!live[a])
            continue;
        for (i64 b = a + 1; b < n; b++) {
            if (live[b] && scan_ids[b] == scan_ids[a]) {
                if (first) {
                    first[k] = a;
                    second[k] = b;
                }
                k++;
            }
        }
    }
    free(live);
    return k;
}

/* nn_matrix_uniform_from in single precision (u (4, L N) the scaled rows and their
 * gaps, as nn_cross_uniform_single): the upper triangle i < j, rows i leaving out their
 * entries i < j < first[i] in whole vectors of eight, then the lower triangle copied;
 * diagonal untouched. */
static CLONES int nn_matrix_uniform_single(const float *restrict u,
                                           const float *restrict weights, i64 size, i64 n,
                                           double scale, const i64 *restrict first,
                                           double *restrict out)
{
    i64 total = size * n;
    float *restrict acc = malloc((size_t)(total > 0 ? total : 1) * sizeof(float));
    if (!acc)
        return -1;
    const float *U0 = u, *U1 = u + total, *U2 = u + 2 * total, *U3 = u + 3 * total;
    for (i64 i = 0; i < n; i++) {
        i64 from = first ? i + 1 + ((first[i] - i - 1) & ~(i64)7) : i + 1;
        if (size == 4) {
            /* Point i's four nodes held in registers through each pass over a slot. */
            float p[4][4], w[4];
            for (i64 k = 0; k < 4; k++) {
                p[k][0] = U0[k * n + i]; p[k][1] = U1[k * n + i];
                p[k][2] = U2[k * n + i]; p[k][3] = U3[k * n + i];
                w[k] = weights[k];
            }
            for (i64 slot = 0; slot < 4; slot++) {
                i64 lo = slot * n + from;
                const float *restrict v0 = U0 + lo, *restrict v1 = U1 + lo;
                const float *restrict v2 = U2 + lo, *restrict v3 = U3 + lo;
                float *restrict row = acc + lo;
                for (i64 j = 0; j < n - from; j++) {
                    float y0 = v0[j], y1 = v1[j], y2 = v2[j], y3 = v3[j];
                    float t = 0.0f;
                    for (i64 k = 0; k < 4; k++) {
                        float z = p[k][0] * y0 + p[k][1] * y1 + p[k][2] * y2;
                        t += w[k] * asin_single(z, half_gap(z, p[k][0], p[k][1], p[k][2],
                                                            p[k][3], y0, y1, y2, y3));
                    }
                    row[j] = t;
                }
            }
        } else {
            for (i64 slot = 0; slot < size; slot++)
                for (i64 j = from; j < n; j++)
                    acc[slot * n + j] = 0.0f;
            for (i64 k = 0; k < size; k++) {
                float x0 = U0[k * n + i], x1 = U1[k * n + i], x2 = U2[k * n + i];
                float x3 = U3[k * n + i];
                float wa = weights[k];
                for (i64 slot = 0; slot < size; slot++) {
                    i64 lo = slot * n + from;
                    const float *restrict v0 = U0 + lo, *restrict v1 = U1 + lo;
                    const float *restrict v2 = U2 + lo, *restrict v3 = U3 + lo;
                    float *restrict row = acc + lo;
                    for (i64 j = 0; j < n - from; j++) {
                        float z = x0 * v0[j] + x1 * v1[j] + x2 * v2[j];
                        row[j] += wa * asin_single(z, half_gap(z, x0, x1, x2, x3, v0[j], v1[j],
                                                               v2[j], v3[j]));
                    }
                }
            }
        }
        for (i64 j = from; j < n; j++) {
            float value = 0.0f;
            for (i64 slot = 0; slot < size; slot++)
                value += acc[slot * n + j] * weights[slot];
            out[i * n + j] = scale * (double)value;
        }
    }
    for (i64 i = 0; i < n; i++)
        for (i64 j = 0; j < i; j++)
            out[i * n + j] = out[j * n + i];
    free(acc);
    return 0;
}

/* gpocc_nn_cross_uniform in single precision: q (4, Q) and u (4, L N) hold the scaled
 * rows and their gaps 1 - |row|^2 (row 3), node-major as there; weights (L,); out
 * (Q, N) in double. Returns -1 if out of memory. */
static CLONES int nn_cross_uniform_single(const float *restrict q, i64 nq,
                                          const float *restrict u,
                                          const float *restrict weights, i64 size, i64 n,
                                          double scale, double *restrict out)
{
    i64 total = size * n;
    const float *U0 = u, *U1 = u + total, *U2 = u + 2 * total, *U3 = u + 3 * total;
    if (size == 4) { /* level 2, the default: the four nodes summed in registers */
        for (i64 r = 0; r < nq; r++) {
            float x0 = q[r], x1 = q[nq + r], x2 = q[2 * nq + r], x3 = q[3 * nq + r];
            double *restrict dst = out + r * n;
            for (i64 i = 0; i < n; i++) {
                float t = 0.0f;
                for (i64 k = 0; k < 4; k++) {
                    i64 c = k * n + i;
                    float v0 = U0[c], v1 = U1[c], v2 = U2[c], v3 = U3[c];
                    float z = x0 * v0 + x1 * v1 + x2 * v2;
                    t += weights[k] * asin_single(z, half_gap(z, x0, x1, x2, x3, v0, v1, v2,
                                                              v3));
                }
                dst[i] = scale * (double)t;
            }
        }
        return 0;
    }
    float *restrict row = malloc((size_t)(n > 0 ? n : 1) * sizeof(float));
    if (!row)
        return -1;
    for (i64 r = 0; r < nq; r++) {
        float x0 = q[r], x1 = q[nq + r], x2 = q[2 * nq + r], x3 = q[3 * nq + r];
        for (i64 i = 0; i < n; i++)
            row[i] = 0.0f;
        for (i64 k = 0; k < size; k++) {
            float wk = weights[k];
            const float *restrict v0 = U0 + k * n, *restrict v1 = U1 + k * n;
            const float *restrict v2 = U2 + k * n, *restrict v3 = U3 + k * n;
            for (i64 i = 0; i < n; i++) {
                float z = x0 * v0[i] + x1 * v1[i] + x2 * v2[i];
                row[i] += wk * asin_single(z, half_gap(z, x0, x1, x2, x3, v0[i], v1[i], v2[i],
                                                       v3[i]));
            }
        }
        double *restrict dst = out + r * n;
        for (i64 i = 0; i < n; i++)
            dst[i] = scale * (double)row[i];
    }
    free(row);
    return 0;
}

/* Every covariance one local GP problem needs, in one call, for N points that all share
 * one 2-D rule (unit (L, 2), weights (L,)):
 *   k_out (N, N): the expected training matrix (product rule; same-scan pairs by the 4-D
 *   rule unit4 (L4, 4) / weights4 when correlated and L > 1; one-point diagonal) plus
 *   ``diagonal`` on the diagonal;
 *   cross_out (Q, N): expected cross-covariances of the exact (Q, 2) queries;
 *   prior_out (Q,): k(q, q).
 * With ``single``, the product-rule part of k_out and cross_out are computed in single
 * precision (nn_matrix_uniform_single, nn_cross_uniform_single: about 1e-6 of the
 * kernel's scale), the diagonal, the same-scan pairs and prior_out in double.
 * Returns -1 if out of memory. */
EXPORT int gpocc_nn_local_system(const double *restrict means, const double *restrict cov,
                                 const i64 *restrict scan_ids, const double *restrict pf,
                                 i64 n, const double *restrict queries, i64 nq,
                                 const double *restrict unit, const double *restrict weights,
                                 i64 size, const double *restrict unit4,
                                 const double *restrict weights4, i64 size4,
                                 const double *restrict root, double scale, double diagonal,
                                 int correlated, double pose_share_min, double zero_variance,
                                 int single, double *restrict k_out,
                                 double *restrict cross_out, double *restrict prior_out)
{
    i64 total = n * size;
    size_t cells = (size_t)(total > 0 ? total : 1);
    size_t queries_cells = (size_t)(nq > 0 ? nq : 1);
    double *nodes = malloc(2 * cells * sizeof(double));
    double *u = malloc(3 * cells * sizeof(double));
    double *q = single ? NULL : malloc(3 * queries_cells * sizeof(double));
    /* Single precision: rows (4, .) of the scaled rows and their gaps 1 - |row|^2. */
    float *us = single ? malloc(4 * cells * sizeof(float)) : NULL;
    float *qs = single ? malloc(4 * queries_cells * sizeof(float)) : NULL;
    float *ws = single ? malloc((size_t)(size > 0 ? size : 1) * sizeof(float)) : NULL;
    i64 *pair_index = NULL;
    i64 *first = NULL;
    double *values = NULL;
    int status = -1;
    if (!nodes || !u || (single ? !us || !qs || !ws : !q))
        goto done;
    gpocc_gaussian_nodes_2d(means, cov, n, unit, size, nodes);
    /* Node-major scaled rows (node k of point i in column k N + i). */
    for (i64 i = 0; i < n; i++) {
        for (i64 k = 0; k < size; k++) {
            i64 m = i * size + k, c = k * n + i;
            double inv;
            scaled_row(nodes[m], nodes[total + m], root, &u[c], &u[total + c],
                       &u[2 * total + c], &inv);
            if (single) {
                us[c] = (float)u[c];
                us[total + c] = (float)u[total + c];
                us[2 * total + c] = (float)u[2 * total + c];
                us[3 * total + c] = (float)(inv * inv); /* 1 - |u|^2 = inv^2 exactly */
            }
        }
    }
    for (i64 k = 0; single && k < size; k++)
        ws[k] = (float)weights[k];
    i64 pairs = 0;
    if (correlated && size > 1) {
        pairs = gpocc_correlated_pairs(cov, scan_ids, pf, n, pose_share_min, zero_variance,
                                       NULL, NULL);
        if (pairs < 0)
            goto done;
        if (pairs > 0) {
            pair_index = malloc((size_t)(2 * pairs) * sizeof(i64));
            values = malloc((size_t)pairs * sizeof(double));
            first = malloc((size_t)n * sizeof(i64));
            if (!pair_index || !values || !first)
                goto done;
            gpocc_correlated_pairs(cov, scan_ids, pf, n, pose_share_min, zero_variance,
                                   pair_index, pair_index + pairs);
            /* The product rule skips, in each row i, the run of partners i + 1, i + 2, ...
             * that the 4-D rule below replaces: pairs come in row-major order. */
            for (i64 i = 0; i < n; i++)
                first[i] = i + 1;
            for (i64 p = 0; p < pairs; p++) {
                i64 a = pair_index[p], b = pair_index[pairs + p];
                if (b == first[a])
                    first[a] = b + 1;
            }
        }
    }
    if ((single ? nn_matrix_uniform_single(us, ws, size, n, scale, first, k_out)
                : nn_matrix_uniform_from(u, weights, size, n, scale, first, k_out)) != 0)
        goto done;
    /* The diagonal and the priors in double precision: each is one arcsine of a row
     * with itself, and the variances subtract from them. */
    for (i64 i = 0; i < n; i++) {
        double acc = 0.0;
        for (i64 k = 0; k < size; k++) {
            i64 m = k * n + i;
            double x0 = u[m], x1 = u[total + m], x2 = u[2 * total + m];
            acc += weights[k] * asin_fast(clip1(x0 * x0 + x1 * x1 + x2 * x2));
        }
        k_out[i * n + i] = scale * acc + diagonal;
    }
    if (pairs > 0) {
        if (gpocc_nn_same_scan_pairs(means, cov, pf, pair_index, pair_index + pairs, pairs,
                                     unit4, weights4, size4, root, scale, 1.0, values, 0,
                                     0) != 0)
            goto done;
        for (i64 p = 0; p < pairs; p++) {
            i64 a = pair_index[p], b = pair_index[pairs + p];
            k_out[a * n + b] = values[p];
            k_out[b * n + a] = values[p];
        }
    }
    for (i64 r = 0; r < nq; r++) {
        double q0, q1, q2, inv;
        scaled_row(queries[2 * r], queries[2 * r + 1], root, &q0, &q1, &q2, &inv);
        if (single) {
            qs[r] = (float)q0;
            qs[nq + r] = (float)q1;
            qs[2 * nq + r] = (float)q2;
            qs[3 * nq + r] = (float)(inv * inv);
        } else {
            q[r] = q0;
            q[nq + r] = q1;
            q[2 * nq + r] = q2;
        }
        prior_out[r] = scale * asin_fast(clip1(q0 * q0 + q1 * q1 + q2 * q2));
    }
    if (single) {
        if (nn_cross_uniform_single(qs, nq, us, ws, size, n, scale, cross_out) != 0)
            goto done;
    } else {
        gpocc_nn_cross_uniform(q, nq, u, weights, size, n, scale, cross_out);
    }
    status = 0;
done:
    free(nodes);
    free(u);
    free(q);
    free(us);
    free(qs);
    free(ws);
    free(pair_index);
    free(first);
    free(values);
    return status;
}

/* ------------------------------------------------------------------ beam samples */

#define N_INPUTS 5
#define SIGMA (2 * N_INPUTS + 1)

/* The scaled unscented transform of N beam samples (gpocc/samples/beam_unscented.py):
 * inputs (range, bearing, base x, y, yaw) with the block-diagonal root (range_sd[i],
 * bearing_sd, pose_root[s]); each sigma point moves one input. Writes means (N, 2),
 * covariances (N, 2, 2) and pose factors (N, 2, 3). */
EXPORT void gpocc_beam_unscented(const double *restrict dist, const double *restrict bearing,
                                 const double *restrict range_sd, double bearing_sd,
                                 const i64 *restrict scan, i64 n, const double *restrict poses,
                                 const double *restrict pose_root,
                                 const double *restrict pose_map, const double *restrict mount,
                                 const double *restrict wm, const double *restrict wc,
                                 double gamma, double *restrict means,
                                 double *restrict covariances, double *restrict factors)
{
    double mx = mount[0], my = mount[1], myaw = mount[2];
    double points[SIGMA][N_INPUTS];
    double ys[SIGMA][2];
    /* Each sigma point's step from the centre: +-gamma times a column of the root. The
     * bearing and pose steps, and the cosines and sines of the yaw and beam-angle steps,
     * are the same for every sample of a scan: set once per scan. */
    double steps[SIGMA][N_INPUTS];
    double step_cos[SIGMA][2], step_sin[SIGMA][2]; /* columns: yaw, beam angle */
    /* Also per scan: each sigma point's rotation by the yaw (cos and sin of the scan's
     * yaw plus the point's step), and the products of the pose root and pose map that
     * weight the cross-covariance into the pose factor. Per beam (the samples of one beam
     * come one after another): each sigma point's rotation by the beam's direction. Each
     * is the very value a sample would compute for itself. */
    double yaw_cos[SIGMA], yaw_sin[SIGMA], beam_cos[SIGMA], beam_sin[SIGMA];
    double last_bearing = 0.0;
    double weights[3][3][3]; /* [j][d][m]: root[d][j] * pmap[d][m] */
    memset(steps, 0, sizeof(steps));
    i64 last_scan = 0;
    for (i64 i = 0; i < n; i++) {
        i64 s = scan[i];
        const double *root = pose_root + 9 * s;
        int new_scan = i == 0 || s != last_scan;
        if (new_scan) {
            last_scan = s;
            const double *pmap = pose_map + 9 * s;
            for (int j = 0; j < 3; j++)
                for (int d = 0; d < 3; d++)
                    for (int m = 0; m < 3; m++)
                        weights[j][d][m] = root[d * 3 + j] * pmap[d * 3 + m];
            double c0 = cos(poses[3 * s + 2]), s0 = sin(poses[3 * s + 2]);
            steps[2][1] = gamma * bearing_sd;
            steps[2 + N_INPUTS][1] = -gamma * bearing_sd;
            for (int j = 0; j < 3; j++) {
                for (int d = 0; d < 3; d++) {
                    double step = gamma * root[d * 3 + j];
                    steps[3 + j][2 + d] = step;
                    steps[3 + j + N_INPUTS][2 + d] = -step;
                }
            }
            for (int k = 0; k < SIGMA; k++) {
                double yaw = steps[k][4], angle = steps[k][4] + steps[k][1];
                step_cos[k][0] = cos(yaw);
                step_sin[k][0] = sin(yaw);
                step_cos[k][1] = cos(angle);
                step_sin[k][1] = sin(angle);
                yaw_cos[k] = c0 * step_cos[k][0] - s0 * step_sin[k][0];
                yaw_sin[k] = s0 * step_cos[k][0] + c0 * step_sin[k][0];
            }
        }
        steps[1][0] = gamma * range_sd[i];
        steps[1 + N_INPUTS][0] = -gamma * range_sd[i];
        double centre[N_INPUTS] = {dist[i], bearing[i], poses[3 * s], poses[3 * s + 1],
                                   poses[3 * s + 2]};
        for (int k = 0; k < SIGMA; k++)
            for (int d = 0; d < N_INPUTS; d++)
                points[k][d] = centre[d] + steps[k][d];
        double mean_x = 0.0, mean_y = 0.0;
        if (new_scan || centre[1] != last_bearing) {
            double phi0 = centre[4] + myaw + centre[1];
            last_bearing = centre[1];
            double cp0 = cos(phi0), sp0 = sin(phi0);
            for (int k = 0; k < SIGMA; k++) {
                beam_cos[k] = cp0 * step_cos[k][1] - sp0 * step_sin[k][1];
                beam_sin[k] = sp0 * step_cos[k][1] + cp0 * step_sin[k][1];
            }
        }
        /* Without range noise the range's two sigma points are the centre itself. */
        int exact_range = range_sd[i] == 0.0;
        for (int k = 0; k < SIGMA; k++) {
            if (exact_range && (k == 1 || k == 1 + N_INPUTS)) {
                ys[k][0] = ys[0][0];
                ys[k][1] = ys[0][1];
            } else {
                double r = points[k][0], x = points[k][2], y = points[k][3];
                double c = yaw_cos[k], sn = yaw_sin[k], cp = beam_cos[k], sp = beam_sin[k];
                ys[k][0] = x + c * mx - sn * my + r * cp;
                ys[k][1] = y + sn * mx + c * my + r * sp;
            }
            mean_x += wm[k] * ys[k][0];
            mean_y += wm[k] * ys[k][1];
        }
        double cxx = 0.0, cxy = 0.0, cyy = 0.0;
        for (int k = 0; k < SIGMA; k++) {
            double dx = ys[k][0] - mean_x, dy = ys[k][1] - mean_y;
            cxx += wc[k] * dx * dx;
            cxy += wc[k] * dx * dy;
            cyy += wc[k] * dy * dy;
        }
        means[2 * i] = mean_x;
        means[2 * i + 1] = mean_y;
        covariances[4 * i] = cxx;
        covariances[4 * i + 1] = cxy;
        covariances[4 * i + 2] = cxy;
        covariances[4 * i + 3] = cyy;
        /* Cross-covariance of the pose inputs and the position: only the pose sigma
         * points move the pose, by +-gamma L[:, j], with the (equal) weight wc[1]. */
        double *f = factors + 6 * i;
        for (int k = 0; k < 6; k++)
            f[k] = 0.0;
        for (int j = 0; j < 3; j++) {
            double dpx = (ys[3 + j][0] - ys[3 + j + N_INPUTS][0]) * gamma * wc[1];
            double dpy = (ys[3 + j][1] - ys[3 + j + N_INPUTS][1]) * gamma * wc[1];
            for (int d = 0; d < 3; d++) {
                for (int m = 0; m < 3; m++) {
                    double weight = weights[j][d][m];
                    f[m] += weight * dpx;
                    f[3 + m] += weight * dpy;
                }
            }
        }
    }
}

/* ------------------------------------------------------------------ thinning */

static inline i64 thin_slot(i64 key, i64 mask)
{
    /* Fibonacci hashing: packed cells of one neighbourhood differ in their low bits. */
    return (i64)(((uint64_t)key * 0x9E3779B97F4A7C15ULL) >> 32) & mask;
}

/* Thinning's groups (gpocc/samples/beams.py, _thinned): the samples' (cell, label) keys
 * (N,) and covariance traces (N,), single precision and finite. For each distinct key,
 * in the order of its first sample: the key, its number of samples, and the index of
 * its sample with the smallest trace (the earliest of those that have it). Writes up to
 * N entries of each output; returns the number of distinct keys, or -1 when memory ran
 * out. One pass over a hash table of the keys seen, which grows with the keys, not with
 * N: a chunk of 100,000 beam samples has a few thousand. */
EXPORT i64 gpocc_thin_groups(const i64 *restrict keys, const float *restrict trace, i64 n,
                             i64 *restrict group_keys, i64 *restrict group_counts,
                             i64 *restrict kept)
{
    i64 capacity = 1024, mask = capacity - 1, groups = 0;
    i64 *table = malloc(sizeof(i64) * (size_t)capacity);
    float *best = malloc(sizeof(float) * (size_t)(n > 0 ? n : 1));
    if (table == NULL || best == NULL) {
        free(table);
        free(best);
        return -1;
    }
    for (i64 t = 0; t < capacity; t++)
        table[t] = -1;
    for (i64 i = 0; i < n; i++) {
        i64 key = keys[i];
        i64 slot = thin_slot(key, mask);
        i64 g;
        while ((g = table[slot]) >= 0 && group_keys[g] != key)
            slot = (slot + 1) & mask;
        if (g >= 0) {
            group_counts[g] += 1;
            if (trace[i] < best[g]) { /* strictly: ties keep the earliest sample */
                best[g] = trace[i];
                kept[g] = i;
            }
            continue;
        }
        g = groups++;
        table[slot] = g;
        group_keys[g] = key;
        group_counts[g] = 1;
        best[g] = trace[i];
        kept[g] = i;
        if (2 * groups > capacity) { /* half full: double the table and re-insert */
            i64 *grown = malloc(sizeof(i64) * (size_t)(2 * capacity));
            if (grown == NULL) {
                free(table);
                free(best);
                return -1;
            }
            free(table);
            table = grown;
            capacity *= 2;
            mask = capacity - 1;
            for (i64 t = 0; t < capacity; t++)
                table[t] = -1;
            for (i64 h = 0; h < groups; h++) {
                i64 at = thin_slot(group_keys[h], mask);
                while (table[at] >= 0)
                    at = (at + 1) & mask;
                table[at] = h;
            }
        }
    }
    free(table);
    free(best);
    return groups;
}

/* Set the cells of covered (H, W) (one byte each) that hold a point every 1 cell along
 * each segment start -> end (N, 2), cell units from the raster's corner, or its end. */
EXPORT void gpocc_mark_segments(const double *restrict start, const double *restrict end,
                                i64 n, unsigned char *restrict covered, i64 height, i64 width)
{
    for (i64 s = 0; s < n; s++) {
        double sx = start[2 * s], sy = start[2 * s + 1];
        double dx = end[2 * s] - sx, dy = end[2 * s + 1] - sy;
        double length = hypot(dx, dy);
        double safe = length > 1e-12 ? length : 1e-12;
        double ux = dx / safe, uy = dy / safe;
        i64 steps = (i64)floor(length) + 2; /* 0, 1, ..., and the end */
        for (i64 k = 0; k < steps; k++) {
            double t = (double)k < length ? (double)k : length;
            i64 col = (i64)(sx + t * ux), row = (i64)(sy + t * uy);
            col = col < 0 ? 0 : (col > width - 1 ? width - 1 : col);
            row = row < 0 ? 0 : (row > height - 1 ? height - 1 : row);
            covered[row * width + col] = 1;
        }
    }
}

/* ------------------------------------------------------------------ text */

/* A character a number token may hold: digits, sign, point, exponent and the letters of
 * inf, infinity and nan, all Python's float() reads; so strtod's hex floats and nan(...)
 * never parse here. */
static inline int number_char(unsigned char c)
{
    return (c >= '0' && c <= '9') || c == '+' || c == '-' || c == '.' || c == 'e'
        || c == 'E' || c == 'i' || c == 'I' || c == 'n' || c == 'N' || c == 'f' || c == 'F'
        || c == 'a' || c == 'A' || c == 't' || c == 'T' || c == 'y' || c == 'Y';
}

static inline int blank(unsigned char c)
{
    return c == ' ' || c == '\t' || c == '\r' || c == '\v' || c == '\f';
}

/* The numbers of `lines` lines of text (NUL-terminated, with no other NUL; lines ending
 * at '\n'), each of exactly per_line whitespace-separated tokens, into out (lines,
 * per_line): strtod's correctly rounded doubles, the ones float() reads. Returns -1, or
 * the first line that is not such a line (a token strtod does not read whole, another
 * count, no line), or `lines` when text follows the last line. */
EXPORT i64 gpocc_parse_rows(const unsigned char *restrict text, i64 per_line, i64 lines,
                            double *restrict out)
{
    const unsigned char *p = text;
    for (i64 k = 0; k < lines; k++) {
        i64 m = 0;
        for (;;) {
            while (blank(*p))
                p++;
            if (*p == '\n' || *p == '\0')
                break;
            const unsigned char *start = p;
            while (*p != '\0' && *p != '\n' && !blank(*p)) {
                if (!number_char(*p))
                    return k;
                p++;
            }
            if (m == per_line)
                return k;
            char *stop;
            out[k * per_line + m++] = strtod((const char *)start, &stop);
            if ((const unsigned char *)stop != p)
                return k;
        }
        if (m != per_line)
            return k;
        if (*p == '\n')
            p++;
        else if (k + 1 < lines)
            return k + 1;
    }
    while (blank(*p) || *p == '\n')
        p++;
    return *p == '\0' ? -1 : lines;
}

/* ------------------------------------------------------------------ module */

/* An importable module, so that a missing or stale build shows as an ImportError; the
 * loops above are called through ctypes (gpocc/compiled.py), which releases the GIL. */
static struct PyModuleDef kernels_module = {
    PyModuleDef_HEAD_INIT, "_kernels",
    "gpocc's compiled loops (C); call them through gpocc.compiled.", -1, NULL,
};

PyMODINIT_FUNC PyInit__kernels(void)
{
    return PyModule_Create(&kernels_module);
}
