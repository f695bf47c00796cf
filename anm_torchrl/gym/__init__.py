"""gymnasium and Stable-Baselines3 interfaces to the envs of this package.

Importing :mod:`anm_torchrl` registers ``anm_torchrl/ANM6Easy-v0``:

- ``gymnasium.make("anm_torchrl/ANM6Easy-v0")``: :class:`anm_torchrl.gym.env.ANMGymEnv`, one grid with
  gym-anm's interface;
- ``gymnasium.make_vec("anm_torchrl/ANM6Easy-v0", num_envs=N)``: :class:`anm_torchrl.gym.vector.ANMVectorEnv`,
  N grids stepped by one batched TorchRL env (numpy in and out);
- :class:`anm_torchrl.gym.sb3.SB3VecEnv`: the same batch as a Stable-Baselines3 ``VecEnv``.

Spaces equal gym-anm's ``ANM6Easy`` (float64 boxes). Entry points are strings: registering imports neither torch nor
TorchRL.
"""

from __future__ import annotations

import gymnasium

#: gymnasium id -> registered network name.
GYM_IDS = {"anm_torchrl/ANM6Easy-v0": "anm6_easy"}


def register_envs() -> None:
    """Register every id of :data:`GYM_IDS` with gymnasium (idempotent)."""
    for gym_id, network in GYM_IDS.items():
        if gym_id in gymnasium.registry:
            continue
        gymnasium.register(id=gym_id, entry_point="anm_torchrl.gym.env:ANMGymEnv",
                           vector_entry_point="anm_torchrl.gym.vector:ANMVectorEnv", kwargs={"network": network})


register_envs()
