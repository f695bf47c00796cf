"""ANM6Env contract: specs, resets (sampled, set_state, partial), determinism, bad input, make_env."""

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from anm_torchrl import make_env
from anm_torchrl.envs import ANM6Env

torch.set_num_threads(1)


def test_check_env_specs_and_dtypes():
    env = ANM6Env(4, seed=0)
    check_env_specs(env)
    td = env.rand_step(env.reset())
    assert td["state"].dtype == torch.float64 and td["observation"].dtype == torch.float32
    assert td["action"].shape == (4, 6) and td["next", "reward"].shape == (4, 1)
    assert td["next", "grid", "v_magn"].shape == (4, 6) and td["next", "grid", "branch_s"].shape == (4, 5)


@pytest.mark.parametrize("init", ["gym_anm", "intended", "uniform"])
def test_check_env_specs_every_init(init):
    check_env_specs(ANM6Env(3, seed=1, init=init))


def test_reset_distribution_quirks():
    env = ANM6Env(2000, seed=0)
    s = env.reset()["state"]
    soc, q_pv, q_wind, aux = s[:, 14], s[:, 9], s[:, 11], s[:, 17]
    assert soc.min() >= 0 and soc.max() < 1  # gym-anm: SoC uniform in [0, 1) MWh
    assert q_pv.abs().max() <= 0.3 and q_wind.abs().max() <= 0.5  # ±0.3 / ±0.5 MVAr
    assert set(aux.long().tolist()) == set(range(96))
    s2 = ANM6Env(2000, seed=0, init="intended").reset()["state"]
    assert s2[:, 14].max() > 50 and s2[:, 11].abs().max() > 5


def test_same_seed_same_rollout_and_different_seed_differs():
    def roll(seed):
        env = ANM6Env(8, seed=seed)
        torch.manual_seed(123)
        return env.rollout(20, break_when_any_done=False)

    a, b, c = roll(3), roll(3), roll(4)
    assert torch.equal(a["next", "state"], b["next", "state"])
    assert torch.equal(a["next", "reward"], b["next", "reward"])
    assert not torch.equal(a["state"][:, 0], c["state"][:, 0])


def test_set_state_puts_exact_state_and_steps_from_it():
    env = ANM6Env(5, seed=0)
    src = ANM6Env(5, seed=7).reset()["state"]
    td = env.reset(TensorDict({"state": src.clone()}, [5]), set_state=True)
    assert torch.equal(td["state"], src)
    td["action"] = torch.tensor([[30.0, 50, 0, 0, 0, 0]]).expand(5, 6).clone()
    out = env.step(td)
    nxt, tr = env.sim.step(src, td["action"].double())
    assert torch.equal(out["next", "state"], nxt)
    assert torch.equal(out["next", "reward"].squeeze(1), tr.reward.float())


def test_partial_reset_only_touches_masked_rows():
    env = ANM6Env(6, seed=0)
    td = env.rand_step(env.reset())
    td = td["next"].clone()
    before = td["state"].clone()
    mask = torch.tensor([True, False, False, True, False, False]).unsqueeze(1)
    td["_reset"] = mask
    out = env.reset(td, set_state=False)
    assert torch.equal(out["state"][~mask.squeeze(1)], before[~mask.squeeze(1)])
    assert not torch.equal(out["state"][mask.squeeze(1)], before[mask.squeeze(1)])
    assert not out["done"].any()


def test_terminal_step_reward_and_zero_state():
    env = ANM6Env(2, seed=0)
    s = torch.tensor([[25.34521365, -5, 4, -10, 11, -25, 0, 10.48302624, -1, -0.13812797, -2, -0.45902648, -5, 0,
                       0.01652764, 4, 11, 81]], dtype=torch.float64).expand(2, 18).clone()
    td = env.reset(TensorDict({"state": s}, [2]), set_state=True)
    td["action"] = torch.tensor([[30.0, 50, -30, -50, 0, -50], [30.0, 50, 0, 0, 0, 0]])
    out = env.step(td)["next"]
    assert out["terminated"].squeeze(1).tolist() == [True, False]
    assert out["reward"][0].item() == pytest.approx(-19999.99999999998)
    assert torch.count_nonzero(out["state"][0]) == 0


def test_rollout_with_auto_reset_recovers_from_terminations():
    env = ANM6Env(64, seed=0)
    policy_action = torch.tensor([30.0, 50, -30, -50, 0, -50])  # provokes voltage collapse often

    def policy(td):
        td["action"] = policy_action.expand(64, 6).clone()
        return td

    r = env.rollout(5, policy, break_when_any_done=False)
    assert r["next", "terminated"].any()
    # after a terminal step the next row starts from a fresh (non-zero) reset state
    term = r["next", "terminated"][:, :-1].squeeze(-1)
    assert (r["state"][:, 1:][term].abs().sum(-1) > 0).all()


def test_bad_actions_raise_clear_errors():
    env = ANM6Env(3, seed=0)
    td = env.reset()
    td["action"] = torch.zeros(3, 6)
    td["action"][1, 4] = 60.0
    with pytest.raises(ValueError, match=r"outside the box.*\(1, 4\)"):
        env.step(td)
    td["action"] = torch.zeros(3, 6)
    td["action"][2, 0] = float("nan")
    with pytest.raises(ValueError, match=r"non-finite action.*\(2, 0\)"):
        env.step(td)
    assert torch.isfinite(td["state"]).all()  # nothing reached the state


def test_wrong_action_shape_raises():
    env = ANM6Env(3, seed=0)
    td = env.reset()
    with pytest.raises((ValueError, RuntimeError)):
        td["action"] = torch.zeros(3, 5)
        env.step(td)
    with pytest.raises(ValueError, match="shape"):
        env._step(TensorDict({"state": td["state"], "action": torch.zeros(3, 5)}, [3]))


def test_clip_mode_clips():
    env = ANM6Env(1, seed=0, action_mode="clip")
    td = env.reset()
    td["action"] = torch.tensor([[100.0, -5, 0, 0, 0, 0]])
    out = env.step(td)
    ref = ANM6Env(1, seed=0)
    td2 = ref.reset(TensorDict({"state": td["state"]}, [1]), set_state=True)
    td2["action"] = torch.tensor([[30.0, 0, 0, 0, 0, 0]])
    assert torch.equal(out["next", "state"], ref.step(td2)["next", "state"])


def test_bad_set_state_raises():
    env = ANM6Env(2, seed=0)
    good = env.reset()["state"]
    for bad, msg in [(good[:, :17], "shape"), (good.clone().index_fill_(1, torch.tensor([17]), 3.5), "time index"),
                     (good.clone().index_fill_(1, torch.tensor([14]), 101.0), "SoC"),
                     (good.clone().index_fill_(1, torch.tensor([0]), float("nan")), "non-finite")]:
        with pytest.raises(ValueError, match=msg):
            env.reset(TensorDict({"state": bad}, [bad.shape[0]]), set_state=True)


def test_constructor_rejects_bad_options():
    with pytest.raises(ValueError, match="action_mode"):
        ANM6Env(1, action_mode="wrap")
    with pytest.raises(ValueError, match="init"):
        ANM6Env(1, init="foo")
    with pytest.raises(ValueError, match="num_envs"):
        ANM6Env(0)


def test_staggered_time_limit_spreads_the_first_episode_ends():
    """stagger=True starts each env's step count at a seeded uniform 0..max_steps-1 on a full reset (later, partial
    resets count from 0), so the first episodes are cut after 1..max_steps steps; without it all envs count from 0. Either way an env is cut when its count reaches
    max_steps (random actions also end some episodes early: a terminated episode restarts its count)."""
    first = {}
    for stagger in (False, True):
        env = make_env("none", num_envs=16, max_steps=8, seed=3, stagger=stagger)
        check_env_specs(env)
        rollout = env.rollout(24, break_when_any_done=False)
        count = rollout["next", "step_count"].squeeze(-1)  # [env, step]
        assert torch.equal(rollout["next", "truncated"].squeeze(-1), count >= 8)
        first[stagger] = count[:, 0].tolist()
    assert set(first[False]) == {1}
    assert len(set(first[True])) >= 4 and set(first[True]) <= set(range(1, 9))
    a, b = (make_env("none", num_envs=16, max_steps=8, seed=3, stagger=True) for _ in range(2))
    assert torch.equal(a.reset()["step_count"], b.reset()["step_count"])  # drawn from the seed


def test_make_env_time_limit_and_errors():
    env = make_env("none", num_envs=2, max_steps=4, seed=0)
    check_env_specs(env)
    r = env.rollout(9, break_when_any_done=False)
    assert r["next", "truncated"][0].squeeze(-1).tolist() == [False, False, False, True] * 2 + [False]
    with pytest.raises(ValueError, match=r"stagger=True needs a time limit \(max_steps\)"):
        make_env("none", num_envs=2, stagger=True)
    with pytest.raises(ValueError, match="stagger must be True or False, got 'yes'"):
        make_env("none", num_envs=2, max_steps=4, stagger="yes")
    with pytest.raises(ValueError, match="unknown surrogate 'foo'"):
        make_env("foo")
    with pytest.raises(ValueError, match="takes no surrogate options"):
        make_env("none", dataset="agent")
