"""``ANMVectorEnv``: a natively batched ``gymnasium.vector.VectorEnv`` over one TorchRL env of this package."""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from torchrl.envs import EnvBase

from anm_torchrl.envs.specs import check_action_dtype, check_integer
from anm_torchrl.gym.batch import NumpyBatch, make_torchrl_env

AUTORESET_MODES = (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP)
RENDER_MODES = ("rgb_array",)


class ANMVectorEnv(VectorEnv):
    """N grids stepped together by one batched TorchRL env; numpy in and out, spaces equal to gym-anm's.

    ``gymnasium.make_vec("anm_torchrl/ANM6Easy-v0", num_envs=N)`` builds it. Observation (N, 18) float64 (the
    state clipped to its bounds, as gym-anm's ``ANM6Easy``), action (N, 6) float64 MW/MVAr, reward (N,) float64
    (the TorchRL env's float32 reward), ``terminated`` when the power flow does not converge (as gym-anm).
    gym-anm has no time limit; ``max_episode_steps`` adds one (``truncated``).

    Autoreset follows gymnasium 1.x (``metadata["autoreset_mode"]``):

    - ``NEXT_STEP`` (default, as ``SyncVectorEnv``): the step after an episode ends resets that env; its action
      is ignored and it returns the first observation with reward 0, ``terminated = truncated = False``.
    - ``SAME_STEP``: an env that ends is reset within the same step; the returned observation is the new
      episode's first and ``info["final_obs"]`` (N, 18) holds the last one where ``info["_final_obs"]`` (N,).

    ``reset(seed=s)`` re-seeds the batch's one reset sampler (an int, not a list); ``reset(options={"reset_mask":
    m})`` resets only the envs where ``m`` (N,) bool is true.

    Args:
        num_envs: batch size N.
        network: a registered network name or the path of a network file (ignored when ``env`` is given).
        seed: seed of the reset sampler (``None``: random).
        max_episode_steps: truncate episodes after this many steps (``None``: never, as gym-anm).
        autoreset_mode: ``AutoresetMode.NEXT_STEP`` or ``SAME_STEP`` (or their string values).
        env: an existing TorchRL env of this package with batch size (N,) (e.g. a ``SurrogateEnv``).
        render_mode: None or ``"rgb_array"``: :meth:`render` returns one (H, W, 3) uint8 image per env (the network
            after the last reset or step, as ``ANMGymEnv.render``), a tuple of N (``SyncVectorEnv``'s convention).
        **env_kwargs: passed to the true-simulator env (``action_mode``, ``init``, ``backend``).
    """

    def __init__(self, num_envs: int = 1, network: str = "anm6_easy", seed: int | None = None,
                 max_episode_steps: int | None = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP, env: EnvBase | None = None,
                 render_mode: str | None = None, **env_kwargs: Any):
        if render_mode is not None and render_mode not in RENDER_MODES:
            raise ValueError(f"render_mode must be None or one of {list(RENDER_MODES)}, got {render_mode!r}")
        mode = AutoresetMode(autoreset_mode)
        if mode not in AUTORESET_MODES:
            raise ValueError(f"autoreset_mode must be one of {[m.value for m in AUTORESET_MODES]}, got {mode.value!r}")
        check_integer("max_episode_steps", max_episode_steps, low=1, optional=True)  # 2.5 was cut to 2
        check_integer("num_envs", num_envs, low=1)
        if env is not None and int(env.batch_size[0]) != int(num_envs):
            raise ValueError(f"env has batch size {tuple(env.batch_size)}, num_envs is {num_envs}")
        self._batch = NumpyBatch(env if env is not None else make_torchrl_env(network, int(num_envs), seed,
                                                                             **env_kwargs))
        self.num_envs = self._batch.num_envs
        self.metadata = {"render_modes": list(RENDER_MODES), "render_fps": 4, "autoreset_mode": mode}
        self.render_mode = render_mode
        self.single_observation_space = self._batch.observation_space
        self.single_action_space = self._batch.action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.max_episode_steps = None if max_episode_steps is None else int(max_episode_steps)
        self._steps = np.zeros(self.num_envs, dtype=np.int64)
        self._needs_reset = np.zeros(self.num_envs, dtype=bool)

    @property
    def torchrl_env(self) -> EnvBase:
        """The TorchRL env stepped underneath."""
        return self._batch.env

    @property
    def state(self) -> np.ndarray:
        """gym-anm states (N, D) float64 of the current step."""
        return self._batch.state

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Reset every env, or those of ``options["reset_mask"]``; returns observations (N, D) and ``{}``."""
        if seed is not None and not isinstance(seed, (int, np.integer)):
            raise ValueError(f"seed must be an int (one sampler for the batch) or None, got {type(seed).__name__}")
        unknown = set(options or {}) - {"reset_mask"}
        if unknown:
            raise ValueError(f"options may only hold 'reset_mask', got {sorted(unknown)}")
        mask = (options or {}).get("reset_mask")
        obs = self._batch.reset(mask=mask, seed=seed)
        rows = slice(None) if mask is None else mask
        self._steps[rows] = 0
        self._needs_reset[rows] = False
        return obs, {}

    def step(self, actions: np.ndarray):
        """Step every env with ``actions`` (N, A) MW/MVAr; returns obs, rewards, terminated, truncated, infos."""
        actions = np.asarray(actions)
        check_action_dtype(actions.dtype)  # bool/complex/object refused, not cast to 0/1 MW
        actions = np.array(actions, dtype=np.float64)  # a copy: rows that reset get a valid dummy action
        resetting = self._needs_reset.copy()
        if resetting.any():  # NEXT_STEP: these envs ignore their action and start a new episode
            actions[resetting] = self.single_action_space.low
        obs, reward, terminated = self._batch.step(actions, discard=resetting)
        self._steps += 1
        truncated = np.zeros(self.num_envs, dtype=bool)
        if self.max_episode_steps is not None:
            truncated = (self._steps >= self.max_episode_steps) & ~terminated
        infos: dict[str, Any] = {}
        if resetting.any():
            obs = self._reset_rows(resetting)
            reward[resetting], terminated[resetting], truncated[resetting] = 0.0, False, False
        ended = terminated | truncated
        if self.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP:
            self._needs_reset = ended
        elif ended.any():  # SAME_STEP
            infos = {"final_obs": obs.copy(), "_final_obs": ended.copy()}
            obs = self._reset_rows(ended)
        return obs, reward, terminated, truncated, infos

    def _reset_rows(self, rows: np.ndarray) -> np.ndarray:
        self._steps[rows] = 0
        return self._batch.reset(mask=rows)

    def render(self) -> tuple[np.ndarray, ...] | None:
        """One (H, W, 3) uint8 image of the network per env, after the last reset or step (``render_mode=
        "rgb_array"``); None when ``render_mode`` is None (gymnasium's convention)."""
        if self.render_mode is None:
            return None
        name = self.spec.id if self.spec else "ANMVectorEnv"
        rows = list(range(self.num_envs))
        return tuple(self._batch.draw(rows, [f"{name} [env {i}]\nstep {self._steps[i]} ({self._batch.clock(i)})"
                                             for i in rows]))
