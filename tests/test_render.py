"""Episode rendering (anm_torchrl.render): layouts, the one-page figure, the animation, render_episode. Headless."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
from PIL import Image  # noqa: E402

from anm_torchrl.baselines.simple import DoNothingPolicy  # noqa: E402
from anm_torchrl.envs import ANM6Env  # noqa: E402
from anm_torchrl.grid.network import make_network  # noqa: E402
from anm_torchrl.render import Episode, episode_figure, episode_from_rollout, network_tables, render_episode, \
    write_episode  # noqa: E402
from anm_torchrl.render.layout import is_radial, network_layout, tree_layout  # noqa: E402
from anm_torchrl.render.network_plot import NetworkArtist, branch_loading  # noqa: E402

COLLAPSE = torch.tensor([30.0, 50, -30, -50, 0, -50])  # drives ANM6's power flow to non-convergence often


@pytest.fixture(scope="module")
def anm6():
    torch.set_num_threads(1)
    env = ANM6Env(1, seed=0)
    rollout = env.rollout(12, DoNothingPolicy(env.sim), tensordict=env.reset(), auto_reset=False)
    return env, rollout


def test_tree_layout_reads_as_a_one_line_diagram():
    # 0 - 1, 1 - 2, 1 - 3, 3 - 4: parents sit at the mean height of their children, x = hops from the slack
    f, t = np.array([0, 1, 1, 3]), np.array([1, 2, 3, 4])
    pos = tree_layout(5, f, t)
    assert pos[:, 0].tolist() == [0, 1, 2, 2, 3]
    assert pos[1, 1] == pytest.approx((pos[2, 1] + pos[3, 1]) / 2) and pos[3, 1] == pos[4, 1]
    assert is_radial(5, f, t) and not is_radial(5, np.r_[f, 2], np.r_[t, 4])
    assert not is_radial(5, f[:3], t[:3])  # bus 4 disconnected


def test_meshed_layout_separates_buses():
    f, t = np.array([0, 1, 2, 3, 0]), np.array([1, 2, 3, 0, 2])
    pos = network_layout(4, f, t)
    dist = np.linalg.norm(pos[:, None] - pos[None], axis=-1) + np.eye(4)
    assert np.isfinite(pos).all() and dist.min() > 0.05  # no two buses drawn on top of each other


def test_network_tables_match_the_simulator(anm6):
    env, _ = anm6
    tb = network_tables(env.sim.net)
    assert tb.gen_ids.tolist() == env.sim.gen_ids and tb.des_ids.tolist() == env.sim.des_ids
    assert tb.load_ids.tolist() == env.sim.load_ids and tb.soc_max.tolist() == [100.0]
    assert tb.state_slices() == env.sim.state_slices()
    assert tb.rate_mva.tolist() == [32.0, 25.0, 18.0, 18.0, 18.0]


def test_episode_figure_draws_the_rollout(anm6):
    env, rollout = anm6
    tb = network_tables(env.sim.net)
    ep = episode_from_rollout(rollout, env.sim.net.base_mva)
    assert ep.state.shape == (13, 18) and ep.action.shape == (12, 6)
    fig = episode_figure(ep, tb, times=[0, 5], title="test")
    assert len(fig.axes) >= 2 + 8 + 2  # 2 snapshots, 8 time series, 2 colour bars (+ twin axes)
    # the bus colours of the second snapshot are the rollout's |V| after step 6
    art_ax = fig.axes[1]
    colours = np.concatenate([c.get_array() for c in art_ax.collections if c.get_array() is not None
                              and c.get_array().shape[0] != tb.f_bus.shape[0]])
    assert sorted(colours.tolist()) == pytest.approx(sorted(ep.v_magn[5].tolist()))
    loading = branch_loading(tb, ep.branch_s[5])
    assert loading == pytest.approx(100 * np.abs(ep.branch_s[5]) / np.array([32, 25, 18, 18, 18]))
    with pytest.raises(ValueError, match="times must be"):
        episode_figure(ep, tb, times=[12])


def test_write_episode_png_and_gif(anm6, tmp_path):
    env, rollout = anm6
    paths = write_episode(rollout, env.sim.net, tmp_path, max_frames=5)
    png, gif = Image.open(paths["png"]), Image.open(paths["gif"])
    assert png.size[0] > 1000 and gif.n_frames == 5


def test_rollout_validation(anm6):
    _, rollout = anm6
    with pytest.raises(ValueError, match=r"lacks keys \[\('next', 'grid', 'v_magn'\)\]"):
        episode_from_rollout(rollout.exclude(("next", "grid", "v_magn")), 100.0)
    with pytest.raises(ValueError, match="one env"):
        episode_from_rollout(torch.stack([rollout[0], rollout[0]]), 100.0)


def test_render_episode_stops_at_a_termination(tmp_path):
    torch.set_num_threads(1)
    env = ANM6Env(1, seed=0)
    state = env.reset()["state"][0]

    def collapse(td):
        return td.set("action", COLLAPSE.expand(*td.batch_size, 6).clone())

    paths = render_episode(collapse, env, state, 30, tmp_path, title="collapse", gif=False)
    assert paths["png"].exists() and "gif" not in paths
    with pytest.raises(ValueError, match=r"batch size \(1,\)"):
        render_episode(collapse, ANM6Env(2), torch.stack([state, state]), 3, tmp_path)


def test_meshed_network_figure_without_a_simulator():
    # a 4-bus ring with a chord, no ratings on one branch, one renewable, one storage unit and one load
    buses = [[0, 0, 20, 1.0, 1.0], [1, 1, 20, 1.05, 0.95], [2, 1, 20, 1.05, 0.95], [3, 1, 20, 1.05, 0.95]]
    branches = [[0, 1, 0.01, 0.05, 0, 20, 1, 0], [1, 2, 0.01, 0.05, 0, 20, 1, 0], [2, 3, 0.01, 0.05, 0, 20, 1, 0],
                [3, 0, 0.01, 0.05, 0, None, 1, 0], [0, 2, 0.01, 0.05, 0, 10, 1, 0]]
    nan = float("nan")
    devices = [[0, 0, 0, None, 200, -200, 200, -200] + [nan] * 7,
               [1, 1, -1, 0.2, 0, -10] + [nan] * 9,
               [2, 2, 2, None, 30, 0, 30, -30] + [nan] * 7,
               [3, 3, 3, None, 50, -50, 50, -50, nan, nan, nan, nan, 100, 0, 0.9]]
    net = make_network(buses, branches, devices, 100.0, 0.25)
    tb = network_tables(net)
    assert not is_radial(tb.n_bus, tb.f_bus, tb.t_bus)
    T, rng = 6, np.random.default_rng(0)
    ep = Episode(state=rng.uniform(-5, 5, (T + 1, 2 * 4 + 1 + 1 + 1)), action=rng.uniform(-5, 5, (T, 4)),
                 reward=-rng.uniform(0, 3, T), terminated=np.zeros(T, bool), v_magn=rng.uniform(0.9, 1.1, (T, 4)),
                 branch_s=rng.uniform(-25, 25, (T, 5)), e_loss=rng.uniform(0, 1, T), penalty=rng.uniform(0, 1, T),
                 curtailment=rng.uniform(0, 5, T))
    ep.state[:, -1] = np.arange(T + 1)
    fig = episode_figure(ep, tb)
    art = NetworkArtist(fig.axes[0], tb, network_layout(tb.n_bus, tb.f_bus, tb.t_bus))
    art.update(np.array([1.0, 1.2, 1.0, 0.8]), np.zeros(5))
    rings = np.concatenate([sc.get_linewidths() for sc in art.buses])
    assert sorted(rings.tolist()) == [0.8, 0.8, 3.0, 3.0]  # the two buses outside [0.95, 1.05] are ringed


def test_render_episode_on_case33bw(tmp_path):
    from anm_torchrl.envs import ANMEnv
    from anm_torchrl.networks import get_network

    torch.set_num_threads(1)
    c = get_network("case33bw")
    env = ANMEnv(network=c.network, load_p=c.load_p, gen_p_max=c.gen_p_max, delta_t=c.delta_t, gamma=c.gamma,
                 lamb=c.lamb, costs_clipping=c.costs_clipping, num_envs=1, seed=0)
    tb = network_tables(env.sim.net)
    assert tb.n_bus == 33 and is_radial(tb.n_bus, tb.f_bus, tb.t_bus)

    def idle(td):  # no generation, no reactive power, idle storage: inside every device's box
        return td.set("action", torch.zeros(*td.batch_size, env.sim.action_dim))

    paths = render_episode(idle, env, env.reset()["state"][0], 6, tmp_path, gif=False)  # GIFs: tested above
    assert Image.open(paths["png"]).size[0] > 1000
