"""gym-anm's MPC DC-OPF baseline (``gym_anm/agents/mpc*.py``, spec §7.1) as an OSQP linear program.

At a state with time index ``t`` the policy plans the N stages ``t+1 … t+N`` (indices modulo the series
length) over, per stage ``k`` (all p.u.):

* variables: bus angles θ_k (n_bus), device injections P_k (n_dev), DES charge/discharge p_ch,k, p_dis,k ≥ 0
  and, added here to linearise ``max(0, |P_ij| − β·rate_ij)``, one epigraph variable s_k ≥ 0 per branch
  with s ≥ P_ij − β·rate and s ≥ −P_ij − β·rate;
* DC power balance Σ_{d at i} P_d = Σ_{branches (i, j) ∋ i} B_ij (θ_i − θ_j) with B = Im(Y_bus);
  branch flow P_ij = B_ij (θ_i − θ_j) for branch (i → j);
* loads equal to the forecast; PMIN ≤ P_gen ≤ min(PMAX, forecast P_pot); PMIN ≤ P_DES ≤ PMAX;
  P_DES = p_dis − p_ch; SoC_{k+1} = SoC_k + Δt·EFF·p_ch − Δt·p_dis/EFF ∈ [SOC_MIN, SOC_MAX];
* θ ∈ [−π, π], θ_slack-bus = 0; the slack P is free;
* objective Σ_k γ^k [P_slack,k + λ Σ_branches s_k].

The action is the first-stage P of the renewable generators and the DES in MW, all Q = 0, clipped to the
action box. Forecasts: ``"constant"`` (the state's load P and P_pot held flat, as ``MPCAgentConstant``) or
``"perfect"`` (the raw series at t+1 … t+N, as ``MPCAgentPerfect``: the unclipped 36.75 MW PV values appear).

The constraint matrix and the cost are built once; per solve only the bounds (loads, P_pot, initial SoC)
change. Two back-ends solve the LP with OSQP:

* ``backend="osqp"`` (default): one persistent ``osqp.OSQP`` object, factorised once, updated with the new
  bounds and warm-started per environment from that environment's previous solution (≈ 3–6 ms per solve
  for N = 16 on one core);
* ``backend="qpsolvers"``: ``qpsolvers.solve_problem(..., solver="osqp")`` on the cached matrices (a fresh
  OSQP set-up per solve, ≈ 2× slower), kept as the literal "qpsolvers + OSQP" formulation.

Both use tight tolerances and OSQP's polishing, so they match gym-anm's cvxpy/Clarabel solution to
≈ 1e-6 MW on the action when the LP optimum is unique (see ``tests/test_baselines.py``).

Defaults: N = 16 planning steps and β = 0.96. gym-anm-exp sweeps N ∈ {8, 16, 32, 64, 128} and
β ∈ {0.92, …, 1.0}; its best MPC in ``MPC_returns_T2000.txt`` uses N = 32, β = 0.96. N = 16 keeps a solve
at a few ms (the cost grows roughly linearly in N) — pass ``horizon=32`` for the paper's best setting.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from anm_torchrl.grid import devices as dv
from anm_torchrl.grid.network import SLACK
from anm_torchrl.grid.simulator import GridSimulator

DEFAULT_HORIZON = 16
DEFAULT_SAFETY_MARGIN = 0.96

# OSQP settings: LPs need tight tolerances plus polishing to land on the exact vertex.
OSQP_SETTINGS = dict(eps_abs=1e-9, eps_rel=1e-9, max_iter=200_000, polishing=True, polish_refine_iter=10,
                     verbose=False)


class MPCPolicy(TensorDictModuleBase):
    """gym-anm's N-stage MPC DC-OPF policy (``MPCAgentPerfect`` / ``MPCAgentConstant``) as a TorchRL policy.

    Args:
        sim: the :class:`GridSimulator` (network, series, λ).
        horizon: number N of planning stages.
        forecast: ``"perfect"`` or ``"constant"``.
        safety_margin: β, the fraction of each branch rating above which flows are penalised.
        gamma: discount of the stage costs (gym-anm-exp uses 0.995).
        backend: ``"osqp"`` (persistent solver, warm starts) or ``"qpsolvers"``.
        in_key: TensorDict key of the gym-anm state (..., state_dim) in MW/MVAr/MWh.
        warm_start: warm-start each environment from its previous solution (``"osqp"`` only).

    ``forward`` writes ``"action"`` (..., action_dim) float32 in MW/MVAr; :meth:`solve` returns the full plan.
    """

    def __init__(self, sim: GridSimulator, horizon: int = DEFAULT_HORIZON, forecast: str = "perfect",
                 safety_margin: float = DEFAULT_SAFETY_MARGIN, gamma: float = 0.995, backend: str = "osqp",
                 in_key: str = "state", warm_start: bool = True, **osqp_settings):
        super().__init__()
        if forecast not in ("perfect", "constant"):
            raise ValueError(f"forecast must be 'perfect' or 'constant', got {forecast!r}")
        if backend not in ("osqp", "qpsolvers"):
            raise ValueError(f"backend must be 'osqp' or 'qpsolvers', got {backend!r}")
        if horizon < 1:
            raise ValueError("horizon must be >= 1")
        self.in_keys = [in_key]
        self.out_keys = ["action"]
        self.sim, self.horizon, self.forecast = sim, int(horizon), forecast
        self.safety_margin, self.gamma, self.backend = float(safety_margin), float(gamma), backend
        self.warm_start = warm_start
        self.settings = {**OSQP_SETTINGS, **osqp_settings}
        self._build()
        self._solver = None
        self._warm: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        lo, hi = sim.action_bounds()
        self._a_low, self._a_high = lo.cpu().numpy(), hi.cpu().numpy()
        self.last_info: list[dict] = []

    # ------------------------------------------------------------------------------------------ LP build
    def _build(self) -> None:
        sim, net = self.sim, self.sim.net
        nb, nd, nbr = net.n_bus, net.n_dev, len(net.branches.rate)
        gen, des, load = sim.gen_ids, sim.des_ids, sim.load_ids
        nes = len(des)
        slack = [i for i, k in enumerate(net.dev_type.tolist()) if k == SLACK][0]
        dev = net.dev.cpu().numpy()
        b_bus = net.y_bus.imag.cpu().numpy()
        f_bus, t_bus = net.branches.f_bus.cpu().numpy(), net.branches.t_bus.cpu().numpy()
        rate = net.branches.rate.cpu().numpy()
        dt, lamb, beta, n_stage = net.delta_t, sim.lamb, self.safety_margin, self.horizon
        eff = dev[des, dv.EFF]

        # Per-stage variable layout.
        o_th, o_p = 0, nb
        o_ch = o_p + nd
        o_dis = o_ch + nes
        o_s = o_dis + nes
        nv = o_s + nbr
        self._layout = dict(theta=o_th, p=o_p, p_ch=o_ch, p_dis=o_dis, s=o_s, n=nv)
        self._nb, self._nd, self._nes, self._nbr, self._nv = nb, nd, nes, nbr, nv
        n_var = nv * n_stage

        # Stage-local rows (same for every stage): balance, DES split, slack angle, two epigraph rows.
        # Branch flow row coefficients: P_ij = B[f, t] (θ_f − θ_t).
        flow = np.zeros((nbr, nv))
        bal = np.zeros((nb, nv))
        for e, (f, t) in enumerate(zip(f_bus, t_bus)):
            flow[e, o_th + f], flow[e, o_th + t] = b_bus[f, t], -b_bus[f, t]
            # gym-anm's balance: row f gets B[f,t](θ_f − θ_t), row t gets B[t,f](θ_t − θ_f).
            bal[f, o_th + f] -= b_bus[f, t]
            bal[f, o_th + t] += b_bus[f, t]
            bal[t, o_th + t] -= b_bus[t, f]
            bal[t, o_th + f] += b_bus[t, f]
        for d in range(nd):
            bal[int(net.dev_bus[d]), o_p + d] += 1.0  # Σ P_dev at bus − Σ flows = 0
        split = np.zeros((nes, nv))
        for k, d in enumerate(des):
            split[k, o_p + d], split[k, o_ch + k], split[k, o_dis + k] = 1.0, 1.0, -1.0  # P = p_dis − p_ch
        ang = np.zeros((1, nv))
        ang[0, o_th + 0] = 1.0  # gym-anm fixes θ at index dev_id_mapping[slack] = 0, the slack bus
        finite = np.isfinite(rate)
        ep_hi = flow.copy()
        ep_hi[:, o_s:o_s + nbr] -= np.eye(nbr)  # P_ij − s ≤ β rate
        ep_lo = -flow
        ep_lo[:, o_s:o_s + nbr] -= np.eye(nbr)  # −P_ij − s ≤ β rate
        ep_hi, ep_lo = ep_hi[finite], ep_lo[finite]
        eq_local = np.vstack([bal, split, ang])
        ineq_local = np.vstack([ep_hi, ep_lo])
        blk = lambda m: sp.block_diag([sp.csc_matrix(m)] * n_stage, format="csc")  # noqa: E731

        # SoC rows: SoC_{k+1} − SoC_0 = Σ_{j≤k} Δt (EFF p_ch,j − p_dis,j / EFF).
        soc_rows = np.zeros((n_stage * nes, n_var))
        for k in range(n_stage):
            for j in range(k + 1):
                for u in range(nes):
                    soc_rows[k * nes + u, j * nv + o_ch + u] = dt * eff[u]
                    soc_rows[k * nes + u, j * nv + o_dis + u] = -dt / eff[u]

        self._a_eq = blk(eq_local)
        self._b_eq = np.zeros(self._a_eq.shape[0])
        eps = np.concatenate([beta * rate[finite], beta * rate[finite]])
        self._g = sp.vstack([blk(ineq_local), sp.csc_matrix(soc_rows)], format="csc")
        self._h_ep = np.tile(eps, n_stage)
        self._n_ep = self._h_ep.size
        self._soc_min, self._soc_max = dev[des, dv.SOC_MIN], dev[des, dv.SOC_MAX]

        # Cost.
        c_local = np.zeros(nv)
        c_local[o_p + slack] = 1.0
        c_local[o_s:o_s + nbr] = lamb * finite  # s of an unrated branch stays 0 (cost 0, bounds [0, 0])
        self._c = np.concatenate([self.gamma ** k * c_local for k in range(n_stage)])
        self._p_zero = sp.csc_matrix((n_var, n_var))

        # Variable bounds, stage-local; loads and generator upper bounds are filled per solve.
        lb, ub = np.full(nv, -np.inf), np.full(nv, np.inf)
        lb[o_th:o_th + nb], ub[o_th:o_th + nb] = -math.pi, math.pi
        lb[o_p + np.array(gen)], ub[o_p + np.array(gen)] = dev[gen, dv.PMIN], dev[gen, dv.PMAX]
        lb[o_p + np.array(des)], ub[o_p + np.array(des)] = dev[des, dv.PMIN], dev[des, dv.PMAX]
        lb[o_ch:o_s + nbr] = 0.0
        ub[o_s:o_s + nbr][~finite] = 0.0
        self._lb0, self._ub0 = np.tile(lb, n_stage), np.tile(ub, n_stage)
        self._gen_idx = np.array([[k * nv + o_p + g for g in gen] for k in range(n_stage)])  # (N, n_gen)
        self._load_idx = np.array([[k * nv + o_p + d for d in load] for k in range(n_stage)])  # (N, n_load)
        self._gen_pmax = dev[gen, dv.PMAX]
        self._n_var = n_var

        # OSQP form l ≤ A x ≤ u with A = [A_eq; G; I].
        self._a_osqp = sp.vstack([self._a_eq, self._g, sp.eye(n_var, format="csc")], format="csc")

    # ------------------------------------------------------------------------------------------ forecasts
    def forecasts(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Load P (N, n_load) and generator potential (N, n_gen) forecasts in p.u. for one state (MW units)."""
        sim, sl, b = self.sim, self.sim.state_slices(), self.sim.net.base_mva
        if self.forecast == "constant":
            p_load = state[sl["dev_p"]][self.sim.load_ids] / b
            p_pot = state[sl["gen_p_max"]] / b
            return np.tile(p_load, (self.horizon, 1)), np.tile(p_pot, (self.horizon, 1))
        t = int(state[sl["aux"]][0])
        idx = (t + 1 + np.arange(self.horizon)) % sim.n_time
        return (sim.load_series[:, idx].T.cpu().numpy().copy(), sim.p_max_series[:, idx].T.cpu().numpy().copy())

    def _bounds(self, state: np.ndarray):
        p_load, p_pot = self.forecasts(state)
        soc0 = state[self.sim.state_slices()["des_soc"]] / self.sim.net.base_mva
        lb, ub = self._lb0.copy(), self._ub0.copy()
        lb[self._load_idx], ub[self._load_idx] = p_load, p_load
        ub[self._gen_idx] = np.minimum(self._gen_pmax, p_pot)
        h_soc_hi = np.tile(self._soc_max - soc0, self.horizon)
        h_soc_lo = np.tile(self._soc_min - soc0, self.horizon)
        return lb, ub, h_soc_lo, h_soc_hi

    # ------------------------------------------------------------------------------------------ solving
    def _solve_x(self, state: np.ndarray, env_index: int = 0) -> tuple[np.ndarray, dict]:
        lb, ub, h_soc_lo, h_soc_hi = self._bounds(state)
        if self.backend == "qpsolvers":
            import qpsolvers

            # Two-sided SoC rows as G x ≤ h: [G_ep; G_soc; −G_soc].
            g_soc = self._g[self._n_ep:]
            g = sp.vstack([self._g, -g_soc], format="csc")
            h = np.concatenate([self._h_ep, h_soc_hi, -h_soc_lo])
            prob = qpsolvers.Problem(self._p_zero, self._c, g, h, self._a_eq, self._b_eq, lb, ub)
            sol = qpsolvers.solve_problem(prob, solver="osqp", **self.settings)
            info = sol.extras["info"]
            return sol.x, {"status": info.status, "iter": info.iter, "obj": info.obj_val,
                           "solve_time": info.solve_time + info.setup_time, "polished": info.status_polish}
        import osqp

        l = np.concatenate([self._b_eq, np.full(self._n_ep, -np.inf), h_soc_lo, lb])
        u = np.concatenate([self._b_eq, self._h_ep, h_soc_hi, ub])
        if self._solver is None:
            self._solver = osqp.OSQP()
            self._solver.setup(P=self._p_zero, q=self._c, A=self._a_osqp, l=l, u=u, **self.settings)
        else:
            self._solver.update(l=l, u=u)
        if self.warm_start and env_index in self._warm:
            x0, y0 = self._warm[env_index]
            self._solver.warm_start(x=x0, y=y0)
        elif self.warm_start:
            self._solver.warm_start(x=np.zeros(self._n_var), y=np.zeros(self._a_osqp.shape[0]))
        res = self._solver.solve()
        info = res.info
        if info.status_val in (1, 2):  # solved / solved inaccurate
            self._warm[env_index] = (res.x.copy(), res.y.copy())
        return res.x, {"status": info.status, "iter": info.iter, "obj": info.obj_val,
                       "solve_time": info.solve_time + info.setup_time + info.update_time,
                       "polished": info.status_polish}

    def solve(self, state, env_index: int = 0) -> dict:
        """Solve the N-stage DC-OPF at one gym-anm state (state_dim,) in MW/MVAr/MWh.

        Returns a dict of numpy arrays, all p.u.: ``theta`` (N, n_bus), ``p_dev`` (N, n_dev), ``p_ch``,
        ``p_dis``, ``soc`` (N + 1, n_des) (row 0 the initial SoC), ``p_branch`` and ``overload`` (N, n_branch),
        the forecasts ``p_load_forecast`` (N, n_load) and ``p_pot_forecast`` (N, n_gen), the ``action`` (MW,
        clipped) and the solver ``info``.
        """
        state = np.asarray(torch.as_tensor(state).detach().cpu().double().numpy() if torch.is_tensor(state)
                           else state, dtype=np.float64).reshape(-1)
        x, info = self._solve_x(state, env_index)
        if x is None or not np.all(np.isfinite(x)):
            raise RuntimeError(f"MPC DC-OPF not solved: {info}")
        lay, n = self._layout, self.horizon
        xs = x.reshape(n, self._nv)
        theta = xs[:, lay["theta"]:lay["theta"] + self._nb]
        p_dev = xs[:, lay["p"]:lay["p"] + self._nd]
        p_ch = xs[:, lay["p_ch"]:lay["p_ch"] + self._nes]
        p_dis = xs[:, lay["p_dis"]:lay["p_dis"] + self._nes]
        net = self.sim.net
        eff = net.dev[self.sim.des_ids, dv.EFF].cpu().numpy()
        soc0 = state[self.sim.state_slices()["des_soc"]] / net.base_mva
        d_soc = net.delta_t * (eff * p_ch - p_dis / eff)
        soc = np.vstack([soc0, soc0 + np.cumsum(d_soc, 0)])
        b = net.y_bus.imag.cpu().numpy()
        f, t = net.branches.f_bus.cpu().numpy(), net.branches.t_bus.cpu().numpy()
        p_branch = b[f, t] * (theta[:, f] - theta[:, t])
        rate = net.branches.rate.cpu().numpy()
        overload = np.maximum(0.0, np.abs(p_branch) - self.safety_margin * rate)
        p_load, p_pot = self.forecasts(state)
        return {"theta": theta, "p_dev": p_dev, "p_ch": p_ch, "p_dis": p_dis, "soc": soc, "p_branch": p_branch,
                "overload": overload, "p_load_forecast": p_load, "p_pot_forecast": p_pot,
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
            plan = self.solve(s, env_index=i)
            out[i] = plan["action"]
            self.last_info.append(plan["info"])
        return torch.as_tensor(out, dtype=torch.float32, device=states.device).reshape(
            *states.shape[:-1], self.sim.action_dim)

    def reset_warm_start(self) -> None:
        """Forget the per-environment warm starts."""
        self._warm.clear()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict.set(self.out_keys[0], self.act(tensordict.get(self.in_keys[0])))
        return tensordict
