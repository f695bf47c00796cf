"""``ANMGymEnv``: one grid of a TorchRL env of this package as a ``gymnasium.Env`` (gym-anm's interface)."""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from torchrl.envs import EnvBase

from anm_torchrl.gym.batch import NumpyBatch, make_torchrl_env


class ANMGymEnv(gymnasium.Env):
    """A single env with gym-anm's interface, built by ``gymnasium.make("anm_torchrl/ANM6Easy-v0")``.

    Observation (D,) float64 (the state clipped to its bounds), action (A,) float64 MW/MVAr, spaces equal to
    gym-anm's. As in gym-anm, a step whose power flow does not converge is terminal, and stepping on after
    that returns a zero observation, reward 0 and ``terminated=True``. No time limit (``gymnasium.make(...,
    max_episode_steps=T)`` adds one).

    ``render_mode="rgb_array"``: :meth:`render` returns the network after the last reset or step as a
    (480, 640, 3) uint8 image (bus |V| and branch loading against their limits, the step, time of day and
    reward in the title), so ``gymnasium.wrappers.RecordVideo`` films episodes.

    Args:
        network: a registered network name or the path of a network file (ignored when ``env`` is given).
        env: an existing TorchRL env of this package with batch size (1,).
        render_mode: None or ``"rgb_array"``.
        **env_kwargs: passed to the true-simulator env (``action_mode``, ``init``, ``backend``).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, network: str = "anm6_easy", env: EnvBase | None = None, render_mode: str | None = None,
                 **env_kwargs: Any):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got "
                             f"{render_mode!r}")
        if env is not None and tuple(env.batch_size) != (1,):
            raise ValueError(f"env must have batch size (1,), got {tuple(env.batch_size)}")
        self._batch = NumpyBatch(env if env is not None else make_torchrl_env(network, 1, **env_kwargs))
        self.observation_space = self._batch.observation_space
        self.action_space = self._batch.action_space
        self.render_mode = render_mode
        self._terminated = False
        self._steps, self._reward = 0, None

    @property
    def state(self) -> np.ndarray:
        """gym-anm state (D,) float64."""
        return self._batch.state[0]

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Sample an initial state (gym-anm's distribution by default); returns the observation and ``{}``."""
        if options:
            raise ValueError(f"options are not supported, got {sorted(options)}")
        super().reset(seed=seed)
        obs = self._batch.reset(seed=seed)[0]
        self._terminated = False
        self._steps, self._reward = 0, None
        return obs, {}

    def step(self, action: np.ndarray):
        """One transition for ``action`` (A,) MW/MVAr; returns obs, reward, terminated, truncated, ``{}``."""
        if self._terminated:  # gym-anm stays in its terminal state
            return np.zeros(self.observation_space.shape), 0.0, True, False, {}
        action = np.asarray(action)
        if action.shape != self.action_space.shape:  # before the batch axis, so the error names this env's shape
            raise ValueError(f"action must have shape {self.action_space.shape}, got {action.shape}")
        obs, reward, terminated = self._batch.step(action[None])  # dtype checked there
        self._terminated = bool(terminated[0])
        self._steps, self._reward = self._steps + 1, float(reward[0])
        return obs[0], self._reward, self._terminated, False, {}

    def render(self) -> np.ndarray | None:
        """The network after the last reset or step as an (H, W, 3) uint8 image (``render_mode="rgb_array"``);
        None when ``render_mode`` is None (gymnasium's convention)."""
        if self.render_mode is None:
            return None
        what = ("power flow did not converge (terminal)" if self._terminated
                else "after reset" if self._reward is None else f"reward {self._reward:.3f}")
        name = self.spec.id if self.spec else "ANMGymEnv"
        return self._batch.draw([0], [f"{name}\nstep {self._steps} ({self._batch.clock(0)}): {what}"])[0]
