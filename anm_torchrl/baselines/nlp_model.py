"""gym-anm's control problem over N steps as one smooth NLP (CasADi + IPOPT): the AC model behind
:mod:`~anm_torchrl.baselines.optimal` (perfect foresight over the episode) and :mod:`~anm_torchrl.baselines.acmpc`.

Built from the simulator's network tables (``sim.net``, device ids, the polygons ``G x <= h`` of
:mod:`anm_torchrl.grid.devices`), so it holds for any network the simulator runs. Step k = 0 … N−1 applies
set-points at time index t_k with the loads and potentials of t_k (perfect foresight: the profiles; constant
forecast: the state's values) and earns gym-anm's reward (spec §4.3); its weight is γ^k. Per step, in p.u.:

* variables: non-slack bus voltages (``"polar"``: angle, magnitude; ``"rectangular"``: real, imaginary part),
  generator (P, Q), storage Q, charge / discharge powers p_ch, p_dis ≥ 0 (storage P = p_dis − p_ch), the SoC
  after the step, and the slack variables of the penalty: over- / under-voltage per non-slack bus and branch
  overload per rated branch;
* AC power balance at every non-slack bus (the slack device takes the rest at bus 0);
* every device's polygon row — generator rows with P_pot(t_k), storage rows with the SoC before the step — so
  gym-anm's projection of the set-points is the identity;
* SoC_{k+1} = SoC_k + Δt (EFF p_ch − p_dis / EFF) within [SOC_MIN, SOC_MAX];
* |V_i| − u_i ≤ V_max,i, V_min,i − |V_i| ≤ l_i and |S_from|², |S_to|² ≤ (rate + o)² with u, l, o ≥ 0;
* cost per step ΔE + λΦ with ΔE = Δt (Σ_{slack, loads, generators} P + Σ_{g renewable} (P_pot − P_g)) (classical
  generators are not curtailed, gym-anm) and
  λΦ = λ Δt (Σ (u + l) + Σ o), objective Σ_k γ^k (ΔE_k + λΦ_k) (minimised; the return is its negative).

Splitting storage P into p_ch, p_dis is exact when at most one of them is non-zero per step (a step that charges
and discharges at once wastes energy the real SoC update would keep); :meth:`ACHorizonNLP.solve` takes a
``direction`` per step that pins the other one to 0 — the smooth form of gym-anm's piecewise SoC update.

The reward's clipping (ΔE at ±1, λΦ at 100) is not in the NLP: :func:`evaluate_operating_points` reports whether
it is active on a solution (it never was on the ones we solved; where inactive, a local optimum of the smooth
problem is one of the clipped problem too, since both objectives agree on a neighbourhood).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
import math
import time

import numpy as np
import torch

from anm_torchrl._extras import require
from anm_torchrl.envs.specs import check_integer
from anm_torchrl.grid import devices as dv
from anm_torchrl.grid.network import CLASSICAL_GEN, LOAD, RENEWABLE, SLACK, STORAGE, branch_flows
from anm_torchrl.grid.residuals import power_injection
from anm_torchrl.grid.reward import clipped_reward, curtailment, energy_loss, penalty
from anm_torchrl.grid.simulator import GridSimulator

log = logging.getLogger(__name__)

FORMULATIONS = ("polar", "rectangular")
# IPOPT settings: tight tolerances (replay agreement to 1e-6 needs constraint residuals ≪ 1e-6), no bound
# relaxation (set-points must lie inside the polygons, not 1e-8 outside), banner off (no prints in the package).
IPOPT_OPTIONS = {
    "tol": 1e-9,
    "constr_viol_tol": 1e-10,
    "acceptable_tol": 1e-7,
    "acceptable_constr_viol_tol": 1e-9,
    "bound_relax_factor": 0.0,
    "max_iter": 3000,
    "linear_solver": "mumps",
    "print_level": 0,
    "sb": "yes",
}
# Upper bound (p.u.) of the penalty's slack variables. Late steps of a 3,000-step horizon weigh γ^k ≈ 3e-7, so
# their slacks cost less than IPOPT's barrier parameter μ; unbounded, the barrier pushes them to ≈ μ / weight
# (thousands of p.u.) and IPOPT crawls back over hundreds of iterations. A violation of 1 p.u. costs λΔt = 25 a
# step (the optimum's are < 0.04 p.u.), and a solution with a slack at this bound is refused (``slack_at_bound``).
SLACK_MAX = 1.0
# Horizons up to this are expanded to one SX graph (function evaluations ~10x faster, build time growing with N:
# seconds at 256 steps, minutes at 3,000); longer ones keep the mapped stage function.
EXPAND_MAX = 256
# Warm-start settings used when a primal guess is given (interior-point methods need the guess kept close to
# its bounds, not pushed 1 % into the interior).
WARM_OPTIONS = {"warm_start_init_point": "yes", "warm_start_bound_push": 1e-9, "warm_start_bound_frac": 1e-9,
                "warm_start_slack_bound_push": 1e-9, "warm_start_slack_bound_frac": 1e-9,
                "warm_start_mult_bound_push": 1e-9, "mu_init": 1e-4}
_DIRECTIONS = (-1, 0, 1)  # storage direction per step: charge only, free (relaxed split), discharge only


def check_ipopt_options(options: dict) -> None:
    """A ``ValueError`` naming the first IPOPT option in ``options`` that IPOPT does not know or whose value has the
    wrong type, found now on a one-variable problem rather than at the first solve (the horizon's solver is built
    there, after seconds of setup)."""
    ca = require("casadi")
    x = ca.SX.sym("x")
    try:
        ca.nlpsol("ipopt_options", "ipopt", {"x": x, "f": x * x}, {"print_time": False, "ipopt": dict(options)})
    except RuntimeError as err:
        reason = str(err).strip().splitlines()[-1].split(": ", 1)[-1]
        raise ValueError(f"ipopt options {dict(options)!r}: {reason}") from None


@dataclasses.dataclass
class OperatingPoints:
    """Device injections, voltages and SoC of N steps, with gym-anm's reward terms there.

    Attributes:
        p_dev, q_dev: (N, n_dev) p.u., slack from the voltages.  v: (N, n_bus) complex p.u.
        soc: (N + 1, n_des) p.u.·h, row 0 before the first step.  p_pot: (N, n_gen) p.u.
        e_loss, penalty, reward: (N,) gym-anm's ΔE (p.u.·h), λΦ and clipped reward.
        clip_active: (N,) bool, steps where |ΔE| > c0 or λΦ > c1 (the reward's clip binds).
    """

    p_dev: np.ndarray
    q_dev: np.ndarray
    v: np.ndarray
    soc: np.ndarray
    p_pot: np.ndarray
    e_loss: np.ndarray
    penalty: np.ndarray
    reward: np.ndarray
    clip_active: np.ndarray


@dataclasses.dataclass
class PowerFlowOffsets:
    """The simulator's power-flow error at given injections: its Newton iterate minus the exact solution.

    gym-anm's Newton–Raphson stops at ||F||_inf <= 1e-5 (spec §4.1), so the env's |V|, branch |S| and slack P
    differ from the exact power flow by up to ~1e-5 p.u. At the optimum many penalty terms sit exactly on their
    kink (a branch at its rating), where such an error costs λΔt·1e-5 per step; the NLP therefore carries these
    offsets, measured by replaying its set-points, to model the env rather than the exact physics.

    Attributes: (N,) ``p_slack``, (N, n_bus) ``v_magn``, (N, n_branch) ``s_from``, ``s_to`` (magnitudes), p.u.
    """

    p_slack: np.ndarray
    v_magn: np.ndarray
    s_from: np.ndarray
    s_to: np.ndarray

    @staticmethod
    def zeros(sim: GridSimulator, n: int) -> "PowerFlowOffsets":
        """No offsets (the exact power flow) for n steps."""
        nbr = int(sim.net.branches.rate.shape[0])
        return PowerFlowOffsets(np.zeros(n), np.zeros((n, sim.net.n_bus)), np.zeros((n, nbr)), np.zeros((n, nbr)))

    @staticmethod
    def measure(sim: GridSimulator, v_sim: np.ndarray, v_exact: np.ndarray) -> "PowerFlowOffsets":
        """Offsets between the simulator's voltages ``v_sim`` and the exact ``v_exact``, both (N, n_bus) complex."""
        a, b = _flows(sim, v_sim), _flows(sim, v_exact)
        return PowerFlowOffsets(**{k: a[k] - b[k] for k in a})


def _flows(sim: GridSimulator, v: np.ndarray) -> dict[str, np.ndarray]:
    """Bus-0 injection P, |V| and branch |S_from|, |S_to| (p.u.) of voltages (N, n_bus) complex."""
    vt = torch.as_tensor(v, dtype=torch.complex128)
    fl = branch_flows(vt, sim.net.branches)
    return {"p_slack": power_injection(vt, sim.net.y_bus.cpu())[:, 0].real.numpy(), "v_magn": vt.abs().numpy(),
            "s_from": fl["s_from"].abs().numpy(), "s_to": fl["s_to"].abs().numpy()}


def evaluate_operating_points(sim: GridSimulator, p_dev: np.ndarray, q_dev: np.ndarray, v: np.ndarray,
                              soc: np.ndarray, p_pot: np.ndarray,
                              offsets: PowerFlowOffsets | None = None) -> OperatingPoints:
    """gym-anm's reward terms (spec §4.3) at given operating points, with the slack injection taken from ``v``.

    Args:
        p_dev, q_dev: (N, n_dev) p.u. (the slack columns are overwritten from the voltages).
        v: (N, n_bus) complex p.u.  soc: (N + 1, n_des) p.u.·h.  p_pot: (N, n_gen) p.u.
        offsets: the simulator's power-flow error added to slack P, |V| and branch |S| (default none).
    """
    net = sim.net
    off = PowerFlowOffsets.zeros(sim, len(v)) if offsets is None else offsets
    vt = torch.as_tensor(v, dtype=torch.complex128)
    s = power_injection(vt, net.y_bus.cpu())
    p_dev, q_dev = np.array(p_dev, dtype=np.float64), np.array(q_dev, dtype=np.float64)
    slack = sim.slack_ids[0]
    others = [d for d in range(net.n_dev) if d != slack and int(net.dev_bus[d]) == 0]
    p_dev[:, slack] = s[:, 0].real.numpy() + off.p_slack - p_dev[:, others].sum(1)
    q_dev[:, slack] = s[:, 0].imag.numpy() - q_dev[:, others].sum(1)
    pd, pp = torch.as_tensor(p_dev), torch.as_tensor(p_pot, dtype=torch.float64)
    curt = curtailment(pp, pd[:, sim.gen_ids], sim.renewable.cpu())
    e = energy_loss(pd, sim.counted.cpu(), curt, net.delta_t)
    fl = _flows(sim, v)
    s_max = np.maximum(fl["s_from"] + off.s_from, fl["s_to"] + off.s_to)
    pen = penalty(torch.as_tensor(fl["v_magn"] + off.v_magn), torch.as_tensor(s_max), net, sim.lamb)
    clip = sim.costs_clipping
    r = clipped_reward(e, pen, clip)
    active = (e.abs() > clip[0]) | (pen > clip[1])
    return OperatingPoints(p_dev=p_dev, q_dev=q_dev, v=np.asarray(v), soc=np.asarray(soc), p_pot=np.asarray(p_pot),
                           e_loss=e.numpy(), penalty=pen.numpy(), reward=r.numpy(), clip_active=active.numpy())


@dataclasses.dataclass
class NLPResult:
    """One IPOPT solve of :class:`ACHorizonNLP`.

    Attributes:
        setpoints: (N, action_dim) MW/MVAr, action order (P gen, Q gen, P storage, Q storage).
        points: the :class:`OperatingPoints` of the solution (exact reward terms at the NLP's voltages).
        discounted_return: Σ_k γ^k r_k of ``points.reward``.
        objective: IPOPT's objective (≥ −discounted_return: the penalty's slack variables may sit above
            max(0, ·) by barrier round-off, most at late, heavily discounted steps).
        status: IPOPT's return status.  success: IPOPT's success flag.  iterations: IPOPT iterations.
        inf_pr, inf_du: IPOPT's final primal and dual infeasibility (unscaled max-norms), the KKT residual.
        complementarity: max_k min(p_ch, p_dis) p.u. (0 when the split is exact).
        slack_at_bound: whether a penalty slack sits at :data:`SLACK_MAX` (the bound would then be active).
        solve_time: s (wall, IPOPT and function evaluations).
        x, lam_x, lam_g: raw primal and dual vectors (for warm starts).
    """

    setpoints: np.ndarray
    points: OperatingPoints
    discounted_return: float
    objective: float
    status: str
    success: bool
    iterations: int
    inf_pr: float
    inf_du: float
    complementarity: float
    slack_at_bound: bool
    solve_time: float
    x: np.ndarray
    lam_x: np.ndarray
    lam_g: np.ndarray

    def summary(self) -> dict:
        """JSON-ready scalars of the solve."""
        return {"status": self.status, "success": self.success, "iterations": self.iterations,
                "inf_pr": self.inf_pr, "inf_du": self.inf_du, "complementarity": self.complementarity,
                "slack_at_bound": self.slack_at_bound,
                "objective": self.objective, "discounted_return": self.discounted_return,
                "solve_time_s": self.solve_time, "clip_active_steps": int(self.points.clip_active.sum()),
                "max_penalty": float(self.points.penalty.max()),
                "max_abs_e_loss": float(np.abs(self.points.e_loss).max())}


class ACHorizonNLP:
    """The N-step AC optimal-control NLP of a simulator's network, built once, solved for any start.

    Args:
        sim: the :class:`GridSimulator` (network tables, series, λ, clipping).
        horizon: number of steps N.
        gamma: discount of the step costs.
        formulation: ``"polar"`` or ``"rectangular"`` bus voltages.
        ipopt: overrides of :data:`IPOPT_OPTIONS`.
    """

    def __init__(self, sim: GridSimulator, horizon: int, gamma: float, formulation: str = "polar",
                 ipopt: dict | None = None):
        if formulation not in FORMULATIONS:
            raise ValueError(f"formulation must be one of {FORMULATIONS}, got {formulation!r}")
        check_integer("horizon", horizon, low=1)
        if not 0.0 < float(gamma) <= 1.0:
            raise ValueError(f"gamma must lie in (0, 1], got {gamma}")
        kinds = set(sim.net.dev_type.tolist())
        if not kinds <= {SLACK, LOAD, CLASSICAL_GEN, RENEWABLE, STORAGE}:
            raise ValueError(f"device types {sorted(kinds - {SLACK, LOAD, CLASSICAL_GEN, RENEWABLE, STORAGE})} are "
                             "not modelled (the simulator has slack, load, classical and renewable generator and "
                             "storage devices)")
        self.sim, self.horizon, self.gamma, self.formulation = sim, int(horizon), float(gamma), formulation
        unknown = set(ipopt or {}) - set(IPOPT_OPTIONS) - set(WARM_OPTIONS)
        if unknown:
            log.info("passing extra IPOPT options %s", sorted(unknown))
        self.ipopt = {**IPOPT_OPTIONS, **(ipopt or {})}
        check_ipopt_options(self.ipopt)
        self._tables()
        self._build()
        self._solvers: dict[bool, object] = {}

    # ------------------------------------------------------------------------------------------ tables
    def _tables(self) -> None:
        sim, net = self.sim, self.sim.net
        self.nb, self.ng, self.nd, self.nl = net.n_bus, sim.n_gen, sim.n_des, len(sim.load_ids)
        dev = net.dev.cpu().numpy()
        self._dev = dev
        self._y = net.y_bus.cpu().numpy()
        br = net.branches
        y, ysh, tap = (br.y_series.cpu().numpy(), br.y_shunt.cpu().numpy(), br.tap.cpu().numpy())
        # I_from = a_ff V_f + a_ft V_t,  I_to = a_tt V_t + a_tf V_f  (π-model, tap on the from side)
        self._br = dict(f=br.f_bus.cpu().numpy(), t=br.t_bus.cpu().numpy(), a_ff=(y + ysh) / np.abs(tap) ** 2,
                        a_ft=-y / tap.conj(), a_tt=y + ysh, a_tf=-y / tap)
        rate = br.rate.cpu().numpy()
        self._rated = np.flatnonzero(np.isfinite(rate))
        self._rate = rate[self._rated]
        self.nr = self._rated.size
        self._vmin, self._vmax = net.v_min.cpu().numpy(), net.v_max.cpu().numpy()
        # |V_0| = 1 (slack): its penalty is a constant
        self._bus0_pen = max(0.0, 1.0 - self._vmax[0]) + max(0.0, self._vmin[0] - 1.0)
        self._dev_bus = net.dev_bus.cpu().numpy()
        des = sim.des_ids
        self._eff = dev[des, dv.EFF]
        self._soc_lim = (dev[des, dv.SOC_MIN], dev[des, dv.SOC_MAX])
        # storage polygon rows: h(soc) = h_a + h_b soc (rows 8, 9 depend on the SoC before the step)
        h0 = sim.storage_h(torch.zeros(1, self.nd, dtype=torch.float64))[0].cpu().numpy()  # (nd, 10)
        h1 = sim.storage_h(torch.ones(1, self.nd, dtype=torch.float64))[0].cpu().numpy()
        self._des_g = sim.des_g.cpu().numpy() if self.nd else np.zeros((0, dv.DES_ROWS, 2))
        self._des_ha, self._des_hb = h0, h1 - h0
        self._gen_g = self.sim.gen_g.cpu().numpy()  # (ng, 7, 2)
        # generator rows in P only / Q only become variable bounds, the sloped ones linear constraints
        self._gen_sloped = [np.flatnonzero((g[:, 0] != 0) & (g[:, 1] != 0)) for g in self._gen_g]
        self._des_rows = [np.flatnonzero(np.isfinite(h0[k]) & ~((g[:, 0] == 0) & (self._des_hb[k] == 0)))
                          for k, g in enumerate(self._des_g)]  # every row touching P or the SoC
        self._q_over_p = dev[sim.load_ids, 3]
        self._renewable = sim.renewable.cpu().numpy()  # (ng,) 1 renewable, 0 classical (no curtailment term)

    # ------------------------------------------------------------------------------------------ layout
    def _layout(self) -> dict[str, slice]:
        nb1, ng, nd = self.nb - 1, self.ng, self.nd
        sizes = [("v1", nb1), ("v2", nb1), ("pg", ng), ("qg", ng), ("qd", nd), ("pch", nd), ("pdis", nd),
                 ("soc", nd), ("vu", nb1), ("vl", nb1), ("ob", self.nr)]
        out, o = {}, 0
        for name, n in sizes:
            out[name] = slice(o, o + n)
            o += n
        return out

    def _voltages(self, xk):
        """(e, f) real and imaginary parts of all bus voltages (slack 1∠0) and |V| of the non-slack buses."""
        ca = require("casadi")

        v1, v2 = xk[self.lay["v1"]], xk[self.lay["v2"]]
        if self.formulation == "polar":
            e, f, vm = v2 * ca.cos(v1), v2 * ca.sin(v1), v2
        else:
            e, f = v1, v2
            vm = ca.sqrt(e ** 2 + f ** 2)
        return ca.vertcat(1.0, e), ca.vertcat(0.0, f), vm

    def _stage(self):
        """CasADi function (x_k, soc_before, exo_k) -> (constraints g_k, cost c_k) of one step.

        ``exo_k`` = [load P (n_load), |V| offsets (n_bus − 1), |S_from|, |S_to| offsets (n_rated each)].
        """
        ca = require("casadi")

        lay, sim = self.lay, self.sim
        nx = lay["ob"].stop
        xk = ca.SX.sym("x", nx)
        soc_prev = ca.SX.sym("soc_prev", self.nd)
        exo = ca.SX.sym("exo", self.n_exo)
        p_load = exo[:self.nl]
        d_vm = exo[self.nl:self.nl + self.nb - 1]
        d_s = exo[self.nl + self.nb - 1:]  # (2 n_rated): from, to
        e, f, vm = self._voltages(xk)
        gy, by = self._y.real, self._y.imag
        i_re = ca.mtimes(ca.DM(gy), e) - ca.mtimes(ca.DM(by), f)
        i_im = ca.mtimes(ca.DM(gy), f) + ca.mtimes(ca.DM(by), e)
        p_inj, q_inj = e * i_re + f * i_im, f * i_re - e * i_im
        # device injections (the slack's is what bus 0 needs)
        pg, qg, qd = xk[lay["pg"]], xk[lay["qg"]], xk[lay["qd"]]
        pch, pdis = xk[lay["pch"]], xk[lay["pdis"]]
        pdes = pdis - pch
        p_bus, q_bus = [ca.SX(0) for _ in range(self.nb)], [ca.SX(0) for _ in range(self.nb)]
        p_dev = {}
        for ids, p, q in ((sim.gen_ids, pg, qg), (sim.des_ids, pdes, qd), (sim.load_ids, p_load,
                                                                            p_load * ca.DM(self._q_over_p))):
            for k, d in enumerate(ids):
                b = int(self._dev_bus[d])
                p_bus[b], q_bus[b] = p_bus[b] + p[k], q_bus[b] + q[k]
                p_dev[d] = p[k]
        balance = [p_inj[i] - p_bus[i] for i in range(1, self.nb)] + [q_inj[i] - q_bus[i] for i in range(1, self.nb)]
        p_slack = p_inj[0] - p_bus[0]
        # polygons: sloped generator rows, storage rows touching P or the SoC
        poly = []
        for k in range(self.ng):
            g = self._gen_g[k]
            poly += [g[r, 0] * pg[k] + g[r, 1] * qg[k] for r in self._gen_sloped[k]]
        for k in range(self.nd):
            g, hb = self._des_g[k], self._des_hb[k]
            poly += [g[r, 0] * pdes[k] + g[r, 1] * qd[k] - hb[r] * soc_prev[k] for r in self._des_rows[k]]
        dt = self.sim.net.delta_t
        soc = xk[lay["soc"]]
        chain = [soc[k] - soc_prev[k] - dt * (self._eff[k] * pch[k] - pdis[k] / self._eff[k]) for k in range(self.nd)]
        vu, vl, ob = xk[lay["vu"]], xk[lay["vl"]], xk[lay["ob"]]
        volt = [vm + d_vm - vu, -vm - d_vm - vl]  # ≤ V_max, ≤ −V_min
        br = self._br
        flows = []
        for j, b in enumerate(self._rated):
            fb, tb = int(br["f"][b]), int(br["t"][b])
            for side, (a_self, a_other, s_bus, o_bus) in enumerate(((br["a_ff"][b], br["a_ft"][b], fb, tb),
                                                                    (br["a_tt"][b], br["a_tf"][b], tb, fb))):
                ir = a_self.real * e[s_bus] - a_self.imag * f[s_bus] + a_other.real * e[o_bus] - a_other.imag * f[o_bus]
                ii = a_self.real * f[s_bus] + a_self.imag * e[s_bus] + a_other.real * f[o_bus] + a_other.imag * e[o_bus]
                ps, qs = e[s_bus] * ir + f[s_bus] * ii, f[s_bus] * ir - e[s_bus] * ii
                flows.append(ps ** 2 + qs ** 2 - (self._rate[j] + ob[j] - d_s[side * self.nr + j]) ** 2)
        g_k = ca.vertcat(*balance, *poly, *chain, *volt, *flows)
        # ΔE = Δt (P_slack + Σ loads + Σ_g P_g + Σ_{g renewable} (P_pot − P_g)): a renewable's P_g cancels and
        # Δt Σ P_pot is a constant added to the objective in ``solve``; a classical generator's P_g stays
        counted = sum(p_dev[d] for d in sim.load_ids) + p_slack + ca.dot(ca.DM(1.0 - self._renewable), pg)
        cost = dt * counted + self.sim.lamb * dt * (ca.sum1(vu) + ca.sum1(vl) + ca.sum1(ob) + self._bus0_pen)
        self._n_bal, self._n_poly, self._n_chain = len(balance), len(poly), len(chain)
        self._n_volt, self._n_flow = 2 * (self.nb - 1), len(flows)
        return ca.Function("stage", [xk, soc_prev, exo], [g_k, cost])

    def _build(self) -> None:
        ca = require("casadi")

        self.lay = self._layout()
        self.nx = self.lay["ob"].stop
        self.n_exo = self.nl + self.nb - 1 + 2 * self.nr
        stage = self._stage()
        self.ncon = stage.size1_out(0)
        n = self.horizon
        # MX over the mapped SX stage: CasADi differentiates the stage once and maps its derivatives, so the
        # build time does not grow with N (an SX graph of the whole horizon takes minutes at N = 3,000).
        x = ca.MX.sym("x", self.nx, n)
        soc0 = ca.MX.sym("soc0", self.nd)
        exo = ca.MX.sym("exo", self.n_exo, n)
        soc = x[self.lay["soc"], :]
        soc_prev = ca.horzcat(soc0, soc[:, :n - 1]) if n > 1 else soc0
        g, c = stage.map(n)(x, soc_prev, exo)
        self._weights = self.gamma ** np.arange(n)
        self._nlp = {"x": ca.vec(x), "p": ca.vertcat(soc0, ca.vec(exo)), "f": ca.mtimes(c, ca.DM(self._weights)),
                     "g": ca.vec(g)}
        self.n_var, self.n_con = self.nx * n, self.ncon * n

    def _solver(self, warm: bool):
        ca = require("casadi")

        if warm not in self._solvers:
            opts = {**self.ipopt, **(WARM_OPTIONS if warm else {})}
            self._solvers[warm] = ca.nlpsol("ac_horizon", "ipopt", self._nlp,
                                            {"print_time": False, "expand": self.horizon <= EXPAND_MAX, "ipopt": opts})
        return self._solvers[warm]

    # ------------------------------------------------------------------------------------------ data
    def bounds(self, soc0: np.ndarray, p_load: np.ndarray, p_pot: np.ndarray,
               direction: np.ndarray | None = None, offsets: PowerFlowOffsets | None = None) -> dict[str, np.ndarray]:
        """Numeric bounds and parameters of one solve.

        Args:
            soc0: (n_des,) p.u.·h before step 0.  p_load: (N, n_load) p.u.  p_pot: (N, n_gen) p.u. (clipped).
            direction: (N, n_des) in {−1, 0, 1}: charge only, free, discharge only (default all 0).
            offsets: the simulator's power-flow error (default none: the exact power flow).
        """
        n, lay, dev, sim = self.horizon, self.lay, self._dev, self.sim
        if p_load.shape != (n, self.nl) or p_pot.shape != (n, self.ng):
            raise ValueError(f"p_load and p_pot must have shapes ({n}, {self.nl}) and ({n}, {self.ng}), "
                             f"got {p_load.shape} and {p_pot.shape}")
        lbx, ubx = np.full((n, self.nx), -np.inf), np.full((n, self.nx), np.inf)
        if self.formulation == "polar":
            lbx[:, lay["v1"]], ubx[:, lay["v1"]] = -math.pi, math.pi
            lbx[:, lay["v2"]] = 0.0
        for name in ("vu", "vl", "ob", "pch", "pdis"):
            lbx[:, lay[name]] = 0.0
        for name in ("vu", "vl", "ob"):
            ubx[:, lay[name]] = SLACK_MAX
        des = sim.des_ids
        ubx[:, lay["pch"]], ubx[:, lay["pdis"]] = -dev[des, dv.PMIN], dev[des, dv.PMAX]
        if direction is not None:
            direction = np.asarray(direction)
            if direction.shape != (n, self.nd) or not np.isin(direction, _DIRECTIONS).all():
                raise ValueError(f"direction must be ({n}, {self.nd}) in {_DIRECTIONS}, got {direction.shape}")
            ubx[:, lay["pch"]] = np.where(direction > 0, 0.0, ubx[:, lay["pch"]])
            ubx[:, lay["pdis"]] = np.where(direction < 0, 0.0, ubx[:, lay["pdis"]])
        lbx[:, lay["soc"]], ubx[:, lay["soc"]] = self._soc_lim
        # generator box rows (P or Q only) with P_pot, storage Q-only rows
        h = sim.generator_h(torch.as_tensor(p_pot)).cpu().numpy()  # (N, ng, 7)
        sloped = []
        for k in range(self.ng):
            g = self._gen_g[k]
            for r in range(g.shape[0]):
                if g[r, 1] == 0:
                    j, col = 0, lay["pg"].start + k
                elif g[r, 0] == 0:
                    j, col = 1, lay["qg"].start + k
                else:
                    continue
                if g[r, j] > 0:
                    ubx[:, col] = np.minimum(ubx[:, col], h[:, k, r] / g[r, j])
                else:
                    lbx[:, col] = np.maximum(lbx[:, col], h[:, k, r] / g[r, j])
            sloped.append(h[:, k, self._gen_sloped[k]])
        for k in range(self.nd):
            g, ha = self._des_g[k], self._des_ha[k]
            col = lay["qd"].start + k
            for r in np.setdiff1d(np.flatnonzero(np.isfinite(ha)), self._des_rows[k]):
                if g[r, 1] > 0:
                    ubx[:, col] = np.minimum(ubx[:, col], ha[r] / g[r, 1])
                else:
                    lbx[:, col] = np.maximum(lbx[:, col], ha[r] / g[r, 1])
        # constraints: balance = 0, polygon rows ≤ h, chain = 0, voltage ≤ (V_max, −V_min), flows ≤ 0
        lbg, ubg = np.full((n, self.ncon), -np.inf), np.zeros((n, self.ncon))
        o = 0
        lbg[:, :self._n_bal] = 0.0
        o += self._n_bal
        rows = sloped + [np.broadcast_to(self._des_ha[k][self._des_rows[k]], (n, self._des_rows[k].size))
                         for k in range(self.nd)]
        poly = np.concatenate(rows, 1) if rows else np.zeros((n, 0))
        ubg[:, o:o + self._n_poly] = poly
        o += self._n_poly
        lbg[:, o:o + self._n_chain] = 0.0
        o += self._n_chain
        ubg[:, o:o + self._n_volt] = np.concatenate([self._vmax[1:], -self._vmin[1:]])
        off = PowerFlowOffsets.zeros(sim, n) if offsets is None else offsets
        exo = np.concatenate([p_load, off.v_magn[:, 1:], off.s_from[:, self._rated], off.s_to[:, self._rated]], 1)
        p = np.concatenate([np.asarray(soc0, dtype=np.float64).reshape(self.nd), exo.reshape(-1)])
        return {"lbx": lbx.reshape(-1), "ubx": ubx.reshape(-1), "lbg": lbg.reshape(-1), "ubg": ubg.reshape(-1),
                "p": p}

    def guess(self, p_dev: np.ndarray, q_dev: np.ndarray, v: np.ndarray, soc: np.ndarray) -> np.ndarray:
        """A primal starting point (n_var,) from operating points (e.g. a simulated trajectory).

        Args:
            p_dev, q_dev: (N, n_dev) p.u.  v: (N, n_bus) complex p.u.  soc: (N + 1, n_des) p.u.·h.
        """
        n, lay, sim = self.horizon, self.lay, self.sim
        x = np.zeros((n, self.nx))
        vn = v[:, 1:]
        if self.formulation == "polar":
            x[:, lay["v1"]], x[:, lay["v2"]] = np.angle(vn), np.abs(vn)
        else:
            x[:, lay["v1"]], x[:, lay["v2"]] = vn.real, vn.imag
        x[:, lay["pg"]], x[:, lay["qg"]] = p_dev[:, sim.gen_ids], q_dev[:, sim.gen_ids]
        x[:, lay["qd"]] = q_dev[:, sim.des_ids]
        pdes = p_dev[:, sim.des_ids]
        x[:, lay["pch"]], x[:, lay["pdis"]] = np.maximum(-pdes, 0.0), np.maximum(pdes, 0.0)
        x[:, lay["soc"]] = soc[1:]
        vm = np.abs(v[:, 1:])
        x[:, lay["vu"]] = np.maximum(vm - self._vmax[1:], 0.0)
        x[:, lay["vl"]] = np.maximum(self._vmin[1:] - vm, 0.0)
        flows = branch_flows(torch.as_tensor(v), self.sim.net.branches)["s_apparent_max"].numpy()
        x[:, lay["ob"]] = np.maximum(np.abs(flows[:, self._rated]) - self._rate, 0.0)
        return x.reshape(-1)

    # ------------------------------------------------------------------------------------------ solve
    def solve(self, soc0: np.ndarray, p_load: np.ndarray, p_pot: np.ndarray, x0: np.ndarray,
              direction: np.ndarray | None = None, offsets: PowerFlowOffsets | None = None,
              lam_x0: np.ndarray | None = None, lam_g0: np.ndarray | None = None) -> NLPResult:
        """Solve from the primal guess ``x0`` (n_var,) (see :meth:`bounds` for the other arguments).

        With duals ``lam_x0``, ``lam_g0`` (from an earlier :class:`NLPResult`) IPOPT is warm-started. The
        result's reward terms include ``offsets``.
        """
        b = self.bounds(soc0, p_load, p_pot, direction, offsets)
        x0 = np.clip(np.asarray(x0, dtype=np.float64), b["lbx"], b["ubx"])
        warm = lam_x0 is not None and lam_g0 is not None
        args = dict(x0=x0, **b)
        if warm:
            args.update(lam_x0=lam_x0, lam_g0=lam_g0)
        solver = self._solver(warm)
        t0 = time.perf_counter()
        sol = solver(**args)
        wall = time.perf_counter() - t0
        st = solver.stats()
        x = np.asarray(sol["x"]).reshape(-1)
        it = st.get("iterations", {})
        inf_pr = float(it["inf_pr"][-1]) if it.get("inf_pr") else float("nan")
        inf_du = float(it["inf_du"][-1]) if it.get("inf_du") else float("nan")
        points, setpoints, comp = self.extract(x, soc0, p_load, p_pot, offsets)
        ret = float(np.dot(self._weights, points.reward))
        # the constant part of the objective: ΔE's Δt Σ P_pot (see ``_stage``) and the slack-P offsets
        off = np.zeros(self.horizon) if offsets is None else offsets.p_slack
        curt = np.dot(self._weights, self.sim.net.delta_t * (p_pot @ self._renewable + off))
        return NLPResult(setpoints=setpoints, points=points, discounted_return=ret,
                         objective=float(sol["f"]) + float(curt), status=str(st["return_status"]),
                         success=bool(st["success"]), iterations=int(st["iter_count"]), inf_pr=inf_pr,
                         inf_du=inf_du, complementarity=comp, solve_time=wall, x=x,
                         slack_at_bound=bool(self._slacks(x).max(initial=0.0) >= SLACK_MAX - 1e-6),
                         lam_x=np.asarray(sol["lam_x"]).reshape(-1), lam_g=np.asarray(sol["lam_g"]).reshape(-1))

    def _slacks(self, x: np.ndarray) -> np.ndarray:
        xs = x.reshape(self.horizon, self.nx)
        return np.concatenate([xs[:, self.lay[k]] for k in ("vu", "vl", "ob")], 1)

    def extract(self, x: np.ndarray, soc0: np.ndarray, p_load: np.ndarray, p_pot: np.ndarray,
                offsets: PowerFlowOffsets | None = None) -> tuple[OperatingPoints, np.ndarray, float]:
        """Operating points, set-points (N, action_dim) MW/MVAr and max min(p_ch, p_dis) of a primal vector."""
        n, lay, sim = self.horizon, self.lay, self.sim
        xs = x.reshape(n, self.nx)
        v1, v2 = xs[:, lay["v1"]], xs[:, lay["v2"]]
        vn = v2 * np.exp(1j * v1) if self.formulation == "polar" else v1 + 1j * v2
        v = np.concatenate([np.ones((n, 1), dtype=complex), vn], 1)
        p_dev, q_dev = np.zeros((n, sim.net.n_dev)), np.zeros((n, sim.net.n_dev))
        pdes = xs[:, lay["pdis"]] - xs[:, lay["pch"]]
        p_dev[:, sim.gen_ids], q_dev[:, sim.gen_ids] = xs[:, lay["pg"]], xs[:, lay["qg"]]
        p_dev[:, sim.des_ids], q_dev[:, sim.des_ids] = pdes, xs[:, lay["qd"]]
        p_dev[:, sim.load_ids], q_dev[:, sim.load_ids] = p_load, p_load * self._q_over_p
        soc = np.concatenate([np.asarray(soc0, dtype=np.float64).reshape(1, self.nd), xs[:, lay["soc"]]])
        points = evaluate_operating_points(sim, p_dev, q_dev, v, soc, p_pot, offsets)
        b = sim.net.base_mva
        setpoints = np.concatenate([xs[:, lay["pg"]], xs[:, lay["qg"]], pdes, xs[:, lay["qd"]]], 1) * b
        comp = float(np.minimum(xs[:, lay["pch"]], xs[:, lay["pdis"]]).max(initial=0.0))
        return points, setpoints, comp


def storage_direction(sim: GridSimulator, setpoints: np.ndarray) -> np.ndarray:
    """Each step's storage direction (N, n_des) from set-points (N, action_dim) MW/MVAr: 1 (discharge only) where
    the net P is ≥ 0, else −1 (charge only); the ``direction`` of :meth:`ACHorizonNLP.solve`."""
    return np.where(setpoints[:, 2 * sim.n_gen:2 * sim.n_gen + sim.n_des] >= 0, 1, -1)


# ---------------------------------------------------------------------------------------------- trajectories
def time_indices(sim: GridSimulator, state: np.ndarray, n: int) -> np.ndarray:
    """Time indices (n,) of the n steps after ``state`` (state_dim,): t0 + 1, …, t0 + n modulo the series."""
    t0 = int(round(float(state[sim.state_slices()["aux"]][0])))
    return (t0 + 1 + np.arange(n)) % sim.n_time


def exogenous(sim: GridSimulator, t_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Load P (n, n_load) and clipped potentials (n, n_gen) p.u. of the profiles at ``t_index`` (n,)."""
    t = torch.as_tensor(np.asarray(t_index), dtype=torch.long, device=sim.net.dev.device)
    return sim.loads_at(t)[0].cpu().numpy(), sim.p_pot_at(t).cpu().numpy()


@dataclasses.dataclass
class Rollout:
    """A simulated trajectory of n steps (p.u. unless noted).

    Attributes:
        p_dev, q_dev: (n, n_dev).  v: (n, n_bus) complex.  soc: (n + 1, n_des) p.u.·h.  p_pot: (n, n_gen).
        reward: (n,) float64.  converged: (n,) bool.  states: (n + 1, state_dim) MW… (row 0 the start).
    """

    p_dev: np.ndarray
    q_dev: np.ndarray
    v: np.ndarray
    soc: np.ndarray
    p_pot: np.ndarray
    reward: np.ndarray
    converged: np.ndarray
    states: np.ndarray


def rollout(sim: GridSimulator, state: np.ndarray, actions: np.ndarray | Callable[[np.ndarray], np.ndarray],
            n: int | None = None) -> Rollout:
    """Step ``sim`` from ``state`` (state_dim,) MW… in float64.

    Args:
        actions: (n, action_dim) MW/MVAr, or a policy mapping a state (state_dim,) to an action (closed loop).
        n: number of steps (only with a policy).

    Steps after a non-converged one continue from gym-anm's zero state (callers check ``converged``).
    """
    if callable(actions) == (n is None):
        raise ValueError("give either an action array, or a policy and the number of steps n")
    s = torch.as_tensor(np.asarray(state, dtype=np.float64)).reshape(1, -1)
    keep = {k: [] for k in ("p_dev", "q_dev", "v", "soc", "p_pot", "reward", "converged")}
    states = [s[0]]
    for k in range(int(n) if callable(actions) else len(actions)):
        a = actions(s[0].numpy()) if callable(actions) else actions[k]
        s, tr = sim.step(s, torch.as_tensor(np.asarray(a, dtype=np.float64)).reshape(1, -1))
        for key in keep:
            keep[key].append(getattr(tr, key)[0])
        states.append(s[0])
    soc0 = torch.as_tensor(np.asarray(state, dtype=np.float64)[sim.state_slices()["des_soc"]]) / sim.net.base_mva
    out = {k: torch.stack(v).cpu().numpy() for k, v in keep.items()}
    out["soc"] = np.concatenate([soc0.reshape(1, -1).numpy(), out["soc"]])
    return Rollout(states=torch.stack(states).cpu().numpy(), **out)
