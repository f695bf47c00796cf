"""Write an episode's figure (PNG) and animation (GIF), and run a policy from a given state to get one."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from matplotlib.animation import PillowWriter
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.figure import Figure
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from anm_torchrl.evaluation import reset_to
from anm_torchrl.grid.network import Network
from anm_torchrl.render.figure import WINDOW_HOURS, Episode, choose_window, episode_figure, episode_from_rollout, \
    snapshot_title
from anm_torchrl.render.layout import network_layout
from anm_torchrl.render.network_plot import LOAD_CMAP, V_CMAP, NetworkArtist, loading_norm, marker_legend, \
    voltage_norm
from anm_torchrl.render.tables import NetworkTables, network_tables

log = logging.getLogger(__name__)
FIGURE_DPI, ANIMATION_DPI = 90, 72  # 1620 x 1530 px page (1845 with the daily bars); 540 x 396 px GIF frames


def write_episode(rollout: TensorDictBase, net: Network, out_dir: str | Path, stem: str = "episode",
                  times: list[int] | None = None, title: str = "", gif: bool = True, max_frames: int = 48,
                  fps: int = 6, window_hours: float = WINDOW_HOURS) -> dict[str, Path]:
    """Write ``<stem>.png`` (:func:`~anm_torchrl.render.figure.episode_figure`) and ``<stem>.gif`` (the
    network over the figure's time-series window, at most ``max_frames`` evenly spaced steps) into ``out_dir``.

    Args:
        rollout: ``env.rollout(...)`` of one env, (T,) or (1, T), with its ``("next", "grid", ...)`` entries.
        net: the env's network (``env.sim.net``).
        out_dir: created if missing.
        stem: file name without extension.
        times, title, window_hours: passed to ``episode_figure`` (``window_hours`` to the animation too).
        gif: also write the animation.
        max_frames, fps: animation length and speed.

    Returns:
        ``{"png": path, "gif": path}`` (no ``"gif"`` when ``gif`` is false or no step converged).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tables = network_tables(net)
    ep = episode_from_rollout(rollout, net.base_mva)
    paths = {"png": out / f"{stem}.png"}
    fig = episode_figure(ep, tables, times=times, title=title, window_hours=window_hours)
    FigureCanvasAgg(fig)
    fig.savefig(paths["png"], dpi=FIGURE_DPI)
    start, stop, _ = choose_window(ep, tables, window_hours)
    if gif and ep.terminated[start:stop].all():  # e.g. a policy that collapses the grid at its first step
        log.warning("no animation: the episode has no converged step to draw (its figure: %s)", paths["png"])
    elif gif:
        paths["gif"] = out / f"{stem}.gif"
        write_animation(ep, tables, paths["gif"], title=title, max_frames=max_frames, fps=fps,
                        window_hours=window_hours)
    log.info("episode figure written to %s", ", ".join(map(str, paths.values())))
    return paths


def write_animation(ep: Episode, tables: NetworkTables, path: str | Path, title: str = "", max_frames: int = 48,
                    fps: int = 6, window_hours: float = WINDOW_HOURS) -> None:
    """An animated GIF of the network over the figure's time-series window (:func:`choose_window`: the whole
    episode if it fits in ``window_hours``), converged steps only, at most ``max_frames`` evenly spaced frames."""
    if max_frames < 1 or fps < 1:
        raise ValueError(f"max_frames and fps must be >= 1, got {max_frames}, {fps}")
    start, stop, _ = choose_window(ep, tables, window_hours)
    steps = np.flatnonzero(~ep.terminated[start:stop]) + start
    if steps.size == 0:
        raise ValueError("the episode has no converged step to animate")
    frames = steps[np.unique(np.linspace(0, steps.size - 1, min(max_frames, steps.size)).round().astype(int))]
    pos = network_layout(tables.n_bus, tables.f_bus, tables.t_bus)
    fig = Figure(figsize=(7.5, 5.5), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    art = NetworkArtist(ax, tables, pos)
    marker_legend(ax, tables)
    fig.colorbar(ScalarMappable(voltage_norm(tables), V_CMAP), ax=ax, label="bus |V| (p.u.)", shrink=0.8,
                 extend="both")
    fig.colorbar(ScalarMappable(loading_norm(), LOAD_CMAP), ax=ax, label="branch loading (%)", shrink=0.8,
                 extend="max")
    art.update(ep.v_magn[frames[0]], ep.branch_s[frames[0]], f"{title}\n{snapshot_title(ep, tables, frames[0])}")
    fig.canvas.draw()
    fig.set_layout_engine("none")  # freeze the layout: every frame only recolours the artists

    writer = PillowWriter(fps=fps)
    with writer.saving(fig, str(path), dpi=ANIMATION_DPI):
        for t in frames.tolist():  # one draw per frame (FuncAnimation draws each frame twice)
            art.update(ep.v_magn[t], ep.branch_s[t], f"{title}\n{snapshot_title(ep, tables, t)}".strip())
            writer.grab_frame()


def render_episode(policy: Callable[[TensorDictBase], TensorDictBase], env: EnvBase, initial_state: torch.Tensor,
                   steps: int, out_dir: str | Path, title: str = "", deterministic: bool = True,
                   **write_kwargs) -> dict[str, Path]:
    """Run ``policy`` on ``env`` from ``initial_state`` for up to ``steps`` steps (stops at a termination)
    and write the episode's figure and animation with :func:`write_episode`.

    Args:
        policy: a TensorDict policy (e.g. a PPO actor or a baseline), as for ``env.rollout``.
        env: an env of this package with batch size (1,) (e.g. ``ANM6Env(1)``), or a transformed one whose
            base env has ``sim``.
        initial_state: (D,) or (1, D) gym-anm state (MW, MVAr, MWh, time index), set with ``set_state``.
        steps: episode length T.
        out_dir: where the files go.
        title: figure title.
        deterministic: act with the policy's deterministic action (``ExplorationType.DETERMINISTIC``).
        **write_kwargs: passed to :func:`write_episode` (``stem``, ``times``, ``gif``, ``max_frames``, ``fps``,
            ``window_hours``).

    Returns:
        The written paths, as :func:`write_episode`.

    Raises:
        ValueError: the env is not batched as (1,), ``steps`` < 1, or a bad initial state.
    """
    if tuple(env.batch_size) != (1,):
        raise ValueError(f"env must have batch size (1,), got {tuple(env.batch_size)}")
    if int(steps) < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    base = getattr(env, "base_env", env)
    td = reset_to(env, torch.as_tensor(initial_state, dtype=torch.float64).reshape(1, -1))
    mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    with torch.no_grad(), set_exploration_type(mode):
        rollout = env.rollout(int(steps), policy, tensordict=td, auto_reset=False, break_when_any_done=True)
    return write_episode(rollout, base.sim.net, out_dir, title=title, **write_kwargs)
