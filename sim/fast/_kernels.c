/* The FE-IB step's kernels in C (sim/fast/kernels.py): the momentum load's element integrals and their scatter, the
   immersed boundary's point location, interpolation and spreading, the membranes' self-intersection test, the split
   solve's vector work and the fluid step's glue. The same functions as sim/fast/kernels_numba.py (the reference and the
   fallback), called with the same arguments; they exist so that a process that steps the FE-IB plant does not load
   numba (its import and the loading of its cached kernels cost ~0.35-0.5 s a process: docs/numerics.md, "The step's kernels").

   Arithmetic: every sum runs in the order written here and the library is compiled with -ffp-contract=off (no fused
   multiply-adds), so each kernel gives numba's bits where numba's kernel is exact (all but the momentum kernel,
   which numba compiles with fastmath: there the two agree to round-off). The momentum kernel is compiled for
   AVX-512, AVX2 and the baseline (target_clones, picked when the library loads); its vector loops run across
   elements, never inside a sum, so every build gives the same bits.

   Arrays arrive through the buffer protocol (C-contiguous, their type checked by format and size: a mismatch raises
   TypeError, and sim/fast/kernels.py then calls numba's kernel); the kernels numba compiled with nogil release the GIL
   here too. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#define BLOCK 128          /* elements the momentum kernel takes at a time (kernels_numba.BLOCK) */
#define LAYOUT 1           /* the functions' argument lists (sim/fast/kernels.py's LAYOUT) */
#ifdef __FAST_MATH__
#error "sim/fast/_kernels.c must not be built with -ffast-math: it promises numba's bits (remove it from CFLAGS)"
#endif
#ifndef VCYTO_KERNELS_SOURCE
#define VCYTO_KERNELS_SOURCE "unknown"
#endif

#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 12 && defined(__x86_64__)
#define CLONED __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define CLONED
#endif

/* ------------------------------------------------------------------------------------------------ arguments */

typedef struct {
    Py_buffer view;
    int held;
} Arg;

/* the buffer of ``object`` when it is a C-contiguous array of ``kind`` (a struct format character) and ``size``
   bytes an item; TypeError otherwise */
static int take(PyObject *object, Arg *arg, char kind, Py_ssize_t size, int writable, const char *name)
{
    arg->held = 0;
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(object, &arg->view, flags) < 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_TypeError, "%s: a C-contiguous%s array of '%c'", name, writable ? " writable" : "", kind);
        return -1;
    }
    arg->held = 1;
    const char *format = arg->view.format ? arg->view.format : "B";
    if (*format == '@' || *format == '=' || *format == '<')
        format++;
    char got = format[0];
    if (got == 'q' && size == 8)
        got = 'l';                         /* int64 is 'l' or 'q' */
    if (got == 'L' || got == 'Q')
        got = 'U';
    if (got != kind || format[1] != '\0' || arg->view.itemsize != size) {
        PyErr_Format(PyExc_TypeError, "%s: an array of '%c' (%zd bytes an item), not '%s'", name, kind, size,
                     arg->view.format ? arg->view.format : "B");
        return -1;
    }
    if ((uintptr_t)arg->view.buf % (uintptr_t)size != 0) {
        PyErr_Format(PyExc_TypeError, "%s: an array aligned to its items", name);
        return -1;
    }
    return 0;
}

static void release(Arg *args, int n)
{
    for (int i = 0; i < n; i++)
        if (args[i].held) {
            PyBuffer_Release(&args[i].view);
            args[i].held = 0;
        }
}

static inline Py_ssize_t count(const Arg *arg) { return arg->view.len / arg->view.itemsize; }
static inline Py_ssize_t dim(const Arg *arg, int axis) { return axis < arg->view.ndim ? arg->view.shape[axis] : 1; }
#define DATA(arg, type) ((type *)(arg).view.buf)

/* whether ``arg`` has ``ndim`` axes of the lengths given (-1: any) */
static int shaped(const Arg *arg, int ndim, Py_ssize_t d0, Py_ssize_t d1, Py_ssize_t d2)
{
    const Py_ssize_t wanted[3] = {d0, d1, d2};
    if (arg->view.ndim != ndim)
        return 0;
    for (int i = 0; i < ndim && i < 3; i++)
        if (wanted[i] >= 0 && arg->view.shape[i] != wanted[i])
            return 0;
    return 1;
}

/* whether every index is in [0, size): checked before a kernel writes through them */
static int within(const int64_t *indices, Py_ssize_t n, int64_t size)
{
    for (Py_ssize_t k = 0; k < n; k++)
        if (indices[k] < 0 || indices[k] >= size)
            return 0;
    return 1;
}

static int arity(Py_ssize_t nargs, Py_ssize_t wanted, const char *name)
{
    if (nargs != wanted) {
        PyErr_Format(PyExc_TypeError, "%s takes %zd arguments (%zd given)", name, wanted, nargs);
        return -1;
    }
    return 0;
}

static int real(PyObject *object, double *value)
{
    *value = PyFloat_AsDouble(object);
    return (*value == -1.0 && PyErr_Occurred()) ? -1 : 0;
}

static PyObject *shape_error(const char *name, const char *what)
{
    PyErr_Format(PyExc_ValueError, "%s: %s", name, what);
    return NULL;
}

/* ------------------------------------------------------------------------------------------------ the momentum */

typedef struct {
    int64_t ne, nq, first, last;           /* blocks first .. last - 1 */
    const int64_t *dofs;                   /* (6, ne) */
    const double *rows, *areas, *phi, *dphi, *weights;   /* (4, ne), (ne), (nq, 6), (nq, 6, 2), (nq) */
    const double *ux, *uy, *ax, *ay, *bx, *by;
    double w0, w1, w2, mass, convection;
    int general, bdf2;
    double *local;                         /* (ne, 2, 6) */
} Momentum;

/* kernels_numba._momentum_kernel's blocks first .. last - 1: each block's nodal values gathered into rows of BLOCK,
   every loop over a block's elements a vector loop */
CLONED static void momentum_blocks(const Momentum *m)
{
    double xs[6][BLOCK], ys[6][BLOCK], cxs[6][BLOCK], cys[6][BLOCK], fx[BLOCK], fy[BLOCK], sums[12][BLOCK];
    const int64_t ne = m->ne;
    for (int64_t b = m->first; b < m->last; b++) {
        const int64_t start = b * BLOCK;
        const int64_t n = ne - start < BLOCK ? ne - start : BLOCK;
        for (int i = 0; i < 6; i++) {
            const int64_t *dofs = m->dofs + i * ne + start;
            for (int64_t j = 0; j < n; j++) {
                const int64_t dof = dofs[j];
                const double vx = m->ux[dof], vy = m->uy[dof];
                if (m->bdf2) {
                    double back_x, back_y;
                    if (m->general) {
                        back_x = (m->w0 * vx + m->w1 * m->ax[dof]) + m->w2 * m->bx[dof];
                        back_y = (m->w0 * vy + m->w1 * m->ay[dof]) + m->w2 * m->by[dof];
                    } else {
                        back_x = m->ax[dof];
                        back_y = m->ay[dof];
                    }
                    xs[i][j] = 2.0 * vx - back_x;
                    ys[i][j] = 2.0 * vy - back_y;
                    cxs[i][j] = (4.0 * vx - back_x) / 3.0;
                    cys[i][j] = (4.0 * vy - back_y) / 3.0;
                } else {            /* the carried rows too: the compiler may read them in either case */
                    xs[i][j] = vx;
                    ys[i][j] = vy;
                    cxs[i][j] = vx;
                    cys[i][j] = vy;
                }
            }
        }
        for (int k = 0; k < 12; k++)
            for (int64_t j = 0; j < n; j++)
                sums[k][j] = 0.0;
        const double *a00 = m->rows + start, *a01 = m->rows + ne + start;
        const double *a10 = m->rows + 2 * ne + start, *a11 = m->rows + 3 * ne + start;
        const double *area = m->areas + start;
        for (int64_t q = 0; q < m->nq; q++) {
            const double *p = m->phi + 6 * q, *d = m->dphi + 12 * q;
            const double p0 = p[0], p1 = p[1], p2 = p[2], p3 = p[3], p4 = p[4], p5 = p[5];
            const double r0 = d[0], r1 = d[2], r2 = d[4], r3 = d[6], r4 = d[8], r5 = d[10];
            const double s0 = d[1], s1 = d[3], s2 = d[5], s3 = d[7], s4 = d[9], s5 = d[11];
            const double w = m->weights[q];
            for (int64_t j = 0; j < n; j++) {
                const double u = xs[0][j] * p0 + xs[1][j] * p1 + xs[2][j] * p2 + xs[3][j] * p3 + xs[4][j] * p4
                                 + xs[5][j] * p5;
                const double v = ys[0][j] * p0 + ys[1][j] * p1 + ys[2][j] * p2 + ys[3][j] * p3 + ys[4][j] * p4
                                 + ys[5][j] * p5;
                const double ux_r = xs[0][j] * r0 + xs[1][j] * r1 + xs[2][j] * r2 + xs[3][j] * r3 + xs[4][j] * r4
                                    + xs[5][j] * r5;
                const double ux_s = xs[0][j] * s0 + xs[1][j] * s1 + xs[2][j] * s2 + xs[3][j] * s3 + xs[4][j] * s4
                                    + xs[5][j] * s5;
                const double uy_r = ys[0][j] * r0 + ys[1][j] * r1 + ys[2][j] * r2 + ys[3][j] * r3 + ys[4][j] * r4
                                    + ys[5][j] * r5;
                const double uy_s = ys[0][j] * s0 + ys[1][j] * s1 + ys[2][j] * s2 + ys[3][j] * s3 + ys[4][j] * s4
                                    + ys[5][j] * s5;
                const double ux_x = a00[j] * ux_r + a10[j] * ux_s, ux_y = a01[j] * ux_r + a11[j] * ux_s;
                const double uy_x = a00[j] * uy_r + a10[j] * uy_s, uy_y = a01[j] * uy_r + a11[j] * uy_s;
                double carried_x = u, carried_y = v;
                if (m->bdf2) {
                    carried_x = cxs[0][j] * p0 + cxs[1][j] * p1 + cxs[2][j] * p2 + cxs[3][j] * p3 + cxs[4][j] * p4
                                + cxs[5][j] * p5;
                    carried_y = cys[0][j] * p0 + cys[1][j] * p1 + cys[2][j] * p2 + cys[3][j] * p3 + cys[4][j] * p4
                                + cys[5][j] * p5;
                }
                const double weight = w * area[j];
                fx[j] = (m->mass * carried_x - m->convection * (u * ux_x + v * ux_y)) * weight;
                fy[j] = (m->mass * carried_y - m->convection * (u * uy_x + v * uy_y)) * weight;
            }
            for (int i = 0; i < 6; i++) {
                const double pi = p[i];
                for (int64_t j = 0; j < n; j++) {
                    sums[i][j] += fx[j] * pi;
                    sums[6 + i][j] += fy[j] * pi;
                }
            }
        }
        for (int64_t j = 0; j < n; j++) {
            double *out = m->local + 12 * (start + j);
            for (int i = 0; i < 12; i++)
                out[i] = sums[i][j];
        }
    }
}

/* element_momentum(element_dofs, jacobian_rows, areas, phi, dphi, weights, ux, uy, ax, ay, bx, by, w0, w1, w2,
                    general, bdf2, mass_coefficient, convection_coefficient, local): on the calling thread, without
   the GIL (a step computes it ahead on the fluid's helper thread while the caller works: one thread is what it
   wants; numba's threads gained ~0.25 ms where it is computed in the step, measured) */
static PyObject *element_momentum(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *name = "element_momentum";
    Arg a[13] = {0};
    PyObject *result = NULL;
    if (arity(nargs, 20, name) < 0)
        return NULL;
    static const char kinds[13] = {'l', 'd', 'd', 'd', 'd', 'd', 'd', 'd', 'd', 'd', 'd', 'd', 'd'};
    static const int slot[13] = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 19};
    for (int i = 0; i < 13; i++)
        if (take(args[slot[i]], &a[i], kinds[i], 8, i == 12, name) < 0)
            goto done;
    Momentum m;
    if (real(args[12], &m.w0) < 0 || real(args[13], &m.w1) < 0 || real(args[14], &m.w2) < 0
        || real(args[17], &m.mass) < 0 || real(args[18], &m.convection) < 0)
        goto done;
    m.general = PyObject_IsTrue(args[15]);
    m.bdf2 = PyObject_IsTrue(args[16]);
    if (m.general < 0 || m.bdf2 < 0)
        goto done;
    m.ne = dim(&a[0], 1);
    m.nq = count(&a[5]);
    if (!shaped(&a[0], 2, 6, -1, -1) || !shaped(&a[1], 2, 4, m.ne, -1) || !shaped(&a[2], 1, m.ne, -1, -1)
        || !shaped(&a[3], 2, m.nq, 6, -1) || !shaped(&a[4], 3, m.nq, 6, 2) || !shaped(&a[5], 1, m.nq, -1, -1)
        || !shaped(&a[12], 3, m.ne, 2, 6)) {
        shape_error(name, "element_dofs (6, ne), jacobian_rows (4, ne), areas (ne), phi (nq, 6), dphi (nq, 6, 2), "
                          "weights (nq), local (ne, 2, 6)");
        goto done;
    }
    Py_ssize_t nodes = count(&a[6]);
    for (int i = 7; i < 12; i++)
        if (count(&a[i]) != nodes) {
            shape_error(name, "the velocity components (and the earlier ones) must have one length");
            goto done;
        }
    if (!within(DATA(a[0], int64_t), 6 * m.ne, nodes)) {
        shape_error(name, "an element's dof outside the velocity fields");
        goto done;
    }
    m.dofs = DATA(a[0], int64_t);
    m.rows = DATA(a[1], double);
    m.areas = DATA(a[2], double);
    m.phi = DATA(a[3], double);
    m.dphi = DATA(a[4], double);
    m.weights = DATA(a[5], double);
    m.ux = DATA(a[6], double);
    m.uy = DATA(a[7], double);
    m.ax = DATA(a[8], double);
    m.ay = DATA(a[9], double);
    m.bx = DATA(a[10], double);
    m.by = DATA(a[11], double);
    m.local = DATA(a[12], double);
    m.first = 0;
    m.last = (m.ne + BLOCK - 1) / BLOCK;
    Py_BEGIN_ALLOW_THREADS
    momentum_blocks(&m);
    Py_END_ALLOW_THREADS
    result = Py_NewRef(Py_None);
done:
    release(a, 13);
    return result;
}

/* scatter_momentum(element_dofs, local, positions, out): out[positions[c, dof]] += local[e, c, i] element by element */
static PyObject *scatter_momentum(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *name = "scatter_momentum";
    Arg a[4] = {0};
    PyObject *result = NULL;
    if (arity(nargs, 4, name) < 0 || take(args[0], &a[0], 'l', 8, 0, name) < 0 || take(args[1], &a[1], 'd', 8, 0, name) < 0
        || take(args[2], &a[2], 'l', 8, 0, name) < 0 || take(args[3], &a[3], 'd', 8, 1, name) < 0)
        goto done;
    const int64_t rows = dim(&a[0], 0), ne = dim(&a[0], 1), nodes = dim(&a[2], 1);
    if (rows != 6 || !shaped(&a[0], 2, 6, -1, -1) || !shaped(&a[1], 3, ne, 2, 6) || !shaped(&a[2], 2, 2, -1, -1)) {
        shape_error(name, "element_dofs (6, ne), local (ne, 2, 6), positions (2, N)");
        goto done;
    }
    const int64_t *dofs = DATA(a[0], int64_t), *positions = DATA(a[2], int64_t);
    const double *local = DATA(a[1], double);
    double *out = DATA(a[3], double);
    const int64_t size = count(&a[3]);
    if (!within(dofs, 6 * ne, nodes)) {
        shape_error(name, "an element's dof outside positions");
        goto done;
    }
    for (int64_t k = 0; k < 2 * nodes; k++)
        if (positions[k] >= size) {
            shape_error(name, "a position outside out");
            goto done;
        }
    for (int64_t e = 0; e < ne; e++)
        for (int i = 0; i < 6; i++) {
            const int64_t dof = dofs[i * ne + e];
            for (int c = 0; c < 2; c++) {
                const int64_t position = positions[c * nodes + dof];
                if (position >= 0)                  /* < 0: no entry (a Dirichlet unknown) */
                    out[position] += local[12 * e + 6 * c + i];
            }
        }
    result = Py_NewRef(Py_None);
done:
    release(a, 4);
    return result;
}

/* linearised_convection(element_dofs, inverse_jacobians, determinants, phi, dphi, weights, ux, uy, newton, positions,
                         xx, xy, yx, yy): the convection linearised about u on a fixed CSR pattern (data overwritten) */
static PyObject *linearised_convection(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *name = "linearised_convection";
    Arg a[13] = {0};
    PyObject *result = NULL;
    static const char kinds[13] = {'l', 'd', 'd', 'd', 'd', 'd', 'd', 'd', 'l', 'd', 'd', 'd', 'd'};
    static const int slot[13] = {0, 1, 2, 3, 4, 5, 6, 7, 9, 10, 11, 12, 13};
    if (arity(nargs, 14, name) < 0)
        return NULL;
    const int newton = PyObject_IsTrue(args[8]);
    if (newton < 0)
        return NULL;
    for (int i = 0; i < 13; i++)
        if (take(args[slot[i]], &a[i], kinds[i], 8, i >= 9, name) < 0)
            goto done;
    const int64_t ne = dim(&a[0], 1), nq = count(&a[5]), nodes = count(&a[6]), nnz = count(&a[9]);
    if (!shaped(&a[0], 2, 6, -1, -1) || !shaped(&a[1], 3, ne, 2, 2) || !shaped(&a[2], 1, ne, -1, -1)
        || !shaped(&a[3], 2, nq, 6, -1) || !shaped(&a[4], 3, nq, 6, 2) || count(&a[7]) != nodes
        || !shaped(&a[8], 3, ne, 6, 6) || count(&a[10]) != nnz || count(&a[11]) != nnz || count(&a[12]) != nnz
        || !within(DATA(a[0], int64_t), 6 * ne, nodes)) {
        shape_error(name, "element_dofs (6, ne), inverse_jacobians (ne, 2, 2), determinants (ne), phi (nq, 6), dphi "
                          "(nq, 6, 2), weights (nq), ux and uy (N), positions (ne, 6, 6), four data arrays of one length");
        goto done;
    }
    const int64_t *dofs = DATA(a[0], int64_t), *positions = DATA(a[8], int64_t);
    const double *inverse = DATA(a[1], double), *determinants = DATA(a[2], double), *phi = DATA(a[3], double);
    const double *dphi = DATA(a[4], double), *weights = DATA(a[5], double), *ux = DATA(a[6], double);
    const double *uy = DATA(a[7], double);
    double *xx = DATA(a[9], double), *xy = DATA(a[10], double), *yx = DATA(a[11], double), *yy = DATA(a[12], double);
    for (int64_t e = 0; e < ne; e++)
        for (int i = 0; i < 36; i++)
            if (positions[36 * e + i] < 0 || positions[36 * e + i] >= nnz) {
                shape_error(name, "a position outside the pattern");
                goto done;
            }
    memset(xx, 0, nnz * sizeof(double));
    memset(xy, 0, nnz * sizeof(double));
    memset(yx, 0, nnz * sizeof(double));
    memset(yy, 0, nnz * sizeof(double));
    double gx[6], gy[6];
    for (int64_t e = 0; e < ne; e++) {
        const double a00 = inverse[4 * e], a01 = inverse[4 * e + 1], a10 = inverse[4 * e + 2], a11 = inverse[4 * e + 3];
        const double area = fabs(determinants[e]);
        for (int64_t q = 0; q < nq; q++) {
            const double *p = phi + 6 * q, *d = dphi + 12 * q;
            double u = 0.0, v = 0.0, ux_r = 0.0, ux_s = 0.0, uy_r = 0.0, uy_s = 0.0;
            for (int i = 0; i < 6; i++) {
                const int64_t dof = dofs[i * ne + e];
                u += ux[dof] * p[i];
                v += uy[dof] * p[i];
                ux_r += ux[dof] * d[2 * i];
                ux_s += ux[dof] * d[2 * i + 1];
                uy_r += uy[dof] * d[2 * i];
                uy_s += uy[dof] * d[2 * i + 1];
                gx[i] = a00 * d[2 * i] + a10 * d[2 * i + 1];
                gy[i] = a01 * d[2 * i] + a11 * d[2 * i + 1];
            }
            const double weight = weights[q] * area;
            const double ux_x = a00 * ux_r + a10 * ux_s, ux_y = a01 * ux_r + a11 * ux_s;
            const double uy_x = a00 * uy_r + a10 * uy_s, uy_y = a01 * uy_r + a11 * uy_s;
            for (int i = 0; i < 6; i++) {
                const double wi = weight * p[i];
                for (int j = 0; j < 6; j++) {
                    const int64_t position = positions[36 * e + 6 * i + j];
                    const double advection = wi * (u * gx[j] + v * gy[j]);
                    if (newton) {
                        const double mass = wi * p[j];
                        xx[position] += advection + mass * ux_x;
                        xy[position] += mass * ux_y;
                        yx[position] += mass * uy_x;
                        yy[position] += advection + mass * uy_y;
                    } else {
                        xx[position] += advection;
                        yy[position] += advection;
                    }
                }
            }
        }
    }
    result = Py_NewRef(Py_None);
done:
    release(a, 13);
    return result;
}

/* ------------------------------------------------------------------------------------------------ the boundary */

/* numpy's searchsorted(sorted, x) (side 'left'): the first index whose value is >= x */
static inline int64_t search_left(const double *sorted, int64_t n, double x)
{
    int64_t low = 0, high = n;
    while (low < high) {
        const int64_t middle = low + (high - low) / 2;
        if (sorted[middle] < x)
            low = middle + 1;
        else
            high = middle;
    }
    return low;
}

/* locate(points, grid_x, grid_y, square_elements, origins, inverse_jacobians, elements, reference) */
static PyObject *locate(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *name = "locate";
    Arg a[8] = {0};
    PyObject *result = NULL;
    static const char kinds[8] = {'d', 'd', 'd', 'l', 'd', 'd', 'l', 'd'};
    if (arity(nargs, 8, name) < 0)
        return NULL;
    for (int i = 0; i < 8; i++)
        if (take(args[i], &a[i], kinds[i], 8, i >= 6, name) < 0)
            goto done;
    const int64_t points = dim(&a[0], 0), nx = count(&a[1]) - 1, ny = count(&a[2]) - 1;
    const int64_t triangles = dim(&a[4], 0);
    if (!shaped(&a[0], 2, -1, 2, -1) || nx < 1 || ny < 1 || !shaped(&a[3], 3, nx, ny, 2)
        || !shaped(&a[4], 2, -1, 2, -1) || !shaped(&a[5], 3, triangles, 2, 2) || count(&a[6]) != points
        || !shaped(&a[7], 2, points, 2, -1)) {
        shape_error(name, "points (n, 2), grid_x (nx + 1), grid_y (ny + 1), square_elements (nx, ny, 2), origins "
                          "(ne, 2), inverse_jacobians (ne, 2, 2), elements (n), reference (n, 2)");
        goto done;
    }
    const double *p = DATA(a[0], double), *gx = DATA(a[1], double), *gy = DATA(a[2], double);
    const int64_t *squares = DATA(a[3], int64_t);
    const double *origins = DATA(a[4], double), *inverse = DATA(a[5], double);
    int64_t *elements = DATA(a[6], int64_t);
    double *reference = DATA(a[7], double);
    for (int64_t k = 0; k < points; k++) {
        const double x = p[2 * k], y = p[2 * k + 1];
        if (!(gx[0] <= x && x <= gx[nx] && gy[0] <= y && y <= gy[ny])) {
            elements[k] = -1;
            reference[2 * k] = NAN;
            reference[2 * k + 1] = NAN;
            continue;
        }
        int64_t i = search_left(gx, nx + 1, x) - 1, j = search_left(gy, ny + 1, y) - 1;
        i = i < 0 ? 0 : (i > nx - 1 ? nx - 1 : i);
        j = j < 0 ? 0 : (j > ny - 1 ? ny - 1 : j);
        const double s = (x - gx[i]) / (gx[i + 1] - gx[i]);
        const double r = (y - gy[j]) / (gy[j + 1] - gy[j]);
        const int64_t e = squares[(i * ny + j) * 2 + (r > s ? 0 : 1)];
        elements[k] = e;
        if (e < 0 || e >= triangles) {
            reference[2 * k] = NAN;
            reference[2 * k + 1] = NAN;
            continue;
        }
        const double dx = x - origins[2 * e], dy = y - origins[2 * e + 1];
        const double *m = inverse + 4 * e;
        reference[2 * k] = m[0] * dx + m[1] * dy;
        reference[2 * k + 1] = m[2] * dx + m[3] * dy;
    }
    result = Py_NewRef(Py_None);
done:
    release(a, 8);
    return result;
}

static inline void p2_basis(double r, double s, double *out)
{
    out[0] = 1.0 - 3.0 * r - 3.0 * s + 2.0 * r * r + 4.0 * r * s + 2.0 * s * s;
    out[1] = 2.0 * r * r - r;
    out[2] = 2.0 * s * s - s;
    out[3] = 4.0 * r - 4.0 * r * r - 4.0 * r * s;
    out[4] = 4.0 * r * s;
    out[5] = 4.0 * s - 4.0 * r * s - 4.0 * s * s;
}

/* interpolate_p2(elements, reference, element_dofs, values, out) and spread_p2(elements, reference, element_dofs,
   forces, out): the located points' P2 values, and the exact adjoint */
static PyObject *p2_transfer(PyObject *const *args, Py_ssize_t nargs, int spread)
{
    const char *name = spread ? "spread_p2" : "interpolate_p2";
    Arg a[5] = {0};
    PyObject *result = NULL;
    static const char kinds[5] = {'l', 'd', 'l', 'd', 'd'};
    if (arity(nargs, 5, name) < 0)
        return NULL;
    for (int i = 0; i < 5; i++)
        if (take(args[i], &a[i], kinds[i], 8, i == 4, name) < 0)
            goto done;
    const int64_t points = count(&a[0]), ne = dim(&a[2], 1);
    /* interpolate: values (nc, N), out (n, nc); spread: forces (n, nc), out (nc, N) */
    const Arg *field = spread ? &a[4] : &a[3], *at_points = spread ? &a[3] : &a[4];
    const int64_t nc = dim(field, 0), nodes = dim(field, 1);
    if (!shaped(&a[1], 2, points, 2, -1) || !shaped(&a[2], 2, 6, -1, -1) || !shaped(at_points, 2, points, nc, -1)
        || field->view.ndim != 2) {
        shape_error(name, "elements (n), reference (n, 2), element_dofs (6, ne), the field (nc, N), the points' "
                          "values (n, nc)");
        goto done;
    }
    const int64_t *elements = DATA(a[0], int64_t), *dofs = DATA(a[2], int64_t);
    const double *reference = DATA(a[1], double);
    double phi[6];
    for (int64_t k = 0; k < points; k++)           /* the dofs of the points' elements: written through in spread */
        if (elements[k] >= 0 && elements[k] < ne)
            for (int i = 0; i < 6; i++)
                if (dofs[i * ne + elements[k]] < 0 || dofs[i * ne + elements[k]] >= nodes) {
                    shape_error(name, "an element's dof outside the field");
                    goto done;
                }
    if (!spread) {
        const double *values = DATA(a[3], double);
        double *out = DATA(a[4], double);
        for (int64_t k = 0; k < points; k++) {
            const int64_t e = elements[k];
            if (e < 0 || e >= ne) {
                for (int64_t c = 0; c < nc; c++)
                    out[k * nc + c] = NAN;
                continue;
            }
            p2_basis(reference[2 * k], reference[2 * k + 1], phi);
            for (int64_t c = 0; c < nc; c++) {
                double total = 0.0;
                for (int i = 0; i < 6; i++)
                    total += values[c * nodes + dofs[i * ne + e]] * phi[i];
                out[k * nc + c] = total;
            }
        }
    } else {
        const double *forces = DATA(a[3], double);
        double *out = DATA(a[4], double);
        for (int64_t k = 0; k < points; k++) {
            const int64_t e = elements[k];
            if (e < 0 || e >= ne)
                continue;
            p2_basis(reference[2 * k], reference[2 * k + 1], phi);
            for (int64_t c = 0; c < nc; c++)
                for (int i = 0; i < 6; i++)
                    out[c * nodes + dofs[i * ne + e]] += forces[k * nc + c] * phi[i];
        }
    }
    result = Py_NewRef(Py_None);
done:
    release(a, 5);
    return result;
}

static PyObject *interpolate_p2(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    return p2_transfer(args, nargs, 0);
}

static PyObject *spread_p2(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    return p2_transfer(args, nargs, 1);
}

/* first_self_intersection(points): (i, j) of the first two non-adjacent edges of the closed polygon that cross */
static PyObject *first_self_intersection(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *name = "first_self_intersection";
    Arg a[1] = {0};
    PyObject *result = NULL;
    if (arity(nargs, 1, name) < 0 || take(args[0], &a[0], 'd', 8, 0, name) < 0)
        goto done;
    if (a[0].view.ndim != 2 || dim(&a[0], 1) != 2) {
        shape_error(name, "points (n, 2)");
        goto done;
    }
    const int64_t n = dim(&a[0], 0);
    const double *p = DATA(a[0], double);
    int64_t found_i = -1, found_j = -1;
    for (int64_t i = 0; i < n && found_i < 0; i++) {
        const double ax = p[2 * i], ay = p[2 * i + 1];
        const double bx = p[2 * ((i + 1) % n)], by = p[2 * ((i + 1) % n) + 1];
        for (int64_t j = i + 2; j < n; j++) {
            if (i == 0 && j == n - 1)
                continue;
            const double cx = p[2 * j], cy = p[2 * j + 1];
            const double dx = p[2 * ((j + 1) % n)], dy = p[2 * ((j + 1) % n) + 1];
            const double d1 = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax);
            const double d2 = (bx - ax) * (dy - ay) - (by - ay) * (dx - ax);
            const double d3 = (dx - cx) * (ay - cy) - (dy - cy) * (ax - cx);
            const double d4 = (dx - cx) * (by - cy) - (dy - cy) * (bx - cx);
            if (d1 * d2 < 0 && d3 * d4 < 0) {
                found_i = i;
                found_j = j;
                break;
            }
        }
    }
    result = Py_BuildValue("(LL)", (long long)found_i, (long long)found_j);
done:
    release(a, 1);
    return result;
}

/* ------------------------------------------------------------------------------------------------ the split solve */
/* (sim/fast/splitsolve.py) every sum in index order from zero in the vectors' own precision, as scipy's CSR product */

#define SPLIT_KERNELS(SUFFIX, REAL, INDEX)                                                                           \
static void gather_residual_##SUFFIX(int64_t n, const double *rhs, const int64_t *rows, const double *data,          \
                                     const INDEX *indices, const int32_t *indptr, int with_rows, const double *x,    \
                                     REAL *out)                                                                      \
{                                                                                                                    \
    if (!with_rows) {                                                                                                \
        for (int64_t k = 0; k < n; k++) out[k] = (REAL)rhs[rows[k]];                                                 \
        return;                                                                                                      \
    }                                                                                                                \
    for (int64_t k = 0; k < n; k++) {                                                                                \
        double total = 0.0;                                                                                          \
        for (int64_t jj = indptr[k]; jj < indptr[k + 1]; jj++) total += data[jj] * x[indices[jj]];                   \
        out[k] = (REAL)(rhs[rows[k]] - total);                                                                       \
    }                                                                                                                \
}                                                                                                                    \
                                                                                                                     \
/* four rows' chains side by side, each summed in its own order (kernels_numba._four_rows) */                        \
static void transposed_products_##SUFFIX(int64_t ny, const REAL *y, int with_dinv, const REAL *dinv, REAL *z,        \
                                         const REAL *data, const INDEX *indices, const int32_t *indptr, int64_t ng,  \
                                         REAL *g)                                                                    \
{                                                                                                                    \
    if (with_dinv)                                                                                                   \
        for (int64_t k = 0; k < ny; k++) z[k] = dinv[k] * y[k];                                                      \
    int64_t r = 0;                                                                                                   \
    for (; r + 4 <= ng; r += 4) {                                                                                    \
        int64_t a0 = indptr[r], a1 = indptr[r + 1], a2 = indptr[r + 2], a3 = indptr[r + 3];                          \
        const int64_t e0 = indptr[r + 1], e1 = indptr[r + 2], e2 = indptr[r + 3], e3 = indptr[r + 4];                \
        REAL t0 = 0, t1 = 0, t2 = 0, t3 = 0;                                                                         \
        int64_t common = e0 - a0;                                                                                    \
        if (e1 - a1 < common) common = e1 - a1;                                                                      \
        if (e2 - a2 < common) common = e2 - a2;                                                                      \
        if (e3 - a3 < common) common = e3 - a3;                                                                      \
        for (int64_t j = 0; j < common; j++) {                                                                       \
            t0 += data[a0 + j] * y[indices[a0 + j]];                                                                 \
            t1 += data[a1 + j] * y[indices[a1 + j]];                                                                 \
            t2 += data[a2 + j] * y[indices[a2 + j]];                                                                 \
            t3 += data[a3 + j] * y[indices[a3 + j]];                                                                 \
        }                                                                                                            \
        for (int64_t jj = a0 + common; jj < e0; jj++) t0 += data[jj] * y[indices[jj]];                               \
        for (int64_t jj = a1 + common; jj < e1; jj++) t1 += data[jj] * y[indices[jj]];                               \
        for (int64_t jj = a2 + common; jj < e2; jj++) t2 += data[jj] * y[indices[jj]];                               \
        for (int64_t jj = a3 + common; jj < e3; jj++) t3 += data[jj] * y[indices[jj]];                               \
        g[r] = t0;                                                                                                   \
        g[r + 1] = t1;                                                                                               \
        g[r + 2] = t2;                                                                                               \
        g[r + 3] = t3;                                                                                               \
    }                                                                                                                \
    for (; r < ng; r++) {                                                                                            \
        REAL total = 0;                                                                                              \
        for (int64_t jj = indptr[r]; jj < indptr[r + 1]; jj++) total += data[jj] * y[indices[jj]];                   \
        g[r] = total;                                                                                                \
    }                                                                                                                \
}                                                                                                                    \
                                                                                                                     \
static void minus_product_##SUFFIX(int64_t nw, int64_t nsums, int64_t nz, const REAL *z, const REAL *data,           \
                                   const INDEX *indices, const int32_t *indptr, const REAL *w, REAL *sums, REAL *out)\
{                                                                                                                    \
    for (int64_t r = 0; r < nsums; r++) sums[r] = 0;                                                                 \
    for (int64_t c = 0; c < nw; c++) {                                                                               \
        const REAL weight = w[c];                                                                                    \
        for (int64_t jj = indptr[c]; jj < indptr[c + 1]; jj++) sums[indices[jj]] += data[jj] * weight;               \
    }                                                                                                                \
    for (int64_t r = 0; r < nz; r++) out[r] = z[r] - sums[r];                                                        \
}

SPLIT_KERNELS(f32_u16, float, uint16_t)
SPLIT_KERNELS(f32_i32, float, int32_t)
SPLIT_KERNELS(f64_u16, double, uint16_t)
SPLIT_KERNELS(f64_i32, double, int32_t)

/* the real type ('f' or 'd') and index type ('H' or 'i') of the buffers at args[real_at], args[index_at] */
static int variant(PyObject *real_object, PyObject *index_object, char *real_kind, char *index_kind, const char *name)
{
    Arg probe = {0};
    *real_kind = *index_kind = 0;
    if (take(real_object, &probe, 'f', 4, 0, name) == 0)
        *real_kind = 'f';
    else if (PyErr_Clear(), release(&probe, 1), take(real_object, &probe, 'd', 8, 0, name) == 0)
        *real_kind = 'd';
    release(&probe, 1);
    if (!*real_kind)
        return -1;
    if (take(index_object, &probe, 'H', 2, 0, name) == 0)
        *index_kind = 'H';
    else if (PyErr_Clear(), release(&probe, 1), take(index_object, &probe, 'i', 4, 0, name) == 0)
        *index_kind = 'i';
    release(&probe, 1);
    return *index_kind ? 0 : -1;
}

#define CALL_VARIANT(FUNCTION, real_kind, index_kind, ...)                                                           \
    do {                                                                                                             \
        if (real_kind == 'f' && index_kind == 'H') FUNCTION##_f32_u16(__VA_ARGS__);                                  \
        else if (real_kind == 'f') FUNCTION##_f32_i32(__VA_ARGS__);                                                  \
        else if (index_kind == 'H') FUNCTION##_f64_u16(__VA_ARGS__);                                                 \
        else FUNCTION##_f64_i32(__VA_ARGS__);                                                                        \
    } while (0)

/* the CSR arrays' sizes: indptr of rows + 1 non-decreasing entries from 0 within data and indices (O(rows)). The
   column indices' values are not checked (as numba's kernels do not): they are the split solve's own, built once,
   and checking them would be a pass over them as long as the product's own */
static int csr_valid(const Arg *data, const Arg *indices, const Arg *indptr, int64_t rows, const char *name)
{
    const int64_t nnz = count(data);
    const int32_t *p = DATA(*indptr, int32_t);
    if (count(indptr) != rows + 1 || count(indices) != nnz || p[0] != 0 || p[rows] > nnz) {
        shape_error(name, "CSR arrays of inconsistent sizes");
        return -1;
    }
    for (int64_t r = 0; r < rows; r++)
        if (p[r + 1] < p[r]) {
            shape_error(name, "a CSR row pointer that decreases");
            return -1;
        }
    return 0;
}

/* gather_residual(rhs, rows, data, indices, indptr, x, out): out[k] = rhs[rows[k]] - (A x)_k */
static PyObject *gather_residual(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *name = "gather_residual";
    Arg a[7] = {0};
    PyObject *result = NULL;
    char real_kind, index_kind;
    if (arity(nargs, 7, name) < 0 || variant(args[6], args[3], &real_kind, &index_kind, name) < 0)
        return NULL;
    const Py_ssize_t real_size = real_kind == 'f' ? 4 : 8, index_size = index_kind == 'H' ? 2 : 4;
    if (take(args[0], &a[0], 'd', 8, 0, name) < 0 || take(args[1], &a[1], 'l', 8, 0, name) < 0
        || take(args[2], &a[2], 'd', 8, 0, name) < 0 || take(args[3], &a[3], index_kind, index_size, 0, name) < 0
        || take(args[4], &a[4], 'i', 4, 0, name) < 0 || take(args[5], &a[5], 'd', 8, 0, name) < 0
        || take(args[6], &a[6], real_kind, real_size, 1, name) < 0)
        goto done;
    const int64_t n = count(&a[1]);
    if (n == 0) {                                  /* nothing to gather (numba's kernel: a loop of no rows) */
        result = Py_NewRef(Py_None);
        goto done;
    }
    const int with_rows = count(&a[4]) == n + 1;
    if (count(&a[6]) < n
        || (with_rows && csr_valid(&a[2], &a[3], &a[4], n, name) < 0)) {
        if (!PyErr_Occurred())
            shape_error(name, "out shorter than rows");
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS
    CALL_VARIANT(gather_residual, real_kind, index_kind, n, DATA(a[0], double), DATA(a[1], int64_t),
                 DATA(a[2], double), a[3].view.buf, DATA(a[4], int32_t), with_rows, DATA(a[5], double), a[6].view.buf);
    Py_END_ALLOW_THREADS
    result = Py_NewRef(Py_None);
done:
    release(a, 7);
    return result;
}

/* transposed_products(y, dinv, z, data, indices, indptr, g, zero): z = dinv * y (when dinv has y's length) and
   g = H^T y */
static PyObject *transposed_products(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *name = "transposed_products";
    Arg a[7] = {0};
    PyObject *result = NULL;
    char real_kind, index_kind;
    if (arity(nargs, 8, name) < 0 || variant(args[0], args[4], &real_kind, &index_kind, name) < 0)
        return NULL;
    const Py_ssize_t real_size = real_kind == 'f' ? 4 : 8, index_size = index_kind == 'H' ? 2 : 4;
    if (take(args[0], &a[0], real_kind, real_size, 0, name) < 0
        || take(args[1], &a[1], real_kind, real_size, 0, name) < 0
        || take(args[2], &a[2], real_kind, real_size, 1, name) < 0
        || take(args[3], &a[3], real_kind, real_size, 0, name) < 0
        || take(args[4], &a[4], index_kind, index_size, 0, name) < 0 || take(args[5], &a[5], 'i', 4, 0, name) < 0
        || take(args[6], &a[6], real_kind, real_size, 1, name) < 0)
        goto done;
    const int64_t ny = count(&a[0]), ng = count(&a[6]);
    const int with_dinv = count(&a[1]) == ny;
    if ((with_dinv && count(&a[2]) < ny) || csr_valid(&a[3], &a[4], &a[5], ng, name) < 0) {
        if (!PyErr_Occurred())
            shape_error(name, "z shorter than y");
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS
    CALL_VARIANT(transposed_products, real_kind, index_kind, ny, a[0].view.buf, with_dinv, a[1].view.buf,
                 a[2].view.buf, a[3].view.buf, a[4].view.buf, DATA(a[5], int32_t), ng, a[6].view.buf);
    Py_END_ALLOW_THREADS
    result = Py_NewRef(Py_None);
done:
    release(a, 7);
    return result;
}

/* minus_product(z, data, indices, indptr, w, sums, out, zero): out = z - H w, H by its transpose in CSR */
static PyObject *minus_product(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *name = "minus_product";
    Arg a[7] = {0};
    PyObject *result = NULL;
    char real_kind, index_kind;
    if (arity(nargs, 8, name) < 0 || variant(args[0], args[2], &real_kind, &index_kind, name) < 0)
        return NULL;
    const Py_ssize_t real_size = real_kind == 'f' ? 4 : 8, index_size = index_kind == 'H' ? 2 : 4;
    if (take(args[0], &a[0], real_kind, real_size, 0, name) < 0
        || take(args[1], &a[1], real_kind, real_size, 0, name) < 0
        || take(args[2], &a[2], index_kind, index_size, 0, name) < 0 || take(args[3], &a[3], 'i', 4, 0, name) < 0
        || take(args[4], &a[4], real_kind, real_size, 0, name) < 0
        || take(args[5], &a[5], real_kind, real_size, 1, name) < 0
        || take(args[6], &a[6], real_kind, real_size, 1, name) < 0)
        goto done;
    const int64_t nz = count(&a[0]), nw = count(&a[4]), nsums = count(&a[5]);
    if (nsums < nz || count(&a[6]) < nz || csr_valid(&a[1], &a[2], &a[3], nw, name) < 0) {
        if (!PyErr_Occurred())
            shape_error(name, "sums and out must be at least as long as z");
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS
    CALL_VARIANT(minus_product, real_kind, index_kind, nw, nsums, nz, a[0].view.buf, a[1].view.buf, a[2].view.buf,
                 DATA(a[3], int32_t), a[4].view.buf, a[5].view.buf, a[6].view.buf);
    Py_END_ALLOW_THREADS
    result = Py_NewRef(Py_None);
done:
    release(a, 7);
    return result;
}

/* scatter_add(solution, rows, x, accumulate): solution[rows[k]] (+)= x[k]; (largest |x[k]|, largest |value|), NaN
   for both when a value is not finite */
static PyObject *scatter_add(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *name = "scatter_add";
    Arg a[3] = {0};
    PyObject *result = NULL;
    if (arity(nargs, 4, name) < 0)
        return NULL;
    Arg probe = {0};
    char real_kind = 0;
    if (take(args[2], &probe, 'f', 4, 0, name) == 0)
        real_kind = 'f';
    else if (PyErr_Clear(), release(&probe, 1), take(args[2], &probe, 'd', 8, 0, name) == 0)
        real_kind = 'd';
    release(&probe, 1);
    if (!real_kind)
        return NULL;
    const int accumulate = PyObject_IsTrue(args[3]);
    if (accumulate < 0 || take(args[0], &a[0], 'd', 8, 1, name) < 0 || take(args[1], &a[1], 'l', 8, 0, name) < 0
        || take(args[2], &a[2], real_kind, real_kind == 'f' ? 4 : 8, 0, name) < 0)
        goto done;
    const int64_t n = count(&a[1]);
    if (count(&a[2]) < n || !within(DATA(a[1], int64_t), n, count(&a[0]))) {
        shape_error(name, "x shorter than rows, or a row outside solution");
        goto done;
    }
    double *solution = DATA(a[0], double);
    const int64_t *rows = DATA(a[1], int64_t);
    double size = 0.0, scale = 0.0;
    int finite = 1;
    Py_BEGIN_ALLOW_THREADS
    for (int64_t k = 0; k < n; k++) {
        const double change = real_kind == 'f' ? (double)DATA(a[2], float)[k] : DATA(a[2], double)[k];
        const double value = accumulate ? solution[rows[k]] + change : change;
        solution[rows[k]] = value;
        if (!(isfinite(change) && isfinite(value)))
            finite = 0;
        const double magnitude = fabs(change), level = fabs(value);
        size = size > magnitude ? size : magnitude;       /* numba's max(a, b): a unless b is larger */
        scale = scale > level ? scale : level;
    }
    Py_END_ALLOW_THREADS
    if (!finite)
        size = scale = NAN;
    result = Py_BuildValue("(dd)", size, scale);
done:
    release(a, 3);
    return result;
}

/* ------------------------------------------------------------------------------------------------ the step's glue */

/* free_rhs(momentum, free_velocity, continuity, out): out = [momentum[free_velocity], continuity] (zeros for an
   empty one) */
static PyObject *free_rhs(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *name = "free_rhs";
    Arg a[4] = {0};
    PyObject *result = NULL;
    if (arity(nargs, 4, name) < 0 || take(args[0], &a[0], 'd', 8, 0, name) < 0
        || take(args[1], &a[1], 'l', 8, 0, name) < 0 || take(args[2], &a[2], 'd', 8, 0, name) < 0
        || take(args[3], &a[3], 'd', 8, 1, name) < 0)
        goto done;
    const int64_t nv = count(&a[1]), n = count(&a[3]), nm = count(&a[0]), nc = count(&a[2]);
    if (nv > n || (nc > 0 && nc < n - nv)) {
        if (!PyErr_Occurred())
            shape_error(name, "out must hold the free velocities and the continuity rows");
        goto done;
    }
    const double *momentum = DATA(a[0], double), *continuity = DATA(a[2], double);
    const int64_t *free = DATA(a[1], int64_t);
    double *out = DATA(a[3], double);
    for (int64_t k = 0; k < nv; k++)
        out[k] = nm == 0 ? 0.0 : momentum[free[k]];
    for (int64_t k = 0; k < n - nv; k++)
        out[nv + k] = nc == 0 ? 0.0 : continuity[k];
    result = Py_NewRef(Py_None);
done:
    release(a, 4);
    return result;
}

/* subtract_scaled(out, weight, vector): out -= weight * vector */
static PyObject *subtract_scaled(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *name = "subtract_scaled";
    Arg a[2] = {0};
    PyObject *result = NULL;
    double weight;
    if (arity(nargs, 3, name) < 0 || real(args[1], &weight) < 0 || take(args[0], &a[0], 'd', 8, 1, name) < 0
        || take(args[2], &a[1], 'd', 8, 0, name) < 0)
        goto done;
    const int64_t n = count(&a[0]);
    if (count(&a[1]) < n) {
        shape_error(name, "vector shorter than out");
        goto done;
    }
    double *out = DATA(a[0], double);
    const double *vector = DATA(a[1], double);
    for (int64_t k = 0; k < n; k++)
        out[k] = out[k] - weight * vector[k];
    result = Py_NewRef(Py_None);
done:
    release(a, 2);
    return result;
}

/* boundary_velocity(inflow_weight, inflow, jet_weight, jet, free_velocity, solution, out) */
static PyObject *boundary_velocity(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *name = "boundary_velocity";
    Arg a[5] = {0};
    PyObject *result = NULL;
    double inflow_weight, jet_weight;
    if (arity(nargs, 7, name) < 0 || real(args[0], &inflow_weight) < 0 || real(args[2], &jet_weight) < 0
        || take(args[1], &a[0], 'd', 8, 0, name) < 0 || take(args[3], &a[1], 'd', 8, 0, name) < 0
        || take(args[4], &a[2], 'l', 8, 0, name) < 0 || take(args[5], &a[3], 'd', 8, 0, name) < 0
        || take(args[6], &a[4], 'd', 8, 1, name) < 0)
        goto done;
    const int64_t n = count(&a[4]), nv = count(&a[2]);
    const int both_zero = inflow_weight == 0.0 && jet_weight == 0.0;
    if ((!both_zero && (count(&a[0]) < n || count(&a[1]) < n)) || count(&a[3]) < nv
        || !within(DATA(a[2], int64_t), nv, n)) {
        if (!PyErr_Occurred())
            shape_error(name, "inflow and jet as long as out, solution as long as free_velocity, each free velocity in out");
        goto done;
    }
    const double *inflow = DATA(a[0], double), *jet = DATA(a[1], double), *solution = DATA(a[3], double);
    const int64_t *free = DATA(a[2], int64_t);
    double *out = DATA(a[4], double);
    for (int64_t k = 0; k < n; k++)
        out[k] = both_zero ? 0.0 : inflow_weight * inflow[k] + jet_weight * jet[k];
    for (int64_t k = 0; k < nv; k++)
        out[free[k]] = solution[k];
    result = Py_NewRef(Py_None);
done:
    release(a, 5);
    return result;
}

/* free_solution(velocity, free_velocity, pressure, pressure_scale, out): out = [velocity[free_velocity],
   pressure / pressure_scale] */
static PyObject *free_solution(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *name = "free_solution";
    Arg a[4] = {0};
    PyObject *result = NULL;
    double scale;
    if (arity(nargs, 5, name) < 0 || real(args[3], &scale) < 0 || take(args[0], &a[0], 'd', 8, 0, name) < 0
        || take(args[1], &a[1], 'l', 8, 0, name) < 0 || take(args[2], &a[2], 'd', 8, 0, name) < 0
        || take(args[4], &a[3], 'd', 8, 1, name) < 0)
        goto done;
    const int64_t nv = count(&a[1]), np_ = count(&a[2]);
    if (scale == 0.0 && np_ > 0) {                 /* as numba's kernel (Python's error model) */
        PyErr_SetString(PyExc_ZeroDivisionError, "free_solution: a pressure scale of zero");
        goto done;
    }
    if (count(&a[3]) < nv + np_) {
        if (!PyErr_Occurred())
            shape_error(name, "out must hold the free velocities and the pressure");
        goto done;
    }
    const double *velocity = DATA(a[0], double), *pressure = DATA(a[2], double);
    const int64_t *free = DATA(a[1], int64_t);
    double *out = DATA(a[3], double);
    for (int64_t k = 0; k < nv; k++)
        out[k] = velocity[free[k]];
    for (int64_t k = 0; k < np_; k++)
        out[nv + k] = pressure[k] / scale;
    result = Py_NewRef(Py_None);
done:
    release(a, 4);
    return result;
}

/* ------------------------------------------------------------------------------------------------ the module */

static PyObject *layout(PyObject *self, PyObject *unused) { return PyLong_FromLong(LAYOUT); }
/* what the bits depend on besides the arithmetic written here: the source and the compiler that built it */
static PyObject *source(PyObject *self, PyObject *unused)
{
#ifdef __VERSION__
    return PyUnicode_FromFormat("%s %s", VCYTO_KERNELS_SOURCE, __VERSION__);
#else
    return PyUnicode_FromString(VCYTO_KERNELS_SOURCE);
#endif
}

#define FAST(name) {#name, (PyCFunction)(void (*)(void))name, METH_FASTCALL, NULL}
static PyMethodDef methods[] = {
    FAST(element_momentum), FAST(scatter_momentum), FAST(linearised_convection), FAST(locate), FAST(interpolate_p2), FAST(spread_p2),
    FAST(first_self_intersection), FAST(gather_residual), FAST(transposed_products), FAST(minus_product),
    FAST(scatter_add), FAST(free_rhs), FAST(subtract_scaled), FAST(boundary_velocity), FAST(free_solution),
    {"layout", layout, METH_NOARGS, "The argument lists' version (sim/fast/kernels.py's LAYOUT)."},
    {"source", source, METH_NOARGS, "The SHA-256 of the source this library was built from (setup.py) and the compiler."},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_kernels",
                                    "The FE-IB step's kernels in C (sim/fast/kernels.py calls them).", -1, methods,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&module); }
