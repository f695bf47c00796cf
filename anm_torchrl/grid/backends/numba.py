"""The ``numba`` backend: the transition of a :class:`~anm_torchrl.grid.simulator.GridSimulator` as one compiled
CPU loop (float64, not differentiable), behind the contract of :mod:`anm_torchrl.grid.backends`.

The torch implementation spends its time in dispatch and in memory traffic: at batch 16,384 every one of
its ~400 small ops streams (N, 2n-2, 2n-2) tensors through memory. Here each env runs the same maths start to
end in registers and cache — edge-clamp projections, SoC update, Newton–Raphson, slack, branch flows, reward —
on any network, whose tables arrive as one :class:`~anm_torchrl.grid.constants.TransitionConstants`. The
Newton step is a dense LU on small networks and a band LU after an RCM ordering on larger ones
(:func:`~anm_torchrl.grid.constants.jacobian_ordering`; O(n·kl²) instead of O(n³)). With
``torch.get_num_threads() > 1`` and a large batch, the batch is split into that many slices run by Python threads
(the kernel releases the GIL). Not numba's ``parallel=True``: its OpenMP layer resets torch's thread count and
its own pool hangs a process forked after first use (TorchRL's multi-process collectors); the pool here is per
process. Same algorithms, same stopping rule and order of operations as the torch code,
so results agree to float64 round-off (tested against both the torch backend and gym-anm).

Compiled on first use (cached on disk by numba); ``available()`` says whether numba can be used.
"""

from __future__ import annotations

import logging
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from anm_torchrl.grid import fastoutput
from anm_torchrl.grid.devices import _FEAS_TOL, EFF, PMAX, PMIN, SOC_MAX, SOC_MIN
from anm_torchrl.grid.jit import available
from anm_torchrl.grid.jit import njit as _njit
from anm_torchrl.grid.transition import Transition

log = logging.getLogger(__name__)
PARALLEL_MIN_BATCH = 1024  # below this, splitting the batch over threads costs more than it saves
SLICES_PER_THREAD = 8
_KERNEL_READY = False  # set by _first_call once this process has loaded (or compiled) the kernel
_POOL: dict[int, tuple[int, ThreadPoolExecutor]] = {}  # pid -> (threads, pool): a forked child makes its own


# --------------------------------------------------------------------------------------------- scalars
@_njit()
def _relu(x):
    return x if (x > 0.0 or x != x) else 0.0  # keeps NaN, as torch.relu


@_njit()
def _clamp(x, lo, hi):
    return min(max(x, lo), hi)


# ------------------------------------------------------------------------------------------ projection
@_njit(inline="always")
def _project(tx, ty, h_raw, c, poly, h):
    """Edge-clamp projection of (tx, ty) onto polygon ``c`` of ``poly`` = (m, group, g, gn2, d, coup, kind,
    inv_a) (see :func:`_polygon_arrays`; ``kind`` 1 upper, -1 lower, 0 parallel) with right-hand sides
    ``h_raw``. Mirrors :meth:`anm_torchrl.grid.devices.Polygon.project` for one point; ``h`` is scratch.

    Returns (x, y). Arrays are indexed in place, never sliced: views cost reference counting per call.
    """
    n_lines, group, g, gn2, d, coup, kind, inv_a = poly
    m = n_lines[c]
    inside = True
    for j in range(m):
        hj = np.inf
        for w in range(group.shape[2]):
            r = group[c, j, w]
            if r >= 0 and h_raw[r] < hj:
                hj = h_raw[r]
        h[j] = hj
        if not (tx * g[c, j, 0] + ty * g[c, j, 1] <= hj + _FEAS_TOL):
            inside = False
    if inside:
        return tx, ty
    best, bx, by = np.inf, 0.0, 0.0
    for j in range(m):
        t_hi, t_lo, ok = np.inf, -np.inf, True
        for i in range(m):
            b = h[i] - coup[c, i, j] * h[j]
            k = kind[c, i, j]
            if k == 0:
                if not (b >= -_FEAS_TOL):
                    ok = False
            else:
                ratio = b * inv_a[c, i, j]
                if k > 0:
                    t_hi = min(t_hi, ratio)
                else:
                    t_lo = max(t_lo, ratio)
        if not ok or not (t_lo <= t_hi + _FEAS_TOL) or h[j] == np.inf:  # a line at +inf holds nothing
            continue
        t = min(max((tx * d[c, j, 0] + ty * d[c, j, 1]) / gn2[c, j], t_lo), t_hi)
        cx = h[j] / gn2[c, j] * g[c, j, 0] + t * d[c, j, 0]
        cy = h[j] / gn2[c, j] * g[c, j, 1] + t * d[c, j, 1]
        dist = (cx - tx) * (cx - tx) + (cy - ty) * (cy - ty)
        if dist < best:
            best, bx, by = dist, cx, cy
    return bx, by


# ---------------------------------------------------------------------------------------- power flow
@_njit(inline="always")
def _injection(vm, va, ycsr, s, v):
    """V (into ``v``) and S = V ⊙ conj(Y V) (into ``s``), both (n,), for magnitudes/angles (n,).

    ``ycsr`` = (row pointers, column indices ascending, values) of Y's non-zeros: the same sum in the same order
    as a dense row loop that skips exact zeros, in O(nnz)."""
    ptr, col, val = ycsr
    n = vm.shape[0]
    for i in range(n):
        v[i] = complex(vm[i] * math.cos(va[i]), vm[i] * math.sin(va[i]))
    for i in range(n):
        acc = 0j
        for e in range(ptr[i], ptr[i + 1]):
            acc += val[e] * v[col[e]]
        s[i] = v[i] * acc.conjugate()


@_njit(inline="always")
def _mismatch_inf(s, s_bus, f, ix):
    """F = [Re, Im] of the non-slack mismatch into ``f`` (variable ``j`` at ``f[ix[j]]``); returns ||F||_inf."""
    n = s.shape[0]
    k = n - 1
    for i in range(1, n):
        m = s[i] - s_bus[i]
        f[ix[i - 1]], f[ix[k + i - 1]] = m.real, m.imag
    return _inf_norm(f)


@_njit(inline="always")
def _inf_norm(f):
    """max |f| (NaN sticks, as ``amax``)."""
    worst = 0.0
    for i in range(f.shape[0]):
        a = abs(f[i])
        if a > worst or a != a:
            worst = a
            if a != a:
                break
    return worst


@_njit(inline="always")
def _lu_factor(a, piv, kl, ku):
    """In-place band LU with partial pivoting (LAPACK ``gbtrf`` semantics on dense storage): ``kl``/``ku`` sub/
    super-diagonals; multipliers of step c stay in column c (rows c+1..c+kl). With kl = ku = n - 1 it is the
    plain dense LU, bit for bit. False when a pivot is exactly 0 (singular)."""
    n = a.shape[0]
    for c in range(n):
        last = min(n - 1, c + kl)
        p, pv = c, abs(a[c, c])
        for r in range(c + 1, last + 1):
            if abs(a[r, c]) > pv:
                p, pv = r, abs(a[r, c])
        piv[c] = p
        if pv == 0.0:
            return False
        right = min(n - 1, c + kl + ku)  # fill after pivoting stays within kl + ku super-diagonals
        if p != c:
            for q in range(c, right + 1):
                a[c, q], a[p, q] = a[p, q], a[c, q]
        for r in range(c + 1, last + 1):
            f = a[r, c] / a[c, c]
            a[r, c] = f
            if f != 0.0:
                for q in range(c + 1, right + 1):
                    a[r, q] -= f * a[c, q]
    return True


@_njit(inline="always")
def _lu_solve(a, piv, b, kl, ku):
    """b <- A⁻¹ b from :func:`_lu_factor`'s ``a``, ``piv`` (row interchanges applied step by step, ``gbtrs``)."""
    n = b.shape[0]
    for c in range(n):
        p = piv[c]
        if p != c:
            b[c], b[p] = b[p], b[c]
        for r in range(c + 1, min(n - 1, c + kl) + 1):
            b[r] -= a[r, c] * b[c]
    for c in range(n - 1, -1, -1):
        acc = b[c]
        for q in range(c + 1, min(n - 1, c + kl + ku) + 1):
            acc -= a[c, q] * b[q]
        b[c] = acc / a[c, c]


@_njit(inline="always")
def _tree_factor(a, parent):
    """Block LU without fill of a Jacobian whose buses form a forest, eliminated leaves first (position j holds
    θ, |V| of the j-th bus in that order at rows 2j, 2j+1; ``parent[j]`` is the position of its parent or -1).

    Each 2×2 diagonal block is replaced by its inverse, each parent←child block L by L·D⁻¹; only the blocks of
    the tree are read, in O(n). No pivoting across buses. False when a diagonal block is singular."""
    for j in range(parent.shape[0]):
        r = 2 * j
        d00, d01, d10, d11 = a[r, r], a[r, r + 1], a[r + 1, r], a[r + 1, r + 1]
        det = d00 * d11 - d01 * d10
        if det == 0.0 or det != det:
            return False
        i00, i01, i10, i11 = d11 / det, -d01 / det, -d10 / det, d00 / det
        a[r, r], a[r, r + 1], a[r + 1, r], a[r + 1, r + 1] = i00, i01, i10, i11
        p = parent[j]
        if p < 0:
            continue
        q = 2 * p
        l00, l01, l10, l11 = a[q, r], a[q, r + 1], a[q + 1, r], a[q + 1, r + 1]
        m00, m01 = l00 * i00 + l01 * i10, l00 * i01 + l01 * i11  # M = L D^-1
        m10, m11 = l10 * i00 + l11 * i10, l10 * i01 + l11 * i11
        a[q, r], a[q, r + 1], a[q + 1, r], a[q + 1, r + 1] = m00, m01, m10, m11
        u00, u01, u10, u11 = a[r, q], a[r, q + 1], a[r + 1, q], a[r + 1, q + 1]
        a[q, q] -= m00 * u00 + m01 * u10  # D_p -= M U
        a[q, q + 1] -= m00 * u01 + m01 * u11
        a[q + 1, q] -= m10 * u00 + m11 * u10
        a[q + 1, q + 1] -= m10 * u01 + m11 * u11
    return True


@_njit(inline="always")
def _tree_solve(a, parent, b):
    """b <- A⁻¹ b from :func:`_tree_factor`'s ``a``: forward sweep leaves to roots, back sweep roots to leaves."""
    n = parent.shape[0]
    for j in range(n):
        p = parent[j]
        if p >= 0:
            r, q = 2 * j, 2 * p
            b[q] -= a[q, r] * b[r] + a[q, r + 1] * b[r + 1]
            b[q + 1] -= a[q + 1, r] * b[r] + a[q + 1, r + 1] * b[r + 1]
    for j in range(n - 1, -1, -1):
        r, p = 2 * j, parent[j]
        c0, c1 = b[r], b[r + 1]
        if p >= 0:
            q = 2 * p
            c0 -= a[r, q] * b[q] + a[r, q + 1] * b[q + 1]
            c1 -= a[r + 1, q] * b[q] + a[r + 1, q + 1] * b[q + 1]
        b[r], b[r + 1] = a[r, r] * c0 + a[r, r + 1] * c1, a[r + 1, r] * c0 + a[r + 1, r + 1] * c1


@_njit(inline="always")
def _factor(a, piv, kl, ku, parent):
    return _tree_factor(a, parent) if parent.shape[0] > 0 else _lu_factor(a, piv, kl, ku)


@_njit(inline="always")
def _solve(a, piv, b, kl, ku, parent):
    if parent.shape[0] > 0:
        _tree_solve(a, parent, b)
    else:
        _lu_solve(a, piv, b, kl, ku)


@_njit(inline="always")
def _jacobian(ycsr, v, vm, s, jac, ix, kl, ku):
    """Polar Jacobian (2n-2, 2n-2) into ``jac``, as :func:`anm_torchrl.grid.powerflow._jacobian`, with variable /
    equation ``j`` at row / column ``ix[j]`` (an ordering that makes it banded for large feeders). Only the band
    the LU reads (columns r - kl .. r + kl + ku of row r) is cleared, then Y's non-zeros are written."""
    ptr, col, val = ycsr
    k = v.shape[0] - 1
    nv = 2 * k
    for r in range(nv):
        for q in range(max(0, r - kl), min(nv - 1, r + kl + ku) + 1):
            jac[r, q] = 0.0
    for i in range(k):
        vi = v[i + 1]
        ri, rk = ix[i], ix[k + i]
        for e in range(ptr[i + 1], ptr[i + 2]):
            q = col[e] - 1
            if q < 0:  # the slack bus column
                continue
            cq, ck = ix[q], ix[k + q]
            a = vi * (val[e] * v[q + 1]).conjugate()  # A_iq = V_i conj(Y_iq V_q)
            b = a / vm[q + 1]
            jac[ri, cq], jac[rk, cq] = a.imag, -a.real
            jac[ri, ck], jac[rk, ck] = b.real, b.imag
        sr, si = s[i + 1].real, s[i + 1].imag
        jac[ri, ri] -= si
        jac[rk, rk] += si / vm[i + 1]
        jac[ri, rk] += sr / vm[i + 1]
        jac[rk, ri] += sr


@_njit()
def _flat_start_lu(y, ycsr, dense, ix, kl, ku, parent):
    """LU factors of the Jacobian at the flat start (the same for every env): (lu, piv, non-singular), in the
    layout of the path that will use them (``dense``: :func:`_dense_newton_raphson`)."""
    n = y.shape[0]
    vm, va = np.ones(n), np.zeros(n)
    s, v = np.empty(n, dtype=np.complex128), np.empty(n, dtype=np.complex128)
    lu, piv = np.zeros((2 * n - 2, 2 * n - 2)), np.empty(2 * n - 2, dtype=np.int64)
    if dense:
        _dense_injection(vm, va, y, s, v)
        _dense_jacobian(y, v, vm, s, lu)
        return lu, piv, _lu_factor(lu, piv, 2 * n - 3, 2 * n - 3)
    _injection(vm, va, ycsr, s, v)
    _jacobian(ycsr, v, vm, s, lu, ix, kl, ku)
    return lu, piv, _factor(lu, piv, kl, ku, parent)


@_njit(inline="always")
def _newton_raphson(ycsr, lu0, piv0, ok0, ix, kl, ku, parent, s_bus, tol, max_iter, vm, va, s, v, f, jac, piv):
    """Flat-start NR (spec §4.1) for one env; fills vm, va, s, v (n,) (``f``, ``jac``, ``piv``: scratch).

    The first iteration reuses the flat-start factors ``lu0``, ``piv0`` (``ok0`` False: singular). A singular
    Jacobian gives a NaN step, as gym-anm's ``spsolve``. Returns (n_iter, ||F||_inf).
    """
    n = s_bus.shape[0]
    k = n - 1
    for i in range(n):
        vm[i], va[i] = 1.0, 0.0
    _injection(vm, va, ycsr, s, v)
    diff = _mismatch_inf(s, s_bus, f, ix)
    it = 0
    while diff > tol and it < max_iter:
        it += 1
        if it == 1:
            lu, pv, ok = lu0, piv0, ok0
        else:
            _jacobian(ycsr, v, vm, s, jac, ix, kl, ku)
            lu, pv, ok = jac, piv, _factor(jac, piv, kl, ku, parent)
        if ok:
            _solve(lu, pv, f, kl, ku, parent)
        else:
            f[:] = np.nan
        for i in range(k):
            va[i + 1] -= f[ix[i]]
            vm[i + 1] -= f[ix[k + i]]
        _injection(vm, va, ycsr, s, v)
        diff = _mismatch_inf(s, s_bus, f, ix)
    return it, diff


# ------------------------------------------------------------------------------- small-network power flow
# The dense layout (``TransitionConstants.dense``: gym-anm's Jacobian layout, full band, no tree) gets its own
# Newton–Raphson: Y read densely and no index indirection (the LU is the band LU at full bandwidth). It performs
# the same operations on the same numbers as the generic path with that layout (bit-identical results, tested),
# and is ~10 % faster on ANM6-Easy, where the Newton step is most of a transition. Kept as separate functions
# rather than branches inside the generic ones: measured, a runtime flag inside them recovered a third of it.
@_njit(inline="always")
def _dense_injection(vm, va, y, s, v):
    """:func:`_injection` with Y (n, n) read densely (exact zeros skipped: the same terms in the same order)."""
    n = vm.shape[0]
    for i in range(n):
        v[i] = complex(vm[i] * math.cos(va[i]), vm[i] * math.sin(va[i]))
    for i in range(n):
        acc = 0j
        for k in range(n):
            if y[i, k] != 0:
                acc += y[i, k] * v[k]
        s[i] = v[i] * acc.conjugate()


@_njit(inline="always")
def _dense_mismatch_inf(s, s_bus, f):
    """:func:`_mismatch_inf` in gym-anm's layout (variable ``j`` at ``f[j]``)."""
    k = s.shape[0] - 1
    for i in range(1, k + 1):
        m = s[i] - s_bus[i]
        f[i - 1], f[k + i - 1] = m.real, m.imag
    return _inf_norm(f)


@_njit(inline="always")
def _dense_jacobian(y, v, vm, s, jac):
    """:func:`_jacobian` in gym-anm's layout, every entry written in one pass over Y."""
    k = v.shape[0] - 1
    for i in range(k):
        vi = v[i + 1]
        for q in range(k):
            if y[i + 1, q + 1] == 0:  # A_iq = 0 exactly
                jac[i, q], jac[k + i, q], jac[i, k + q], jac[k + i, k + q] = 0.0, 0.0, 0.0, 0.0
                continue
            a = vi * (y[i + 1, q + 1] * v[q + 1]).conjugate()  # A_iq = V_i conj(Y_iq V_q)
            b = a / vm[q + 1]
            jac[i, q], jac[k + i, q] = a.imag, -a.real
            jac[i, k + q], jac[k + i, k + q] = b.real, b.imag
        sr, si = s[i + 1].real, s[i + 1].imag
        jac[i, i] -= si
        jac[k + i, k + i] += si / vm[i + 1]
        jac[i, k + i] += sr / vm[i + 1]
        jac[k + i, i] += sr


@_njit(inline="always")
def _dense_newton_raphson(y, lu0, piv0, ok0, s_bus, tol, max_iter, vm, va, s, v, f, jac, piv):
    """:func:`_newton_raphson` for the dense layout (Jacobian (2n-2, 2n-2), full bandwidth)."""
    n = s_bus.shape[0]
    k = n - 1
    for i in range(n):
        vm[i], va[i] = 1.0, 0.0
    _dense_injection(vm, va, y, s, v)
    diff = _dense_mismatch_inf(s, s_bus, f)
    it = 0
    while diff > tol and it < max_iter:
        it += 1
        if it == 1:
            lu, pv, ok = lu0, piv0, ok0
        else:
            _dense_jacobian(y, v, vm, s, jac)
            lu, pv, ok = jac, piv, _lu_factor(jac, piv, 2 * k - 1, 2 * k - 1)
        if ok:
            _lu_solve(lu, pv, f, 2 * k - 1, 2 * k - 1)
        else:
            f[:] = np.nan
        for i in range(k):
            va[i + 1] -= f[i]
            vm[i + 1] -= f[k + i]
        _dense_injection(vm, va, y, s, v)
        diff = _dense_mismatch_inf(s, s_bus, f)
    return it, diff


# ------------------------------------------------------------------------------------ power flow alone
@_njit()
def _power_flows(c, s_bus, tol, max_iter, x, converged, n_iter, diff):
    """Flat-start NR of every row of ``s_bus`` (N, n) complex p.u. (entry 0, the slack's, ignored) on the network
    of ``c``, written into ``x`` (N, 2n-2) = [θ_1.., |V|_1..] (rad, p.u.), ``converged`` (N,), ``n_iter`` (N,) and
    ``diff`` (N,) = ||F||_inf p.u.: what :func:`~anm_torchrl.grid.powerflow.newton_iterates` returns."""
    n = s_bus.shape[1]
    k = n - 1
    vm, va = np.empty(n), np.empty(n)
    s, v = np.empty(n, dtype=np.complex128), np.empty(n, dtype=np.complex128)
    f, jac, piv = np.empty(2 * k), np.zeros((2 * k, 2 * k)), np.empty(2 * k, dtype=np.int64)
    for e in range(s_bus.shape[0]):
        if c.dense:
            it, d = _dense_newton_raphson(c.y, c.lu0, c.piv0, c.ok0, s_bus[e], tol, max_iter, vm, va, s, v, f, jac,
                                          piv)
        else:
            it, d = _newton_raphson(c.ycsr, c.lu0, c.piv0, c.ok0, c.ix, c.kl, c.ku, c.parent, s_bus[e], tol, max_iter,
                                    vm, va, s, v, f, jac, piv)
        for i in range(k):
            x[e, i], x[e, k + i] = va[i + 1], vm[i + 1]
        converged[e], n_iter[e], diff[e] = d == d and d <= tol, it, d


@_njit()
def _adjoints(c, x, rhs, lam, info):
    """``lam`` (N, 2n-2) = J⁻ᵀ ``rhs`` (N, 2n-2) per row, J the polar Jacobian at the solution ``x`` (N, 2n-2) =
    [θ_1.., |V|_1..]: the backward of :class:`~anm_torchrl.grid.implicit.ImplicitPowerFlow`, as
    :func:`~anm_torchrl.grid.powerflow.solve_newton_step` with ``transpose=True``. Jᵀ is written by the forward's
    Jacobian functions into the transpose of its buffer (Y's pattern is symmetric, so the band / tree factors
    apply to it unchanged); ``info`` (N,) 1 where J is singular or the solution is not finite (``lam`` then 0)."""
    k = x.shape[1] // 2
    n = k + 1
    vm, va = np.empty(n), np.empty(n)
    s, v = np.empty(n, dtype=np.complex128), np.empty(n, dtype=np.complex128)
    jt, piv, b = np.zeros((2 * k, 2 * k)), np.empty(2 * k, dtype=np.int64), np.empty(2 * k)
    vm[0], va[0] = 1.0, 0.0
    for e in range(x.shape[0]):
        for i in range(k):
            va[i + 1], vm[i + 1] = x[e, i], x[e, k + i]
        if c.dense:
            _dense_injection(vm, va, c.y, s, v)
            _dense_jacobian(c.y, v, vm, s, jt.T)
            ok = _lu_factor(jt, piv, 2 * k - 1, 2 * k - 1)
            if ok:
                b[:] = rhs[e]
                _lu_solve(jt, piv, b, 2 * k - 1, 2 * k - 1)
        else:
            _injection(vm, va, c.ycsr, s, v)
            for r in range(2 * k):  # the band the LU reads (the Jacobian function clears J's band, not Jᵀ's)
                for q in range(max(0, r - c.kl), min(2 * k - 1, r + c.kl + c.ku) + 1):
                    jt[r, q] = 0.0
            _jacobian(c.ycsr, v, vm, s, jt.T, c.ix, c.kl, c.ku)
            ok = _factor(jt, piv, c.kl, c.ku, c.parent)
            if ok:
                for j in range(2 * k):
                    b[c.ix[j]] = rhs[e, j]
                _solve(jt, piv, b, c.kl, c.ku, c.parent)
        for j in range(2 * k):
            lam[e, j] = b[j] if c.dense else b[c.ix[j]]
            ok = ok and lam[e, j] - lam[e, j] == 0.0  # finite
        info[e] = 0 if ok else 1
        if not ok:
            lam[e, :] = 0.0


class CompiledPowerFlow:
    """:func:`~anm_torchrl.grid.powerflow.newton_iterates` of one network as the compiled loop above: called as
    ``(y_bus, s_bus, tol, max_iter) -> (x, converged, n_iter, ||F||_inf)`` on CPU complex128 ``s_bus`` (N, n) p.u.
    (``y_bus`` must be the network's: the constants hold its factorised flat start). The same algorithm and
    stopping rule; the numbers agree to float64 round-off. On ANM6-Easy at 128 rows ~7x faster than the torch ops
    (0.27 against 1.96 ms, this 2-core VM): the forward of the implicit power flow (:mod:`anm_torchrl.grid.implicit`),
    whose backward solves with Jᵀ here too (:meth:`adjoint`).
    """

    def __init__(self, constants):
        self.constants = constants

    def __call__(self, y_bus: torch.Tensor, s_bus: torch.Tensor, tol: float, max_iter: int):
        c = self.constants
        if y_bus.shape != c.y.shape or s_bus.device.type != "cpu" or s_bus.dtype != torch.complex128:
            raise ValueError(f"the compiled power flow takes CPU complex128 injections of its own {c.y.shape[0]}-bus "
                             f"network; got {tuple(s_bus.shape)} {s_bus.dtype} on {s_bus.device} with a "
                             f"{tuple(y_bus.shape)} Y-bus")
        n_env, n = s_bus.shape
        x, converged = np.empty((n_env, 2 * n - 2)), np.empty(n_env, dtype=np.bool_)
        n_iter, diff = np.empty(n_env, dtype=np.int64), np.empty(n_env)
        _power_flows(c, np.ascontiguousarray(s_bus.detach().numpy()), float(tol), int(max_iter), x, converged,
                     n_iter, diff)
        return tuple(torch.from_numpy(a) for a in (x, converged, n_iter, diff))

    def adjoint(self, x: torch.Tensor, rhs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(J⁻ᵀ rhs, info)`` (N, 2n-2), (N,) at the solutions ``x`` (N, 2n-2) this solver returned, for the
        backward of :class:`~anm_torchrl.grid.implicit.ImplicitPowerFlow` (as
        :func:`~anm_torchrl.grid.powerflow.solve_newton_step` with ``transpose=True``; info nonzero: singular)."""
        lam, info = np.empty(tuple(rhs.shape)), np.empty(rhs.shape[0], dtype=np.int32)
        _adjoints(self.constants, np.ascontiguousarray(x.detach().numpy()),
                  np.ascontiguousarray(rhs.detach().to(torch.float64).numpy()), lam, info)
        return torch.from_numpy(lam).to(rhs.dtype), torch.from_numpy(info)


# ---------------------------------------------------------------------------------------- transition
@_njit()
def _env_steps(c, soc, p_load, p_pot_raw, setpoints, out, scratch):
    """The loop of :func:`_transition` over the envs, with its scratch arrays passed in (measured ~8 % faster
    than allocating them in the same function). ``c`` is a :class:`TransitionConstants`, read by field name (numba
    types a NamedTuple as a record: resolved at compile time) into locals once, so that the loop body reads as
    gym-anm's steps (and compiles as the positional unpacking did: same speed, measured)."""
    dev, lid, gid, did, renewable, slack, dev_bus = c.dev, c.lid, c.gid, c.did, c.renewable, c.slack, c.dev_bus
    counted, gen_poly, des_poly, gen_h0, des_h0 = c.counted, c.gen_poly, c.des_poly, c.gen_h0, c.des_h0
    gen_ppot_row, des_soc_rows, y, ycsr, dense, lu0 = c.gen_ppot_row, c.des_soc_rows, c.y, c.ycsr, c.dense, c.lu0
    piv0, ok0, ix, kl, ku, parent, f_bus, t_bus = c.piv0, c.ok0, c.ix, c.kl, c.ku, c.parent, c.f_bus, c.t_bus
    y_ff, y_ft, y_tf, y_tt, rate, v_min, v_max = c.y_ff, c.y_ft, c.y_tf, c.y_tt, c.rate, c.v_min, c.v_max
    delta_t, lamb, c0, c1, term_reward, tol = c.delta_t, c.lamb, c.c0, c.c1, c.term_reward, c.tol
    max_iter = c.max_iter
    p_dev, q_dev, soc_next, p_pot, v_out, s_max, converged, n_iter, e_loss, pen, curt, reward = out
    hp, h_gen, h_des, s_bus, s, vm, va, f, jac, piv = scratch
    n_gen, n_des = gid.shape[0], did.shape[0]
    for e in range(setpoints.shape[0]):
        pd, qd, v = p_dev[e], q_dev[e], v_out[e]
        pd[:] = 0.0
        qd[:] = 0.0
        for k in range(lid.shape[0]):  # 1. loads follow their exogenous P, clipped, at constant Q/P
            r = lid[k]
            p = _clamp(p_load[e, k], dev[r, PMIN], dev[r, PMAX])
            pd[r], qd[r] = p, p * dev[r, 3]
        for k in range(n_gen):  # 2. generators: potential, then projection
            r = gid[k]
            pp = _clamp(p_pot_raw[e, k], dev[r, PMIN], dev[r, PMAX])
            p_pot[e, k] = pp
            for w in range(h_gen.shape[0]):
                h_gen[w] = gen_h0[k, w]
            h_gen[gen_ppot_row] = pp
            pd[r], qd[r] = _project(setpoints[e, k], setpoints[e, n_gen + k], h_gen, k, gen_poly, hp)
        for k in range(n_des):  # 3. storage: SoC-dependent projection, SoC update
            r = did[k]
            eff = dev[r, EFF]
            for w in range(h_des.shape[0]):
                h_des[w] = des_h0[k, w]
            h_des[des_soc_rows[0]] = -(soc[e, k] - dev[r, SOC_MAX]) / (delta_t * eff)
            h_des[des_soc_rows[1]] = eff * (soc[e, k] - dev[r, SOC_MIN]) / delta_t
            px, qx = _project(setpoints[e, 2 * n_gen + k], setpoints[e, 2 * n_gen + n_des + k], h_des, k, des_poly,
                              hp)
            pd[r], qd[r] = px, qx
            nxt = soc[e, k] - delta_t * eff * px if px <= 0 else soc[e, k] - delta_t * px / eff
            soc_next[e, k] = _clamp(nxt, dev[r, SOC_MIN], dev[r, SOC_MAX])
        # 4. bus injections and the AC power flow
        s_bus[:] = 0.0
        for r in range(pd.shape[0]):
            s_bus[dev_bus[r]] += complex(pd[r], qd[r])
        if dense:
            it, diff = _dense_newton_raphson(y, lu0, piv0, ok0, s_bus, tol, max_iter, vm, va, s, v, f, jac, piv)
        else:
            it, diff = _newton_raphson(ycsr, lu0, piv0, ok0, ix, kl, ku, parent, s_bus, tol, max_iter, vm, va, s, v,
                                       f, jac, piv)
        ok = diff == diff and diff <= tol
        converged[e], n_iter[e] = ok, it
        # 5. slack injection (+inf when NaN) and branch flows
        pd[slack] = np.inf if s[0].real != s[0].real else s[0].real
        qd[slack] = np.inf if s[0].imag != s[0].imag else s[0].imag
        viol = 0.0
        for i in range(v.shape[0]):
            a = abs(v[i])
            viol += _relu(a - v_max[i]) + _relu(v_min[i] - a)
        for b in range(f_bus.shape[0]):
            vf, vt = v[f_bus[b]], v[t_bus[b]]
            i_f = y_ff[b] * vf - y_ft[b] * vt  # π-model, as network.branch_flows
            i_t = y_tt[b] * vt - y_tf[b] * vf
            sf, st = vf * i_f.conjugate(), vt * i_t.conjugate()
            af, at = abs(sf), abs(st)
            big = af if (af > at or af != af) else at  # NaN-propagating max, as torch.maximum
            sgn = 1.0 if sf.real > 0 else (-1.0 if sf.real < 0 else (0.0 if sf.real == 0 else np.nan))
            s_max[e, b] = sgn * big
            viol += _relu(abs(s_max[e, b]) - rate[b])
        # 6. reward terms (curtailment of renewable generators only); a non-converged power flow is terminal
        cu = 0.0
        for k in range(n_gen):
            cu += _relu(p_pot[e, k] - pd[gid[k]]) * renewable[k]
        tot = 0.0
        for r in range(pd.shape[0]):
            tot += pd[r] * counted[r]
        el = delta_t * (tot + cu)
        pe = lamb * delta_t * viol
        curt[e], e_loss[e], pen[e] = cu, el, pe
        if ok:
            sg = 1.0 if el > 0 else (-1.0 if el < 0 else 0.0)
            reward[e] = -(sg * min(abs(el), c0) + min(max(pe, 0.0), c1))
        else:
            reward[e] = term_reward


@_njit()
def _transition(c, soc, p_load, p_pot_raw, setpoints, out):
    """The whole transition (spec §3.5 steps 4–7) of every env of a batch slice, written into ``out``.

    Inputs soc (N, n_des) p.u.·h, p_load (N, n_load) and p_pot_raw (N, n_gen) p.u. (unclipped exogenous
    values), setpoints (N, action_dim) p.u.; ``out`` a tuple of preallocated (N, ...) arrays in the order of
    :data:`OUTPUTS`. Called once per batch slice, never per env.
    """
    n_bus = c.y.shape[0]
    scratch = (np.empty(max(c.gen_poly[1].shape[1], c.des_poly[1].shape[1])),
               np.empty(c.gen_h0.shape[1]), np.empty(c.des_h0.shape[1]), np.empty(n_bus, dtype=np.complex128),
               np.empty(n_bus, dtype=np.complex128), np.empty(n_bus), np.empty(n_bus),
               np.empty(2 * n_bus - 2), np.zeros((2 * n_bus - 2, 2 * n_bus - 2)),
               np.empty(2 * n_bus - 2, dtype=np.int64))
    _env_steps(c, soc, p_load, p_pot_raw, setpoints, out, scratch)


def _on_disk_cache_present() -> bool:
    """Whether numba's on-disk cache holds an index for the transition kernel (False: the first call compiles)."""
    try:
        return os.path.exists(_transition._cache._cache_file._index_path)
    except AttributeError:  # another numba layout: say nothing about the cache, only time the first call
        return True


def _first_call(run) -> None:
    """Run the first transition of the process, saying what it does: loading the compiled kernels from numba's
    on-disk cache (about a second), or compiling them (about a minute on 2 cores, once per install)."""
    cold = not _on_disk_cache_present()
    if cold:
        log.warning("numba: compiling the transition kernels (first use of this install; about a minute on 2 cores, "
                    "cached on disk afterwards)")
    global _KERNEL_READY
    start = time.perf_counter()
    run()
    # a flag, not ``_transition.signatures``: that property re-hashes every argument type of the kernel's
    # signature (~0.1 ms a call, 40 % of a 16-env step)
    _KERNEL_READY = True
    log.info("numba: transition kernels %s in %.1f s", "compiled" if cold else "loaded", time.perf_counter() - start)


def _pool(threads: int) -> ThreadPoolExecutor:
    """This process's thread pool with ``threads`` workers (re-created after a fork or a thread-count change)."""
    pid = os.getpid()
    if pid not in _POOL or _POOL[pid][0] != threads:
        if pid in _POOL:
            _POOL[pid][1].shutdown(wait=False)
        _POOL[pid] = (threads, ThreadPoolExecutor(threads, thread_name_prefix="anm_torchrl-kernel"))
    return _POOL[pid][1]


def _polygon_arrays(polys, h0: torch.Tensor | None) -> tuple:
    """Stack the precomputed data of :class:`~anm_torchrl.grid.devices.Polygon` objects (padded to the largest
    number of distinct lines; the group index is padded with -1)."""
    m = max((p.g.shape[0] for p in polys), default=1)  # default: a network without such devices
    w = max((p.group_idx.shape[1] for p in polys), default=1)
    k = len(polys)
    out_m = np.array([p.g.shape[0] for p in polys], dtype=np.int64)
    grp = -np.ones((k, m, w), dtype=np.int64)
    g, d = np.zeros((k, m, 2)), np.zeros((k, m, 2))
    gn2, coup, inv = np.ones((k, m)), np.zeros((k, m, m)), np.zeros((k, m, m))
    kind = np.zeros((k, m, m), dtype=np.int64)
    for c, p in enumerate(polys):
        mc = p.g.shape[0]
        gi = p.group_idx.cpu().numpy()
        grp[c, :mc, : gi.shape[1]] = gi
        g[c, :mc], d[c, :mc], gn2[c, :mc] = p.g.cpu().numpy(), p.d.cpu().numpy(), p.gn2.cpu().numpy()
        coup[c, :mc, :mc], inv[c, :mc, :mc] = p.coupling.cpu().numpy(), p.inv_a.cpu().numpy()
        kind[c, :mc, :mc] = p.upper.cpu().numpy().astype(np.int64) - p.lower.cpu().numpy().astype(np.int64)
    h0 = np.zeros((0, 1)) if h0 is None else h0.cpu().numpy()
    return (out_m, grp, g, gn2, d, coup, kind, inv), np.ascontiguousarray(h0)


OUTPUTS = ("p_dev", "q_dev", "soc", "p_pot", "v", "s_apparent_max", "converged", "n_iter", "e_loss", "penalty",
           "curtailment", "reward")


class CompiledTransition:
    """The transition of a float64 CPU :class:`~anm_torchrl.grid.simulator.GridSimulator` as a numba kernel.

    Built from the simulator's :class:`~anm_torchrl.grid.constants.TransitionConstants` (one structure, the
    kernel unpacks it in one place). Call it like ``GridSimulator.apply`` (soc (N, n_des) p.u.·h, p_load
    (N, n_load), p_pot (N, n_gen) and setpoints (N, action_dim) p.u.); it returns the fields of a
    ``Transition`` as a dict of CPU tensors.
    """

    def __init__(self, constants):
        self.constants = constants
        c = constants
        self.sizes = (c.dev.shape[0], c.did.shape[0], c.gid.shape[0], c.y.shape[0], c.f_bus.shape[0])

    def __call__(self, soc: torch.Tensor, p_load: torch.Tensor, p_pot: torch.Tensor, setpoints: torch.Tensor
                 ) -> dict[str, torch.Tensor]:
        n = setpoints.shape[0]
        n_dev, n_des, n_gen, n_bus, n_br = self.sizes
        out = {"p_dev": np.empty((n, n_dev)), "q_dev": np.empty((n, n_dev)), "soc": np.empty((n, n_des)),
               "p_pot": np.empty((n, n_gen)), "v": np.empty((n, n_bus), dtype=np.complex128),
               "s_apparent_max": np.empty((n, n_br)), "converged": np.empty(n, dtype=np.bool_),
               "n_iter": np.empty(n, dtype=np.int64), "e_loss": np.empty(n), "penalty": np.empty(n),
               "curtailment": np.empty(n), "reward": np.empty(n)}
        arr = lambda x: np.ascontiguousarray(x.detach().cpu().numpy(), dtype=np.float64)  # noqa: E731
        inputs = tuple(arr(x) for x in (soc, p_load, p_pot, setpoints))
        outs = tuple(out[k] for k in OUTPUTS)
        c = self.constants

        def run(lo: int, hi: int) -> None:
            _transition(c, *(x[lo:hi] for x in inputs), tuple(o[lo:hi] for o in outs))

        threads = torch.get_num_threads()
        if not _KERNEL_READY:  # the process's first call: load or compile, and say which
            _first_call(lambda: run(0, n))
        elif threads > 1 and n >= PARALLEL_MIN_BATCH:
            # more slices than threads: a slice holding the rare 100-iteration envs does not hold up the rest
            bounds = np.linspace(0, n, SLICES_PER_THREAD * threads + 1).astype(int)
            for job in [_pool(threads).submit(run, lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:])]:
                job.result()
        else:
            run(0, n)
        return {k: torch.from_numpy(v) for k, v in out.items()}


class NumbaBackend:
    """The ``numba`` backend (see :mod:`anm_torchrl.grid.backends` for the contract): the compiled kernel above
    on the simulator's :class:`~anm_torchrl.grid.constants.TransitionConstants`, and one-pass compiled output
    assembly (:mod:`anm_torchrl.grid.fastoutput`), bit for bit what the torch ops would give."""

    name = "numba"

    def unusable(self, net) -> str | None:
        """Why this backend cannot run ``net`` (a :class:`~anm_torchrl.grid.network.Network`), or ``None``."""
        if not available():
            return "numba is not installed"
        if net.dev.device.type != "cpu" or net.dev.dtype != torch.float64:
            return f"it needs a float64 network on the CPU, got {net.dev.dtype} on {net.dev.device}"
        return None

    def bind(self, sim):
        """The transition function of ``sim`` (builds, once, its :class:`TransitionConstants`)."""
        kernel = CompiledTransition(sim.constants)
        return lambda soc, p_load, p_pot, setpoints: Transition(**kernel(soc, p_load, p_pot, setpoints))

    def build_state(self, tr, aux: torch.Tensor, base_mva: float) -> torch.Tensor:
        return fastoutput.build_state(tr, aux, base_mva)

    def output_bounds(self, low: torch.Tensor, high: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """``low``/``high`` (state_dim,) in the form :meth:`env_outputs` reads (contiguous float64 arrays)."""
        return tuple(np.ascontiguousarray(x.numpy(), dtype=np.float64) for x in (low, high))

    def env_outputs(self, state: torch.Tensor, tr, base_mva: float, bounds) -> dict[str, torch.Tensor]:
        return fastoutput.env_outputs(state, tr, base_mva, *(bounds or (None, None)))
