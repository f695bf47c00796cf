"""A batch of TorchRL envs of this package driven with numpy arrays: the engine of the gymnasium adapters.

Every env of the package (the true simulator and the surrogates) follows one contract (DESIGN.md §3); this
module turns it into gym-anm's numpy interface — float64 observations equal to gym-anm's (the state clipped to
its bounds, ``observation="state"``), float64 actions in MW/MVAr, float rewards — for N envs at once.
"""

from __future__ import annotations

import os

import numpy as np
import torch
from gymnasium import error, spaces
from tensordict import TensorDict
from torchrl.envs import EnvBase

from anm_torchrl.envs.specs import check_action_dtype

RENDER_KEYS = ("v_magn", "branch_s")  # the ("grid", ...) entries a rendered frame shows


def make_torchrl_env(network: str | os.PathLike, num_envs: int, seed: int | None = None, **kwargs) -> EnvBase:
    """The true-simulator TorchRL env of a registered network, batched over ``num_envs``.

    ``anm6_easy`` is :class:`~anm_torchrl.envs.ANM6Env` (gym-anm's ``ANM6Easy``, its reset distribution); any
    other registered network is :class:`~anm_torchrl.envs.ANMEnv` with the network's profiles and constants
    (reset: ``init="uniform"`` unless given).

    Args:
        network: a name of :func:`anm_torchrl.networks.list_networks` or the path of a network file.
        num_envs: batch size N.
        seed: seed of the reset sampler (``None``: random).
        **kwargs: passed to the env (``action_mode``, ``init``, ``backend``).

    Raises:
        ValueError: unknown network, or a network file that is missing or invalid.
    """
    from anm_torchrl.envs import ANM6Env, ANMEnv
    from anm_torchrl.networks import check_network_name, get_network

    check_network_name(network)
    network = os.fspath(network)  # a name, a path string or a pathlib.Path of a network file
    if network == "anm6_easy":
        return ANM6Env(num_envs=num_envs, seed=seed, **kwargs)
    case = get_network(network)
    return ANMEnv(network=case.network, load_p=case.load_p, gen_p_max=case.gen_p_max, num_envs=num_envs,
                  delta_t=case.delta_t, gamma=case.gamma, lamb=case.lamb, costs_clipping=case.costs_clipping,
                  seed=seed, **kwargs)


class NumpyBatch:
    """N envs of one batched TorchRL env, stepped and reset with numpy arrays; no autoreset.

    Observation (D,) float64: the state clipped to its bounds, as gym-anm's ``observation="state"``. Action (A,)
    float64 in MW/MVAr, passed to the TorchRL env as float32 (its action dtype). Rewards are the env's float32
    rewards as float64.

    Args:
        env: a TorchRL env of this package (``ANM6Env``, ``SurrogateEnv``, …) with batch size (N,).

    Raises:
        ValueError: the env is not batched in one dimension, or its observation is not its state.
    """

    def __init__(self, env: EnvBase):
        if len(env.batch_size) != 1:
            raise ValueError(f"env batch_size must be (N,), got {tuple(env.batch_size)}")
        obs_map = getattr(env, "obs_map", None)
        if obs_map is None or not obs_map.is_state:
            raise ValueError("the gymnasium adapter needs an env built with observation='state' (its observation "
                             f"is the clipped state, as gym-anm's ANM6Easy); got {type(env).__name__} with "
                             f"observation map {obs_map!r}")
        self.env = env
        self.num_envs = int(env.batch_size[0])
        s_low, s_high = (b.cpu().numpy() for b in env.sim.state_bounds())
        a_low, a_high = (b.cpu().numpy() for b in env.sim.action_bounds())
        self.observation_space = spaces.Box(s_low, s_high, dtype=np.float64)
        self.action_space = spaces.Box(a_low, a_high, dtype=np.float64)
        self._state: torch.Tensor | None = None  # (N, D) float64, the TorchRL env's "state"
        self._grid: dict[str, torch.Tensor] = {}  # ("grid", k) (N, ...) of the last reset / step, for rendering
        self._time: torch.Tensor | None = None  # (N,) time index of each row, counted on past a termination
        self._frame = None  # anm_torchrl.render.frame.NetworkFrame, built on the first draw

    @property
    def state(self) -> np.ndarray:
        """gym-anm state (N, D) float64 (MW, MVAr, MWh, time index); zeros on terminated rows."""
        self._require_reset()
        return self._state.cpu().numpy().copy()

    def grid(self, key: str) -> np.ndarray | None:
        """The env's ``("grid", key)`` (N, ...) float64 after the last reset or step (e.g. ``"v_magn"`` p.u.,
        ``"branch_s"`` MVA); None if the env does not report it."""
        self._require_reset()
        value = self._grid.get(key)
        return None if value is None else value.to(torch.float64).cpu().numpy()

    def clock(self, row: int) -> str:
        """Time of day ``HH:MM`` of env ``row``'s current state (from its time index; after a termination, whose
        state is zeroed, the index it would have)."""
        self._require_reset()
        minutes = int(round(float(self._time[row]) * float(self.env.sim.net.delta_t) * 60))
        return f"{minutes // 60 % 24:02d}:{minutes % 60:02d}"

    def _time_index(self, state: torch.Tensor) -> torch.Tensor:
        return state[:, self.env.sim.state_slices()["aux"]][:, 0].clone()

    def draw(self, rows: list[int], titles: list[str]) -> list[np.ndarray]:
        """(H, W, 3) uint8 images of the network of envs ``rows`` after the last reset or step (bus |V|, branch
        loading), one per title.

        Raises:
            ValueError: the env reports no ``("grid", "v_magn" / "branch_s")`` (nothing to draw)."""
        from anm_torchrl.render.frame import NetworkFrame  # matplotlib only when rendering
        from anm_torchrl.render.tables import network_tables

        v_magn, branch_s = self.grid("v_magn"), self.grid("branch_s")
        if v_magn is None or branch_s is None:
            raise ValueError(f"{type(self.env).__name__} reports no ('grid', 'v_magn' / 'branch_s'), "
                             "so there is nothing to draw")
        if self._frame is None:
            self._frame = NetworkFrame(network_tables(self.env.sim.net))
        return [self._frame.draw(v_magn[i], branch_s[i], t) for i, t in zip(rows, titles)]

    def _keep_grid(self, td, mask: torch.Tensor | None = None) -> None:
        grid = td.get("grid", None)
        for key in RENDER_KEYS:
            value = None if grid is None else grid.get(key, None)
            if value is None:
                self._grid.pop(key, None)
            elif mask is None or key not in self._grid:
                self._grid[key] = value.clone()
            else:
                self._grid[key] = torch.where(mask.unsqueeze(-1), value, self._grid[key])

    def observe(self, state: torch.Tensor) -> np.ndarray:
        """Observations (N, D) float64 of states (N, D): clipped to the observation bounds."""
        return np.clip(state.cpu().numpy(), self.observation_space.low, self.observation_space.high)

    def reset(self, mask: np.ndarray | None = None, seed: int | None = None) -> np.ndarray:
        """Reset all envs (``mask=None``) or the rows where ``mask`` (N,) bool is true; returns observations (N, D).

        ``seed`` re-seeds the batch's reset sampler first (one generator for the whole batch).
        """
        if seed is not None:
            self.env.set_seed(int(seed))
        if mask is None:
            td = self.env.reset()
            self._state = td.get("state").clone()
            self._time = self._time_index(self._state)
            self._keep_grid(td)
        else:
            self._require_reset()
            mask_t = torch.as_tensor(self._check_mask(mask), device=self.env.device)
            td = self.env.reset(TensorDict({"_reset": mask_t.unsqueeze(-1)}, self.env.batch_size,
                                           device=self.env.device))
            self._state = torch.where(mask_t.unsqueeze(-1), td.get("state"), self._state)
            self._time = torch.where(mask_t, self._time_index(self._state), self._time)
            self._keep_grid(td, mask_t)
        return self.observe(self._state)

    def step(self, action: np.ndarray, discard: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray,
                                                                                  np.ndarray]:
        """One transition of every env for ``action`` (N, A) MW/MVAr.

        ``discard`` (N,) bool: rows whose transition the caller throws away (they are reset next): stepped from
        their state clipped to its bounds, so a terminated row's all-zero state (SoC below a SOC_MIN > 0) is not
        refused by the env's state check.

        Returns observations (N, D) float64, rewards (N,) float64 and ``terminated`` (N,) bool.

        Raises:
            ValueError: wrong action shape, or an action outside the box (the env's ``action_mode="raise"``).
            TypeError: a bool, complex, object or string action (floats and integers are cast exactly).
        """
        self._require_reset()
        action = np.asarray(action)
        check_action_dtype(action.dtype)
        action = action.astype(np.float64, copy=False)
        expected = (self.num_envs, self.action_space.shape[0])
        if action.shape != expected:
            raise ValueError(f"action must have shape {expected}, got {action.shape}")
        state = self._state
        if discard is not None and discard.any():
            rows = torch.as_tensor(self._check_mask(discard), device=state.device).unsqueeze(-1)
            state = torch.where(rows, torch.as_tensor(self.observe(state), dtype=state.dtype, device=state.device),
                                state)
        td = TensorDict({"state": state,
                         "action": torch.as_tensor(self._to_float32(action), device=self.env.device)},
                        self.env.batch_size, device=self.env.device)
        nxt = self.env.step(td).get("next")
        self._state = nxt.get("state")
        done = nxt.get("terminated").squeeze(-1)
        self._time = torch.where(done, self._time + 1, self._time_index(self._state))
        self._keep_grid(nxt)
        for key, value in self._grid.items():  # a diverged power flow's last iterate is not the grid's: missing
            if value.is_floating_point():
                self._grid[key] = value.masked_fill(done.reshape(-1, *[1] * (value.dim() - 1)), float("nan"))
        reward = nxt.get("reward").squeeze(-1).to(torch.float64).cpu().numpy()
        return self.observe(self._state), reward, done.cpu().numpy()

    def _to_float32(self, action: np.ndarray) -> np.ndarray:
        """The env's float32 actions: a float64 action inside the box stays inside it after rounding.

        Rounding to float32 can move a bound (e.g. 0.754 MW) one float32 step outside the box, which the env
        would reject; such entries are moved one step back in. Actions outside the float64 box raise (unless
        the env clips), as they would in gym-anm.
        """
        low, high = self.action_space.low, self.action_space.high
        if getattr(self.env, "action_mode", "raise") == "raise" and not np.isnan(action).any():
            out = (action < low) | (action > high)
            if out.any():
                envs, entries = np.nonzero(out)
                pairs = list(zip(envs.tolist(), entries.tolist()))[:5]
                raise ValueError(f"action outside the box at (env, entry) {pairs}; values "
                                 f"{action[envs[:5], entries[:5]].tolist()}; box low {low.tolist()} high "
                                 f"{high.tolist()} (MW/MVAr)")
        a32 = action.astype(np.float32)
        up, down = a32 > high, a32 < low
        a32[up] = np.nextafter(a32[up], np.float32(-np.inf))
        a32[down] = np.nextafter(a32[down], np.float32(np.inf))
        return a32

    def _check_mask(self, mask: np.ndarray) -> np.ndarray:
        mask = np.asarray(mask)
        if mask.shape != (self.num_envs,) or mask.dtype != np.bool_:
            raise ValueError(f"reset mask must be a bool array of shape ({self.num_envs},), got {mask.dtype} "
                             f"{mask.shape}")
        return mask

    def _require_reset(self) -> None:
        if self._state is None:
            raise error.ResetNeeded("call reset() before step() or a partial reset")
