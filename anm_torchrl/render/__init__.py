"""Watch an episode: the network drawn from its topology with voltages and loadings against their limits, the
time series of every device, and an animation of the network over the episode. Headless (matplotlib Agg).

- :func:`~anm_torchrl.render.figure.episode_figure`: one page for one recorded episode;
- :func:`~anm_torchrl.render.episode.write_episode`: writes that page (PNG) and an animated GIF;
- :func:`~anm_torchrl.render.episode.render_episode`: runs a policy from a given state and writes both.
"""

from anm_torchrl.render.episode import render_episode, write_episode
from anm_torchrl.render.figure import Episode, episode_figure, episode_from_rollout
from anm_torchrl.render.tables import NetworkTables, network_tables

__all__ = ["Episode", "NetworkTables", "episode_figure", "episode_from_rollout", "network_tables",
           "render_episode", "write_episode"]
