"""``ANM6Env``: gym-anm's ANM6-Easy as a preset of :class:`~anm_torchrl.envs.anm_env.ANMEnv`."""

from __future__ import annotations

from typing import Literal

import torch

from anm_torchrl.envs.anm_env import INITS, ANMEnv
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator


class ANM6Env(ANMEnv):
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
            (:func:`anm_torchrl.grid.reset.random_state`; the surrogates' default, as in the paper).
        sim: a custom :class:`GridSimulator` (default: ANM6-Easy).
        backend: physics backend of the default simulator: ``"auto"`` (the compiled numba loop on the CPU,
            batched torch ops elsewhere), ``"numba"`` or ``"torch"``; same transitions to round-off.

    Reset: ``env.reset()`` samples; ``env.reset(TensorDict({"state": s}, [N]), set_state=True)`` puts each env
    in the exact state ``s``; partial resets follow ``"_reset"``.
    """

    def __init__(self, num_envs: int = 1, device: str | torch.device = "cpu", seed: int | None = None,
                 action_mode: Literal["raise", "clip"] = "raise",
                 init: Literal["gym_anm", "intended", "uniform"] = "gym_anm", sim: GridSimulator | None = None,
                 backend: str = "auto"):
        if init not in INITS:
            raise ValueError(f"init must be one of {INITS}, got {init!r}")
        if sim is None:
            sim = network_simulator(ANM6_EASY, device=torch.device(device), backend=backend)
        super().__init__(num_envs=num_envs, seed=seed, device=device, action_mode=action_mode, init=init, sim=sim)
