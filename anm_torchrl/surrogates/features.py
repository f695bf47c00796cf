"""Inputs and targets of the data-driven surrogates (shared by the regressors and the terminal classifier).

Inputs (``Featurizer``, all float64, N rows):

* the state_dim state entries (gym-anm order, MW / MVAr / MWh / time index; 18 on ANM6-Easy), named by
  ``GridState`` block (:func:`state_names`),
* ``sin`` and ``cos`` of the time of day (2π·aux/T), so that linear models and networks see the daily cycle,
* the action_dim action entries (MW / MVAr; 6 on ANM6-Easy),
* with ``foresight`` (default): the exogenous values of the *next* step — load P (MW) and clipped renewable
  potentials (MW) from the simulator's ``next_vars`` (its time series at ``aux + 1``). The surrogate env has
  perfect foresight of them anyway (it writes them into the next state), and the projection and the power flow of the
  step depend on them, not on the current ones.

Targets (``target_layout``): the next-state entries the physics decides — P and Q of the slack, the renewable
generators and the storage, the storage SoC — followed by the reward. Load P/Q, potentials and the time
index of the next state are exogenous and written by ``SurrogateEnv``.
"""

from __future__ import annotations

import math

import torch

from anm_torchrl.networks.resolve import is_anm6
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.grid.state import STATE_KEYS, from_vector

ANM6_DEVICE_NAMES = {0: "slack", 1: "load1", 2: "pv", 3: "load3", 4: "wind", 5: "load5", 6: "des"}


def device_names(sim: GridSimulator) -> list[str]:
    """A name per device: ANM6-Easy's (``slack``, ``pv``, ``wind``, ``des``, ``load<i>``), ``dev<i>`` elsewhere."""
    names = ANM6_DEVICE_NAMES if is_anm6(sim) else {}
    return [names.get(i, f"dev{i}") for i in range(sim.net.n_dev)]


def state_names(sim: GridSimulator) -> list[str]:
    """Names of the state entries, e.g. ``p_slack`` (MW), ``q_pv`` (MVAr), ``soc_des`` (MWh), ``aux``, in the order
    of the ``GridState`` blocks (:data:`anm_torchrl.grid.state.STATE_KEYS`)."""
    dev = device_names(sim)
    per_block = {"dev_p": [f"p_{d}" for d in dev], "dev_q": [f"q_{d}" for d in dev],
                 "des_soc": [f"soc_{dev[i]}" for i in sim.des_ids],
                 "gen_p_max": [f"p_pot_{dev[i]}" for i in sim.gen_ids], "aux": ["aux"]}
    return [n for k in STATE_KEYS for n in per_block[k]]


def target_layout(sim: GridSimulator) -> tuple[list[int], list[str]]:
    """Indices (into the state) of the predicted next-state entries and the names of all targets.

    Returns ``(index, names)``: ``index`` has the state positions of P/Q of the slack, generators and storage
    and of the SoC; ``names`` has their names followed by ``"reward"``.
    """
    sl = sim.state_slices()
    devs = sorted(sim.slack_ids + sim.gen_ids + sim.des_ids)
    index = ([sl["dev_p"].start + d for d in devs] + [sl["dev_q"].start + d for d in devs]
             + list(range(sl["des_soc"].start, sl["des_soc"].stop)))
    names = state_names(sim)
    return index, [names[i] for i in index] + ["reward"]


class Featurizer:
    """Map ``(state (N, S), action (N, A))`` float64 to model inputs ``(N, F)`` float64 (see module doc).

    Args:
        sim: the simulator whose layout and time series are used.
        foresight: append next-step loads and potentials.
    """

    def __init__(self, sim: GridSimulator, foresight: bool = True):
        self.sim, self.foresight = sim, bool(foresight)
        dev = device_names(sim)
        a_names = [f"a_p_{dev[i]}" for i in sim.gen_ids] + [f"a_q_{dev[i]}" for i in sim.gen_ids]
        a_names += [f"a_p_{dev[i]}" for i in sim.des_ids] + [f"a_q_{dev[i]}" for i in sim.des_ids]
        names = state_names(sim) + ["time_sin", "time_cos"] + a_names
        if self.foresight:
            names += [f"next_p_{dev[i]}" for i in sim.load_ids] + [f"next_p_pot_{dev[i]}" for i in sim.gen_ids]
        self.names = names

    @property
    def n_features(self) -> int:
        return len(self.names)

    def __call__(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        sim = self.sim
        if state.ndim != 2 or state.shape[1] != sim.state_dim:
            raise ValueError(f"state must have shape (N, {sim.state_dim}), got {tuple(state.shape)}")
        if action.ndim != 2 or action.shape[1] != sim.action_dim or action.shape[0] != state.shape[0]:
            raise ValueError(f"action must have shape ({state.shape[0]}, {sim.action_dim}), got {tuple(action.shape)}")
        state = state.to(torch.float64)
        action = action.to(torch.float64)
        aux = from_vector(state, sim.state_sizes)["aux"][:, 0]
        ang = 2 * math.pi * aux / sim.n_time
        cols = [state, torch.sin(ang).unsqueeze(1), torch.cos(ang).unsqueeze(1), action]
        if self.foresight:  # the simulator's own next_vars (so a next_vars hook is followed), clipped as it uses them
            b = sim.net.base_mva
            p_load, p_pot, _ = sim.next_vars(state.to(sim.net.dev.device))
            cols += [sim.load_pq(p_load / b)[0].to(state.device) * b, sim.clip_p_pot(p_pot / b).to(state.device) * b]
        return torch.cat(cols, 1)
