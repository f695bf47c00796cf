"""Device feasible sets as polygons ``G x <= h`` and their exact batched Euclidean projection.

A controllable device's set-point ``x = (P, Q)`` (p.u.) is mapped onto its feasible set by
``argmin ||x - target||^2 s.t. G x <= h`` (gym-anm solves this with cvxpy + OSQP on every call; spec §3.3).
Here ``G`` (m, 2) is constant per device and only ``h`` depends on the state (P_pot, SoC), so the
projection is computed exactly by enumerating candidates: the target, its projection onto every line and
every pairwise vertex; the closest feasible candidate is the projection (the QP is strictly convex in 2-D).
"""

from __future__ import annotations

import numpy as np
import torch

from anm_torchrl.grid.network import LOAD, SLACK, Network
from anm_torchrl.grid.residuals import constraint_slack

# Column indices of the device table (gym_anm/simulator/components/constants.py).
PMAX, PMIN, QMAX, QMIN, P_PLUS, P_MINUS, Q_PLUS, Q_MINUS, SOC_MAX, SOC_MIN, EFF = range(4, 15)

GEN_ROWS = 7
DES_ROWS = 10
GEN_PPOT_ROW = 2  # the row P <= P_pot of the generator set
DES_SOC_ROWS = (8, 9)  # the SoC rows of the storage set (charge, discharge)
_FEAS_TOL = 1e-10  # p.u. (|h| ≲ 500); candidates on a line carry ~1e-16 round-off


def _slopes(row: list[float]) -> tuple[float, ...]:
    """Capability-line slopes and offsets (tau1, rho1, tau2, rho2, tau3, rho3, tau4, rho4), spec §1.5.

    Corners that are not given (NaN) take gym-anm's defaults P+ = PMAX, P- = PMIN, Q+ = QMAX, Q- = QMIN,
    which make the corresponding lines flat (a plain box).
    """
    pmax, pmin, qmax, qmin = row[PMAX], row[PMIN], row[QMAX], row[QMIN]
    given = lambda v, default: default if v != v else v  # noqa: E731  (NaN -> default)
    pp, pm = given(row[P_PLUS], pmax), given(row[P_MINUS], pmin)
    qp, qm = given(row[Q_PLUS], qmax), given(row[Q_MINUS], qmin)
    if pmax == pp:
        t1 = t2 = 0.0
    else:
        t1 = (qp - qmax) / (pmax - pp)
        t2 = (qm - qmin) / (pmax - pp)
    r1, r2 = qmax - t1 * pp, qmin - t2 * pp
    if pmin == pm:  # no left corner
        t3 = t4 = 0.0
        r3, r4 = qmin, qmax
    else:
        t3 = (qmin - qm) / (pm - pmin)
        t4 = (qmax - qp) / (pm - pmin)
        r3, r4 = qmin - t3 * pm, qmax - t4 * pm
    return t1, r1, t2, r2, t3, r3, t4, r4


def generator_polygon(net: Network, dev_ids: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Constant part of the 7-row generator sets of ``dev_ids``.

    Returns ``G`` (n_gen, 7, 2) and ``h0`` (n_gen, 7); row 2 (P <= P_pot) of ``h0`` is +inf and is filled
    by :func:`generator_h`. Rows: -P<=-PMIN, P<=PMAX, P<=P_pot, -Q<=-QMIN, Q<=QMAX, Q-t1 P<=r1, t2 P-Q<=-r2.
    """
    gs, hs = [], []
    for d in dev_ids:
        row = net.dev[d].tolist()
        t1, r1, t2, r2, *_ = _slopes(row)
        gs.append([[-1, 0], [1, 0], [1, 0], [0, -1], [0, 1], [-t1, 1], [t2, -1]])
        hs.append([-row[PMIN], row[PMAX], float("inf"), -row[QMIN], row[QMAX], r1, -r2])
    kw = dict(dtype=net.dev.dtype, device=net.dev.device)
    return torch.tensor(gs, **kw).reshape(-1, GEN_ROWS, 2), torch.tensor(hs, **kw).reshape(-1, GEN_ROWS)


def generator_h(h0: torch.Tensor, p_pot: torch.Tensor) -> torch.Tensor:
    """Right-hand side (N, n_gen, 7) for potentials ``p_pot`` (N, n_gen) p.u. (already clipped)."""
    h = h0.expand(*p_pot.shape, GEN_ROWS).clone()
    h[..., GEN_PPOT_ROW] = p_pot
    return h


def storage_polygon(net: Network, dev_id: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Constant part of the 10-row storage set: ``G`` (10, 2), ``h0`` (10,) with the SoC rows 8, 9 = +inf.

    Rows: -P<=-PMIN, P<=PMAX, -Q<=-QMIN, Q<=QMAX, Q-t1 P<=r1, t2 P-Q<=-r2, t3 P-Q<=-r3, Q-t4 P<=r4,
    -P <= -(SoC-SOC_MAX)/(dt EFF), P <= EFF (SoC-SOC_MIN)/dt.
    """
    row = net.dev[dev_id].tolist()
    t1, r1, t2, r2, t3, r3, t4, r4 = _slopes(row)
    g = [[-1, 0], [1, 0], [0, -1], [0, 1], [-t1, 1], [t2, -1], [t3, -1], [-t4, 1], [-1, 0], [1, 0]]
    inf = float("inf")
    h = [-row[PMIN], row[PMAX], -row[QMIN], row[QMAX], r1, -r2, -r3, r4, inf, inf]
    kw = dict(dtype=net.dev.dtype, device=net.dev.device)
    return torch.tensor(g, **kw), torch.tensor(h, **kw)


def storage_h(net: Network, dev_id: int, h0: torch.Tensor, soc: torch.Tensor) -> torch.Tensor:
    """Right-hand side (N, 10) for the state of charge ``soc`` (N,) p.u.·h before the step."""
    row = net.dev[dev_id]
    dt, eff = net.delta_t, row[EFF]
    h = h0.expand(*soc.shape, DES_ROWS).clone()
    h[..., DES_SOC_ROWS[0]] = -(soc - row[SOC_MAX]) / (dt * eff)
    h[..., DES_SOC_ROWS[1]] = eff * (soc - row[SOC_MIN]) / dt
    return h


class Polygon:
    """A constant-normal polygon ``{x : G x <= h}`` (G fixed, h per call) with its exact batched projection.

    If the target is feasible it is its own projection; otherwise the projection lies on an edge, i.e. on the
    feasible segment of some constraint line. For line j, parametrised as p(t) = p0_j + t d_j (d_j ⊥ g_j), every
    other row i bounds t from above (g_i·d_j > 0), from below (< 0) or not at all (parallel: then it must simply
    hold on the line); the target projects onto the segment at clamp(t*_j, t_lo_j, t_hi_j). The closest of these
    m candidates is the exact answer — O(m²) work per point, with every sign pattern precomputed.

    Args:
        g: (m, 2) constraint normals.
    """

    def __init__(self, g: torch.Tensor):
        # Rows with the same normal (e.g. P <= PMAX and P <= P_pot) bound the same half-plane: keep the tightest.
        normals: list[tuple[float, float]] = []
        groups: list[list[int]] = []
        for r, row in enumerate(g.tolist()):
            if tuple(row) in normals:
                groups[normals.index(tuple(row))].append(r)
            else:
                normals.append(tuple(row))
                groups.append([r])
        width = max(len(grp) for grp in groups)
        self.group_idx = torch.tensor([grp + grp[:1] * (width - len(grp)) for grp in groups], device=g.device)
        self.g = gm = torch.tensor(normals, dtype=g.dtype, device=g.device)  # (m, 2)
        self.gn2 = (gm * gm).sum(-1)
        self.d = torch.stack([-gm[:, 1], gm[:, 0]], -1)  # line directions
        a = gm @ self.d.T  # a[i, j] = g_i · d_j
        self.coupling = (gm @ gm.T) / self.gn2  # b_ij = h_i - coupling_ij h_j = h_i - g_i · p0_j
        par = a.abs() <= 1e-12
        self.upper, self.lower, self.parallel = (a > 0) & ~par, (a < 0) & ~par, par
        self.inv_a = torch.where(par, torch.zeros_like(a), 1.0 / torch.where(par, torch.ones_like(a), a))

    def project(self, target: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """Closest point (..., 2) of the polygon with right-hand sides ``h`` (..., m) to ``target`` (..., 2)."""
        g, d = self.g, self.d
        h = h[..., self.group_idx].amin(-1)  # (..., m)
        inside = ((target @ g.T) <= h + _FEAS_TOL).all(-1, keepdim=True)
        b = h.unsqueeze(-1) - self.coupling * h.unsqueeze(-2)  # (..., i, j)
        ratio = b * self.inv_a
        inf = torch.tensor(float("inf"), dtype=h.dtype, device=h.device)
        t_hi = torch.where(self.upper, ratio, inf).amin(-2)  # (..., j)
        t_lo = torch.where(self.lower, ratio, -inf).amax(-2)
        ok = torch.where(self.parallel, b >= -_FEAS_TOL, True).all(-2) & (t_lo <= t_hi + _FEAS_TOL)
        ok = ok & torch.isfinite(h)  # a line at +inf (a bound given as None) never holds the projection
        t = torch.minimum(torch.maximum((target @ d.T) / self.gn2, t_lo), t_hi)  # (..., j)
        cand = (h / self.gn2).unsqueeze(-1) * g + t.unsqueeze(-1) * d  # p0_j + t_j d_j: (..., j, 2)
        diff = cand - target.unsqueeze(-2)
        dist = torch.where(ok, torch.einsum("...ck,...ck->...c", diff, diff), inf)
        best = dist.argmin(-1, keepdim=True)
        on_edge = torch.gather(cand, -2, best.unsqueeze(-1).expand(*best.shape, 2)).squeeze(-2)
        return torch.where(inside, target, on_edge)


def project(target: torch.Tensor, g: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """Exact Euclidean projection of ``target`` (..., 2) onto ``{x : g x <= h}``.

    Args:
        target: (..., 2) points to project.
        g: (m, 2) constraint normals, or (k, m, 2) for k devices with ``target`` (..., k, 2).
        h: (..., m) or (..., k, m) right-hand sides; the set must be non-empty (true for every gym-anm device).

    Returns:
        (..., 2) or (..., k, 2): the unique closest feasible point.
    """
    if g.ndim == 2:
        return Polygon(g).project(target, h)
    return torch.stack([Polygon(g[k]).project(target[..., k, :], h[..., k, :]) for k in range(g.shape[0])], -2)


def projection_duals(x_star: torch.Tensor, target: torch.Tensor, g: torch.Tensor, h: torch.Tensor,
                     active_tol: float = 1e-9) -> torch.Tensor:
    """Lagrange multipliers λ ≥ 0 (N, m) of ``min 1/2 ||x - target||^2 s.t. g x <= h`` at the solution ``x_star``.

    Solves ``g_Aᵀ λ_A = -(x_star - target)`` by non-negative least squares over the active rows ``A``
    (|g x - h| <= ``active_tol``); inactive rows get 0. NNLS rather than least-norm because active rows can be
    opposite (P >= 0 and P <= P_pot = 0), where a least-norm split gives λ < 0. A reference for tests and
    validation (a per-row loop over scipy), not for hot paths.

    Args:
        x_star, target: (..., 2).  g: (..., m, 2), broadcast against ``h``.  h: (..., m).
    """
    from scipy.optimize import nnls

    m = h.shape[-1]
    g = g.expand(*h.shape, 2).reshape(-1, m, 2)
    x_flat, t_flat, h_flat = x_star.reshape(-1, 2), target.reshape(-1, 2), h.reshape(-1, m)
    active = (constraint_slack(x_flat, g, h_flat).abs() <= active_tol).cpu().numpy()
    gn, rhs = g.detach().cpu().numpy(), (t_flat - x_flat).detach().cpu().numpy()
    lam = np.zeros(h_flat.shape, dtype=np.float64)
    for r in range(h_flat.shape[0]):
        rows = np.flatnonzero(active[r])
        if rows.size:
            lam[r, rows] = nnls(gn[r, rows].T, rhs[r])[0]
    return torch.as_tensor(lam, dtype=h.dtype, device=h.device).reshape(h.shape)


def bus_injection_box(net: Network) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-bus box of the injections the devices can produce: sums of the device bounds (spec §1.6).

    Loads: P ∈ [PMIN, PMAX], Q = (Q/P)·P; generators and storage: their P and Q ranges. The slack device is
    left out (its injection is an output of the power flow).

    Returns:
        ``p_low, p_high, q_low, q_high``, each (n_bus,) p.u. For ANM6-Easy (MW/MVAr): bus 3 P [−10, 30],
        Q [−32, 30]; bus 4 P [−30, 50], Q [−56, 50]; bus 5 P [−80, 50], Q [−56, 50]; buses 0–2: 0.
    """
    dev = net.dev
    kind = net.dev_type
    p_lo, p_hi = dev[:, PMIN].clone(), dev[:, PMAX].clone()
    qp = torch.nan_to_num(dev[:, 3])
    is_load = kind == LOAD
    q_a, q_b = qp * dev[:, PMIN], qp * dev[:, PMAX]
    q_lo = torch.where(is_load, torch.minimum(q_a, q_b), dev[:, QMIN])
    q_hi = torch.where(is_load, torch.maximum(q_a, q_b), dev[:, QMAX])
    other = kind != SLACK  # the slack's bounds may be ±inf (gym-anm's default): zeroed, never multiplied by 0
    p_lo, p_hi, q_lo, q_hi = (torch.where(other, x, torch.zeros_like(x)) for x in (p_lo, p_hi, q_lo, q_hi))
    keep = other.to(dev.dtype).unsqueeze(1) * net.incidence  # (n_dev, n_bus)
    return p_lo @ keep, p_hi @ keep, q_lo @ keep, q_hi @ keep
