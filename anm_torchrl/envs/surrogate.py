"""``SurrogateEnv``: any learned transition model as a TorchRL env with the specs of ``ANM6Env``."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase

from anm_torchrl.envs.anm6 import ANM6Env
from anm_torchrl.envs.specs import GRID_KEYS, check_action, grid_sizes, observation_from_state
from anm_torchrl.grid.simulator import GridSimulator


class SurrogateEnv(ANM6Env):
    """An env whose transition is a learned ``model`` instead of the simulator; specs equal ``ANM6Env``'s.

    The model is a ``TensorDictModule`` (or sequence) that reads ``"state"`` (N, 18) float64 and ``"action"``
    (N, 6) float64 MW/MVAr (validated as in ``ANM6Env``) and writes ``"next_state"`` (N, 18), ``"reward"``
    (N, 1) and ``"terminated"`` (N, 1) bool, plus any ``("grid", k)`` diagnostics it can predict (the others
    are NaN). Under the perfect-foresight assumption the env, not the model, writes the exogenous entries of
    the next state — load P/Q, renewable potentials and the time index — from the time series; terminal rows
    get the simulator's terminal reward and a zero state, as in gym-anm.

    Resets reuse the simulator's samplers (``init="uniform"`` by default, as in the paper; ``"gym_anm"`` for
    gym-anm's distribution); ``set_state`` and ``"_reset"`` behave as in ``ANM6Env``.

    Args:
        model: the transition model; moved to ``device`` and frozen (``requires_grad_(False)``).
        num_envs, device, seed, action_mode: as ``ANM6Env``.
        init: reset distribution, ``"uniform"`` (default), ``"gym_anm"`` or ``"intended"``.
        sim: the simulator providing specs, time series and resets (default ANM6-Easy).
    """

    def __init__(self, model: TensorDictModuleBase, num_envs: int = 1, device="cpu", seed: int | None = None,
                 action_mode: str = "raise", init: str = "uniform", sim: GridSimulator | None = None):
        super().__init__(num_envs=num_envs, device=device, seed=seed, action_mode=action_mode, init=init, sim=sim)
        self.model = model.to(self.device).requires_grad_(False)
        self._grid_sizes = grid_sizes(self.sim)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = check_action(tensordict.get("action"), self._a_low, self._a_high, clip=self.action_mode == "clip")
        state = tensordict.get("state")
        with torch.no_grad():
            pred = self.model(TensorDict({"state": state, "action": action}, batch_size=self.batch_size))
        terminated = pred.get("terminated").reshape(-1, 1).to(torch.bool)
        reward = pred.get("reward").reshape(-1).to(torch.float64)
        reward = torch.where(terminated.squeeze(1), torch.full_like(reward, self.sim.terminal_reward), reward)
        aux_next = (state[:, self._aux].squeeze(1).round().long() + 1) % self.sim.n_time
        next_state = self.sim.with_exogenous(pred.get("next_state").to(torch.float64), aux_next)
        next_state = torch.where(terminated, torch.zeros_like(next_state), next_state)
        nan = float("nan")
        grid = {k: pred.get(("grid", k), None) for k in GRID_KEYS}
        grid = {k: (v.reshape(-1, n) if v is not None else state.new_full((state.shape[0], n), nan)).to(torch.float32)
                for (k, v), n in zip(grid.items(), self._grid_sizes.values())}
        return TensorDict(
            {"state": next_state, "observation": observation_from_state(next_state, self._s_low, self._s_high),
             "grid": grid, "reward": reward.to(torch.float32).unsqueeze(-1), "terminated": terminated,
             "done": terminated.clone()},
            batch_size=self.batch_size, device=self.device)
