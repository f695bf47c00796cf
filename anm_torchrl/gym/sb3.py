"""``SB3VecEnv``: Stable-Baselines3's ``VecEnv`` over one batched TorchRL env (through ``ANMVectorEnv``)."""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode

from anm_torchrl._extras import require

# checked before the torch / TorchRL imports below, so a missing extra fails at once, naming [sb3]
VecEnv = require("stable_baselines3.common.vec_env").VecEnv

from anm_torchrl.gym.vector import ANMVectorEnv  # noqa: E402


class SB3VecEnv(VecEnv):
    """N grids as one SB3 ``VecEnv``: ``PPO("MlpPolicy", SB3VecEnv(num_envs=64))``.

    SB3's conventions: ``reset()`` returns observations only; an env that ends is reset in the same step and
    its last observation is ``infos[i]["terminal_observation"]``, with ``infos[i]["TimeLimit.truncated"]``
    true when it ended by the time limit. Rewards are float32, as SB3's own vector envs return them.

    Args:
        num_envs, network, seed, max_episode_steps, env, **env_kwargs: as :class:`ANMVectorEnv` (built in
            ``SAME_STEP`` autoreset mode).
    """

    def __init__(self, num_envs: int = 1, network: str = "anm6_easy", seed: int | None = None,
                 max_episode_steps: int | None = None, **kwargs: Any):
        self.venv = ANMVectorEnv(num_envs, network=network, seed=seed, max_episode_steps=max_episode_steps,
                                 autoreset_mode=AutoresetMode.SAME_STEP, **kwargs)
        self._actions: np.ndarray | None = None
        super().__init__(self.venv.num_envs, self.venv.single_observation_space, self.venv.single_action_space)

    def reset(self) -> np.ndarray:
        """Reset every env (seeded by the first of ``seed()``'s seeds, if any); returns (N, D) observations."""
        obs, _ = self.venv.reset(seed=self._seeds[0])
        self._reset_seeds()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self):
        obs, reward, terminated, truncated, info = self.venv.step(self._actions)
        dones = terminated | truncated
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for i in np.flatnonzero(dones):
            infos[i] = {"terminal_observation": info["final_obs"][i],
                        "TimeLimit.truncated": bool(truncated[i] and not terminated[i])}
        return obs, reward.astype(np.float32), dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        """An attribute of the vector env, repeated once per index (the envs share one object)."""
        return [getattr(self.venv, attr_name)] * len(list(self._get_indices(indices)))

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        raise NotImplementedError(f"set_attr({attr_name!r}): the {self.num_envs} envs are one batched object")

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        raise NotImplementedError(f"env_method({method_name!r}): the {self.num_envs} envs are one batched object")

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False] * len(list(self._get_indices(indices)))

    def get_images(self) -> list[np.ndarray | None]:
        """One (H, W, 3) uint8 image of the network per env (``render_mode="rgb_array"``; what SB3's ``render()``
        tiles), None per env without a render mode."""
        images = self.venv.render()
        return [None] * self.num_envs if images is None else list(images)
