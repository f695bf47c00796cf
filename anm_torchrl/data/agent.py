"""The *Agent-based* dataset: trajectories of a random agent with smooth, "higher-level" actions.

``num_envs`` grids run in one batch from gym-anm's initial-state distribution (:meth:`GridSimulator.reset`).
Each env's action follows a sequence of random waypoints over the action box, one every 1…``waypoint_every``
steps (segment lengths drawn at random), joined by cosine (ease-in/ease-out) interpolation, so consecutive
actions are close and the trajectory drifts through the state space like a slowly varying controller would —
the paper's random agent "with interpolated action sequences" (higher-level actions). Waypoint coordinates
follow the arcsine law (Beta(1/2, 1/2)) so that decisive moves to the box edges — and the rare terminal
steps they cause — are as frequent as under i.i.d. uniform actions (see :class:`WaypointAgent`). An env is
reset (new initial state, new waypoints) when its step is terminal or after ``max_episode_steps`` steps. Rows
are stored env-major (each env's steps are contiguous) and the train/validation/test split is by env, so no
trajectory straddles two splits.
"""

from __future__ import annotations

import functools
import logging
import math

import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

from anm_torchrl.networks.resolve import is_anm6
from anm_torchrl.data.options import WAYPOINT_DISTS, check_agent_split, check_split_units
from anm_torchrl.data.storage import DEFAULT_FRACTIONS, SPLITS, simulator_settings, split_codes, transition_rows
from anm_torchrl.envs.specs import check_integer
from anm_torchrl.grid import reset as grid_reset
from anm_torchrl.grid.simulator import GridSimulator

log = logging.getLogger(__name__)



class WaypointAgent:
    """Random agent whose actions interpolate between random waypoints (batched, seeded by ``generator``).

    Args:
        low, high: (A,) action box (MW / MVAr).
        num_envs: batch size.
        every: steps between waypoints (k); the action equals a waypoint at the end of each segment.
        generator: torch random generator.
        random_every: draw each segment's length uniformly from 1…``every`` instead (a mix of quick and slow
            moves).
        waypoints: ``"arcsine"`` (default) draws each waypoint coordinate from Beta(1/2, 1/2) over the box,
            ``"uniform"`` uniformly. The arcsine law puts more waypoints near the box edges — decisive moves
            such as full charge/discharge, full curtailment or extreme reactive support — which is where the
            voltage-collapse terminations are: with uniform waypoints and smooth interpolation only ≈0.05 % of
            steps are terminal (too few to train the terminal classifier), with arcsine ones ≈0.6 %, like
            i.i.d. uniform actions.
    """

    def __init__(self, low: torch.Tensor, high: torch.Tensor, num_envs: int, every: int,
                 generator: torch.Generator, random_every: bool = True, waypoints: str = "arcsine"):
        if every < 1:
            raise ValueError(f"waypoint_every must be >= 1, got {every}")
        if waypoints not in WAYPOINT_DISTS:
            raise ValueError(f"waypoints must be one of {WAYPOINT_DISTS}, got {waypoints!r}")
        self.low, self.high, self.every, self.random_every, self.gen = low, high, int(every), random_every, generator
        self.waypoints = waypoints
        self.prev = self._draw(num_envs)
        self.next = self._draw(num_envs)
        self.span = self._span(num_envs)
        # a random phase per env so the envs do not switch waypoints in lock-step
        self.phase = (torch.rand(num_envs, generator=generator, dtype=low.dtype, device=low.device)
                      * self.span).floor().long()

    def _span(self, n: int) -> torch.Tensor:
        if self.random_every:
            return torch.randint(1, self.every + 1, (n,), generator=self.gen, device=self.low.device)
        return torch.full((n,), self.every, dtype=torch.long, device=self.low.device)

    def _draw(self, n: int) -> torch.Tensor:
        u = torch.rand(n, self.low.shape[0], generator=self.gen, dtype=self.low.dtype, device=self.low.device)
        if self.waypoints == "arcsine":  # Beta(1/2, 1/2) by inverse CDF
            u = torch.sin(math.pi * u / 2) ** 2
        return self.low + u * (self.high - self.low)

    def act(self) -> torch.Tensor:
        """The current actions (N, A) and advance one step."""
        w = (1 - torch.cos(math.pi * self.phase.to(self.low.dtype) / self.span)) / 2
        action = self.prev + w.unsqueeze(1) * (self.next - self.prev)
        self.phase = self.phase + 1
        turn = self.phase >= self.span
        if turn.any():
            idx = turn.nonzero().squeeze(1)
            self.prev[idx] = self.next[idx]
            self.next[idx] = self._draw(idx.numel())
            self.span[idx] = self._span(idx.numel())
            self.phase[idx] = 0
        return action

    def restart(self, mask: torch.Tensor) -> None:
        """New waypoint sequences for envs in ``mask`` (N,) bool, starting a fresh episode."""
        idx = mask.nonzero().squeeze(1)
        if idx.numel():
            self.prev[idx] = self._draw(idx.numel())
            self.next[idx] = self._draw(idx.numel())
            self.span[idx] = self._span(idx.numel())
            self.phase[idx] = 0


def initial_sampler(sim: GridSimulator):
    """The env's default reset distribution of ``sim``'s network, ``(n, generator) -> (state, transition)``:
    gym-anm's ANM6-Easy resets on ANM6-Easy, uniform reachable states (``random_state``, ``ANMEnv``'s default
    ``init="uniform"``) on every other network, whose gym-anm reset distribution is not defined."""
    return functools.partial(grid_reset.gym_anm_reset if is_anm6(sim) else grid_reset.random_state, sim)


def generate_agent(size: int, seed: int = 0, *, sim: GridSimulator, num_envs: int = 100,
                   waypoint_every: int = 8, random_every: bool = True, waypoints: str = "arcsine",
                   max_episode_steps: int = 480, fractions=DEFAULT_FRACTIONS,
                   progress: bool = False) -> tuple[TensorDict, dict]:
    """Roll out the waypoint agent until ``size`` transitions are collected.

    Args:
        size: number of transitions, >= 3 (the last env's trajectory is cut to fit).
        seed: seed of the resets, waypoints and the env-level split.
        sim: the simulator (``anm_torchrl.networks.simulator(<network>)``).
        num_envs: envs stepped together, >= 3 so that every split gets an env (as ``size``; a ``ValueError``
            otherwise).
        waypoint_every: steps between waypoints (8 = 2 h); with ``random_every`` the largest such interval.
        random_every, waypoints: see :class:`WaypointAgent`.
        max_episode_steps: an episode is also ended (reset) after this many steps (480 = 5 days).
        fractions: train/validation/test fractions of the envs.
        progress: show a progress bar.

    Returns:
        ``(td, meta)``: rows as in :mod:`anm_torchrl.data.storage` (plus ``episode`` and ``step``) and metadata.
    """
    for name, value in (("size", size), ("num_envs", num_envs), ("max_episode_steps", max_episode_steps)):
        check_integer(name, value, low=1)
    # the split is by env (and size caps the envs): fewer than 3 leaves the validation or test split empty
    check_split_units(num_envs, "num_envs")
    check_split_units(size, "size")
    check_agent_split(size, num_envs)
    num_envs = int(min(num_envs, size))
    gen = torch.Generator(device=sim.net.dev.device).manual_seed(int(seed))
    a_low, a_high = sim.action_bounds()
    agent = WaypointAgent(a_low, a_high, num_envs, waypoint_every, gen, random_every=random_every,
                          waypoints=waypoints)
    reset = initial_sampler(sim)
    state, _ = reset(num_envs, gen)
    episode = torch.arange(num_envs)
    ep_step = torch.zeros(num_envs, dtype=torch.long)
    next_episode = num_envs
    n_steps = math.ceil(size / num_envs)
    steps, n_reset, n_trunc = [], 0, 0
    for _ in tqdm(range(n_steps), desc="agent", unit="steps", disable=not progress):
        action = agent.act()
        next_state, tr = sim.step(state, action)
        rows = transition_rows(sim, state, action, next_state, tr)
        rows.set("episode", episode.clone())
        rows.set("step", ep_step.clone())
        steps.append(rows)
        ep_step = ep_step + 1
        term = ~tr.converged
        trunc = ep_step >= max_episode_steps
        done = term | trunc
        state = next_state
        if done.any():
            idx = done.nonzero().squeeze(1)
            fresh, _ = reset(idx.numel(), gen)
            state = state.index_copy(0, idx, fresh)
            agent.restart(done)
            ep_step[idx] = 0
            episode[idx] = torch.arange(next_episode, next_episode + idx.numel())
            next_episode += idx.numel()
            n_reset += int(term.sum())
            n_trunc += int((trunc & ~term).sum())
    td = torch.stack(steps, 1).reshape(-1)[:size]  # (num_envs, n_steps) env-major, flattened
    # the split is over the envs that hold rows: the cut to ``size`` leaves the last envs empty when size is not a
    # multiple of num_envs and n_steps < num_envs (an empty env drawn for validation or test would shrink it)
    env_split = split_codes(-(-size // n_steps), fractions, gen)
    env_id = torch.arange(num_envs).repeat_interleave(n_steps)[:size]
    td.set("split", env_split[env_id])
    n_term = int(td.get("terminated").sum())
    log.info("agent dataset: %d rows, %d envs x %d steps, %d terminal steps, %d time-limit resets",
             size, num_envs, n_steps, n_term, n_trunc)
    meta = {
        "kind": "agent", "size": int(size), "seed": int(seed), "simulator": simulator_settings(sim),
        "generator": {"method": "random waypoint agent, cosine-interpolated actions, "
                                + ("gym-anm resets" if is_anm6(sim) else "uniform resets (grid.reset.random_state)"),
                      "num_envs": num_envs, "steps_per_env": n_steps, "waypoint_every": int(waypoint_every),
                      "random_every": bool(random_every), "waypoints": waypoints,
                      "max_episode_steps": int(max_episode_steps), "episodes": next_episode},
        "splits": {name: int((td.get("split") == code).sum()) for name, code in SPLITS.items()},
        "split_fractions": [float(f) for f in fractions], "split_unit": "env",
        "n_terminal": n_term,
    }
    return td, meta
