"""Numba kernels for the per-step hot path: array in, array out, tested against scikit-fem.

The reference for ``sim.fast.kernels``, which calls the compiled C copies of these kernels (``sim/fast/_kernels.c``)
where they are installed and these otherwise (importing this module imports numba). The mesh is affine, so each element
carries its inverse Jacobian and determinant; P2 basis values and reference gradients are tabulated once at the
quadrature points (scikit-fem's own reference element supplies them, so local ordering matches
``basis.element_dofs``). Element contributions are computed in parallel into a per-element buffer, then scattered
serially (no write races).
"""

from __future__ import annotations

import os
import threading

import numba
import numpy as np
from numba import njit, prange

_LAUNCH = threading.Lock()   # one launch of the parallel momentum kernel at a time (``element_momentum``)


def _new_launch_lock():
    """A forked child's own lock: the parent's may have been held by a thread the child does not have."""
    global _LAUNCH
    _LAUNCH = threading.Lock()


os.register_at_fork(after_in_child=_new_launch_lock)
BLOCK = 128    # elements a thread takes at a time in ``_element_momentum``: its scratch stays in the L1 cache


def _momentum_kernel(bdf2: bool):
    """The element kernel of the momentum load; ``bdf2``: BDF2's one pass, whose mass term carries (4 v - b) / 3 and
    whose convection is that of 2 v - b, with b the velocity one step back formed in the gather (no pass over the
    whole fields before the kernel); else both act on the velocity v itself (its values taken once)."""

    @njit(cache=True, parallel=True, fastmath=True, boundscheck=False, nogil=True)
    def kernel(element_dofs, jacobian_rows, areas, phi, dphi, weights, ux, uy, ax, ay, bx, by, w0, w1, w2, general,
               mass_coefficient, convection_coefficient, local):
        """local[e, c, i] = integral over element e of (m w_c - k ((u . grad) u)_c) phi_i.

        euler: u = w = v = (ux, uy). BDF2: u = 2 v - b and w = (4 v - b) / 3 with b = a (a = (ax, ay)), or when
        ``general`` b = (w0 v + w1 a) + w2 b' (b' = (bx, by)): the value one step back, an earlier velocity itself
        or the parabola through the last three (``NavierStokes._momentum_back``). ``jacobian_rows`` (4, ne): the
        inverse Jacobians' entries a00, a01, a10, a11 per element; ``areas`` (ne,): |det J|. The elements go in
        blocks of ``BLOCK``, each block's nodal values gathered into contiguous rows, and every loop over a block's
        elements is one the compiler turns into vector instructions (measured: 2.2-2.4x faster than one element at a
        time)."""
        n_elements = element_dofs.shape[1]
        n_blocks = (n_elements + BLOCK - 1) // BLOCK
        for b in prange(n_blocks):
            start = b * BLOCK
            n = min(BLOCK, n_elements - start)
            xs = np.empty((6, BLOCK))
            ys = np.empty((6, BLOCK))
            cxs = np.empty((6, BLOCK if bdf2 else 1))
            cys = np.empty((6, BLOCK if bdf2 else 1))
            fx = np.empty(BLOCK)
            fy = np.empty(BLOCK)
            sums = np.zeros((12, BLOCK))
            for i in range(6):
                for j in range(n):
                    dof = element_dofs[i, start + j]
                    vx = ux[dof]
                    vy = uy[dof]
                    if bdf2:
                        if general:
                            back_x = (w0 * vx + w1 * ax[dof]) + w2 * bx[dof]
                            back_y = (w0 * vy + w1 * ay[dof]) + w2 * by[dof]
                        else:
                            back_x = ax[dof]
                            back_y = ay[dof]
                        xs[i, j] = 2.0 * vx - back_x
                        ys[i, j] = 2.0 * vy - back_y
                        cxs[i, j] = (4.0 * vx - back_x) / 3.0
                        cys[i, j] = (4.0 * vy - back_y) / 3.0
                    else:
                        xs[i, j] = vx
                        ys[i, j] = vy
            a00 = jacobian_rows[0, start:start + n]
            a01 = jacobian_rows[1, start:start + n]
            a10 = jacobian_rows[2, start:start + n]
            a11 = jacobian_rows[3, start:start + n]
            area = areas[start:start + n]
            x0, x1, x2, x3, x4, x5 = xs[0], xs[1], xs[2], xs[3], xs[4], xs[5]
            y0, y1, y2, y3, y4, y5 = ys[0], ys[1], ys[2], ys[3], ys[4], ys[5]
            c0, c1, c2, c3, c4, c5 = cxs[0], cxs[1], cxs[2], cxs[3], cxs[4], cxs[5]
            d0, d1, d2, d3, d4, d5 = cys[0], cys[1], cys[2], cys[3], cys[4], cys[5]
            for q in range(weights.shape[0]):
                p0, p1, p2, p3, p4, p5 = phi[q, 0], phi[q, 1], phi[q, 2], phi[q, 3], phi[q, 4], phi[q, 5]
                r0, r1, r2 = dphi[q, 0, 0], dphi[q, 1, 0], dphi[q, 2, 0]
                r3, r4, r5 = dphi[q, 3, 0], dphi[q, 4, 0], dphi[q, 5, 0]
                s0, s1, s2 = dphi[q, 0, 1], dphi[q, 1, 1], dphi[q, 2, 1]
                s3, s4, s5 = dphi[q, 3, 1], dphi[q, 4, 1], dphi[q, 5, 1]
                w = weights[q]
                for j in range(n):
                    u = x0[j] * p0 + x1[j] * p1 + x2[j] * p2 + x3[j] * p3 + x4[j] * p4 + x5[j] * p5
                    v = y0[j] * p0 + y1[j] * p1 + y2[j] * p2 + y3[j] * p3 + y4[j] * p4 + y5[j] * p5
                    ux_r = x0[j] * r0 + x1[j] * r1 + x2[j] * r2 + x3[j] * r3 + x4[j] * r4 + x5[j] * r5
                    ux_s = x0[j] * s0 + x1[j] * s1 + x2[j] * s2 + x3[j] * s3 + x4[j] * s4 + x5[j] * s5
                    uy_r = y0[j] * r0 + y1[j] * r1 + y2[j] * r2 + y3[j] * r3 + y4[j] * r4 + y5[j] * r5
                    uy_s = y0[j] * s0 + y1[j] * s1 + y2[j] * s2 + y3[j] * s3 + y4[j] * s4 + y5[j] * s5
                    # physical gradient = A^{-T} (reference gradient)
                    ux_x = a00[j] * ux_r + a10[j] * ux_s
                    ux_y = a01[j] * ux_r + a11[j] * ux_s
                    uy_x = a00[j] * uy_r + a10[j] * uy_s
                    uy_y = a01[j] * uy_r + a11[j] * uy_s
                    if bdf2:
                        carried_x = c0[j] * p0 + c1[j] * p1 + c2[j] * p2 + c3[j] * p3 + c4[j] * p4 + c5[j] * p5
                        carried_y = d0[j] * p0 + d1[j] * p1 + d2[j] * p2 + d3[j] * p3 + d4[j] * p4 + d5[j] * p5
                    else:
                        carried_x, carried_y = u, v
                    weight = w * area[j]
                    fx[j] = (mass_coefficient * carried_x - convection_coefficient * (u * ux_x + v * ux_y)) * weight
                    fy[j] = (mass_coefficient * carried_y - convection_coefficient * (u * uy_x + v * uy_y)) * weight
                for i in range(6):
                    p = phi[q, i]
                    sum_x = sums[i]
                    sum_y = sums[6 + i]
                    for j in range(n):
                        sum_x[j] += fx[j] * p
                        sum_y[j] += fy[j] * p
            for j in range(n):
                for i in range(6):
                    local[start + j, 0, i] = sums[i, j]
                    local[start + j, 1, i] = sums[6 + i, j]
    return kernel


_element_momentum = _momentum_kernel(False)
_element_momentum_bdf2 = _momentum_kernel(True)


@njit(cache=True)
def scatter_momentum(element_dofs, local, positions, out):
    """Add ``element_momentum``'s values ``local`` to ``out[positions[c, dof]]`` for dof = element_dofs[i, e], each
    component c, element by element in order (the same sums in the same order, however ``local`` was computed);
    positions < 0 are skipped."""
    for e in range(element_dofs.shape[1]):
        for i in range(element_dofs.shape[0]):
            dof = element_dofs[i, e]
            for c in range(2):
                position = positions[c, dof]
                if position >= 0:
                    out[position] += local[e, c, i]


def element_momentum(element_dofs, jacobian_rows, areas, phi, dphi, weights, velocity, mass_coefficient,
                     convection_coefficient, out, back=None, threads: int | None = None):
    """Each element's integrals (m w - k (u . grad) u) . phi_i into ``out`` (ne, 2, 6); ``jacobian_rows`` and ``areas``
    as ``_element_momentum`` takes them. Without ``back`` u = w = v (``velocity``, (2, N)); with ``back`` = (weights
    (w0, w1, w2), (a, b)), BDF2's: u = 2 v - b^, w = (4 v - b^) / 3, b^ = w0 v + w1 a + w2 b the velocity one step
    back (``sim.method.fluid.NavierStokes._momentum_back``; (0, 1, 0) takes a itself, with no arithmetic on its values).

    ``threads``: numba's threads for this call (default: numba's setting; 1: the calling thread alone, while the
    process's other threads work; numba's setting is per thread and is restored). Each block of elements is
    computed alone, whichever thread takes it, so the values are the same bits with any number. The GIL is released
    while it runs; a lock keeps two threads from launching it at once (numba's threading layers need not allow
    concurrent launches)."""
    if back is None:
        kernel, (w0, w1, w2), (a, b) = _element_momentum, (0.0, 0.0, 0.0), (velocity, velocity)
    else:
        kernel, (w0, w1, w2), (a, b) = _element_momentum_bdf2, back[0], back[1]
    general = bool(w0 != 0.0 or w2 != 0.0 or w1 != 1.0)
    with _LAUNCH:
        previous = numba.get_num_threads()
        if threads is not None:
            numba.set_num_threads(threads)
        try:
            kernel(element_dofs, jacobian_rows, areas, phi, dphi, weights, velocity[0], velocity[1], a[0], a[1], b[0],
                   b[1], float(w0), float(w1), float(w2), general, mass_coefficient, convection_coefficient, out)
        finally:
            if threads is not None:
                numba.set_num_threads(previous)
    return out


@njit(cache=True)
def locate(points, grid_x, grid_y, square_elements, origins, inverse_jacobians, elements, reference):
    """Find the triangle holding each point of a tensor-grid triangulation and its reference coordinates.

    square_elements (nx, ny, 2): the triangles of square (i, j), [0] above its rising diagonal, [1] below.
    Points outside the rectangle get element -1. ``elements`` (n,) and ``reference`` (n, 2) are outputs.
    """
    nx = grid_x.shape[0] - 1
    ny = grid_y.shape[0] - 1
    for k in range(points.shape[0]):
        x = points[k, 0]
        y = points[k, 1]
        if not (grid_x[0] <= x <= grid_x[nx] and grid_y[0] <= y <= grid_y[ny]):
            elements[k] = -1
            reference[k, 0] = np.nan
            reference[k, 1] = np.nan
            continue
        i = min(max(np.searchsorted(grid_x, x) - 1, 0), nx - 1)
        j = min(max(np.searchsorted(grid_y, y) - 1, 0), ny - 1)
        s = (x - grid_x[i]) / (grid_x[i + 1] - grid_x[i])
        r = (y - grid_y[j]) / (grid_y[j + 1] - grid_y[j])
        e = square_elements[i, j, 0] if r > s else square_elements[i, j, 1]
        elements[k] = e
        dx = x - origins[e, 0]
        dy = y - origins[e, 1]
        reference[k, 0] = inverse_jacobians[e, 0, 0] * dx + inverse_jacobians[e, 0, 1] * dy
        reference[k, 1] = inverse_jacobians[e, 1, 0] * dx + inverse_jacobians[e, 1, 1] * dy


@njit(cache=True)
def p2_basis(r, s, out):
    """The six P2 basis functions on the reference triangle, scikit-fem's local order."""
    out[0] = 1.0 - 3.0 * r - 3.0 * s + 2.0 * r * r + 4.0 * r * s + 2.0 * s * s
    out[1] = 2.0 * r * r - r
    out[2] = 2.0 * s * s - s
    out[3] = 4.0 * r - 4.0 * r * r - 4.0 * r * s
    out[4] = 4.0 * r * s
    out[5] = 4.0 * s - 4.0 * r * s - 4.0 * s * s


@njit(cache=True)
def interpolate_p2(elements, reference, element_dofs, values, out):
    """out[k, c] = sum_i values[c, dof_i] phi_i(point k): P2 fields (nc, N) at located points (NaN outside)."""
    phi = np.empty(6)
    for k in range(elements.shape[0]):
        e = elements[k]
        if e < 0:
            for c in range(values.shape[0]):
                out[k, c] = np.nan
            continue
        p2_basis(reference[k, 0], reference[k, 1], phi)
        for c in range(values.shape[0]):
            total = 0.0
            for i in range(6):
                total += values[c, element_dofs[i, e]] * phi[i]
            out[k, c] = total


@njit(cache=True)
def spread_p2(elements, reference, element_dofs, forces, out):
    """out[c, dof_i] += forces[k, c] phi_i(point k): point forces (n, nc) onto P2 load vectors (nc, N).

    The exact adjoint of ``interpolate_p2``; points with element -1 (outside the mesh) are skipped.
    """
    phi = np.empty(6)
    for k in range(elements.shape[0]):
        e = elements[k]
        if e < 0:
            continue
        p2_basis(reference[k, 0], reference[k, 1], phi)
        for c in range(forces.shape[1]):
            for i in range(6):
                out[c, element_dofs[i, e]] += forces[k, c] * phi[i]


@njit(cache=True)
def first_self_intersection(points):
    """Index pair (i, j) of the first two non-adjacent edges of the closed polygon that cross, else (-1, -1)."""
    n = points.shape[0]
    for i in range(n):
        ax, ay = points[i, 0], points[i, 1]
        bx, by = points[(i + 1) % n, 0], points[(i + 1) % n, 1]
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue
            cx, cy = points[j, 0], points[j, 1]
            dx, dy = points[(j + 1) % n, 0], points[(j + 1) % n, 1]
            d1 = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
            d2 = (bx - ax) * (dy - ay) - (by - ay) * (dx - ax)
            d3 = (dx - cx) * (ay - cy) - (dy - cy) * (ax - cx)
            d4 = (dx - cx) * (by - cy) - (dy - cy) * (bx - cx)
            if d1 * d2 < 0 and d3 * d4 < 0:
                return i, j
    return -1, -1


@njit(cache=True)
def linearised_convection(element_dofs, inverse_jacobians, determinants, phi, dphi, weights, ux, uy, newton,
                          positions, xx, xy, yx, yy):
    """Matrices of the convection linearised about u, on a fixed CSR pattern (data arrays overwritten).

    Oseen: C_ij = integral (u . grad phi_j) phi_i on the diagonal blocks; Newton adds
    D_ab,ij = integral (d_b u_a) phi_j phi_i to block (a, b). ``positions[e, i, j]`` is the index in the
    pattern's data of the pair (element_dofs[i, e], element_dofs[j, e]).
    """
    xx[:] = 0.0
    xy[:] = 0.0
    yx[:] = 0.0
    yy[:] = 0.0
    gx = np.empty(6)
    gy = np.empty(6)
    for e in range(element_dofs.shape[1]):
        a00 = inverse_jacobians[e, 0, 0]
        a01 = inverse_jacobians[e, 0, 1]
        a10 = inverse_jacobians[e, 1, 0]
        a11 = inverse_jacobians[e, 1, 1]
        area = abs(determinants[e])
        for q in range(weights.shape[0]):
            u = 0.0
            v = 0.0
            ux_r = 0.0
            ux_s = 0.0
            uy_r = 0.0
            uy_s = 0.0
            for i in range(6):
                dof = element_dofs[i, e]
                u += ux[dof] * phi[q, i]
                v += uy[dof] * phi[q, i]
                ux_r += ux[dof] * dphi[q, i, 0]
                ux_s += ux[dof] * dphi[q, i, 1]
                uy_r += uy[dof] * dphi[q, i, 0]
                uy_s += uy[dof] * dphi[q, i, 1]
                gx[i] = a00 * dphi[q, i, 0] + a10 * dphi[q, i, 1]
                gy[i] = a01 * dphi[q, i, 0] + a11 * dphi[q, i, 1]
            weight = weights[q] * area
            ux_x = a00 * ux_r + a10 * ux_s
            ux_y = a01 * ux_r + a11 * ux_s
            uy_x = a00 * uy_r + a10 * uy_s
            uy_y = a01 * uy_r + a11 * uy_s
            for i in range(6):
                wi = weight * phi[q, i]
                for j in range(6):
                    position = positions[e, i, j]
                    advection = wi * (u * gx[j] + v * gy[j])
                    if newton:
                        mass = wi * phi[q, j]
                        xx[position] += advection + mass * ux_x
                        xy[position] += mass * ux_y
                        yx[position] += mass * uy_x
                        yy[position] += advection + mass * uy_y
                    else:
                        xx[position] += advection
                        yy[position] += advection


# ---------------------------------------------------------------------- the split solve's vector work
# (sim.fast.splitsolve) Each runs on one thread without the GIL, so the two halves of a solve work at once. Every
# sum runs in index order from zero in the vectors' own precision, as scipy's CSR product does: the same bits.
# A row's sum is a chain of dependent additions (its order is fixed, so it cannot be vectorised): H^T's rows are
# long (~780 entries at the paper's mesh), so its chains bound the product by the adder's latency, and
# ``transposed_products`` runs four rows' chains side by side, each in its own order (``_four_rows``: the same
# bits, 1.3-1.7x faster in three in-process A/B runs). A's rows (~18 entries) gained nothing that way (the
# processor already overlaps such short chains): they sum one row at a time. H w is summed from H^T by columns
# (``minus_product``): each row's sum still runs in index order, and the solve keeps one copy of H.

@njit(cache=True, nogil=True, inline="always")
def _row(data, indices, indptr, v, r, zero):
    """The sum of CSR row r times v, in index order from ``zero``."""
    total = zero
    for jj in range(np.uint64(indptr[r]), np.uint64(indptr[r + 1])):
        total += data[jj] * v[np.uint64(indices[jj])]
    return total


@njit(cache=True, nogil=True, inline="always")
def _four_rows(data, indices, indptr, v, r0, r1, r2, r3, zero):
    """The sums of CSR rows r0 .. r3 times v, each in index order from ``zero`` (as ``_row``), run side by side."""
    a0 = np.uint64(indptr[r0])
    a1 = np.uint64(indptr[r1])
    a2 = np.uint64(indptr[r2])
    a3 = np.uint64(indptr[r3])
    e0 = np.uint64(indptr[r0 + 1])
    e1 = np.uint64(indptr[r1 + 1])
    e2 = np.uint64(indptr[r2 + 1])
    e3 = np.uint64(indptr[r3 + 1])
    t0 = zero
    t1 = zero
    t2 = zero
    t3 = zero
    common = min(e0 - a0, e1 - a1, e2 - a2, e3 - a3)
    for j in range(common):
        t0 += data[a0 + j] * v[np.uint64(indices[a0 + j])]
        t1 += data[a1 + j] * v[np.uint64(indices[a1 + j])]
        t2 += data[a2 + j] * v[np.uint64(indices[a2 + j])]
        t3 += data[a3 + j] * v[np.uint64(indices[a3 + j])]
    for jj in range(a0 + common, e0):
        t0 += data[jj] * v[np.uint64(indices[jj])]
    for jj in range(a1 + common, e1):
        t1 += data[jj] * v[np.uint64(indices[jj])]
    for jj in range(a2 + common, e2):
        t2 += data[jj] * v[np.uint64(indices[jj])]
    for jj in range(a3 + common, e3):
        t3 += data[jj] * v[np.uint64(indices[jj])]
    return t0, t1, t2, t3


@njit(cache=True, nogil=True)
def gather_residual(rhs, rows, data, indices, indptr, x, out):
    """out[k] = rhs[rows[k]] - (A x)_k, A's rows k given in CSR (none given: out[k] = rhs[rows[k]]); rounded to
    ``out``'s precision."""
    if indptr.shape[0] != rows.shape[0] + 1:
        for k in range(rows.shape[0]):
            out[k] = rhs[np.uint64(rows[k])]
        return
    for k in range(rows.shape[0]):
        out[k] = rhs[np.uint64(rows[k])] - _row(data, indices, indptr, x, k, 0.0)


@njit(cache=True, nogil=True)
def transposed_products(y, dinv, z, data, indices, indptr, g, zero):
    """z = dinv * y (when ``dinv`` has entries) and g = H^T y, H^T given in CSR (``zero``: the sums' type)."""
    if dinv.shape[0] == y.shape[0]:
        for k in range(y.shape[0]):
            z[k] = dinv[k] * y[k]
    n = g.shape[0]
    r = 0
    while r + 4 <= n:
        g[r], g[r + 1], g[r + 2], g[r + 3] = _four_rows(data, indices, indptr, y, r, r + 1, r + 2, r + 3, zero)
        r += 4
    for r in range(r, n):
        g[r] = _row(data, indices, indptr, y, r, zero)


@njit(cache=True, nogil=True)
def minus_product(z, data, indices, indptr, w, sums, out, zero):
    """out = z - H w, H given by its transpose in CSR (H's columns; ``sums``: scratch of z's length, ``zero``: the
    sums' type). Each (H w)_r is summed in increasing column order from ``zero``, as scipy's CSR product of H with
    sorted indices sums it (the same bits), but the products are scattered column by column: H^T, which
    ``transposed_products`` reads, is the only copy of H the split solve keeps (~2 MB a half at the paper's mesh)."""
    for r in range(sums.shape[0]):
        sums[r] = zero
    for c in range(w.shape[0]):
        weight = w[c]
        for jj in range(np.uint64(indptr[c]), np.uint64(indptr[c + 1])):
            row = np.uint64(indices[jj])
            sums[row] += data[jj] * weight
    for r in range(z.shape[0]):
        out[r] = z[r] - sums[r]


@njit(cache=True, nogil=True)
def scatter_add(solution, rows, x, accumulate):
    """solution[rows[k]] (+)= x[k] (added with ``accumulate``, else set); the largest |x[k]| and the largest
    |solution[rows[k]]| after it, NaN for either when a value is not finite."""
    size = 0.0
    scale = 0.0
    finite = True
    for k in range(rows.shape[0]):
        row = np.uint64(rows[k])
        change = np.float64(x[k])
        value = solution[row] + change if accumulate else change
        solution[row] = value
        if not (np.isfinite(change) and np.isfinite(value)):
            finite = False
        size = max(size, abs(change))
        scale = max(scale, abs(value))
    if not finite:
        return np.nan, np.nan
    return size, scale


# ---- the glue of a fluid step (``sim.method.fluid``): one pass each instead of numpy's temporaries, the same bits


@njit(cache=True)
def free_rhs(momentum, free_velocity, continuity, out):
    """out = [momentum.ravel()[free_velocity], continuity] (zeros where ``momentum``/``continuity`` are empty)."""
    n_velocity = free_velocity.shape[0]
    if momentum.shape[0] == 0:
        out[:n_velocity] = 0.0
    else:
        for k in range(n_velocity):
            out[k] = momentum[free_velocity[k]]
    if continuity.shape[0] == 0:
        out[n_velocity:] = 0.0
    else:
        for k in range(out.shape[0] - n_velocity):
            out[n_velocity + k] = continuity[k]


@njit(cache=True)
def subtract_scaled(out, weight, vector):
    """out -= weight * vector (the product rounded first, as numpy's expression)."""
    for k in range(out.shape[0]):
        out[k] = out[k] - weight * vector[k]


@njit(cache=True)
def boundary_velocity(inflow_weight, inflow, jet_weight, jet, free_velocity, solution, out):
    """out = inflow_weight * inflow + jet_weight * jet (flat; zeros when both weights are), then
    out[free_velocity] = solution[:len(free_velocity)]."""
    if inflow_weight == 0.0 and jet_weight == 0.0:
        out[:] = 0.0
    else:
        for k in range(out.shape[0]):
            out[k] = inflow_weight * inflow[k] + jet_weight * jet[k]
    for k in range(free_velocity.shape[0]):
        out[free_velocity[k]] = solution[k]


@njit(cache=True)
def free_solution(velocity, free_velocity, pressure, pressure_scale, out):
    """out = [velocity.ravel()[free_velocity], pressure / pressure_scale]."""
    n_velocity = free_velocity.shape[0]
    for k in range(n_velocity):
        out[k] = velocity[free_velocity[k]]
    for k in range(pressure.shape[0]):
        out[n_velocity + k] = pressure[k] / pressure_scale
