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
from anm_torchrl.render.figure import choose_window, day_of_step, default_times, snapshot_title  # noqa: E402
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
    # asked for a GIF of an episode with no converged step (a ValueError after the PNG, before): the PNG alone
    paths = render_episode(collapse, env, state, 30, tmp_path / "gif", title="collapse")
    assert paths["png"].exists() and "gif" not in paths and not (tmp_path / "gif" / "episode.gif").exists()


def test_a_diverged_step_is_drawn_as_missing_at_its_own_time(anm6):
    """The state after a diverged power flow is zeroed and its voltages and flows are the solver's last iterate:
    the snapshot's clock counts on from s_0 (it read 00:00) and |V| / flows are missing (NaN), not drawn."""
    torch.set_num_threads(1)
    env = ANM6Env(1, seed=0)
    td = env.reset()

    def collapse(td):
        return td.set("action", COLLAPSE.expand(*td.batch_size, 6).clone())

    rollout = env.rollout(3, collapse, tensordict=td, auto_reset=False, break_when_any_done=True)
    ep = episode_from_rollout(rollout, env.sim.net.base_mva)
    assert ep.terminated[-1]
    tb = network_tables(env.sim.net)
    t = ep.steps - 1
    minutes = int((float(td["state"][0, tb.state_slices()["aux"]][0]) + t + 1) * tb.delta_t * 60)
    assert f", {minutes // 60 % 24:02d}:{minutes % 60:02d}): " in snapshot_title(ep, tb, t)
    assert np.isnan(ep.v_magn[t]).all() and np.isnan(ep.branch_s[t]).all()
    assert np.isfinite(ep.v_magn[~ep.terminated]).all()


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


@pytest.mark.parametrize("kind, empty", [("storage", "no generator but the slack in this network"),
                                         ("renewable", "no storage in this network")])
def test_episode_figure_of_a_network_without_generators_or_without_storage(kind, empty, tmp_path):
    """A user's network with a storage unit only (no generator but the slack) or a renewable only (no storage, as
    SimBench's feeder): the page is drawn and written, its empty panel says what is missing, and no warning is
    raised (an empty panel's legend had warned)."""
    import warnings

    from anm_torchrl.envs import ANMEnv
    from tests.test_user_network import _one_kind

    torch.set_num_threads(1)
    net, load_p, gen_p_max = _one_kind(kind)
    env = ANMEnv(network=net, load_p=load_p, gen_p_max=gen_p_max, num_envs=1, seed=0)

    def idle(td):
        return td.set("action", torch.zeros(*td.batch_size, env.sim.action_dim))

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rollout = env.rollout(6, idle, tensordict=env.reset(), auto_reset=False)
        fig = episode_figure(episode_from_rollout(rollout, env.sim.net.base_mva), network_tables(env.sim.net))
        paths = render_episode(idle, env, env.reset()["state"][0], 6, tmp_path, gif=False)
    assert empty in [a.get_title() for a in fig.axes]
    assert Image.open(paths["png"]).size[0] > 1000


def test_episode_figure_labels_devices_by_their_ids():
    """Bug: the legends named devices by their row ("gen 9"), not their DEV_ID, which differ when the ids are not
    0..n-1 (gym-anm accepts any unique ids): the storage unit with id 50 of this network was labelled "DES 9"."""
    from anm_torchrl.envs import ANMEnv
    from anm_torchrl.networks.random import generate

    torch.set_num_threads(1)
    case = generate(7003, n_bus=9)
    net = {**case.network, "device": [list(r) for r in case.network["device"]]}
    assert net["device"][-1][2] == 3  # the last row is a storage unit
    net["device"][-1][0] = 50
    env = ANMEnv(network=net, load_p=case.load_p, gen_p_max=case.gen_p_max, num_envs=1, seed=0)
    rollout = env.rollout(2, lambda td: td.set("action", torch.zeros(1, env.sim.action_dim)), tensordict=env.reset(),
                          auto_reset=False)
    fig = episode_figure(episode_from_rollout(rollout, env.sim.net.base_mva), network_tables(env.sim.net))
    labels = {t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()}
    assert any(t.startswith("DES 50 (bus") for t in labels), labels
    assert not any(t.startswith("DES 9 ") for t in labels), labels


def _long_episode(tb, steps: int, start_index: int) -> Episode:
    """A synthetic ANM6 episode of ``steps`` 15-min steps from time index ``start_index``: one costly step (300),
    a load peak (310), curtailment (320) and a penalty (305), all else quiet."""
    T = steps
    state = np.zeros((T + 1, 18))
    state[:, -1] = start_index + np.arange(T + 1)
    state[1:, tb.load_ids] = -1.0
    state[311, tb.load_ids] = -20.0  # s_311 is after step index 310
    ep = Episode(state=state, action=np.zeros((T, 6)), reward=-np.full(T, 0.1), terminated=np.zeros(T, bool),
                 v_magn=np.ones((T, 6)), branch_s=np.ones((T, 5)), e_loss=np.full(T, 0.01), penalty=np.zeros(T),
                 curtailment=np.zeros(T))
    ep.reward[300] = -9.0
    ep.curtailment[320] = 5.0
    ep.penalty[305] = 2.0
    return ep


def test_long_episode_shows_a_day_around_its_costliest_step_and_daily_bars(anm6):
    env, _ = anm6
    tb = network_tables(env.sim.net)
    ep = _long_episode(tb, 3000, start_index=44)  # from 11:00, as the figure of a 3000-step evaluation
    start, stop, why = choose_window(ep, tb)
    assert (start, stop) == (300 - 48, 300 + 48) and "costliest step (step 301" in why  # 24 h = 96 steps
    picks = default_times(ep, tb, start, stop)
    assert picks == [(305, "largest penalty"), (310, "peak load"), (320, "most curtailment")]
    fig = episode_figure(ep, tb, title="long")
    assert "time series: 24 h around the costliest step" in fig._suptitle.get_text()
    assert [ax.get_title().split("\n")[0] for ax in fig.axes[:3]] == [
        "A: largest penalty", "B: peak load", "C: most curtailment"]
    loss = [ax for ax in fig.axes if ax.get_title().startswith("energy loss ΔE per day")]
    days = day_of_step(ep, tb)
    n_days = days[-1] - days[0] + 1
    heights = [p.get_height() for p in loss[0].patches[:n_days]]  # the day bars (then the partial-day overlays)
    # 0.01 MWh per step: day 1 runs 11:00-24:00 (52 steps), full days 96 steps, the last the remainder
    assert len(loss) == 1 and n_days == 32 and heights[:3] == pytest.approx([0.52, 0.96, 0.96])
    assert sum(heights) == pytest.approx(30.0)
    gen = next(ax for ax in fig.axes if ax.get_title().startswith("generator active power"))
    assert gen.get_xlim() == (start + 0.5, stop + 0.5)  # the time series: the window only
    # a short episode is shown whole, without daily bars
    short = episode_figure(ep.window(0, 96), tb)
    assert not [ax for ax in short.axes if "per day" in ax.get_title()]


def test_window_centres_on_the_first_diverged_step_and_days_follow_the_clock(anm6):
    env, _ = anm6
    tb = network_tables(env.sim.net)
    ep = _long_episode(tb, 400, start_index=92)  # from 23:00
    ep.terminated[200] = True
    start, stop, why = choose_window(ep, tb, hours=12)
    assert (start, stop) == (200 - 24, 200 + 24) and "first diverged power flow (step 201)" in why
    days = day_of_step(ep, tb)
    assert days[:5].tolist() == [1, 1, 1, 1, 2]  # steps start at 23:00, 23:15, 23:30, 23:45, then 00:00
    with pytest.raises(ValueError, match="window_hours must be > 0"):
        episode_figure(ep, tb, window_hours=0)


def test_gif_animates_the_window_of_a_long_episode(anm6, tmp_path):
    from anm_torchrl.render.episode import write_animation

    env, _ = anm6
    tb = network_tables(env.sim.net)
    ep = _long_episode(tb, 1000, start_index=0)
    write_animation(ep, tb, tmp_path / "a.gif", title="t", max_frames=200, window_hours=6)
    assert Image.open(tmp_path / "a.gif").n_frames == 24  # the 6 h window's 24 steps, not 200 of 1000


def test_the_potential_snapshot_says_renewable_only_where_there_is_one(anm6):
    """Cosmetic bug: on a network whose generators are all classical the snapshot read "peak renewable potential"."""
    import dataclasses

    env, _ = anm6
    tb = network_tables(env.sim.net)
    ep = _long_episode(tb, 400, start_index=44)
    ep.curtailment[:] = 0.0  # no curtailment: the third snapshot is the peak potential (after step 330)
    ep.state[331, tb.state_slices()["gen_p_max"]] = 10.0
    assert default_times(ep, tb)[-1][1] == "peak renewable potential"
    classical = tb.dev_type.copy()
    classical[tb.gen_ids] = 1  # CLASSICAL_GEN
    assert default_times(ep, dataclasses.replace(tb, dev_type=classical))[-1][1] == "peak generation potential"


def test_a_one_step_episode_marks_its_points(anm6):
    """A line through one point is invisible: a window of one or two steps draws markers (its panels were blank)."""
    env, rollout = anm6
    tb = network_tables(env.sim.net)
    ep = episode_from_rollout(rollout, env.sim.net.base_mva)
    fig = episode_figure(ep.window(0, 1), tb)
    series = [line for ax in fig.axes for line in ax.get_lines() if len(line.get_xdata()) == 1]
    assert series and all(line.get_marker() == "o" for line in series)
    fig = episode_figure(ep, tb)  # 12 steps: lines
    assert all(line.get_marker() in ("None", "", None) for ax in fig.axes for line in ax.get_lines()
               if len(line.get_xdata()) == ep.steps)


def test_render_cli_refuses_bad_input_in_one_line(tmp_path, capsys):
    from anm_torchrl.render.__main__ import main

    (tmp_path / "file").write_text("")
    for argv, message in ((["--policy", "nope"], "invalid choice: 'nope'"),
                          (["--steps", "0"], "--steps: must be an integer >= 1, got 0"),
                          (["--policy", "random", "--steps", "2", "--out", str(tmp_path / "file")], "File exists")):
        with pytest.raises(SystemExit) as err:
            main(argv)
        assert err.value.code == 2 and message in capsys.readouterr().err
    # the optimum plans the 2 steps drawn (it planned gym-anm's 3,000: minutes)
    main(["--policy", "optimal", "--steps", "2", "--no-gif", "--out", str(tmp_path / "opt")])
    assert (tmp_path / "opt" / "episode_optimal.png").is_file()
