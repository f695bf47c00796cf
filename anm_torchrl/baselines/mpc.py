"""gym-anm's MPC DC-OPF baseline (``gym_anm/agents/mpc*.py``, spec §7.1) as a linear program via qpsolvers.

At a state with time index ``t`` the policy plans the N stages ``t+1 … t+N`` (indices modulo the series
length, as gym-anm's ``MPCAgentPerfect`` wraps around the day), per stage ``k`` (all p.u.):

* variables: bus angles θ_k (n_bus), device injections P_k (n_dev), DES charge/discharge p_ch,k, p_dis,k ≥ 0,
  and, per branch, the epigraph variables cvxpy creates for the objective: a_k ≥ |P_ij| (a ≥ P_ij, a ≥ −P_ij)
  and o_k ≥ max(0, a_k − β·rate) (o ≥ 0, o ≥ a − β·rate);
* DC power balance Σ_{d at i} P_d = Σ_{branches at i} B_ij (θ_i − θ_j) with B = Im(Y_bus); branch flow
  P_ij = B_ij (θ_i − θ_j) for branch (i → j);
* loads = forecast; PMIN ≤ P_gen ≤ PMAX and P_gen ≤ forecast P_pot; PMIN ≤ P_DES ≤ PMAX; P_DES = p_dis − p_ch;
  SoC_{k+1} = SoC_k + Δt·EFF·p_ch − Δt·p_dis/EFF ∈ [SOC_MIN, SOC_MAX] (SoC_0 from the state);
* θ ∈ [−π, π], θ = 0 at the bus whose position is the slack device's (gym-anm's rule; the slack bus whenever the
  slack is device 0 at bus 0, as on every registered network); the slack P is free;
* objective Σ_k γ^k [P_slack,k + Σ P_classical,k + λ Σ_branches o_k] (gym-anm's cost: every non-renewable
  generator's P).

Any network: classical and renewable generators are both planned (P ≤ min(PMAX, forecast potential), the
classical ones at a cost), any number of storage units (zero included), unrated branches carry no overload term.
The action is the first-stage P of every non-slack generator and storage unit.

The action is the first-stage P of the non-slack generators and of the DES in MW, all Q = 0, clipped to the
action box. Forecasts: ``"constant"`` (the state's load P and P_pot held flat, as ``MPCAgentConstant``) or
``"perfect"`` (the raw series at t+1 … t+N, as ``MPCAgentPerfect``: the unclipped 36.75 MW PV values appear).

**Solver.** The matrices are built once; per solve only the right-hand sides (loads, P_pot, SoC_0) change.
The LP goes through ``qpsolvers.solve_problem`` with ``solver`` (default ``"clarabel"``):

* ``"clarabel"`` is what gym-anm's ``dc_opf.solve()`` uses (cvxpy's default for an LP). With the constraint rows
  above, one per gym-anm cvxpy row, Clarabel follows the same path and the actions agree with gym-anm's to
  ≈ 1e-9 MW, *including* states where the LP optimum is not unique (around noon, several PV/wind/DES splits
  reach the same cost; any other solver or formulation then picks another optimal action, up to ~3 MW away).
* ``"highs"`` (simplex) gives the same optimal value but a vertex on those ties.
* ``"osqp"`` (ADMM) is *not* usable here: even with eps 1e-9, polishing and 1e5 iterations it stops short on
  about a third of the states along a day (objective off by up to 1.9, actions by up to 5 MW, ≈ 0.7 s per
  solve). It is accepted for completeness only.

Clarabel and HiGHS are installed with cvxpy (gym-anm's dependency), not by qpsolvers itself: a project that
needs the MPC without gym-anm should depend on ``clarabel``. Without it :func:`default_solver` falls back.

**Defaults**: N = 32 planning steps and β = 0.96, the best configuration of gym-anm-exp's sweep
(N ∈ {8, 16, 32, 64, 128} × β ∈ {0.92, …, 1.0}, ``MPC_returns_T2000.txt``). Measured here from gym-anm's
``reset(seed=0)`` state (t0 = 81, SoC 0.017 MWh), 3,000 steps, discounted (γ = 0.995) return of MPC-perfect:
N = 8: −96.0, N = 16: −56.9, N = 32: −13.5, N = 64: −13.5 (same actions as N = 32, 3.5× slower);
N = 32 with β = 0.92: −12.7, β = 1.0: −30.1. MPC-constant N = 16 or 32: −120.6; do-nothing: −883.8.
The solve time grows about linearly in N: ≈ 4 / 8 / 14 / 47 ms for N = 8 / 16 / 32 / 64.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import scipy.sparse as sp
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from anm_torchrl._extras import require
from anm_torchrl.envs.specs import check_integer
from anm_torchrl.evaluation import EVAL_GAMMA
from anm_torchrl.grid import devices as dv
from anm_torchrl.grid.network import CLASSICAL_GEN, SLACK
from anm_torchrl.grid.simulator import GridSimulator

DEFAULT_HORIZON = 32
DEFAULT_SAFETY_MARGIN = 0.96

# Per-solver settings passed to qpsolvers. OSQP (ADMM) needs tight tolerances and polishing on an LP and still
# often stops short of the optimum here (module docstring); the interior-point / simplex solvers use their defaults.
SOLVER_SETTINGS = {
    "clarabel": {},
    "highs": {},
    "osqp": dict(eps_abs=1e-9, eps_rel=1e-9, max_iter=100_000, polishing=True, polish_refine_iter=10),
}


def default_solver() -> str:
    """``"clarabel"`` (gym-anm's cvxpy default for this LP) if qpsolvers has it, else ``"highs"``, else ``"osqp"``."""
    qpsolvers = require("qpsolvers")

    for name in ("clarabel", "highs", "osqp"):
        if name in qpsolvers.available_solvers:
            return name
    raise ImportError("qpsolvers has none of clarabel, highs, osqp")


def check_solver_settings(solver: str, settings: dict, given: list[str]) -> None:
    """Raise ``ValueError`` naming ``given`` (the caller's keys) if ``solver`` refuses ``settings``: tried on a
    one-variable LP now, not at the first step of an episode (qpsolvers hands unknown keys to the solver, which
    fails with its own AttributeError or TypeError)."""
    qpsolvers = require("qpsolvers")

    from scipy import sparse

    one = np.ones(1)
    lp = qpsolvers.Problem(sparse.csc_matrix((1, 1)), one, sparse.csc_matrix(one[None]), one)
    try:
        qpsolvers.solve_problem(lp, solver=solver, **settings)
    except (AttributeError, TypeError, ValueError, KeyError) as err:  # the solver's own words for a bad setting
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ValueError(f"MPC options {given} are not settings of the {solver!r} solver, or a value is invalid "
                         f"(MPC's own options: horizon, safety_margin, gamma, solver): {first}") from None


class MPCPolicy(TensorDictModuleBase):
    """gym-anm's N-stage MPC DC-OPF policy (``MPCAgentPerfect`` / ``MPCAgentConstant``) as a TorchRL policy.

    Args:
        sim: the :class:`GridSimulator` (network, series, λ).
        horizon: number N of planning stages.
        forecast: ``"perfect"`` or ``"constant"``.
        safety_margin: β, the fraction of each branch rating above which flows are penalised.
        gamma: discount of the stage costs (gym-anm-exp uses the evaluation discount, 0.995).
        solver: qpsolvers solver name; default :func:`default_solver` (``"clarabel"``).
        in_key: TensorDict key of the gym-anm state (..., state_dim) in MW/MVAr/MWh.
        **solver_settings: overrides of :data:`SOLVER_SETTINGS` passed to the solver.

    ``forward`` writes ``"action"`` (..., action_dim) float32 in MW/MVAr; :meth:`solve` returns the full plan
    of one state. A state whose LP is not solved gets the do-nothing action (a warning is issued and
    ``last_info[i]["fallback"]`` is True).
    """

    def __init__(self, sim: GridSimulator, horizon: int = DEFAULT_HORIZON, forecast: str = "perfect",
                 safety_margin: float = DEFAULT_SAFETY_MARGIN, gamma: float = EVAL_GAMMA, solver: str | None = None,
                 in_key: str = "state", **solver_settings):
        super().__init__()
        if forecast not in ("perfect", "constant"):
            raise ValueError(f"forecast must be 'perfect' or 'constant', got {forecast!r}")
        horizon = check_integer("horizon", horizon, low=1)  # 2.5 was cut to 2
        self.in_keys = [in_key]
        self.out_keys = ["action"]
        self.sim, self.horizon, self.forecast = sim, horizon, forecast
        self.safety_margin, self.gamma = float(safety_margin), float(gamma)
        self.solver = default_solver() if solver is None else solver
        self.solver_settings = {**SOLVER_SETTINGS.get(self.solver, {}), **solver_settings}
        if solver_settings:
            check_solver_settings(self.solver, self.solver_settings, sorted(solver_settings))
        self._load_series = sim.load_series.detach().cpu().numpy()
        self._p_max_series = sim.p_max_series.detach().cpu().numpy()
        self._sl = sim.state_slices()
        self._build()
        lo, hi = sim.action_bounds()
        self._a_low, self._a_high = lo.cpu().numpy(), hi.cpu().numpy()
        self._fallback = np.concatenate([self._a_high[:sim.n_gen], np.zeros(sim.action_dim - sim.n_gen)])
        self.last_info: list[dict] = []

    # ------------------------------------------------------------------------------------------ LP build
    def _build(self) -> None:
        """Constant LP data: ``min c·x  s.t.  A_eq x = b_eq,  G x <= h`` (only b_eq's loads and h change)."""
        sim, net = self.sim, self.sim.net
        nb, nd, nbr = net.n_bus, net.n_dev, len(net.branches.rate)
        gen, des, load = sim.gen_ids, sim.des_ids, sim.load_ids
        nes, nl = len(des), len(load)
        kinds = net.dev_type.tolist()
        slack = kinds.index(SLACK)
        if slack >= nb:
            raise ValueError(f"the slack device's position {slack} must be < n_bus = {nb}: gym-anm fixes the angle "
                             f"of the bus at that position (MPCAgent: V_bus_ang[dev_id_mapping[slack]] = 0)")
        # gym-anm's stage cost P_slack + Σ P_classical: every generator that is not renewable
        costly = [slack] + [i for i, k in enumerate(kinds) if k == CLASSICAL_GEN]
        dev = net.dev.cpu().numpy()
        b_bus = net.y_bus.imag.cpu().numpy()
        f_bus, t_bus = net.branches.f_bus.cpu().numpy(), net.branches.t_bus.cpu().numpy()
        rate = net.branches.rate.cpu().numpy()
        dt, lamb, beta, n_stage = net.delta_t, sim.lamb, self.safety_margin, self.horizon
        eff = dev[des, dv.EFF]

        # Per-stage variable layout x_k = [θ (nb), P (nd), p_ch (nes), p_dis (nes), a (nbr), o (nbr)] with the
        # epigraph variables a ≥ |P_ij| and o ≥ max(0, a − β rate) that cvxpy creates for abs() and maximum().
        o_th, o_p = 0, nb
        o_ch = o_p + nd
        o_dis = o_ch + nes
        o_a = o_dis + nes
        o_o = o_a + nbr
        nv = o_o + nbr
        self._layout = dict(theta=o_th, p=o_p, p_ch=o_ch, p_dis=o_dis, abs=o_a, over=o_o, n=nv)
        self._nb, self._nd, self._nes, self._nbr, self._nv = nb, nd, nes, nbr, nv
        n_var = nv * n_stage
        self._n_var = n_var

        def unit(cols) -> np.ndarray:
            cols = np.atleast_1d(np.asarray(cols, dtype=int))
            m = np.zeros((cols.size, nv))
            m[np.arange(cols.size), cols] = 1.0
            return m

        # Equalities per stage: DC balance, loads = forecast, DES split, slack angle.
        flow = np.zeros((nbr, nv))  # P_ij = B[f, t] (θ_f − θ_t)
        bal = np.zeros((nb, nv))  # Σ_{d at i} P_d − Σ_{branches at i} B (θ_i − θ_j) = 0, as gym-anm writes it
        for e, (f, t) in enumerate(zip(f_bus, t_bus)):
            flow[e, o_th + f], flow[e, o_th + t] = b_bus[f, t], -b_bus[f, t]
            bal[f, o_th + f] -= b_bus[f, t]
            bal[f, o_th + t] += b_bus[f, t]
            bal[t, o_th + t] -= b_bus[t, f]
            bal[t, o_th + f] += b_bus[t, f]
        for d in range(nd):
            bal[int(net.dev_bus[d]), o_p + d] += 1.0
        fix_load = unit(o_p + np.array(load, dtype=int))
        split = unit(o_p + np.array(des, dtype=int))  # P_DES − p_dis + p_ch = 0
        split[np.arange(nes), o_ch + np.arange(nes)] = 1.0
        split[np.arange(nes), o_dis + np.arange(nes)] = -1.0
        ang = unit(o_th + slack)  # gym-anm fixes θ at index dev_id_mapping[slack] (the slack bus on every registered
        # network, where the slack is device 0 at bus 0)
        eq = np.vstack([bal, fix_load, split, ang])
        n_eq = eq.shape[0]
        self._a_eq = sp.block_diag([sp.csc_matrix(eq)] * n_stage, format="csc")
        self._b_eq0 = np.zeros(n_eq * n_stage)
        self._load_rows = np.arange(n_stage)[:, None] * n_eq + nb + np.arange(nl)  # (N, n_load)

        # Inequalities per stage, the rows of gym-anm's cvxpy problem (kept separate, e.g. P_gen ≤ PMAX and
        # P_gen ≤ forecast, so that an interior-point solver meets the same problem).
        g_gen = unit(o_p + np.array(gen, dtype=int))
        g_des = unit(o_p + np.array(des, dtype=int))
        th = unit(o_th + np.arange(nb))
        fin = np.isfinite(rate)
        a_v, o_v = unit(o_a + np.arange(nbr)), unit(o_o + np.arange(nbr))
        blocks = [
            (-g_gen, -dev[gen, dv.PMIN]),  # PMIN ≤ P_gen
            (g_gen, dev[gen, dv.PMAX]),  # P_gen ≤ PMAX
            (-g_des, -dev[des, dv.PMIN]),  # PMIN ≤ P_DES
            (g_des, dev[des, dv.PMAX]),  # P_DES ≤ PMAX
            (g_gen, np.zeros(len(gen))),  # P_gen ≤ forecast P_pot (filled per solve)
            (-th, np.full(nb, math.pi)),  # −π ≤ θ
            (th, np.full(nb, math.pi)),  # θ ≤ π
            (-unit(o_ch + np.arange(2 * nes)), np.zeros(2 * nes)),  # p_ch, p_dis ≥ 0
            (flow - a_v, np.zeros(nbr)),  # P_ij ≤ a
            (-flow - a_v, np.zeros(nbr)),  # −P_ij ≤ a
            (-o_v, np.zeros(nbr)),  # o ≥ 0
            ((a_v - o_v)[fin], beta * rate[fin]),  # o ≥ a − β rate (unrated branches: o = 0 at the optimum)
        ]
        g_loc = np.vstack([m for m, _ in blocks])
        h_loc = np.concatenate([v for _, v in blocks])
        n_loc = g_loc.shape[0]
        fc_row0 = sum(m.shape[0] for m, _ in blocks[:4])
        self._gen_rows = np.arange(n_stage)[:, None] * n_loc + fc_row0 + np.arange(len(gen))  # (N, n_gen)
        # SoC rows: SoC_{k+1} = SoC_0 + Σ_{j≤k} Δt (EFF p_ch,j − p_dis,j / EFF) within [SOC_MIN, SOC_MAX].
        soc = np.zeros((n_stage * nes, n_var))
        for k in range(n_stage):
            for j in range(k + 1):
                for u in range(nes):
                    soc[k * nes + u, j * nv + o_ch + u] = dt * eff[u]
                    soc[k * nes + u, j * nv + o_dis + u] = -dt / eff[u]
        self._g = sp.vstack([sp.block_diag([sp.csc_matrix(g_loc)] * n_stage), -sp.csc_matrix(soc),
                             sp.csc_matrix(soc)], format="csc")
        self._h0 = np.concatenate([np.tile(h_loc, n_stage), np.zeros(2 * n_stage * nes)])
        self._soc_lo_rows = n_loc * n_stage + np.arange(n_stage * nes)
        self._soc_hi_rows = self._soc_lo_rows + n_stage * nes
        self._soc_min, self._soc_max = dev[des, dv.SOC_MIN], dev[des, dv.SOC_MAX]

        # Cost Σ_k γ^k [P_slack + Σ P_classical + λ Σ o].
        c_loc = np.zeros(nv)
        c_loc[o_p + np.array(costly, dtype=int)] = 1.0
        c_loc[o_o + np.flatnonzero(fin)] = lamb
        self._c = np.concatenate([self.gamma ** k * c_loc for k in range(n_stage)])
        self._p_zero = sp.csc_matrix((n_var, n_var))

    # ------------------------------------------------------------------------------------------ forecasts
    def forecasts(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Load P (N, n_load) and generator potential (N, n_gen) forecasts in p.u. for one state (MW units)."""
        sim, sl, b = self.sim, self._sl, self.sim.net.base_mva
        if self.forecast == "constant":
            p_load = state[sl["dev_p"]][self.sim.load_ids] / b
            p_pot = state[sl["gen_p_max"]] / b
            return np.tile(p_load, (self.horizon, 1)), np.tile(p_pot, (self.horizon, 1))
        t = int(round(float(state[sl["aux"]][0])))
        idx = (t + 1 + np.arange(self.horizon)) % sim.n_time
        return self._load_series[:, idx].T.copy(), self._p_max_series[:, idx].T.copy()

    def _rhs(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p_load, p_pot = self.forecasts(state)
        soc0 = state[self._sl["des_soc"]] / self.sim.net.base_mva
        b_eq, h = self._b_eq0.copy(), self._h0.copy()
        b_eq[self._load_rows] = p_load
        h[self._gen_rows] = p_pot
        h[self._soc_lo_rows] = np.tile(soc0 - self._soc_min, self.horizon)
        h[self._soc_hi_rows] = np.tile(self._soc_max - soc0, self.horizon)
        return b_eq, h

    # ------------------------------------------------------------------------------------------ solving
    def _solve_x(self, state: np.ndarray) -> tuple[np.ndarray | None, dict]:
        qpsolvers = require("qpsolvers")

        b_eq, h = self._rhs(state)
        prob = qpsolvers.Problem(self._p_zero, self._c, self._g, h, self._a_eq, b_eq)
        sol = qpsolvers.solve_problem(prob, solver=self.solver, **self.solver_settings)
        # an infeasible LP's solver still hands back its last iterate (Clarabel's PrimalInfeasible); a near-optimal
        # stop (Clarabel's AlmostSolved, which qpsolvers counts as not found) is kept, as gym-anm's cvxpy keeps it
        status = str(sol.extras.get("status", "")) if isinstance(sol.extras, dict) else ""
        infeasible = "infeasible" in status.lower()
        x = sol.x if not infeasible and sol.x is not None and np.all(np.isfinite(sol.x)) else None
        info = {"found": bool(sol.found), "solver": self.solver,
                "objective": float(self._c @ x) if x is not None else float("nan")}
        return x, info

    def solve(self, state) -> dict:
        """Solve the N-stage DC-OPF at one gym-anm state (state_dim,) in MW/MVAr/MWh.

        Returns a dict of numpy arrays, all p.u.: ``theta`` (N, n_bus), ``p_dev`` (N, n_dev), ``p_ch``,
        ``p_dis``, ``soc`` (N + 1, n_des) (row 0 the initial SoC), ``p_branch`` and ``overload`` (N, n_branch)
        = max(0, |P_ij| − β rate), the raw LP solution ``x`` (N, n_var_per_stage) laid out as ``_layout``,
        the forecasts ``p_load_forecast`` (N, n_load) and ``p_pot_forecast`` (N, n_gen), the ``action`` (MW,
        clipped) and the solver ``info`` (``objective`` is gym-anm's ``dc_opf.value``: Σ_k γ^k [P_slack + λ Σ o]).
        Raises ``RuntimeError`` when the solver returns no solution.
        """
        state = np.asarray(torch.as_tensor(state).detach().cpu().double().numpy() if torch.is_tensor(state)
                           else state, dtype=np.float64).reshape(-1)
        x, info = self._solve_x(state)
        if x is None:
            raise RuntimeError(f"MPC DC-OPF not solved: {info}")
        lay, n = self._layout, self.horizon
        xs = x.reshape(n, self._nv)
        theta = xs[:, lay["theta"]:lay["theta"] + self._nb]
        p_dev = xs[:, lay["p"]:lay["p"] + self._nd]
        p_ch = xs[:, lay["p_ch"]:lay["p_ch"] + self._nes]
        p_dis = xs[:, lay["p_dis"]:lay["p_dis"] + self._nes]
        net = self.sim.net
        eff = net.dev[self.sim.des_ids, dv.EFF].cpu().numpy()
        soc0 = state[self._sl["des_soc"]] / net.base_mva
        d_soc = net.delta_t * (eff * p_ch - p_dis / eff)
        soc = np.vstack([soc0, soc0 + np.cumsum(d_soc, 0)])
        b = net.y_bus.imag.cpu().numpy()
        f, t = net.branches.f_bus.cpu().numpy(), net.branches.t_bus.cpu().numpy()
        p_branch = b[f, t] * (theta[:, f] - theta[:, t])
        rate = net.branches.rate.cpu().numpy()
        overload = np.maximum(0.0, np.abs(p_branch) - self.safety_margin * rate)
        p_load, p_pot = self.forecasts(state)
        return {"theta": theta, "p_dev": p_dev, "p_ch": p_ch, "p_dis": p_dis, "soc": soc, "p_branch": p_branch,
                "overload": overload, "x": xs, "p_load_forecast": p_load, "p_pot_forecast": p_pot,
                "action": self._action(p_dev[0]), "info": info}

    def _action(self, p_dev0: np.ndarray) -> np.ndarray:
        sim, b = self.sim, self.sim.net.base_mva
        ng, nd = sim.n_gen, sim.n_des
        a = np.concatenate([p_dev0[sim.gen_ids] * b, np.zeros(ng), p_dev0[sim.des_ids] * b, np.zeros(nd)])
        return np.clip(a, self._a_low, self._a_high)

    def act(self, states: torch.Tensor) -> torch.Tensor:
        """Actions (..., action_dim) float32 MW/MVAr for states (..., state_dim); one LP per state."""
        flat = states.detach().reshape(-1, states.shape[-1]).cpu().double().numpy()
        out, self.last_info = np.empty((flat.shape[0], self.sim.action_dim)), []
        for i, s in enumerate(flat):
            try:
                plan = self.solve(s)
                out[i] = plan["action"]
                self.last_info.append({**plan["info"], "fallback": False})
            except RuntimeError as err:
                warnings.warn(f"MPC: {err}; using the do-nothing action", RuntimeWarning, stacklevel=2)
                out[i] = self._fallback
                self.last_info.append({"found": False, "solver": self.solver, "fallback": True})
        return torch.as_tensor(out, dtype=torch.float32, device=states.device).reshape(
            *states.shape[:-1], self.sim.action_dim)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict.set(self.out_keys[0], self.act(tensordict.get(self.in_keys[0])))
        return tensordict
