"""Receding-horizon AC-MPC: at every step, solve the N-step AC optimal-control NLP and apply its first set-points.

The model is :class:`~anm_torchrl.baselines.nlp_model.ACHorizonNLP` (AC power flow, device polygons, SoC chain,
gym-anm's ΔE and penalty, discount γ) — the optimum's, over N steps instead of the episode, with no terminal
value (as gym-anm's DC-OPF MPC). Forecasts of the N steps after the state:

* ``"perfect"``: the profiles' loads and (clipped) potentials;
* ``"constant"``: the state's own loads and potentials held flat.

Warm start: a state that follows the previous solve's first step (next time index, SoC within ``soc_tol``) starts
from that solution shifted by one step, duals included; any other state starts from N do-nothing steps simulated
from it. If IPOPT fails, the solve is retried from that do-nothing start; if that fails too, the previous plan's
next step is applied (``last_info[i]["fallback"]``, a warning); without one a ``RuntimeError`` is raised.

Storage direction: the NLP splits storage P into p_ch, p_dis ≥ 0 with both free, so a plan can charge and
discharge a unit in the same step — an energy sink gym-anm's SoC update does not have (the env applies the net
p_dis − p_ch, and the next SoC is not the plan's). When a solution has min(p_ch, p_dis) > :data:`OVERLAP_TOL` at
any step, it is re-solved with every step's direction pinned from the sign of its net power (as the optimum's
round 2), warm-started from it, duals included (``last_info[i]["pinned"]``). If that pinned solve fails, the
free-split solution is applied (its net set-points are valid; its SoC path is not gym-anm's) with a warning and
``last_info[i]["pinned_failed"]``.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from anm_torchrl.baselines.nlp_model import (ACHorizonNLP, NLPResult, exogenous, rollout, storage_direction,
                                             time_indices)
from anm_torchrl.baselines.optimal import warm_start_actions
from anm_torchrl.envs.specs import check_integer
from anm_torchrl.evaluation import EVAL_GAMMA
from anm_torchrl.grid.simulator import GridSimulator

log = logging.getLogger(__name__)

FORECASTS = ("perfect", "constant")
DEFAULT_HORIZON = 16
# p.u. (100 W on ANM6-Easy's 100 MVA base): a plan whose min(p_ch, p_dis) exceeds this at any step is re-solved
# with the direction pinned. IPOPT leaves an unused p_ch or p_dis at 1e-11 to 4e-9 p.u. (interior-point round-off,
# tol 1e-9), and the real overlaps it plans are 1e-3 p.u. and more (N = 8 and 16 from the 8 test states: none in
# between). An overlap c applied for one step moves the SoC by Δt c (1/EFF − EFF): 5e-6 MWh at 1e-6 p.u. on
# ANM6-Easy, 2,000 times less than ``soc_tol``.
OVERLAP_TOL = 1e-6


@dataclasses.dataclass
class _Plan:
    """A solution kept for the state that follows: its time index ``aux``, warm start ``x``, ``lam_x``, ``lam_g``
    (already shifted one step), the set-points (k, action_dim) MW/MVAr still ahead and the SoC path (k + 1,
    n_des) MWh, row 0 the SoC that state should have."""

    aux: int
    x: np.ndarray
    lam_x: np.ndarray
    lam_g: np.ndarray
    setpoints: np.ndarray
    soc_path: np.ndarray


def _shift(v: np.ndarray, n: int) -> np.ndarray:
    """A per-step vector (n·k,) moved one step earlier, its last step repeated."""
    m = v.reshape(n, -1)
    return np.concatenate([m[1:], m[-1:]]).reshape(-1)


class ACMPCPolicy(TensorDictModuleBase):
    """AC-MPC over N steps as a TorchRL policy (one IPOPT solve per state).

    Args:
        sim: the :class:`GridSimulator`.
        horizon: number of planning steps N.
        forecast: ``"perfect"`` or ``"constant"``.
        gamma: discount of the step costs.
        formulation: ``"polar"`` or ``"rectangular"`` voltages.
        in_key: TensorDict key of the gym-anm state (..., state_dim).
        soc_tol: MWh, how close a state's SoC must be to the previous plan's to reuse it as a warm start.
        ipopt: IPOPT option overrides.
        warm_start: start each solve from the previous one shifted by a step (False: always from N simulated
            do-nothing steps; to measure what the shifted start saves).
        pin_direction: re-solve a plan whose storage charges and discharges in the same step with each step's
            direction pinned (module doc; False: apply the free split, the controller before this fix, to measure
            what the fix changes).

    ``forward`` writes ``"action"`` (..., action_dim) float32 MW/MVAr; ``last_info`` holds one dict per state of
    the last call (:meth:`plan`'s, with ``fallback``, ``soc_off_plan``: MWh between the state's SoC and the
    previous call's plan of its time index, None without one, and ``off_plan``: that distance above ``soc_tol``);
    ``infos`` those of every call, ``solve_times`` their wall seconds.
    """

    def __init__(self, sim: GridSimulator, horizon: int = DEFAULT_HORIZON, forecast: str = "perfect",
                 gamma: float = EVAL_GAMMA, formulation: str = "polar", in_key: str = "state", soc_tol: float = 1e-2,
                 ipopt: dict | None = None, warm_start: bool = True, pin_direction: bool = True):
        super().__init__()
        if forecast not in FORECASTS:
            raise ValueError(f"forecast must be one of {FORECASTS}, got {forecast!r}")
        self.in_keys, self.out_keys = [in_key], ["action"]
        self.sim, self.horizon, self.forecast, self.soc_tol = sim, check_integer("horizon", horizon, low=1), \
            forecast, float(soc_tol)
        self.warm_start, self.pin_direction = bool(warm_start), bool(pin_direction)
        self.nlp = ACHorizonNLP(sim, horizon, gamma, formulation, ipopt)
        sl = sim.state_slices()
        self._sl = sl
        lo, hi = sim.action_bounds()
        self._lo, self._hi = lo.cpu().numpy(), hi.cpu().numpy()
        self._plans: list[_Plan] = []  # the last call's solutions, as warm starts for the states that follow
        self.last_info: list[dict] = []
        self.infos: list[dict] = []
        self.solve_times: list[float] = []

    def forecasts(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Load P (N, n_load) and potential (N, n_gen) forecasts, p.u., for the N steps after ``state``."""
        n, b = self.horizon, self.sim.net.base_mva
        if self.forecast == "perfect":
            return exogenous(self.sim, time_indices(self.sim, state, n))
        p_load = state[self._sl["dev_p"]][self.sim.load_ids] / b
        return np.tile(p_load, (n, 1)), np.tile(state[self._sl["gen_p_max"]] / b, (n, 1))

    def _match(self, state: np.ndarray, plans: list[_Plan]) -> tuple[_Plan | None, float | None]:
        """The plan ``state`` follows (None if none), and its SoC's distance (MWh, max over units) to the nearest
        plan of its time index (None if none has it)."""
        aux, soc = int(round(state[self._sl["aux"]][0])), state[self._sl["des_soc"]]
        dev = [(float(np.abs(p.soc_path[0] - soc).max(initial=0.0)), p) for p in plans if p.aux == aux]
        best = min(dev, key=lambda d: d[0], default=None)
        if best is None:
            return None, None
        return (best[1] if best[0] <= self.soc_tol else None), best[0]

    def _cold_guess(self, state: np.ndarray) -> np.ndarray:
        ro = rollout(self.sim, state, warm_start_actions(self.sim, state, self.horizon, "do_nothing"))
        return self.nlp.guess(ro.p_dev, ro.q_dev, ro.v, ro.soc)

    def plan(self, state: np.ndarray, prev: _Plan | None = None) -> tuple[NLPResult, dict]:
        """Solve the N-step NLP at one state (state_dim,) MW…, warm-started from ``prev`` when given; re-solve with
        the storage direction pinned where the free split overlaps (module doc).

        Returns the solution to apply (``success`` False if IPOPT failed from both starts) and its info dict
        (``status``, ``iterations``: the free-split solve's; ``warm_status``: IPOPT's status from the shifted
        start, None without one; ``overlap``: max min(p_ch, p_dis) p.u. of the free split; ``pinned``,
        ``pinned_status``, ``pinned_iterations``, ``pinned_failed``: the pinned re-solve's; ``overlap_applied``:
        max min(p_ch, p_dis) p.u. of the solution returned; ``slack_at_bound``: whether a penalty slack of that
        solution sits at its bound, so the plan's penalty is under-counted (logged); ``solve_time``: wall s of all
        IPOPT calls; ``cpu_time``: process CPU s of all of it).
        """
        c0 = time.process_time()
        soc0 = state[self._sl["des_soc"]] / self.sim.net.base_mva
        p_load, p_pot = self.forecasts(state)
        res, warm_status, wall = None, None, 0.0
        if prev is not None:
            res = self.nlp.solve(soc0, p_load, p_pot, prev.x, lam_x0=prev.lam_x, lam_g0=prev.lam_g)
            warm_status, wall = res.status, res.solve_time
        if res is None or not res.success:
            res = self.nlp.solve(soc0, p_load, p_pot, self._cold_guess(state))
            wall += res.solve_time
        info = {"status": res.status, "iterations": res.iterations, "warm": prev is not None,
                "warm_status": warm_status, "fallback": False, "overlap": res.complementarity if res.success else None,
                "pinned": False, "pinned_status": None, "pinned_iterations": 0, "pinned_failed": False}
        if res.success and self.pin_direction and res.complementarity > OVERLAP_TOL:
            pinned = self.nlp.solve(soc0, p_load, p_pot, res.x, direction=storage_direction(self.sim, res.setpoints),
                                    lam_x0=res.lam_x, lam_g0=res.lam_g)
            wall += pinned.solve_time
            info.update(pinned=True, pinned_status=pinned.status, pinned_iterations=pinned.iterations)
            if pinned.success:
                res = pinned
            else:
                log.warning("AC-MPC: the pinned-direction re-solve failed (%s); applying the free split "
                            "(overlap %.2e p.u.)", pinned.status, res.complementarity)
                info["pinned_failed"] = True
        self.solve_times.append(wall)
        if res.success and res.slack_at_bound:  # the plan is still the best this NLP found; its penalty is not
            log.warning("AC-MPC: a penalty slack sits at its bound (SLACK_MAX, nlp_model): the plan's penalty is "
                        "under-counted; the env scores the true one")
        info.update(overlap_applied=res.complementarity if res.success else None, solve_time=wall,
                    cpu_time=time.process_time() - c0, slack_at_bound=bool(res.success and res.slack_at_bound))
        return res, info

    def act(self, states: torch.Tensor) -> torch.Tensor:
        """Actions (..., action_dim) float32 MW/MVAr for states (..., state_dim); one NLP per state."""
        flat = states.detach().reshape(-1, states.shape[-1]).cpu().double().numpy()
        out = np.empty((flat.shape[0], self.sim.action_dim))
        n, b, t_len = self.horizon, self.sim.net.base_mva, self.sim.n_time
        old, new, self.last_info = self._plans, [], []
        for i, s in enumerate(flat):
            match, soc_dev = self._match(s, old)
            prev = match if self.warm_start else None
            res, info = self.plan(s, prev)
            info.update(soc_off_plan=soc_dev, off_plan=soc_dev is not None and match is None)
            aux = (int(round(s[self._sl["aux"]][0])) + 1) % t_len
            if res.success:
                nxt = _Plan(aux, _shift(res.x, n), _shift(res.lam_x, n), _shift(res.lam_g, n), res.setpoints,
                            res.points.soc * b)
            elif prev is not None and len(prev.setpoints) > 0:
                log.warning("AC-MPC: IPOPT failed (%s) from both starts; applying the previous plan's next step",
                            info["status"])
                info["fallback"] = True
                nxt = _Plan(aux, _shift(prev.x, n), _shift(prev.lam_x, n), _shift(prev.lam_g, n), prev.setpoints,
                            prev.soc_path)
            else:
                raise RuntimeError(f"AC-MPC: IPOPT failed ({info['status']}) at a state with no earlier plan")
            out[i] = nxt.setpoints[0]
            nxt.setpoints, nxt.soc_path = nxt.setpoints[1:], nxt.soc_path[1:]  # what the next state expects
            new.append(nxt)
            self.last_info.append(info)
        self._plans = new
        self.infos.extend(self.last_info)
        out = np.clip(out, self._lo, self._hi)  # inside the polygons up to round-off; the env raises outside
        return torch.as_tensor(out, dtype=torch.float32, device=states.device).reshape(
            *states.shape[:-1], self.sim.action_dim)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict.set(self.out_keys[0], self.act(tensordict.get(self.in_keys[0])))
        return tensordict
