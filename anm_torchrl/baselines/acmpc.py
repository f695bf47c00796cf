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
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from anm_torchrl.baselines.nlp_model import ACHorizonNLP, NLPResult, exogenous, rollout, time_indices
from anm_torchrl.baselines.optimal import EVAL_GAMMA, warm_start_actions
from anm_torchrl.grid.simulator import GridSimulator

log = logging.getLogger(__name__)

FORECASTS = ("perfect", "constant")
DEFAULT_HORIZON = 16


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

    ``forward`` writes ``"action"`` (..., action_dim) float32 MW/MVAr; ``last_info`` holds one dict per state of
    the last call (``status``, ``iterations``, ``solve_time``, ``cpu_time``, ``warm``, ``fallback``); ``infos``
    those of every call, ``solve_times`` their wall seconds.
    """

    def __init__(self, sim: GridSimulator, horizon: int = DEFAULT_HORIZON, forecast: str = "perfect",
                 gamma: float = EVAL_GAMMA, formulation: str = "polar", in_key: str = "state", soc_tol: float = 1e-2,
                 ipopt: dict | None = None, warm_start: bool = True):
        super().__init__()
        if forecast not in FORECASTS:
            raise ValueError(f"forecast must be one of {FORECASTS}, got {forecast!r}")
        self.in_keys, self.out_keys = [in_key], ["action"]
        self.sim, self.horizon, self.forecast, self.soc_tol = sim, int(horizon), forecast, float(soc_tol)
        self.warm_start = bool(warm_start)
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

    def _match(self, state: np.ndarray, plans: list[_Plan]) -> _Plan | None:
        aux, soc = int(round(state[self._sl["aux"]][0])), state[self._sl["des_soc"]]
        return next((p for p in plans if p.aux == aux and np.all(np.abs(p.soc_path[0] - soc) <= self.soc_tol)), None)

    def _cold_guess(self, state: np.ndarray) -> np.ndarray:
        ro = rollout(self.sim, state, warm_start_actions(self.sim, state, self.horizon, "do_nothing"))
        return self.nlp.guess(ro.p_dev, ro.q_dev, ro.v, ro.soc)

    def plan(self, state: np.ndarray, prev: _Plan | None = None) -> tuple[NLPResult, dict]:
        """Solve the N-step NLP at one state (state_dim,) MW…, warm-started from ``prev`` when given.

        Returns the last solve (``success`` False if IPOPT failed from both starts) and its info dict
        (``warm_status``: IPOPT's status from the shifted start, None without one; ``status`` the last solve's).
        """
        c0 = time.process_time()
        soc0 = state[self._sl["des_soc"]] / self.sim.net.base_mva
        p_load, p_pot = self.forecasts(state)
        res, warm_status = None, None
        if prev is not None:
            res = self.nlp.solve(soc0, p_load, p_pot, prev.x, lam_x0=prev.lam_x, lam_g0=prev.lam_g)
            warm_status = res.status
        if res is None or not res.success:
            res = self.nlp.solve(soc0, p_load, p_pot, self._cold_guess(state))
        self.solve_times.append(res.solve_time)
        return res, {"status": res.status, "iterations": res.iterations, "solve_time": res.solve_time,
                     "cpu_time": time.process_time() - c0, "warm": prev is not None, "warm_status": warm_status,
                     "fallback": False}

    def act(self, states: torch.Tensor) -> torch.Tensor:
        """Actions (..., action_dim) float32 MW/MVAr for states (..., state_dim); one NLP per state."""
        flat = states.detach().reshape(-1, states.shape[-1]).cpu().double().numpy()
        out = np.empty((flat.shape[0], self.sim.action_dim))
        n, b, t_len = self.horizon, self.sim.net.base_mva, self.sim.n_time
        old, new, self.last_info = self._plans, [], []
        for i, s in enumerate(flat):
            prev = self._match(s, old) if self.warm_start else None
            res, info = self.plan(s, prev)
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
