"""The transition of :class:`~anm_torchrl.grid.simulator.GridSimulator` as one compiled CPU loop (numba).

The torch implementation spends its time in dispatch and in memory traffic: at batch 16,384 every one of
its ~400 small ops streams (N, 10, 10) tensors through memory. Here each env runs the same maths start to end
in registers and L1 — edge-clamp projections, SoC update, Newton–Raphson with a 10×10 LU, slack, branch flows,
reward — and ``prange`` spreads envs over ``torch.get_num_threads()`` threads. Same algorithms, same stopping
rule and order of operations as the torch code, so results agree to float64 round-off (tested against both
the torch backend and gym-anm).

Compiled on first use (cached on disk by numba); ``available()`` says whether numba can be used.
"""

from __future__ import annotations

import math

import numpy as np
import torch

try:
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; the torch backend is the fallback
    numba = None

from anm_torchrl.grid.devices import _FEAS_TOL, EFF, PMAX, PMIN, SOC_MAX, SOC_MIN


def available() -> bool:
    """True when numba is importable (the ``numba`` backend can be used)."""
    return numba is not None


def _njit(**kw):
    return numba.njit(cache=True, nogil=True, **kw) if numba is not None else (lambda f: f)


# --------------------------------------------------------------------------------------------- scalars
@_njit()
def _relu(x):
    return x if (x > 0.0 or x != x) else 0.0  # keeps NaN, as torch.relu


@_njit()
def _clamp(x, lo, hi):
    return min(max(x, lo), hi)


# ------------------------------------------------------------------------------------------ projection
@_njit()
def _project(tx, ty, h_raw, m, group, g, gn2, d, coup, kind, inv_a, out):
    """Edge-clamp projection of (tx, ty) onto {x : g x <= h}; ``kind`` 1 upper, -1 lower, 0 parallel.

    Mirrors :meth:`anm_torchrl.grid.devices.Polygon.project` for one point (writes ``out[0:2]``).
    """
    h = np.empty(m)
    inside = True
    for j in range(m):
        hj = np.inf
        for r in group[j]:
            if r >= 0 and h_raw[r] < hj:
                hj = h_raw[r]
        h[j] = hj
        if not (tx * g[j, 0] + ty * g[j, 1] <= hj + _FEAS_TOL):
            inside = False
    if inside:
        out[0], out[1] = tx, ty
        return
    best, bx, by = np.inf, 0.0, 0.0
    for j in range(m):
        t_hi, t_lo, ok = np.inf, -np.inf, True
        for i in range(m):
            b = h[i] - coup[i, j] * h[j]
            k = kind[i, j]
            if k == 0:
                if not (b >= -_FEAS_TOL):
                    ok = False
            else:
                ratio = b * inv_a[i, j]
                if k > 0:
                    t_hi = min(t_hi, ratio)
                else:
                    t_lo = max(t_lo, ratio)
        if not ok or not (t_lo <= t_hi + _FEAS_TOL):
            continue
        t = min(max((tx * d[j, 0] + ty * d[j, 1]) / gn2[j], t_lo), t_hi)
        cx = h[j] / gn2[j] * g[j, 0] + t * d[j, 0]
        cy = h[j] / gn2[j] * g[j, 1] + t * d[j, 1]
        dist = (cx - tx) * (cx - tx) + (cy - ty) * (cy - ty)
        if dist < best:
            best, bx, by = dist, cx, cy
    out[0], out[1] = bx, by


# ---------------------------------------------------------------------------------------- power flow
@_njit()
def _injection(vm, va, y, s):
    """S = V ⊙ conj(Y V) into ``s`` (n,) for magnitudes/angles (n,)."""
    n = vm.shape[0]
    v = np.empty(n, dtype=np.complex128)
    for i in range(n):
        v[i] = complex(vm[i] * math.cos(va[i]), vm[i] * math.sin(va[i]))
    for i in range(n):
        acc = 0j
        for k in range(n):
            acc += y[i, k] * v[k]
        s[i] = v[i] * acc.conjugate()
    return v


@_njit()
def _mismatch_inf(s, s_bus, f):
    n = s.shape[0]
    k = n - 1
    worst = 0.0
    for i in range(1, n):
        m = s[i] - s_bus[i]
        f[i - 1], f[k + i - 1] = m.real, m.imag
    for i in range(2 * k):
        a = abs(f[i])
        if a > worst or a != a:  # NaN sticks, as amax
            worst = a
            if a != a:
                break
    return worst


@_njit()
def _solve_in_place(a, b):
    """Gaussian elimination with partial pivoting: b <- a⁻¹ b; NaN when a pivot is exactly 0 (singular)."""
    n = b.shape[0]
    for c in range(n):
        p, pv = c, abs(a[c, c])
        for r in range(c + 1, n):
            if abs(a[r, c]) > pv:
                p, pv = r, abs(a[r, c])
        if pv == 0.0:
            for r in range(n):
                b[r] = np.nan
            return
        if p != c:
            for q in range(n):
                a[c, q], a[p, q] = a[p, q], a[c, q]
            b[c], b[p] = b[p], b[c]
        for r in range(c + 1, n):
            f = a[r, c] / a[c, c]
            if f != 0.0:
                for q in range(c + 1, n):
                    a[r, q] -= f * a[c, q]
                b[r] -= f * b[c]
    for c in range(n - 1, -1, -1):
        acc = b[c]
        for q in range(c + 1, n):
            acc -= a[c, q] * b[q]
        b[c] = acc / a[c, c]


@_njit()
def _newton_raphson(y, s_bus, tol, max_iter, vm, va, s):
    """Flat-start NR (spec §4.1) for one env; fills vm, va, s (n,). Returns (n_iter, ||F||_inf)."""
    n = s_bus.shape[0]
    k = n - 1
    for i in range(n):
        vm[i], va[i] = 1.0, 0.0
    f = np.empty(2 * k)
    jac = np.empty((2 * k, 2 * k))
    v = _injection(vm, va, y, s)
    diff = _mismatch_inf(s, s_bus, f)
    it = 0
    while diff > tol and it < max_iter:
        it += 1
        # polar Jacobian, as powerflow._jacobian: A_ik = V_i conj(Y_ik V_k)
        for i in range(k):
            vi = v[i + 1]
            for q in range(k):
                a = vi * (y[i + 1, q + 1] * v[q + 1]).conjugate()
                b = a / vm[q + 1]
                jac[i, q], jac[k + i, q] = a.imag, -a.real
                jac[i, k + q], jac[k + i, k + q] = b.real, b.imag
            sr, si = s[i + 1].real, s[i + 1].imag
            jac[i, i] -= si
            jac[k + i, k + i] += si / vm[i + 1]
            jac[i, k + i] += sr / vm[i + 1]
            jac[k + i, i] += sr
        _solve_in_place(jac, f)
        for i in range(k):
            va[i + 1] -= f[i]
            vm[i + 1] -= f[k + i]
        v = _injection(vm, va, y, s)
        diff = _mismatch_inf(s, s_bus, f)
    return it, diff


# ---------------------------------------------------------------------------------------- transition
@_njit(parallel=True)
def _transition(soc, t_index, setpoints,  # inputs (N, n_des), (N,), (N, action_dim)
                load_series, p_max_series, dev, lid, gid, did, slack, dev_bus, counted,
                gen_poly, des_poly, gen_h0, des_h0, gen_ppot_row, des_soc_rows,
                y, f_bus, t_bus, y_series, y_shunt, tap, rate, v_min, v_max,
                delta_t, lamb, c0, c1, term_reward, tol, max_iter,
                p_dev, q_dev, soc_next, p_pot, v_out, s_max, converged, n_iter, e_loss, pen, curt, reward):
    n_env = setpoints.shape[0]
    n_gen, n_des, n_load = gid.shape[0], did.shape[0], lid.shape[0]
    n_bus, n_br = y.shape[0], f_bus.shape[0]
    g_m, g_grp, g_g, g_gn2, g_d, g_coup, g_kind, g_inv = gen_poly
    d_m, d_grp, d_g, d_gn2, d_d, d_coup, d_kind, d_inv = des_poly
    for e in numba.prange(n_env):
        t = t_index[e]
        pd, qd = p_dev[e], q_dev[e]
        pd[:] = 0.0
        qd[:] = 0.0
        for c in range(n_load):  # 1. loads
            r = lid[c]
            p = _clamp(load_series[c, t], dev[r, PMIN], dev[r, PMAX])
            pd[r], qd[r] = p, p * dev[r, 3]
        xy = np.empty(2)
        for c in range(n_gen):  # 2. renewables: potential, projection
            r = gid[c]
            pp = _clamp(p_max_series[c, t], dev[r, PMIN], dev[r, PMAX])
            p_pot[e, c] = pp
            h = gen_h0[c].copy()
            h[gen_ppot_row] = pp
            _project(setpoints[e, c], setpoints[e, n_gen + c], h, g_m[c], g_grp[c], g_g[c], g_gn2[c], g_d[c],
                     g_coup[c], g_kind[c], g_inv[c], xy)
            pd[r], qd[r] = xy[0], xy[1]
        for c in range(n_des):  # 3. storage: SoC-dependent projection, SoC update
            r = did[c]
            eff = dev[r, EFF]
            h = des_h0[c].copy()
            h[des_soc_rows[0]] = -(soc[e, c] - dev[r, SOC_MAX]) / (delta_t * eff)
            h[des_soc_rows[1]] = eff * (soc[e, c] - dev[r, SOC_MIN]) / delta_t
            _project(setpoints[e, 2 * n_gen + c], setpoints[e, 2 * n_gen + n_des + c], h, d_m[c], d_grp[c],
                     d_g[c], d_gn2[c], d_d[c], d_coup[c], d_kind[c], d_inv[c], xy)
            pd[r], qd[r] = xy[0], xy[1]
            nxt = soc[e, c] - delta_t * eff * xy[0] if xy[0] <= 0 else soc[e, c] - delta_t * xy[0] / eff
            soc_next[e, c] = _clamp(nxt, dev[r, SOC_MIN], dev[r, SOC_MAX])
        # 4. bus injections and the AC power flow
        s_bus = np.zeros(n_bus, dtype=np.complex128)
        for r in range(pd.shape[0]):
            s_bus[dev_bus[r]] += complex(pd[r], qd[r])
        vm, va, s = np.empty(n_bus), np.empty(n_bus), np.empty(n_bus, dtype=np.complex128)
        it, diff = _newton_raphson(y, s_bus, tol, max_iter, vm, va, s)
        ok = diff == diff and diff <= tol
        converged[e], n_iter[e] = ok, it
        for i in range(n_bus):
            v_out[e, i] = complex(vm[i] * math.cos(va[i]), vm[i] * math.sin(va[i]))
        # 5. slack injection (+inf when NaN) and branch flows
        pd[slack] = np.inf if s[0].real != s[0].real else s[0].real
        qd[slack] = np.inf if s[0].imag != s[0].imag else s[0].imag
        viol = 0.0
        for i in range(n_bus):
            a = abs(v_out[e, i])
            viol += _relu(a - v_max[i]) + _relu(v_min[i] - a)
        for b in range(n_br):
            vf, vt, ys, ysh, tp = v_out[e, f_bus[b]], v_out[e, t_bus[b]], y_series[b], y_shunt[b], tap[b]
            i_f = (ys + ysh) * vf / (abs(tp) ** 2) - ys * vt / tp.conjugate()
            i_t = (ys + ysh) * vt - ys * vf / tp
            sf, st = vf * i_f.conjugate(), vt * i_t.conjugate()
            af, at = abs(sf), abs(st)
            big = af if (af > at or af != af) else at
            sgn = 1.0 if sf.real > 0 else (-1.0 if sf.real < 0 else (0.0 if sf.real == 0 else np.nan))
            s_max[e, b] = sgn * big
            viol += _relu(abs(s_max[e, b]) - rate[b])
        # 6. reward terms
        cu = 0.0
        for c in range(n_gen):
            cu += _relu(p_pot[e, c] - pd[gid[c]])
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


def _polygon_arrays(polys, h0: torch.Tensor) -> tuple:
    """Stack the precomputed data of :class:`~anm_torchrl.grid.devices.Polygon` objects (padded to the largest
    number of distinct lines; the group index is padded with -1)."""
    m = max(p.g.shape[0] for p in polys)
    w = max(p.group_idx.shape[1] for p in polys)
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
    return (out_m, grp, g, gn2, d, coup, kind, inv), np.ascontiguousarray(h0.cpu().numpy())


class CompiledTransition:
    """The transition of a float64 CPU :class:`~anm_torchrl.grid.simulator.GridSimulator` as a numba kernel.

    Call it like ``GridSimulator.transition`` (soc (N, n_des) p.u.·h, t_index (N,) long, setpoints
    (N, action_dim) p.u.); it returns the fields of a ``Transition`` as a dict of CPU tensors.
    """

    def __init__(self, sim, row_ppot: int, rows_soc: tuple[int, int]):
        net = sim.net
        if net.dev.device.type != "cpu" or net.dev.dtype != torch.float64:
            raise ValueError(f"the numba kernel needs a float64 CPU simulator, got {net.dev.dtype} on {net.dev.device}")
        npy = lambda x: np.ascontiguousarray(x.cpu().numpy())  # noqa: E731
        gen_poly, gen_h0 = _polygon_arrays(sim._gen_poly, sim.gen_h0)
        des_poly, des_h0 = _polygon_arrays(sim._des_poly, sim.des_h0)
        br = net.branches
        self.sim = sim  # its series are read on every call: experiments rescale them in place
        self.consts = (
            npy(net.dev), npy(sim._lid), npy(sim._gid), npy(sim._did),
            int(sim.slack_ids[0]), npy(net.dev_bus), npy(sim.counted), gen_poly, des_poly, gen_h0, des_h0,
            int(row_ppot), np.array(rows_soc, dtype=np.int64), npy(net.y_bus), npy(br.f_bus), npy(br.t_bus),
            npy(br.y_series), npy(br.y_shunt), npy(br.tap), npy(br.rate), npy(net.v_min), npy(net.v_max),
            float(net.delta_t), float(sim.lamb), float(sim.costs_clipping[0]), float(sim.costs_clipping[1]),
            float(sim.terminal_reward))
        self.sizes = (net.n_dev, sim.n_des, sim.n_gen, net.n_bus, br.f_bus.shape[0])

    def __call__(self, soc: torch.Tensor, t_index: torch.Tensor, setpoints: torch.Tensor, tol: float,
                 max_iter: int) -> dict[str, torch.Tensor]:
        n = setpoints.shape[0]
        n_dev, n_des, n_gen, n_bus, n_br = self.sizes
        out = {"p_dev": np.empty((n, n_dev)), "q_dev": np.empty((n, n_dev)), "soc": np.empty((n, n_des)),
               "p_pot": np.empty((n, n_gen)), "v": np.empty((n, n_bus), dtype=np.complex128),
               "s_apparent_max": np.empty((n, n_br)), "converged": np.empty(n, dtype=np.bool_),
               "n_iter": np.empty(n, dtype=np.int64), "e_loss": np.empty(n), "penalty": np.empty(n),
               "curtailment": np.empty(n), "reward": np.empty(n)}
        numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))
        arr = lambda x, dt: np.ascontiguousarray(x.detach().cpu().numpy(), dtype=dt)  # noqa: E731
        _transition(arr(soc, np.float64), arr(t_index, np.int64), arr(setpoints, np.float64),
                    arr(self.sim.load_series, np.float64), arr(self.sim.p_max_series, np.float64), *self.consts,
                    float(tol), int(max_iter), *out.values())
        return {k: torch.from_numpy(v) for k, v in out.items()}
