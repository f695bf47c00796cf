"""gymnasium and Stable-Baselines3 interfaces (anm_torchrl.gym): API checks, parity with the TorchRL env, PPO."""

from __future__ import annotations

import warnings
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode
from tensordict import TensorDict

import anm_torchrl.gym  # noqa: F401  registers the gymnasium ids
from anm_torchrl.envs import ANM6Env, ANMEnv
from anm_torchrl.gym import GYM_IDS
from anm_torchrl.gym.env import ANMGymEnv
from anm_torchrl.gym.vector import ANMVectorEnv

ID = "anm_torchrl/ANM6Easy-v0"
# the spaces are gym-anm's (MW / MVAr boxes) by design; the checker's advice to normalise them is not a defect
ASYMMETRIC_BOX_ADVICE = "ignore:.*For Box action spaces, we recommend:UserWarning"  # after ANSI codes
COLLAPSE = np.array([30.0, 50, -30, -50, 0, -50])  # drives the power flow of ANM6 to non-convergence often


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def _gym_anm_spaces():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from gym_anm.envs import ANM6Easy

        env = ANM6Easy()
    return env.observation_space, env.action_space


@pytest.mark.filterwarnings(ASYMMETRIC_BOX_ADVICE)
def test_single_env_passes_gymnasium_checker_with_gym_anm_spaces():
    env = gymnasium.make(ID)
    check_env(env.unwrapped)
    obs_space, act_space = _gym_anm_spaces()
    assert env.observation_space == obs_space and env.action_space == act_space  # float64 boxes, same bounds
    assert set(GYM_IDS) <= set(gymnasium.registry)


def test_make_vec_is_natively_batched_with_gym_anm_spaces():
    venv = gymnasium.make_vec(ID, num_envs=5)
    assert isinstance(venv, ANMVectorEnv) and venv.torchrl_env.batch_size == torch.Size([5])
    obs_space, act_space = _gym_anm_spaces()
    assert venv.single_observation_space == obs_space and venv.single_action_space == act_space
    assert venv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    obs, info = venv.reset(seed=3)
    assert obs.shape == (5, 18) and obs.dtype == np.float64 and info == {}
    assert np.array_equal(obs, venv.reset(seed=3)[0])  # seeded resets are reproducible
    obs, reward, term, trunc, _ = venv.step(venv.action_space.sample())
    assert obs in venv.observation_space and reward.shape == term.shape == trunc.shape == (5,)


@pytest.mark.parametrize("env_id", sorted(GYM_IDS))
def test_every_registered_network_has_a_batched_gym_env(env_id):
    venv = gymnasium.make_vec(env_id, num_envs=2, vectorization_mode="vector_entry_point", seed=0)
    tenv = venv.torchrl_env
    assert venv.single_observation_space.shape == (tenv.sim.state_dim,)
    # the float64 boxes are the TorchRL env's float32 observation / action bounds before rounding
    for space, spec in ((venv.single_observation_space, tenv.observation_spec["observation"]),
                        (venv.single_action_space, tenv.action_spec)):
        assert np.array_equal(space.low.astype(np.float32), spec.space.low[0].numpy())
        assert np.array_equal(space.high.astype(np.float32), spec.space.high[0].numpy())
    obs, _ = venv.reset()
    obs, reward, *_ = venv.step(np.stack([venv.single_action_space.low, venv.single_action_space.high]))
    assert obs in venv.observation_space and np.isfinite(reward).all()


@pytest.mark.filterwarnings(ASYMMETRIC_BOX_ADVICE)
@pytest.mark.parametrize("env_id", sorted(GYM_IDS))
def test_every_registered_network_passes_gymnasium_checker(env_id):
    check_env(gymnasium.make(env_id).unwrapped)


@pytest.mark.filterwarnings(ASYMMETRIC_BOX_ADVICE)
# a random network leaves some limits None, and gym-anm's spaces are then unbounded there: the checker says so
@pytest.mark.filterwarnings("ignore:.*Box observation space m.* value is -?infinity:UserWarning")
def test_any_network_id_takes_a_users_network_by_name_or_file(tmp_path):
    """A user's network, registered after ``anm_torchrl.gym`` was imported or saved to a file, is one gymnasium id
    away (``anm_torchrl/ANM-v0``, ``network=``): single env (checker passes) and natively batched vector env."""
    from anm_torchrl.gym import ANY_NETWORK_ID
    from anm_torchrl.networks import register_network, save_network, unregister_network
    from anm_torchrl.networks.random import generate

    case = generate(11, n_bus=9, meshed=False)
    file = save_network(tmp_path / "feeder.npz", case.network, case.load_p, case.gen_p_max)
    register_network("gym_test_feeder", case.network, case.load_p, case.gen_p_max)
    try:
        for network in ("gym_test_feeder", str(file)):
            env = gymnasium.make(ANY_NETWORK_ID, network=network)
            check_env(env.unwrapped)
            venv = gymnasium.make_vec(ANY_NETWORK_ID, num_envs=3, vectorization_mode="vector_entry_point",
                                      network=network, seed=0)
            obs, _ = venv.reset()
            assert obs.shape == (3, venv.torchrl_env.sim.state_dim) and venv.torchrl_env.sim.net.n_bus == 9
        with pytest.raises(ValueError, match="no such network file"):
            gymnasium.make(ANY_NETWORK_ID, network=str(tmp_path / "missing.npz"))
    finally:
        unregister_network("gym_test_feeder")


@pytest.mark.filterwarnings(ASYMMETRIC_BOX_ADVICE)
def test_single_env_passes_stable_baselines3_checker():
    """SB3's own checker (spaces, dtypes, reset/step contract) on the single gymnasium env."""
    sb3_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    sb3_checker.check_env(gymnasium.make("anm_torchrl/ANM6Easy-v0").unwrapped, warn=False)


def test_rollout_equals_torchrl_env_on_same_seed_and_actions():
    n, steps = 6, 12
    venv = ANMVectorEnv(n, seed=7)
    tenv = ANM6Env(n, seed=7)
    rng = np.random.default_rng(0)
    obs, _ = venv.reset()
    td = tenv.reset()
    low, high = venv.single_action_space.low, venv.single_action_space.high
    terminated_any = False
    for _ in range(steps):
        actions = rng.uniform(low, high, size=(n, 6))
        actions[0] = COLLAPSE  # env 0 ends its episode early: the terminal step is compared too
        s = td["state"].numpy()
        assert np.array_equal(obs, np.clip(s, venv.single_observation_space.low, venv.single_observation_space.high))
        obs, reward, term, _, _ = venv.step(actions)
        td = tenv.step(td.set("action", torch.as_tensor(actions, dtype=torch.float32)))["next"]
        # the adapter steps the same TorchRL env: identical numbers, not close ones
        assert np.array_equal(reward, td["reward"].squeeze(-1).double().numpy())
        assert np.array_equal(term, td["terminated"].squeeze(-1).numpy())
        if term.any():
            terminated_any = True
            break  # autoreset (gymnasium) and no reset (TorchRL without a collector) differ from here
        td = TensorDict({"state": td["state"]}, [n])
    assert terminated_any, "the collapse action should have ended env 0's episode"
    assert np.array_equal(obs[term], np.zeros((int(term.sum()), 18)))  # gym-anm's terminal observation


def test_next_step_autoreset_follows_gymnasium():
    venv = ANMVectorEnv(4, seed=1, max_episode_steps=3)
    venv.reset()
    actions = np.zeros((4, 6))
    actions[0] = COLLAPSE
    for _ in range(5):
        obs, reward, term, trunc, _ = venv.step(actions)
        if term[0]:
            break
    assert term[0], "env 0 should terminate within 5 collapse steps"
    obs, reward, term2, trunc2, _ = venv.step(actions)  # env 0's action is ignored: it resets
    assert reward[0] == 0.0 and not term2[0] and not trunc2[0] and obs[0].any()
    # envs 1-3 hold their action at zero: never terminal, truncated at step 3 then reset on the next step
    venv.reset(seed=1)
    zeros = np.zeros((4, 6))
    flags = [venv.step(zeros)[3] for _ in range(4)]
    assert [f[1] for f in flags] == [False, False, True, False]


def test_next_step_autoreset_after_termination_with_a_positive_soc_min():
    """Bug: a terminated env holds gym-anm's all-zero state; NEXT_STEP stepped it with the batch before resetting it,
    and the env refused the batch (SoC 0 below the storage's SOC_MIN = 2 MWh). A 2-bus network whose load jumps to
    -2000 MW at t = 1 ends every episode by divergence."""
    nan = np.nan
    network = {"baseMVA": 100, "bus": [[0, 0, 33, 1.0, 1.0], [1, 1, 33, 1.1, 0.9]],
               "branch": [[0, 1, 0.01, 0.1, 0.0, nan, nan, nan]],
               "device": [[0, 0, 0] + [nan] * 12, [1, 1, -1, 0.2, 0, -2000] + [nan] * 9,
                          [2, 1, 3, nan, 5, -5, 5, -5] + [nan] * 4 + [10, 2, 0.9]]}
    env = ANMEnv(network=network, load_p=np.array([[-1.0], [-2000.0]]), gen_p_max=np.zeros((2, 0)), num_envs=2,
                 seed=0)
    venv = ANMVectorEnv(2, env=env)
    venv.reset(seed=0)
    zeros = np.zeros((2, 2))
    _, _, term, _, _ = venv.step(zeros)
    assert term.all()
    obs, reward, term, trunc, _ = venv.step(zeros)  # both reset (raised ValueError "SoC (MWh) must lie in" before)
    assert not term.any() and not trunc.any() and (reward == 0).all()
    assert all(venv.single_observation_space.contains(o) for o in obs) and (obs[:, 6] >= 2).all()  # SoC >= SOC_MIN


def test_single_env_action_shape_error_names_its_own_shape():
    env = ANMGymEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action must have shape \(6,\), got \(5,\)"):
        env.step(np.zeros(5))
    with pytest.raises(ValueError, match=r"action must have shape \(6,\), got \(1, 6\)"):
        env.step(np.zeros((1, 6)))


def test_same_step_autoreset_reports_final_obs():
    venv = ANMVectorEnv(3, seed=2, autoreset_mode="SameStep")
    venv.reset()
    actions = np.tile(COLLAPSE, (3, 1))
    for _ in range(8):
        obs, reward, term, _, info = venv.step(actions)
        if term.any():
            break
    assert term.any()
    assert np.array_equal(info["_final_obs"], term)
    assert not info["final_obs"][term].any()  # the terminal observation (zeros, as gym-anm)
    assert (np.abs(obs[term]).sum(1) > 0).all()  # already the next episode's first observation
    assert reward[term] == pytest.approx(-100 / (1 - 0.995), rel=1e-7)  # float32 terminal reward


def test_partial_reset_and_bad_input():
    venv = ANMVectorEnv(3, seed=0)
    obs, _ = venv.reset()
    new, _ = venv.reset(options={"reset_mask": np.array([False, True, False])})
    assert np.array_equal(new[[0, 2]], obs[[0, 2]]) and not np.array_equal(new[1], obs[1])
    with pytest.raises(ValueError, match=r"action must have shape \(3, 6\)"):
        venv.step(np.zeros((2, 6)))
    with pytest.raises(ValueError, match=r"outside the box"):
        venv.step(np.full((3, 6), 1e3))
    with pytest.raises(ValueError, match="seed must be an int"):
        venv.reset(seed=[0, 1, 2])
    with pytest.raises(ValueError, match="reset mask must be a bool array"):
        venv.reset(options={"reset_mask": np.array([1, 0, 1])})
    with pytest.raises(ValueError, match="autoreset_mode"):
        ANMVectorEnv(2, autoreset_mode="Disabled")
    with pytest.raises(ValueError, match="max_episode_steps must be an integer >= 1 or None, got 2.5"):
        ANMVectorEnv(2, max_episode_steps=2.5)
    with pytest.raises(ValueError, match="max_episode_steps must be an integer >= 1 or None, got 2.0"):
        ANMVectorEnv(2, max_episode_steps=2.0)  # a float count is refused as everywhere else (it passed before)
    with pytest.raises(ValueError, match="num_envs must be an integer >= 1, got 2.5"):
        gymnasium.make_vec(ID, num_envs=2.5)  # cut to 2 before
    inf = np.zeros((3, 6))
    inf[1, 4] = np.inf  # reported as the value 3.4e38 (float32's largest) before
    with pytest.raises(ValueError, match=r"outside the box at \(env, entry\) \[\(1, 4\)\]; values \[inf\]"):
        venv.step(inf)
    with pytest.raises(ValueError, match=r"unknown network 'nope'; registered: \['anm6_easy', 'case33bw'"):
        gymnasium.make_vec(ID, num_envs=2, network="nope")
    with pytest.raises(ValueError, match="observation='state'"):
        ANMVectorEnv(2, env=ANMEnv(sim=ANM6Env(1).sim, num_envs=2, observation=[("bus_v_magn", "all", "pu")]))
    with pytest.raises(gymnasium.error.ResetNeeded):
        ANMGymEnv().step(np.zeros(6))


def test_single_env_stays_terminal_like_gym_anm():
    env = ANMGymEnv()
    env.reset(seed=0)
    for _ in range(20):
        _, _, term, _, _ = env.step(COLLAPSE)
        if term:
            break
    assert term
    obs, reward, term, trunc, _ = env.step(np.zeros(6))
    assert not obs.any() and reward == 0.0 and term and not trunc


def test_a_terminated_grid_is_drawn_at_its_own_time_without_the_solvers_iterate():
    """After a diverged power flow the state is zeroed (gym-anm's convention): the clock counts on from the last
    real time index (it read 00:00) and |V| / flows are missing, not the solver's last iterate."""
    env = ANMGymEnv(render_mode="rgb_array")
    env.reset(seed=0)
    batch = env._batch
    t0 = int(batch.state[0, env._batch.env.sim.state_slices()["aux"]][0])
    for k in range(1, 21):
        _, _, term, _, _ = env.step(COLLAPSE)
        if term:
            break
    assert term and np.isnan(batch.grid("v_magn")[0]).all() and np.isnan(batch.grid("branch_s")[0]).all()
    minutes = (t0 + k) * 15
    assert batch.clock(0) == f"{minutes // 60 % 24:02d}:{minutes % 60:02d}" != "00:00"
    assert env.render().shape == (480, 640, 3)


def test_sb3_vec_env_renders_rgb_arrays():
    from anm_torchrl.gym.sb3 import SB3VecEnv

    venv = SB3VecEnv(num_envs=2, seed=0, render_mode="rgb_array")
    venv.reset()
    images = venv.get_images()  # SB3's VecEnv raised NotImplementedError
    assert len(images) == 2 and images[0].shape == (480, 640, 3)
    assert venv.render().ndim == 3  # SB3 tiles them


def _deterministic_loss(model, seed: int = 123, n: int = 64, steps: int = 32) -> float:
    """Mean per-step reward of ``model``'s deterministic policy over ``n`` fixed initial states."""
    venv = ANMVectorEnv(n, seed=seed)
    obs, _ = venv.reset()
    total, alive = np.zeros(n), np.ones(n, dtype=bool)
    for _ in range(steps):
        action, _ = model.predict(obs, deterministic=True)
        obs, reward, term, _, _ = venv.step(np.clip(action, venv.single_action_space.low,
                                                    venv.single_action_space.high))
        total += reward * alive
        alive &= ~term
    return float(total.mean() / steps)


def test_sb3_ppo_learns_on_the_batched_env():
    pytest.importorskip("stable_baselines3")
    from stable_baselines3 import PPO
    from stable_baselines3.common.logger import Logger

    from anm_torchrl.gym.sb3 import SB3VecEnv

    env = SB3VecEnv(num_envs=64, seed=0)
    model = PPO("MlpPolicy", env, n_steps=32, batch_size=512, seed=0, device="cpu")
    model.set_logger(Logger(None, []))  # SB3's default one would leave an empty /tmp/SB3-<time> folder behind
    before = _deterministic_loss(model)
    model.learn(total_timesteps=2 * 64 * 32 * 4)  # 16,384 frames, 8 updates
    after = _deterministic_loss(model)
    # The untrained policy acts near 0 MW, curtailing all renewables (≈ -2.6 per step). Measured: -2.62 -> -2.56
    # after 16k frames, improving monotonically with more. An update that did not follow the advantage would
    # move the policy at random and is as likely to lose reward as to gain it; 1 % of the loss is the margin.
    assert after > before + 0.01 * abs(before), (before, after)


def test_float32_rounding_keeps_actions_on_the_bound_inside_the_box():
    from gymnasium import spaces

    from anm_torchrl.gym.batch import NumpyBatch

    batch = NumpyBatch(ANM6Env(2, seed=0))
    low, high = np.zeros(6), np.array([0.754, 1.1, 1.071, 0.4524, 0.66, 0.6426])  # case33bw-like bounds (MW)
    batch.action_space = spaces.Box(low, high, dtype=np.float64)
    assert (high.astype(np.float32) > high).any()  # the plain cast would leave the box
    a32 = batch._to_float32(np.stack([high, low]))
    assert a32.dtype == np.float32 and (a32 <= high).all() and (a32 >= low).all()
    assert np.abs(a32[0] - high).max() < 1e-7  # one float32 step at most
    with pytest.raises(ValueError, match=r"outside the box at \(env, entry\) \[\(1, 0\)\]"):
        batch._to_float32(np.stack([high, low - np.r_[1e-9, np.zeros(5)]]))


def test_render_rgb_array_draws_the_last_step():
    env = gymnasium.make(ID, render_mode="rgb_array")
    env.reset(seed=0)
    first = env.render()
    assert first.shape == (480, 640, 3) and first.dtype == np.uint8
    env.step(np.zeros(6))
    second = env.render()
    assert second.shape == first.shape and (second != first).any()  # recoloured for the new step's flows
    plain = gymnasium.make(ID)
    plain.reset(seed=0)
    assert plain.render() is None  # no render_mode: nothing drawn (gymnasium's convention)
    with pytest.raises(ValueError, match="render_mode must be None or one of"):
        ANMGymEnv(render_mode="human")


def test_vector_env_renders_one_frame_per_env():
    """``make_vec(..., render_mode="rgb_array").render()`` is a tuple of one image per env (SyncVectorEnv's
    convention), each of that env's own state: two grids reset to different states are drawn differently."""
    from anm_torchrl.gym.vector import ANMVectorEnv

    env = gymnasium.make_vec(ID, num_envs=2, vectorization_mode="vector_entry_point", render_mode="rgb_array")
    env.reset(seed=0)
    frames = env.render()
    assert isinstance(frames, tuple) and len(frames) == 2
    assert all(f.shape == (480, 640, 3) and f.dtype == np.uint8 for f in frames)
    assert (frames[0] != frames[1]).any()
    env.step(np.zeros((2, 6)))
    assert (env.render()[0] != frames[0]).any()
    plain = gymnasium.make_vec(ID, num_envs=2, vectorization_mode="vector_entry_point")
    plain.reset(seed=0)
    assert plain.render() is None
    with pytest.raises(ValueError, match="render_mode must be None or one of"):
        ANMVectorEnv(2, render_mode="human")


def test_record_video_films_an_episode(tmp_path):
    pytest.importorskip("moviepy", reason="gymnasium's RecordVideo writes with moviepy (not a test dependency)")
    from gymnasium.wrappers import RecordVideo

    env = RecordVideo(gymnasium.make(ID, render_mode="rgb_array", max_episode_steps=6), str(tmp_path / "videos"),
                      episode_trigger=lambda k: True, disable_logger=True)
    env.reset(seed=0)
    done = False
    while not done:
        _, _, terminated, truncated, _ = env.step(np.zeros(6))
        done = terminated or truncated
    env.close()
    videos = list((tmp_path / "videos").glob("*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 0


def test_record_video_collects_every_frame_without_moviepy(tmp_path, monkeypatch):
    # RecordVideo needs moviepy only to encode: a stand-in ImageSequenceClip receives the frames it collected, so the
    # part that is ours (one rgb_array frame per reset and step) runs in every test run
    import sys
    import types

    from gymnasium.wrappers import RecordVideo

    clips = []

    class Clip:
        def __init__(self, frames, fps):
            clips.append((list(frames), fps))

        def write_videofile(self, path, logger=None):
            Path(path).write_bytes(b"stand-in")

    fake = types.ModuleType("moviepy")
    io = types.ModuleType("moviepy.video.io.ImageSequenceClip")
    io.ImageSequenceClip = Clip
    for name, mod in {"moviepy": fake, "moviepy.video": types.ModuleType("moviepy.video"),
                      "moviepy.video.io": types.ModuleType("moviepy.video.io"),
                      "moviepy.video.io.ImageSequenceClip": io}.items():
        monkeypatch.setitem(sys.modules, name, mod)
    env = RecordVideo(gymnasium.make(ID, render_mode="rgb_array", max_episode_steps=6), str(tmp_path / "videos"),
                      episode_trigger=lambda k: True, disable_logger=True)
    env.reset(seed=0)
    for _ in range(6):
        env.step(np.zeros(6))
    env.close()
    (frames, fps), = clips
    assert len(frames) == 7, "the reset's frame and one per step"
    assert all(f.shape == (480, 640, 3) and f.dtype == np.uint8 for f in frames) and fps > 0
    assert (frames[0] != frames[-1]).any()


def test_normalised_spaces_through_gymnasium_wrappers():
    # grid2op-style scaling without code of ours: gymnasium's RescaleAction / RescaleObservation map gym-anm's
    # MW / MVAr boxes (finite, every low < high) onto [-1, 1]
    from gymnasium.wrappers import RescaleAction, RescaleObservation

    env = gymnasium.make(ID)
    box = env.action_space
    scaled = RescaleObservation(RescaleAction(env, -1.0, 1.0), -1.0, 1.0)
    assert (scaled.action_space.low == -1).all() and (scaled.observation_space.high == 1).all()
    obs, _ = scaled.reset(seed=0)
    assert np.all(np.abs(obs) <= 1 + 1e-12)
    to_mw = scaled.env.action  # RescaleAction's map from [-1, 1] to MW / MVAr
    np.testing.assert_allclose(to_mw(-np.ones(6)), box.low)
    np.testing.assert_allclose(to_mw(np.ones(6)), box.high)
    obs, *_ = scaled.step(np.zeros(6))  # the box's centre, a valid set-point
    assert np.all(np.abs(obs) <= 1 + 1e-12)
