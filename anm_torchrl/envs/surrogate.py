"""``SurrogateEnv``: any learned transition model as a TorchRL env with the specs of the true env."""

from __future__ import annotations

import logging

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase

from anm_torchrl.envs.anm_env import ANMEnv
from anm_torchrl.envs.specs import GRID_KEYS, check_action, grid_sizes
from anm_torchrl.grid.simulator import GridSimulator

log = logging.getLogger(__name__)
#: (steps per env, share of row-steps): after this many steps per env, a model that ended more than this share of
#: its steps in a termination is named in a warning. The true simulators end an episode only where the power flow
#: has no solution, which is rare: a surrogate that ends one step in ten likely predicts terminations that are not
#: there (an inaccurate model, e.g. the PINN's ``smoke`` preset), and a policy trained on it learns from episodes a
#: few steps long
TERMINATION_CHECK = (20, 0.1)


class TerminationWatch:
    """Counts a model's terminations over its first :data:`TERMINATION_CHECK` steps per row and warns once if they
    are far too many (a surrogate env's steps, SHAC's rollouts through the PINN)."""

    def __init__(self, name: str, rows: int):
        self.name, self.rows = name, int(rows)
        self.stepped, self.terminated, self.done = 0, 0, False

    def __call__(self, terminated: torch.Tensor) -> None:
        """Count ``terminated`` (any shape, bool) until the check has run."""
        if self.done:
            return
        self.stepped += terminated.numel()
        self.terminated += int(terminated.sum())
        steps, share = TERMINATION_CHECK
        if self.stepped < steps * self.rows:
            return
        self.done = True
        rate = self.terminated / self.stepped
        if rate > share:
            log.warning("the surrogate model %s ended %.0f %% of its first %d steps in a termination (an episode "
                        "every %.1f steps); the true simulator ends one only where the power flow has no solution: "
                        "its terminal predictions are likely wrong (an inaccurate model, e.g. a smoke preset), and "
                        "a policy trained on it learns from episodes that short", self.name, 100 * rate,
                        self.stepped, 1 / rate)


class SurrogateEnv(ANMEnv):
    """An env whose transition is a learned ``model`` instead of the simulator; specs equal the true env's.

    The model is a ``TensorDictModule`` (or sequence) that reads ``"state"`` (N, state_dim) float64 and
    ``"action"`` (N, action_dim) float64 MW/MVAr (validated as in ``ANMEnv``) and writes ``"next_state"``
    (N, state_dim), ``"reward"`` (N, 1) and ``"terminated"`` (N, 1) bool, plus any ``("grid", k)`` diagnostics
    it can predict (the others are NaN). Under the perfect-foresight assumption the env, not the model, writes
    the exogenous entries of the next state — load P/Q, generator potentials and the auxiliary variable — from
    the simulator's ``next_vars``; terminal rows get the terminal reward and a zero state, as in gym-anm.

    A model that carries a ``transition_key`` attribute must have been built for this env's network and profiles
    (:func:`anm_torchrl.grid.identity.transition_key`); another key raises ``ValueError``.

    Resets reuse the simulator's samplers (``init="uniform"`` by default, as in the paper; ``"gym_anm"`` for
    gym-anm's ANM6-Easy distribution); ``set_state`` and ``"_reset"`` behave as in ``ANMEnv``.

    Args:
        model: the transition model; moved to ``device`` and frozen (``requires_grad_(False)``).
        num_envs, device, seed, action_mode: as ``ANMEnv``.
        init: reset distribution, ``"uniform"`` (default), ``"gym_anm"``, ``"intended"`` or a callable.
        sim: the simulator providing specs, exogenous variables and resets (required unless ``network`` is
            given).
        **network: ``ANMEnv`` arguments (``network``, ``load_p``, ``gen_p_max``, ``observation``, ``delta_t``,
            ``gamma``, ``lamb``, ``costs_clipping``, ``next_vars``, ``backend``) to run on another network.
            The observation must be computable from the state (no bus or branch quantities).
    """

    def __init__(self, model: TensorDictModuleBase, num_envs: int = 1, device="cpu", seed: int | None = None,
                 action_mode: str = "raise", init="uniform", sim: GridSimulator | None = None, **network):
        if sim is None and "network" not in network:
            raise ValueError("SurrogateEnv needs the network it runs on: sim=anm_torchrl.networks.simulator(...) or "
                             "network=/load_p=/gen_p_max=")
        super().__init__(num_envs=num_envs, device=device, seed=seed, action_mode=action_mode, init=init, sim=sim,
                         **network)
        if self.obs_map.needs_grid:
            raise ValueError("a SurrogateEnv observation must come from the state alone (dev_*, des_soc, "
                             "gen_p_max, aux); bus and branch quantities need the true power flow")
        key = getattr(model, "transition_key", None)
        if key is not None and key != self.transition_key:
            raise ValueError(f"the model was built for another network (transition_key {key[:12]}…), this env runs "
                             f"{self.transition_key[:12]}…")
        self.model = model.to(self.device).requires_grad_(False)
        self._grid_sizes = grid_sizes(self.sim)
        self.termination_watch = TerminationWatch(type(model).__name__, self.batch_size.numel())

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = check_action(tensordict.get("action"), self._a_box, clip=self.action_mode == "clip")
        state = self.validate_state(tensordict.get("state"))
        with torch.no_grad():
            pred = self.model(TensorDict({"state": state, "action": action}, batch_size=self.batch_size))
        name = type(self.model).__name__
        terminated = pred.get("terminated")
        if terminated.dtype != torch.bool:  # a probability cast to bool would end every row
            raise ValueError(f"the surrogate model {name} wrote 'terminated' as {terminated.dtype}; it must be bool")
        terminated = terminated.reshape(-1, 1)
        reward = pred.get("reward").reshape(-1).to(torch.float64)
        # the env writes the exogenous entries (loads, potentials, time): the model's own there are not checked
        next_state = self.sim.with_next_vars(pred.get("next_state").to(torch.float64), *self.sim.next_vars(state))
        live = ~terminated.squeeze(1)
        finite = torch.isfinite(reward) & torch.isfinite(next_state).all(-1)
        if not bool((finite | ~live).all()):  # a NaN reward would enter the data unnoticed
            rows = (~finite & live).nonzero().flatten()[:5].tolist()
            raise ValueError(f"the surrogate model {name} predicted a non-finite reward or next state for "
                             f"non-terminated rows {rows}")
        try:  # e.g. a SoC out of its bounds: refused here, not at the next step (or never, at a time limit)
            self.sim.check_state(next_state if bool(live.all()) else next_state[live])
        except ValueError as err:
            raise ValueError(f"the surrogate model {name} predicted a next state no transition can start from "
                             f"(among its non-terminated rows): {err}") from None
        self.termination_watch(terminated)
        reward = torch.where(terminated.squeeze(1), torch.full_like(reward, self.sim.terminal_reward), reward)
        next_state = torch.where(terminated, torch.zeros_like(next_state), next_state)
        nan = float("nan")
        grid = {k: pred.get(("grid", k), None) for k in GRID_KEYS}
        grid = {k: (v.reshape(-1, n) if v is not None else state.new_full((state.shape[0], n), nan)).to(torch.float32)
                for (k, v), n in zip(grid.items(), self._grid_sizes.values())}
        return TensorDict(
            {"state": next_state, "observation": self.obs_map.observe(next_state, None, terminated.squeeze(1)),
             "grid": grid, "reward": reward.to(torch.float32).unsqueeze(-1), "terminated": terminated,
             "done": terminated.clone()},
            batch_size=self.batch_size, device=self.device)
