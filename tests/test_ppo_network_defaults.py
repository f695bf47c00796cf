"""PPO's per-network settings: the do-nothing initial action (``model.init_action``), the derived reward scale
(``loss.reward_scale=auto``) and the test episode length (``eval.test_max_steps``) — derived as documented, and
ANM6-Easy's defaults unchanged (they select none of it)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from recipe_utils import ROOT, compose

from anm_torchrl.baselines.simple import DoNothingPolicy
from anm_torchrl.training.config_checks import check_ppo_config
from anm_torchrl.training.factory import make_train_env
from anm_torchrl.training.models import initial_mean_bias, make_ppo_models, time_of_day_feature

CLIP = 0.98


def test_anm6_defaults_select_the_old_behaviour():
    """The default config (ANM6-Easy) keeps the hand-tuned scale 0.01, the box-centre start and T_test = T_val."""
    cfg = compose("config", [])
    assert cfg.network == "anm6_easy"
    assert cfg.loss.reward_scale == 0.01 and cfg.model.init_action == "center" and cfg.eval.test_max_steps is None
    env = make_train_env({"name": "none"}, 2, None, 0, "raise", None, "cpu", 1)
    torch.manual_seed(0)
    before = make_ppo_models(env)[0].state_dict()  # the call as it was before the key existed
    torch.manual_seed(0)
    now = make_ppo_models(env, **cfg.model)[0].state_dict()  # every model key, as checkpoints rebuild actors
    assert before.keys() == now.keys() and all(torch.equal(before[k], now[k]) for k in before)


def _models(network: str, cfg_overrides: list[str], seed: int = 0):
    cfg = compose("config", [f"network={network}", *cfg_overrides])
    env = make_train_env({"name": "none"}, 3, None, 0, "raise", None, "cpu", 1, network=network)
    torch.manual_seed(seed)
    actor, _, _ = make_ppo_models(env, **cfg.model)
    return env, actor


def test_do_nothing_start_is_the_do_nothing_action():
    """With ``model.init_action=do_nothing`` the untrained deterministic action is do-nothing's on case33bw: zero Q
    and idle storage exactly (interior targets), renewables at the box top less 1 % of the width (the edge is capped
    at |tanh| = 0.98); the weights are drawn as with the box-centre start, only the last bias differs."""
    env, actor = _models("case33bw", ["model.init_action=do_nothing"])
    _, centre = _models("case33bw", [])
    td = env.reset()
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        a = actor(td)["action"]
    low, high = env.sim.action_bounds()
    target = DoNothingPolicy(env.sim).action_value.to(torch.float64)
    u = (2 * (target - low) / (high - low) - 1).clamp(-CLIP, CLIP)  # the box edge is reached as |u| = CLIP
    expected = low + (high - low) * (1 + u) / 2
    assert (expected[:env.sim.n_gen] < high[:env.sim.n_gen]).all() and (expected[env.sim.n_gen:] == 0).all()
    # float32 network outputs plus the last layer's 0.01-gain weights on the normalised observation: ~1e-2 of the
    # box at most (the centre start has the same spread around the centre)
    spread = (high - low) * 1e-2
    assert ((a.double() - expected).abs() <= spread).all(), (a, expected)
    sd, sd_centre = actor.state_dict(), centre.state_dict()
    differ = [k for k in sd if not torch.equal(sd[k], sd_centre[k])]
    assert len(differ) == 1 and differ[0].endswith("bias")


def test_initial_mean_bias_maps_back_and_rejects_bad_input():
    low, high = torch.tensor([0.0, -1.0, -2.0]), torch.tensor([1.0, 1.0, 2.0])
    b = initial_mean_bias(torch.tensor([1.0, 0.0, -0.5]), low, high, CLIP)
    back = low + (high - low) * (1 + torch.tanh(b)) / 2
    assert torch.allclose(back, torch.tensor([0.5 + 0.5 * CLIP, 0.0, -0.5]), atol=1e-6)  # float32 atanh/tanh
    with pytest.raises(ValueError, match="outside the action box"):
        initial_mean_bias(torch.tensor([2.0, 0.0, 0.0]), low, high, CLIP)
    with pytest.raises(ValueError, match="clip must be in"):
        initial_mean_bias(torch.tensor([0.5, 0.0, 0.0]), low, high, 1.0)
    env = make_train_env({"name": "none"}, 1, None, 0, "raise", None, "cpu", 1)
    with pytest.raises(ValueError, match="init_action must be"):
        make_ppo_models(env, init_action="middle")


def test_auto_reward_scale_is_derived_from_do_nothing():
    """scale = auto_step_reward / |do-nothing's mean step reward|, on both networks; on ANM6-Easy the documented
    step reward 0.043 gives back the hand-tuned 0.01 (do-nothing's mean step is -4.29 there, almost all penalty)."""
    from anm_torchrl.evaluation import draw_initial_states
    from anm_torchrl.training.factory import make_true_env
    from anm_torchrl.training.reward_scale import do_nothing_reward_scale

    for network, steps in (("anm6_easy", 1000), ("case33bw", 50)):
        env = make_true_env(4, seed=1, network=network)
        states = draw_initial_states(4, 1, env.sim, env.init)
        info = do_nothing_reward_scale(env, states, steps, 0.043)
        # independent rollout of the do-nothing action from the same states
        from tensordict import TensorDict

        td = env.reset(TensorDict({"state": states.double()}, [4]), set_state=True)
        roll = env.rollout(steps, DoNothingPolicy(env.sim), tensordict=td, auto_reset=False,
                           break_when_any_done=False)
        mean_step = float(roll["next", "reward"].double().mean())
        assert info["do_nothing_step_reward"] == pytest.approx(mean_step, rel=1e-6)  # float32 rewards summed
        assert info["reward_scale"] == pytest.approx(0.043 / abs(mean_step), rel=1e-6)
        if network == "anm6_easy":  # the states and length 0.043 was derived on: 0.043 / 4.289 = 0.01003
            assert info["reward_scale"] == pytest.approx(0.01, rel=0.005)
        else:  # case33bw's do-nothing steps: line losses plus MAPDN-band (0.95-1.05 p.u.) voltage penalties, ~4e-3
            assert 5 < info["reward_scale"] < 20


@pytest.mark.parametrize("override, message", [
    ("loss.reward_scale=big", "loss.reward_scale must be a number > 0 or auto"),
    ("loss.reward_scale=0", "loss.reward_scale must be in"),
    ("model.init_action=middle", "model.init_action must be one of"),
    ("model.init_action_clip=1.0", "model.init_action_clip must be in"),
    ("eval.test_max_steps=0", "eval.test_max_steps must be"),
])
def test_bad_values_fail_clearly(override, message):
    with pytest.raises(ValueError, match=message):
        check_ppo_config(compose("config", [override]))


@pytest.mark.slow
def test_recipe_on_case33bw_with_network_settings(tmp_path):
    """A tiny case33bw run with the new keys records the derived scale and tests on eval.test_max_steps."""
    run_dir = tmp_path / "run"
    args = ["env.num_envs=4", "collector.frames_per_batch=32", "collector.total_frames=64", "eval.max_steps=10",
            "eval.num_episodes=2", "eval.test_episodes=2", "eval.test_max_steps=15", "loss.mini_batch_size=16",
            "loss.ppo_epochs=2", "logger.progress=false", "network=case33bw", "model.init_action=do_nothing",
            "loss.reward_scale=auto", f"hydra.run.dir={run_dir}"]
    proc = subprocess.run([sys.executable, str(ROOT / "recipes" / "ppo.py"), *args], cwd=tmp_path, capture_output=True,
                          text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    rs = summary["reward_scale"]
    assert rs["max_steps"] == 10 and rs["episodes"] == 2 and 50 < rs["reward_scale"] < 500
    assert summary["test"]["max_steps"] == 15 and summary["test"]["best"]["steps"] == 15
    assert summary["validation"]["max_steps"] == 10
    from anm_torchrl.training.checkpoint import load_actor

    from anm_torchrl.training.factory import make_true_env

    actor = load_actor(run_dir / "checkpoints" / "best.pt")  # rebuilt from a config with the new keys
    env = make_true_env(1, network="case33bw")
    assert actor(env.reset())["action"].shape == (1, 10)  # case33bw: 3 DG x (P, Q) + 2 storage x (P, Q)


def test_time_features_are_continuous_across_midnight():
    """``model.time_features``: two inputs more (sin, cos of the time of day), equal at aux = 95 -> 0 up to one
    step of phase (2π/96), and off by default (the input width is the observation's)."""
    env = make_train_env({"name": "none"}, 2, None, 0, "raise", None, "cpu", 1)
    _, _, plain = make_ppo_models(env)
    _, critic, norm = make_ppo_models(env, time_features=True)
    assert plain.out_features == 18 and norm.out_features == 20 and norm.time_of_day == (17, 96)
    obs = env.reset()["observation"].clone()
    obs[0, 17], obs[1, 17] = 95.0, 0.0
    z = norm(obs)
    assert torch.allclose(z[0, -2:], z[1, -2:], atol=2 * torch.pi / 96 + 1e-6)
    assert not torch.allclose(z[0, 17], z[1, 17], atol=1.0)  # the plain index jumps by its whole range
    assert critic(env.reset())["state_value"].shape == (2, 1)
    with pytest.raises(ValueError, match="model.time_features must be one of false, true; got 'yes'"):
        check_ppo_config(compose("config", ["model.time_features=yes"]))
    # an observation without the time index: the error names the key that asked for it, not an observation entry
    base = env.base_env
    entries = base.obs_map.entries
    try:
        base.obs_map.entries = [e for e in entries if e[0] != "aux"]
        with pytest.raises(ValueError, match=r"^model.forecast_steps needs the time index \('aux'\)"):
            time_of_day_feature(env, "model.forecast_steps")
    finally:
        base.obs_map.entries = entries


@pytest.mark.parametrize("network", ["case33bw", "anm6_easy", "random"])
def test_forecast_features_are_the_loads_and_potentials_the_next_steps_bring(network, tmp_path):
    """``model.forecast_steps=k``: k x (n_load + n_gen) inputs more; made at a state, row j (scaled back to MW) is
    the load P and the potentials the env's own steps then put into the state j steps later (a perfect forecast),
    across the end of the profile too (ANM6-Easy's day wraps every 96 steps); also on a generated network saved as a
    user's file."""
    from anm_torchrl.training.factory import make_true_env

    if network == "random":
        from anm_torchrl.networks.random import generate
        from anm_torchrl.networks.user import save_network

        case = generate(5151, n_bus=12)
        network = str(tmp_path / "random5151.npz")
        save_network(network, case.network, case.load_p, case.gen_p_max)
    k = 3
    env = make_true_env(2, seed=5, network=network)
    sim = env.sim
    _, critic, norm = make_ppo_models(env, forecast_steps=k)
    _, _, plain = make_ppo_models(env)
    m = sim.n_load + sim.n_gen
    assert norm.out_features == plain.out_features + k * m
    td = env.reset()
    if network == "anm6_easy":  # start 2 steps before the wrap, so the forecast crosses it
        state = td["state"].clone()
        state[:, -1] = 94.0
        from anm_torchrl.evaluation import reset_to

        td = reset_to(env, state)
    rows = norm.forecast(td["observation"]).reshape(2, k, m) * norm.forecast.scale * sim.net.base_mva
    sl, b = sim.state_slices(), sim.net.base_mva
    dn = DoNothingPolicy(sim)
    for j in range(k):
        td = env.step(dn(td))["next"]
        state = td["state"]
        seen = torch.cat([state[:, sl["dev_p"].start + sim.load_idx], state[:, sl["gen_p_max"]]], -1)
        assert torch.allclose(rows[:, j].double(), seen, atol=1e-5 * b), (j, rows[:, j], seen)
    assert critic(td)["state_value"].shape == (2, 1)
    with pytest.raises(ValueError, match="model.forecast_steps must be an integer >= 0, got -1"):
        check_ppo_config(compose("config", ["model.forecast_steps=-1"]))


def test_tanh_through_the_sigmoid_is_tanh_to_round_off():
    """``model.activation=tanh_sigmoid`` (opt-in speed): values within 3e-7 of ``torch.tanh`` in float32 (round-off
    of 2 sigmoid(2x) - 1 near |y| = 1), gradients within 2e-6, and finite differences agree in float64."""
    from anm_torchrl.training.models import ACTIVATIONS

    act = ACTIVATIONS["tanh_sigmoid"]()
    x = (torch.randn(4096, generator=torch.Generator().manual_seed(0)) * 4).requires_grad_()
    y = act(x)
    assert (y - torch.tanh(x)).abs().max() < 3e-7
    (g,) = torch.autograd.grad(y.sum(), x)
    (g_ref,) = torch.autograd.grad(torch.tanh(x).sum(), x)
    assert (g - g_ref).abs().max() < 2e-6
    assert torch.autograd.gradcheck(act, torch.randn(6, 3, dtype=torch.float64, requires_grad=True))


def test_state_dependent_scale_is_a_head_of_the_actor():
    """``model.state_dependent_scale``: the actor's MLP also outputs the scale (softplus), equal to
    exp(init_log_std) for the untrained policy up to its small last layer, different between observations; off by
    default (one learned log-std, the same for every observation)."""
    env = make_train_env({"name": "none"}, 4, None, 0, "raise", None, "cpu", 1)
    td = env.reset()
    plain, _, _ = make_ppo_models(env)
    scale = plain(td.clone())["scale"]
    assert torch.equal(scale, scale[:1].expand_as(scale))
    actor, _, _ = make_ppo_models(env, state_dependent_scale=True, init_log_std=-2.0)
    scale = actor(td.clone())["scale"]
    # the last layer's orthogonal gain 0.01 moves the softplus input by ~1e-2: the scale stays within 5 % of e^-2
    assert torch.allclose(scale, torch.full_like(scale, math.exp(-2.0)), rtol=0.05)
    assert not torch.equal(scale, scale[:1].expand_as(scale))
    with pytest.raises(ValueError, match="model.state_dependent_scale must be one of false, true; got 'yes'"):
        check_ppo_config(compose("config", ["model.state_dependent_scale=yes"]))
