"""gymnasium and Stable-Baselines3 interfaces to the envs of this package.

Importing this subpackage (``import anm_torchrl.gym``; not ``import anm_torchrl``, which stays light)
registers one gymnasium id per registered network (:data:`GYM_IDS`):
``anm_torchrl/ANM6Easy-v0`` (gym-anm's name), ``anm_torchrl/Case33bw-v0``, ``anm_torchrl/CigreMv-v0``, …, and
:data:`ANY_NETWORK_ID` ``anm_torchrl/ANM-v0``, which takes ``network=`` (a name registered at any time, or the path
of a network file: ``anm_torchrl.networks.save_network``).

- ``gymnasium.make(id)``: :class:`anm_torchrl.gym.env.ANMGymEnv`, one grid with gym-anm's interface;
- ``gymnasium.make_vec(id, num_envs=N)``: :class:`anm_torchrl.gym.vector.ANMVectorEnv`, N grids stepped by one
  batched TorchRL env (numpy in and out);
- :class:`anm_torchrl.gym.sb3.SB3VecEnv`: the same batch as a Stable-Baselines3 ``VecEnv``.

Spaces equal gym-anm's (float64 boxes). Entry points are strings: registering imports neither torch nor
TorchRL.
"""

from __future__ import annotations

import gymnasium

from anm_torchrl.networks.registry import list_networks


def gym_id(network: str) -> str:
    """``anm_torchrl/<Name>-v0`` for a registered network name: ``anm6_easy`` -> ``ANM6Easy`` (gym-anm's id),
    others in CamelCase (``case33bw`` -> ``Case33bw``, ``cigre_mv`` -> ``CigreMv``)."""
    name = "ANM6Easy" if network == "anm6_easy" else "".join(p.capitalize() for p in network.split("_"))
    return f"anm_torchrl/{name}-v0"


#: gymnasium id -> registered network name.
GYM_IDS = {gym_id(n): n for n in list_networks()}
#: the id of any network: ``gymnasium.make(ANY_NETWORK_ID, network="my_feeder" | "path/to/feeder.npz")``.
ANY_NETWORK_ID = "anm_torchrl/ANM-v0"


def register_envs() -> None:
    """Register every id of :data:`GYM_IDS` and :data:`ANY_NETWORK_ID` with gymnasium (idempotent)."""
    for env_id, network in [*GYM_IDS.items(), (ANY_NETWORK_ID, None)]:
        if env_id in gymnasium.registry:
            continue
        gymnasium.register(id=env_id, entry_point="anm_torchrl.gym.env:ANMGymEnv",
                           vector_entry_point="anm_torchrl.gym.vector:ANMVectorEnv",
                           kwargs={} if network is None else {"network": network})


register_envs()
