/* The split solve's substitutions for one half (sim/fast/supernodal.py): y = L^-1 P b and x = P^T L^-T z of a
   single-precision supernodal L D L^T, in a fixed order (equal inputs give equal bits).

   The layout, per supernode s (columns c0 = starts[s] .. starts[s + 1] - 1, width ns):
   - the strict lower triangle of its diagonal block, ns (ns - 1) / 2 values, twice: column by column at
     dval + doff[s] for the forward kernel (column j's entries L[c0 + k, c0 + j], k = j + 1 .. ns - 1, one after
     the other) and row by row at drow + doff[s] for the backward one (row i's L[c0 + i, c0 + k], k = 0 .. i - 1,
     from i (i - 1) / 2 on), so both kernels update a vector per unknown;
   - the rows below it, nbp = roff[s + 1] - roff[s] of them (a multiple of LANES), column by column at
     bval + boff[s]; their indices at rows + roff[s], the padding rows pointing at the spare slot x[n], whose
     values are zero.
   The row indices are 16-bit where the half has fewer than 65,535 unknowns (half the bytes), else 32-bit: the
   kernels are compiled for both (the _u16 and _i32 functions). Every loop over LANES is written out lane by lane, and every sum is taken in the order written here, so the
   compiler vectorises without reordering a sum: the AVX-512 and AVX2 builds give the same bits. target_clones
   compiles each kernel for AVX-512, AVX2 and the baseline and picks one when the library is loaded; the first two
   fuse multiply-adds (FMA) and the baseline does not, so a machine without AVX2 gets other last bits (measured;
   -ffp-contract=off would make them equal at ~4 % of the kernels' time). On one machine the bits never change. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#define LANES 16

#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 12 && defined(__x86_64__)
#define CLONED __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define CLONED
#endif


/* the kernels for one type of row index: vcyto_forward_SUFFIX and vcyto_backward_SUFFIX */
#define KERNELS(SUFFIX, INDEX)                                                                                       \
                                                                                                                     \
/* x <- L^-1 x */                                                                                                    \
static inline __attribute__((always_inline)) void forward_##SUFFIX(                                                  \
    int64_t nsn, const int64_t *restrict starts, const int64_t *restrict doff, const int64_t *restrict boff,         \
    const int64_t *restrict roff, const float *restrict dval, const float *restrict bval,                            \
    const INDEX *restrict rows, float *x)                                                                            \
{                                                                                                                    \
    for (int64_t s = 0; s < nsn; s++) {                                                                              \
        const int64_t c0 = starts[s], ns = starts[s + 1] - c0;                                                       \
        const float *restrict column = dval + doff[s];                                                               \
        float *xs = x + c0;                                                                                          \
        for (int64_t j = 0; j < ns; j++) {                                                                           \
            const float xj = xs[j];                                                                                  \
            for (int64_t k = j + 1; k < ns; k++) xs[k] -= column[k - j - 1] * xj;                                    \
            column += ns - 1 - j;                                                                                    \
        }                                                                                                            \
        const int64_t nbp = roff[s + 1] - roff[s];                                                                   \
        const float *restrict b = bval + boff[s];                                                                    \
        const INDEX *restrict r = rows + roff[s];                                                                    \
        int64_t q = 0;                                                                                               \
        for (; q + 4 * LANES <= nbp; q += 4 * LANES) {      /* four vectors of rows at a time */                     \
            float acc[4 * LANES] __attribute__((aligned(64)));                                                       \
            for (int w = 0; w < 4 * LANES; w++) acc[w] = 0.0f;                                                       \
            for (int64_t j = 0; j < ns; j++) {                                                                       \
                const float xj = xs[j];                                                                              \
                const float *restrict col = b + j * nbp + q;                                                         \
                for (int w = 0; w < 4 * LANES; w++) acc[w] += col[w] * xj;                                           \
            }                                                                                                        \
            for (int w = 0; w < 4 * LANES; w++) x[r[q + w]] -= acc[w];                                               \
        }                                                                                                            \
        for (; q < nbp; q += LANES) {                                                                                \
            float acc[LANES] __attribute__((aligned(64)));                                                           \
            for (int w = 0; w < LANES; w++) acc[w] = 0.0f;                                                           \
            for (int64_t j = 0; j < ns; j++) {                                                                       \
                const float xj = xs[j];                                                                              \
                const float *restrict col = b + j * nbp + q;                                                         \
                for (int w = 0; w < LANES; w++) acc[w] += col[w] * xj;                                               \
            }                                                                                                        \
            for (int w = 0; w < LANES; w++) x[r[q + w]] -= acc[w];                                                   \
        }                                                                                                            \
    }                                                                                                                \
}                                                                                                                    \
                                                                                                                     \
/* x <- L^-T x (g: scratch of the longest nbp) */                                                                    \
static inline __attribute__((always_inline)) void backward_##SUFFIX(                                                 \
    int64_t nsn, const int64_t *restrict starts, const int64_t *restrict doff, const int64_t *restrict boff,         \
    const int64_t *restrict roff, const float *restrict drow, const float *restrict bval,                            \
    const INDEX *restrict rows, float *x, float *restrict g)                                                         \
{                                                                                                                    \
    for (int64_t s = nsn - 1; s >= 0; s--) {                                                                         \
        const int64_t c0 = starts[s], ns = starts[s + 1] - c0;                                                       \
        const int64_t nbp = roff[s + 1] - roff[s];                                                                   \
        const float *restrict b = bval + boff[s];                                                                    \
        const INDEX *restrict r = rows + roff[s];                                                                    \
        float *xs = x + c0;                                                                                          \
        for (int64_t i = 0; i < nbp; i++) g[i] = x[r[i]];                                                            \
        int64_t j = 0;                                                                                               \
        for (; j + 4 <= ns; j += 4) {                      /* four columns at a time share the gathered rows */      \
            const float *restrict c = b + j * nbp;                                                                   \
            float a0[LANES] __attribute__((aligned(64))), a1[LANES] __attribute__((aligned(64)));                    \
            float a2[LANES] __attribute__((aligned(64))), a3[LANES] __attribute__((aligned(64)));                    \
            for (int w = 0; w < LANES; w++) a0[w] = a1[w] = a2[w] = a3[w] = 0.0f;                                    \
            for (int64_t q = 0; q < nbp; q += LANES)                                                                 \
                for (int w = 0; w < LANES; w++) {                                                                    \
                    const float gw = g[q + w];                                                                       \
                    a0[w] += c[q + w] * gw;                                                                          \
                    a1[w] += c[nbp + q + w] * gw;                                                                    \
                    a2[w] += c[2 * nbp + q + w] * gw;                                                                \
                    a3[w] += c[3 * nbp + q + w] * gw;                                                                \
                }                                                                                                    \
            xs[j] -= lanes_sum(a0);                                                                                  \
            xs[j + 1] -= lanes_sum(a1);                                                                              \
            xs[j + 2] -= lanes_sum(a2);                                                                              \
            xs[j + 3] -= lanes_sum(a3);                                                                              \
        }                                                                                                            \
        for (; j < ns; j++) {                                                                                        \
            const float *restrict c = b + j * nbp;                                                                   \
            float a0[LANES] __attribute__((aligned(64)));                                                            \
            for (int w = 0; w < LANES; w++) a0[w] = 0.0f;                                                            \
            for (int64_t q = 0; q < nbp; q += LANES)                                                                 \
                for (int w = 0; w < LANES; w++) a0[w] += c[q + w] * g[q + w];                                        \
            xs[j] -= lanes_sum(a0);                                                                                  \
        }                                                                                                            \
        /* as the forward kernel, a vector update per unknown: no chain of dependent sums along a row (measured:     \
           the wide blocks' dot products took a third of this kernel) */                                             \
        const float *restrict d = drow + doff[s];                                                                    \
        for (int64_t i = ns - 1; i > 0; i--) {                                                                       \
            const float xi = xs[i];                                                                                  \
            const float *restrict row = d + i * (i - 1) / 2;                                                         \
            for (int64_t k = 0; k < i; k++) xs[k] -= row[k] * xi;                                                    \
        }                                                                                                            \
    }                                                                                                                \
}                                                                                                                    \
                                                                                                                     \
/* PARDISO's phase 331 for one half: dst = L^-1 (src permuted by order); x: n + 1 floats of scratch */              \
CLONED void vcyto_forward_##SUFFIX(                                                                                  \
    int64_t n, int64_t nsn, const int64_t *restrict starts, const int64_t *restrict doff,                           \
    const int64_t *restrict boff, const int64_t *restrict roff, const float *restrict dval,                          \
    const float *restrict bval, const INDEX *restrict rows, const int64_t *restrict order,                           \
    const float *restrict src, float *restrict x, float *restrict dst)                                               \
{                                                                                                                    \
    for (int64_t i = 0; i < n; i++) x[i] = src[order[i]];                                                            \
    x[n] = 0.0f;                                                                                                     \
    forward_##SUFFIX(nsn, starts, doff, boff, roff, dval, bval, rows, x);                                            \
    memcpy(dst, x, (size_t)n * sizeof(float));                                                                       \
}                                                                                                                    \
                                                                                                                     \
/* PARDISO's phase 333 for one half: dst = P^T L^-T src; x: n + 1 floats, g: the longest nbp */                      \
CLONED void vcyto_backward_##SUFFIX(                                                                                 \
    int64_t n, int64_t nsn, const int64_t *restrict starts, const int64_t *restrict doff,                           \
    const int64_t *restrict boff, const int64_t *restrict roff, const float *restrict drow,                          \
    const float *restrict bval, const INDEX *restrict rows, const int64_t *restrict order,                           \
    const float *restrict src, float *restrict x, float *restrict g, float *restrict dst)                            \
{                                                                                                                    \
    memcpy(x, src, (size_t)n * sizeof(float));                                                                       \
    x[n] = 0.0f;                                                                                                     \
    backward_##SUFFIX(nsn, starts, doff, boff, roff, drow, bval, rows, x, g);                                        \
    for (int64_t i = 0; i < n; i++) dst[order[i]] = x[i];                                                            \
}

/* the lanes' sum in a fixed tree order */
static inline __attribute__((always_inline)) float lanes_sum(float *restrict a)
{
    for (int w = 0; w < 8; w++) a[w] += a[w + 8];
    for (int w = 0; w < 4; w++) a[w] += a[w + 4];
    a[0] += a[2];
    a[1] += a[3];
    return a[0] + a[1];
}

KERNELS(u16, uint16_t)
KERNELS(i32, int32_t)

/* the layout these kernels read (sim/fast/supernodal.py's LAYOUT): a library built from an older source is not used */
int64_t vcyto_substitute_layout(void) { return 3; }

/* an importable module without functions: Python finds the library by importing it, ctypes calls the kernels
   (and releases the GIL while they run) */
static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_substitute",
                                    "The split solve's substitution kernels (called through ctypes).", -1, NULL,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__substitute(void) { return PyModule_Create(&module); }
