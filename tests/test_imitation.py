"""The imitation study (anm_torchrl.experiments.imitation): expert labels, the least-squares fit, DAgger rounds."""

import pytest
import torch

from anm_torchrl.experiments import imitation
from anm_torchrl.training.factory import make_true_env
from anm_torchrl.training.models import make_ppo_models


def test_box_coordinates_map_the_box_to_minus_one_one():
    low, high = torch.tensor([0.0, -2.0]), torch.tensor([4.0, 2.0])
    u = imitation.box_coordinates(torch.tensor([[0.0, 2.0], [2.0, -2.0], [9.0, 0.0]]), low, high)
    assert torch.equal(u, torch.tensor([[-1.0, 1.0], [0.0, -1.0], [1.0, 0.0]]))  # out of the box: clamped


def test_fit_drives_the_deterministic_action_to_the_targets():
    env = make_true_env(8, seed=0)
    torch.manual_seed(0)
    actor, _, _ = make_ppo_models(env)
    obs = env.observation_spec["observation"].rand().float()  # 8 distinct points of the observation box
    targets = torch.rand(8, 6, generator=torch.Generator().manual_seed(0)) * 1.6 - 0.8
    with torch.no_grad():
        before = float(((torch.tanh(actor.module[0].module(obs)[0]) - targets) ** 2).mean())
    after = imitation.fit(actor, obs, targets, epochs=300, batch=8, lr=3e-3)
    assert after < before / 20  # 8 points, 64x64 MLP: memorised (the untrained action is the box centre)


def test_labels_are_the_experts_first_setpoints():
    from anm_torchrl.baselines.acmpc import ACMPCPolicy
    from anm_torchrl.evaluation import draw_initial_states

    sim = make_true_env(1).sim
    states = draw_initial_states(2, 5, sim, "intended")
    got = imitation.label_states("anm6_easy", states, horizon=4, jobs=1)
    expert = ACMPCPolicy(sim, horizon=4)
    want = torch.cat([expert.act(states[i:i + 1]) for i in range(2)])
    torch.testing.assert_close(got, want.to(got.dtype), rtol=1e-6, atol=1e-6)  # the same cold IPOPT solve


def test_study_runs_rounds_and_scores_the_round_chosen_on_validation():
    rec = imitation.study(labels=4, rounds=1, visit_starts=2, visit_steps=4, horizon=4, epochs=2, jobs=1,
                          eval_episodes=2, eval_steps=50)
    assert [r["labelled"] for r in rec["rounds"]] == [4, 8]  # DAgger aggregates
    vals = [r["validation"]["discounted_return"] for r in rec["rounds"]]
    assert rec["chosen_round"] == max(range(2), key=vals.__getitem__)
    t = rec["test"]
    assert t["steps"] == 3000 and t["episodes"] == 8  # the gap table's protocol, not the short validation
    assert t["loss_ratio"] == pytest.approx(t["discounted_return"] / rec["optimum"])
    assert "| 1 | 8 |" in imitation.markdown(rec)


def test_study_refuses_seeds_of_the_evaluation_states():
    with pytest.raises(ValueError, match="avoid the validation"):
        imitation.study(seed=0, rounds=1)


@pytest.mark.parametrize("argv, what", [(["--labels", "0"], "--labels"), (["--rounds", "-1"], "--rounds"),
                                        (["--network", "case34bw"], "case34bw")])
def test_cli_refuses_bad_arguments_before_any_solve(argv, what, capsys):
    from anm_torchrl.cli import imitation as cli

    with pytest.raises((SystemExit, ValueError)) as err:
        cli.main(argv)
    assert what in capsys.readouterr().err + str(err.value)
