"""``ANM6Env``: gym-anm's ANM6-Easy as a natively batched, batch-locked TorchRL env (the true simulator)."""

from __future__ import annotations

from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from anm_torchrl.envs.specs import GRID_KEYS, check_action, make_specs, observation_from_state
from anm_torchrl.grid.simulator import GridSimulator, Transition, anm6_easy_simulator


INITS = ("gym_anm", "intended", "uniform")


class ANM6Env(EnvBase):
    """ANM6-Easy (gym-anm 2.0.1), equal to it transition by transition, for ``num_envs`` grids at once.

    Observation / state (18, gym-anm order): P of devices 0–6 (MW: slack, house, PV, factory, wind, EV, DES),
    Q of devices 0–6 (MVAr), DES SoC (MWh), PV and wind potential (MW), time-of-day index 0–95.
    Action (6): P PV ∈ [0, 30], P wind ∈ [0, 50], Q PV ∈ [−30, 30], Q wind ∈ [−50, 50], P DES ∈ [−50, 50],
    Q DES ∈ [−50, 50] (MW / MVAr); the simulator projects it onto each device's feasible set.
    Reward: −(ΔE_c + Pen_c); a step whose power flow does not converge is terminal with reward −100/(1−γ)
    and next state zeros (as gym-anm). gym-anm has no time limit: use ``make_env(max_steps=...)``.

    Args:
        num_envs: batch size N.
        device: torch device of the physics and the TensorDicts.
        seed: seed of the reset sampler (``None``: a random seed).
        action_mode: ``"raise"`` (default, like gym-anm's assert) raises ``ValueError`` on actions outside the
            box; ``"clip"`` clips them. Non-finite actions always raise.
        init: ``"gym_anm"`` samples gym-anm's initial distribution with its unit quirks (SoC in [0, 1) MWh,
            generator Q within ±0.3/±0.5 MVAr); ``"intended"`` samples SoC in [0, 100) MWh and Q in the full
            ±30/±50 MVAr range; ``"uniform"`` spreads states over the whole reachable state space
            (:meth:`GridSimulator.random_state`; the surrogates' default, as in the paper).
        sim: a custom :class:`GridSimulator` (default: ANM6-Easy).
        backend: physics backend of the default simulator: ``"auto"`` (the compiled numba loop on the CPU,
            batched torch ops elsewhere), ``"numba"`` or ``"torch"``; same transitions to round-off.

    Reset: ``env.reset()`` samples; ``env.reset(TensorDict({"state": s}, [N]), set_state=True)`` puts each env
    in the exact state ``s``; partial resets follow ``"_reset"``.
    """

    _supports_set_state = True

    def __init__(self, num_envs: int = 1, device: str | torch.device = "cpu", seed: int | None = None,
                 action_mode: Literal["raise", "clip"] = "raise", init: Literal["gym_anm", "intended", "uniform"] = "gym_anm",
                 sim: GridSimulator | None = None, backend: str = "auto"):
        if action_mode not in ("raise", "clip"):
            raise ValueError(f"action_mode must be 'raise' or 'clip', got {action_mode!r}")
        if init not in INITS:
            raise ValueError(f"init must be one of {INITS}, got {init!r}")
        if int(num_envs) < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        super().__init__(batch_size=torch.Size([int(num_envs)]), device=device)
        self.sim = sim if sim is not None else anm6_easy_simulator(self.device, backend=backend)
        self.action_mode, self.init = action_mode, init
        for name, spec in make_specs(self.sim, self.batch_size, self.device).items():
            setattr(self, name, spec)
        s_low, s_high = self.sim.state_bounds()
        a_low, a_high = self.sim.action_bounds()
        self._s_low, self._s_high, self._a_low, self._a_high = s_low, s_high, a_low, a_high
        self._aux = self.sim.state_slices()["aux"]
        self.set_seed(seed)

    def _set_seed(self, seed: int | None) -> None:
        self.rng = torch.Generator(device=self.device)
        if seed is None:
            self.rng.seed()
        else:
            self.rng.manual_seed(int(seed))

    # ------------------------------------------------------------------------------------------------------
    def _output(self, state: torch.Tensor, tr: Transition) -> TensorDict:
        f32 = torch.float32
        grid = {
            "e_loss": tr.e_loss.unsqueeze(-1), "penalty": tr.penalty.unsqueeze(-1),
            "curtailment": (tr.curtailment * self.sim.net.base_mva).unsqueeze(-1), "v_magn": tr.v.abs(),
            "branch_s": tr.s_apparent_max * self.sim.net.base_mva,
        }
        return TensorDict(
            {"state": state, "observation": observation_from_state(state, self._s_low, self._s_high),
             "grid": {k: grid[k].to(f32) for k in GRID_KEYS}},
            batch_size=self.batch_size, device=self.device)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = check_action(tensordict.get("action"), self._a_low, self._a_high, clip=self.action_mode == "clip")
        state = tensordict.get("state")
        next_state, tr = self.sim.step(state, action)
        out = self._output(next_state, tr)
        terminated = (~tr.converged).unsqueeze(-1)
        out.set("reward", tr.reward.to(torch.float32).unsqueeze(-1))
        out.set("terminated", terminated)
        out.set("done", terminated.clone())
        return out

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        n = self.batch_size[0]
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(n)
        if kwargs.get("set_state") and tensordict is not None and "state" in tensordict.keys():
            state = self.validate_state(tensordict.get("state"))
            tr = self.sim.operating_point(state)
        else:
            rows = n if mask is None else int(mask.sum())
            if self.init == "uniform":
                state_rows, tr_rows = self.sim.random_state(rows, self.rng)
            else:
                state_rows, tr_rows = self.sim.reset(rows, self.rng, intended=self.init == "intended")
            if mask is None:
                state, tr = state_rows, tr_rows
            else:  # values of rows not reset are discarded by TorchRL; only the masked rows are solved
                state, tr = self._scatter_rows(mask, state_rows, tr_rows)
        out = self._output(state, tr)
        out.set("terminated", torch.zeros(n, 1, dtype=torch.bool, device=self.device))
        out.set("done", torch.zeros(n, 1, dtype=torch.bool, device=self.device))
        return out

    def _scatter_rows(self, mask: torch.Tensor, state_rows: torch.Tensor, tr_rows: Transition):
        idx = mask.nonzero().squeeze(1)
        n = self.batch_size[0]

        def full(x: torch.Tensor) -> torch.Tensor:
            return x.new_zeros((n, *x.shape[1:])).index_copy(0, idx, x)

        tr = Transition(**{k: full(v) for k, v in vars(tr_rows).items()})
        return full(state_rows), tr

    def validate_state(self, state: torch.Tensor) -> torch.Tensor:
        """Check a state batch given to ``reset(..., set_state=True)``; returns it as float64.

        Raises ``ValueError`` on a wrong shape, non-finite entries, a time index that is not an integer in
        [0, 95], or a SoC outside the storage range.
        """
        n, d = self.batch_size[0], self.sim.state_dim
        if tuple(state.shape) != (n, d):
            raise ValueError(f"state must have shape ({n}, {d}), got {tuple(state.shape)}")
        state = state.to(self.device, torch.float64)
        bad = ~torch.isfinite(state)
        if bad.any():
            envs, entries = bad.nonzero(as_tuple=True)
            raise ValueError(f"non-finite state at (env, entry) {list(zip(envs.tolist(), entries.tolist()))[:5]}")
        aux = state[:, self._aux].squeeze(1)
        bad_aux = (aux != aux.round()) | (aux < 0) | (aux > self.sim.n_time - 1)
        if bad_aux.any():
            raise ValueError(f"time index (state entry {self._aux.start}) must be an integer in "
                             f"[0, {self.sim.n_time - 1}]; envs {bad_aux.nonzero().squeeze(1).tolist()[:5]} "
                             f"have {aux[bad_aux].tolist()[:5]}")
        soc = state[:, self.sim.state_slices()["des_soc"]]
        soc_max = self.sim.state_bounds()[1][self.sim.state_slices()["des_soc"]]
        bad_soc = ((soc < 0) | (soc > soc_max)).any(1)
        if bad_soc.any():
            raise ValueError(f"SoC (MWh) must lie in [0, {soc_max.tolist()}]; envs "
                             f"{bad_soc.nonzero().squeeze(1).tolist()[:5]} have {soc[bad_soc].tolist()[:5]}")
        return state
