"""``ANMEnv``: gym-anm 2.0.1's generic ``ANMEnv`` on any network, natively batched and batch-locked (TorchRL)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from anm_torchrl.envs.observation import ObservationMap
from anm_torchrl.envs.specs import GRID_KEYS, ActionBox, check_action, check_integer, make_specs
from anm_torchrl.grid import reset as grid_reset
from anm_torchrl.grid.identity import transition_key
from anm_torchrl.grid.simulator import GridSimulator, Transition
from anm_torchrl.networks import simulator as network_simulator

INITS = ("uniform", "gym_anm", "intended")


class ANMEnv(EnvBase):
    """gym-anm's generic environment on ``network``, equal to it transition by transition, for N grids at once.

    State (gym-anm order, float64): P of every device (MW, device-id order), Q (MVAr), SoC of each storage
    unit (MWh), potential of each non-slack generator (MW), the time index t. Action (float32): P of the
    non-slack generators, their Q, P of the storage units, their Q (MW / MVAr), inside gym-anm's action box
    (``action_mode="clip"`` clips instead of raising); the simulator projects it onto each device's feasible set.
    Reward: −(ΔE_c + Pen_c); a step whose power flow does not converge is terminal, with reward
    −costs_clipping[1] / (1 − γ) and a zero state and observation (as gym-anm). No time limit (gym-anm has none).

    Exogenous variables: a step from time index t reads row (t + 1) mod T of ``load_p`` and ``gen_p_max``
    (ANM6-Easy's rule). ``next_vars(state) -> (load P (N, n_load) MW, potentials (N, n_gen) MW, aux (N, 1))``
    replaces that rule with a batched user function (e.g. stochastic profiles); the aux check of states is then
    left to it.

    Args:
        network: gym-anm network dict (built by :func:`anm_torchrl.networks.simulator`: gym-anm's checks).
        load_p: (T, n_load) MW, loads in device-id order.
        gen_p_max: (T, n_gen) MW, non-slack generators (classical and renewable) in device-id order.
        num_envs: batch size N.
        observation: ``"state"`` or gym-anm's list of ``(quantity, ids | "all", unit)``
            (:class:`~anm_torchrl.envs.observation.ObservationMap`); float32, clipped to gym-anm's bounds.
        delta_t, gamma, lamb, costs_clipping: as gym-anm (h; discount; penalty factor; clipping of |ΔE| and λΦ).
        seed: seed of the reset sampler (``None``: random); one generator draws the whole batch, so the state env i
            starts from depends on ``num_envs`` too.
        device: torch device of the physics and the TensorDicts.
        backend: ``"auto"`` (numba on the CPU), ``"numba"`` or ``"torch"``; the same transitions to round-off.
        action_mode: ``"raise"`` (as gym-anm's assert) or ``"clip"``.
        init: reset distribution. ``"uniform"`` (default): time index uniform in [0, T), SoC uniform in
            [SOC_MIN, SOC_MAX), set-points uniform over the action box, then one transition solved at that time
            index (projection, SoC update, power flow); non-converging draws are re-drawn (100 attempts).
            ``"gym_anm"`` / ``"intended"``: ANM6-Easy's ``init_state`` distribution (with / without its unit
            quirks). A callable ``init(n, generator) -> (n, state_dim)`` MW… acts as gym-anm's ``init_state``:
            each state goes through gym-anm's ``Simulator.reset`` (projection, power flow) and is re-drawn if
            its power flow fails.
        next_vars: optional batched exogenous-variable hook (see above).
        sim: a ready :class:`GridSimulator` instead of ``network``/profiles/constants (presets, surrogates).

    Reset: ``env.reset()`` samples; ``env.reset(TensorDict({"state": s}, [N]), set_state=True)`` puts each env
    in the exact state ``s`` (validated; a state whose power flow does not converge is reported terminated);
    partial resets follow ``"_reset"``. ``transition_key``: :func:`anm_torchrl.grid.identity.transition_key` (network,
    profiles, constants).
    """

    _supports_set_state = True

    def __init__(self, network: dict | None = None, load_p=None, gen_p_max=None, num_envs: int = 1,
                 observation="state", delta_t: float = 0.25, gamma: float = 0.995, lamb: float = 100,
                 costs_clipping=(1, 100), seed: int | None = None, *, device: str | torch.device = "cpu",
                 backend: str = "auto", action_mode: Literal["raise", "clip"] = "raise",
                 init: str | Callable = "uniform", next_vars: Callable | None = None,
                 sim: GridSimulator | None = None):
        if action_mode not in ("raise", "clip"):
            raise ValueError(f"action_mode must be 'raise' or 'clip', got {action_mode!r}")
        if not callable(init) and init not in INITS:
            raise ValueError(f"init must be one of {INITS} or a callable, got {init!r}")
        num_envs = check_integer("num_envs", num_envs, low=1)  # 2.7 is an error, not 2 envs
        super().__init__(batch_size=torch.Size([num_envs]), device=device, allow_done_after_reset=True)
        if sim is None:
            if network is None or load_p is None or gen_p_max is None:
                raise ValueError("ANMEnv needs network=, load_p= and gen_p_max=, or a ready sim=")
            sim = network_simulator(network, load_p, gen_p_max, delta_t=delta_t, gamma=gamma, lamb=lamb,
                                    costs_clipping=costs_clipping, device=self.device, backend=backend,
                                    next_vars=next_vars)
        elif network is not None or load_p is not None or gen_p_max is not None or next_vars is not None:
            raise ValueError("pass either sim= or network=/load_p=/gen_p_max=/next_vars=, not both")
        if init in ("gym_anm", "intended"):
            from anm_torchrl.networks.resolve import is_anm6

            if not is_anm6(sim):
                raise ValueError(f"init={init!r} is ANM6-Easy's initial distribution (its init_state, with its "
                                 f"device indices and unit quirks); this network is not ANM6-Easy: use "
                                 f"init='uniform' or a callable sampler")
        self.sim = sim
        self.action_mode, self.init = action_mode, init
        # the time variable's bounds: with a next_vars hook its own (gym-anm's aux_bounds=None: unbounded)
        aux_bounds = (0.0, float(sim.n_time - 1)) if sim.next_vars_hook is None else (-math.inf, math.inf)
        self.obs_map = ObservationMap(sim, observation, aux_bounds)
        # the "state" observation's bounds in the form the backend's output pass reads (None: the map clips)
        self._obs_bounds = sim.physics.output_bounds(self.obs_map.low, self.obs_map.high) if self.obs_map.is_state \
            else None
        for name, spec in make_specs(sim, self.batch_size, self.device, self.obs_map).items():
            setattr(self, name, spec)
        self._a_low, self._a_high = sim.action_bounds()
        self._a_box = ActionBox.of(self._a_low, self._a_high)
        self.transition_key = transition_key(sim)
        self.set_seed(seed)

    def _set_seed(self, seed: int | None) -> None:
        self.rng = torch.Generator(device=self.device)
        if seed is None:
            self.rng.seed()
        else:
            self.rng.manual_seed(check_integer("seed", seed))

    # ------------------------------------------------------------------------------------------------------
    def _output(self, state: torch.Tensor, tr: Transition) -> tuple[TensorDict, torch.Tensor, torch.Tensor]:
        """The TensorDict of ``state`` and ``tr`` (state, observation, grid), and tr's reward (N, 1) float32 and
        ``terminated`` (N, 1), from the backend's ``env_outputs`` (numba: one compiled pass, bit for bit the torch
        backend's ops)."""
        out = self.sim.physics.env_outputs(state, tr, self.sim.net.base_mva, self._obs_bounds)
        grid = {k: out[k] for k in GRID_KEYS}
        obs, reward, terminated = out.get("observation"), out["reward"], out["terminated"]
        if obs is None:
            obs = self.obs_map.observe(state, tr.v if self.obs_map.needs_grid else None, ~tr.converged)
        td = TensorDict({"state": state, "observation": obs, "grid": grid}, batch_size=self.batch_size,
                        device=self.device)
        return td, reward, terminated

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = check_action(tensordict.get("action"), self._a_box, clip=self.action_mode == "clip")
        state = tensordict.get("state")
        ended = tensordict.get("terminated", None)
        ended = None if ended is None or not bool(ended.any()) else ended.reshape(-1, 1).to(self.device)
        if ended is not None:  # stepped from a stand-in, then written back as gym-anm keeps them (below)
            state = torch.where(ended, self._stand_in().to(self.device), state.to(self.device, torch.float64))
        state = self.validate_state(state)
        next_state, tr = self.sim.step(state, action)
        out, reward, terminated = self._output(next_state, tr)
        if ended is not None:
            reward, terminated = self._keep_terminal(out, reward, terminated, ended)
        out.set("reward", reward)
        out.set("terminated", terminated)
        out.set("done", terminated.clone())
        return out

    def _stand_in(self) -> torch.Tensor:
        """A valid state (1, state_dim) to step a terminated row from (its zero state may fail the SoC check)."""
        if getattr(self, "_stand_in_state", None) is None:
            self._stand_in_state = grid_reset.random_state(self.sim, 1, torch.Generator().manual_seed(0))[0]
        return self._stand_in_state

    def _keep_terminal(self, out: TensorDict, reward: torch.Tensor, terminated: torch.Tensor,
                       ended: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A row terminated before this step stays terminal, as in gym-anm: zero state and observation, reward 0,
        ``terminated`` (no energy, penalty or curtailment; voltages and flows missing). Returns (reward,
        terminated)."""
        for key in ("state", "observation"):
            out.set(key, out.get(key).masked_fill(ended, 0.0))
        for key, value in out.get("grid").items():
            missing = 0.0 if key in ("e_loss", "penalty", "curtailment") else float("nan")
            out.set(("grid", key), value.masked_fill(ended, missing))
        return reward.masked_fill(ended, 0.0), terminated | ended

    def _sample(self, rows: int) -> tuple[torch.Tensor, Transition]:
        if callable(self.init):
            return grid_reset.reset_with(self.sim, self.init, rows, self.rng)
        if self.init == "uniform":
            return grid_reset.random_state(self.sim, rows, self.rng)
        return grid_reset.gym_anm_reset(self.sim, rows, self.rng, intended=self.init == "intended")

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        n = self.batch_size[0]
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset")
            if mask.dtype != torch.bool or mask.numel() != n:
                raise ValueError(f"'_reset' must be a bool mask of {n} entries (shape ({n}, 1)), got {mask.dtype} "
                                 f"{tuple(mask.shape)}")
            mask = mask.reshape(n)
        terminated = torch.zeros(n, 1, dtype=torch.bool, device=self.device)
        if kwargs.get("set_state"):
            if tensordict is None or "state" not in tensordict.keys():
                raise ValueError("reset(..., set_state=True) needs a TensorDict with a 'state' entry (N, "
                                 f"{self.sim.state_dim}); got {None if tensordict is None else list(tensordict.keys())}")
            state = tensordict.get("state")
            if mask is None:
                state = self.validate_state(state)
                tr = self.sim.operating_point(state)
            else:  # only the rows being reset are checked and solved (the others may be terminal zeros)
                if state.ndim != 2 or state.shape[0] != n:
                    raise ValueError(f"state must have shape ({n}, {self.sim.state_dim}), got {tuple(state.shape)}")
                rows = state[mask].to(self.device, torch.float64)
                self.sim.check_state(rows)
                state, tr = self._scatter_rows(mask, rows, self.sim.operating_point(rows))
                tr.converged = tr.converged | ~mask
            terminated = (~tr.converged).unsqueeze(-1)  # no power-flow solution: a terminal state
        else:
            rows = n if mask is None else int(mask.sum())
            state_rows, tr_rows = self._sample(rows)
            self.sim.check_state(state_rows)  # every reset passes the one state validator (as set_state, step)
            if mask is None:
                state, tr = state_rows, tr_rows
            else:  # values of rows not reset are discarded by TorchRL; only the masked rows are solved
                state, tr = self._scatter_rows(mask, state_rows, tr_rows)
                tr.converged = tr.converged | ~mask  # rows left alone are not made terminal by the fill
        out = self._output(state, tr)[0]
        out.set("terminated", terminated)
        out.set("done", terminated.clone())
        return out

    def _scatter_rows(self, mask: torch.Tensor, state_rows: torch.Tensor, tr_rows: Transition):
        idx = mask.nonzero().squeeze(1)
        n = self.batch_size[0]

        def full(x: torch.Tensor) -> torch.Tensor:
            return x.new_zeros((n, *x.shape[1:])).index_copy(0, idx, x)

        tr = Transition(**{k: full(v) for k, v in vars(tr_rows).items()})
        return full(state_rows), tr

    def validate_state(self, state: torch.Tensor) -> torch.Tensor:
        """The one state check of ``set_state`` and ``step`` (:meth:`GridSimulator.check_state`): shape, finite
        entries, SoC within [SOC_MIN, SOC_MAX], integer time index in [0, T - 1]. Returns it as float64."""
        n = self.batch_size[0]
        if state.ndim != 2 or state.shape[0] != n:
            raise ValueError(f"state must have shape ({n}, {self.sim.state_dim}), got {tuple(state.shape)}")
        state = state.to(self.device, torch.float64)
        self.sim.check_state(state)
        return state
