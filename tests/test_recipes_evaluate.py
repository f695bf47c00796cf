"""recipes/evaluate.py (run in-process through its ``main(argv)``) and the evaluation helpers behind it.

What it must do: print one JSON line first and only then write ``output=`` (creating the folder; a failed write
is an error after the JSON is out), start from the test states by default, refuse bad values and files with a
message, take its baseline names from the baselines registry.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
EVAL_KEYS = ("return", "discounted_return", "e_loss", "penalty", "steps", "terminated")
RESULT_KEYS = EVAL_KEYS + ("episodes", "env", "policy", "wall_time", "seed")


@pytest.fixture(scope="module")
def evaluate(evaluate_recipe):
    return evaluate_recipe


def printed_json(capsys) -> dict:
    lines = [line for line in capsys.readouterr().out.strip().splitlines() if line.strip()]
    assert lines, "nothing printed"
    return json.loads(lines[-1])


def fails(evaluate, *argv: str) -> str:
    """The message of the SystemExit that ``evaluate.py argv`` ends with."""
    with pytest.raises(SystemExit) as err:
        evaluate.main(list(argv))
    assert err.value.code not in (0, None)
    return str(err.value.code)


# ------------------------------------------------------------------------------------------- evaluate.py
def test_evaluate_checkpoint_json_on_test_states(evaluate, ppo_checkpoint, capsys):
    out = evaluate.main([f"checkpoint={ppo_checkpoint}", "steps=20", "episodes=2"])
    assert printed_json(capsys) == json.loads(json.dumps(out))
    assert set(RESULT_KEYS) <= set(out) and out["policy"] == "ppo" and out["env"] == "exact"
    assert out["episodes"] == 2 and 0 < out["steps"] <= 20 and math.isfinite(out["discounted_return"])
    assert out["seed"] == 0  # the PPO recipe's eval.test_seed (tests/test_config_checks.py keeps them equal)


def test_evaluate_baseline_json_and_output_folder(evaluate, tmp_path, capsys):
    target = tmp_path / "new" / "folder" / "result.json"
    out = evaluate.main(["policy=do_nothing", "steps=20", "episodes=2", f"output={target}"])
    assert printed_json(capsys)["discounted_return"] == out["discounted_return"]
    assert json.loads(target.read_text()) == json.loads(json.dumps(out))
    assert set(RESULT_KEYS) <= set(out) and out["policy"] == "do_nothing" and out["steps"] == 20
    assert out["terminated"] == 0.0 and out["return"] <= out["discounted_return"] < 0


def test_optimal_plans_over_the_evaluated_steps(evaluate, tmp_path, monkeypatch, capsys):
    # on a user's network file: a 6-step evaluation solves a 6-step plan (seconds), not the default T = 3,000 (on a
    # 12-bus network that ran over 10 min without a result before evaluate.py passed `steps` as the plan's horizon)
    from anm_torchrl.networks import save_network
    from anm_torchrl.networks.random import generate

    monkeypatch.chdir(tmp_path)
    case = generate(7, n_bus=8)
    save_network(tmp_path / "feeder.npz", case.network, case.load_p, case.gen_p_max)
    out = evaluate.main(["network=feeder.npz", "policy=optimal", "steps=6", "episodes=1", "gamma=0.99"])
    assert out["network"] == "feeder.npz" and out["steps"] == 6 and out["terminated"] == 0.0
    assert out["wall_time"] < 120 and math.isfinite(out["discounted_return"])


@pytest.mark.slow  # the GIF encoding takes from 20 s (idle machine) to minutes (shared)
def test_render_writes_the_episode_figure_and_animation(evaluate, ppo_checkpoint, tmp_path, capsys):
    out = evaluate.main([f"checkpoint={ppo_checkpoint}", "steps=6", "episodes=1", "render=true",
                         f"render_dir={tmp_path / 'ep'}"])
    assert printed_json(capsys)["policy"] == out["policy"] == "ppo"  # the JSON is still the last stdout line
    png, gif = tmp_path / "ep" / "ppo.png", tmp_path / "ep" / "ppo.gif"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and gif.read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    from PIL import Image

    with Image.open(png) as image:
        assert min(image.size) > 300  # a page, not an empty canvas
    with Image.open(gif) as image:
        assert image.n_frames == 6  # one frame per converged step


def test_failed_output_write_keeps_the_printed_result(evaluate, tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    message = fails(evaluate, "policy=do_nothing", "steps=5", "episodes=1", f"output={blocker}/result.json")
    assert "printed above but could not be written" in message and "a_file/result.json" in message
    assert printed_json(capsys)["policy"] == "do_nothing"  # the evaluation is not lost


def test_bad_options_and_files_fail_clearly(evaluate, tmp_path):
    bogus = tmp_path / "surrogate.pt"
    torch.save({"kind": "anm_torchrl.surrogate.xgb", "model": torch.zeros(2)}, bogus)
    assert "kind='anm_torchrl.surrogate.xgb'" in fails(evaluate, f"checkpoint={bogus}", "steps=5")
    (tmp_path / "notes.txt").write_text("hello\n")
    assert "is not an anm_torchrl training checkpoint" in fails(evaluate, f"checkpoint={tmp_path / 'notes.txt'}")
    assert "checkpoint not found" in fails(evaluate, f"checkpoint={tmp_path / 'missing.pt'}")
    assert "unknown option" in fails(evaluate, "policy=do_nothing", "no_such_option=1")
    assert "gamma must be in (0, 1] or null, got 1.5" in fails(evaluate, "policy=do_nothing", "gamma=1.5")
    assert "steps must be an integer >= 1 or null, got 0" in fails(evaluate, "policy=do_nothing", "steps=0")
    # a string is not false: render=no drew the episode
    assert "render must be true or false, got 'no'" in fails(evaluate, "policy=do_nothing", "render=no")
    assert "progress must be true or false, got 'off'" in fails(evaluate, "policy=do_nothing", "progress=off")
    from anm_torchrl.baselines import available_baselines

    message = fails(evaluate, "policy=nope")  # the registry's names, not a list typed in the recipe
    assert {"optimal", "acmpc"} <= set(available_baselines()) and all(n in message for n in available_baselines())


def test_initial_states_follow_the_networks_reset_distribution():
    """ANM6-Easy: gym-anm's initial distribution (SoC < 1 MWh, its unit quirk); another network: the uniform
    distribution of its true env; both reproducible from the seed."""
    from anm_torchrl.evaluation import draw_initial_states
    from anm_torchrl.training.factory import make_true_env

    anm6 = draw_initial_states(8, seed=4)
    assert anm6.shape == (8, 18) and bool((anm6[:, 14] < 1.0).all())  # gym_anm init: SoC in [0, 1) MWh
    env = make_true_env(8, network="case33bw", seed=4)
    assert env.init == "uniform"
    s1, s2 = (draw_initial_states(8, 4, env.sim, env.init) for _ in range(2))
    assert torch.equal(s1, s2) and s1.shape == (8, env.sim.state_dim)
    assert not torch.equal(s1, draw_initial_states(8, 5, env.sim, env.init))


def test_help_lists_the_options(evaluate, capsys):
    with pytest.raises(SystemExit) as err:
        evaluate.main(["--help"])
    assert err.value.code == 0
    text = capsys.readouterr().out
    for key in ("checkpoint:", "policy:", "env:", "seed:", "steps:", "episodes:", "gamma:", "output:"):
        assert key in text, key


def test_evaluate_gym_anm_json(evaluate, ppo_checkpoint, capsys):
    pytest.importorskip("gym_anm")
    out = evaluate.main([f"checkpoint={ppo_checkpoint}", "env=gym_anm", "steps=5", "episodes=1", "progress=false"])
    assert set(RESULT_KEYS) <= set(out) and out["env"] == "gym_anm" and out["steps"] == 5


# ------------------------------------------------------------------------------------------- helpers
def test_gym_anm_and_anm6_evaluations_agree():
    pytest.importorskip("gym_anm")
    torch.set_num_threads(1)
    from anm_torchrl.baselines import make_baseline
    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy, evaluate_policy_gym_anm

    states = draw_initial_states(2, seed=11)
    policy = make_baseline("do_nothing")
    ours = evaluate_policy(policy, states, max_steps=6)
    ref = evaluate_policy_gym_anm(policy, states, max_steps=6)
    torch.testing.assert_close(ours.discounted_returns, ref.discounted_returns, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(ours.penalty, ref.penalty, rtol=1e-5, atol=1e-5)


def test_episode_metrics_stop_at_first_termination():
    from anm_torchrl.evaluation import episode_metrics

    reward = torch.tensor([[-1.0, -2.0, -20000.0, -5.0], [-1.0, -1.0, -1.0, -1.0]])
    terminated = torch.tensor([[False, False, True, False], [False, False, False, False]])
    e_loss = torch.tensor([[0.5, 0.5, float("nan"), 9.0], [0.25, 0.25, 0.25, 0.25]])
    penalty = torch.tensor([[0.5, 1.5, float("nan"), 9.0], [0.75, 0.75, 0.75, 0.75]])
    res = episode_metrics(reward, e_loss, penalty, terminated, gamma=0.5)
    assert res.steps.tolist() == [3, 4] and res.terminated.tolist() == [True, False]
    assert res.returns.tolist() == [-20003.0, -4.0]
    assert res.discounted_returns.tolist() == [-1.0 - 1.0 - 5000.0, -1.0 - 0.5 - 0.25 - 0.125]
    assert res.e_loss.tolist() == [2.0, 1.0] and res.penalty.tolist() == [102.0, 3.0]  # terminal: clipping values


def test_load_checkpoint_rejects_other_files(tmp_path):
    from anm_torchrl.training.checkpoint import FORMAT_VERSION, CHECKPOINT_KIND, load_checkpoint, save_checkpoint

    torch.save({"state_dict": {}}, tmp_path / "plain.pt")
    with pytest.raises(ValueError, match=r"not an anm_torchrl training checkpoint.*keys \[state_dict\]"):
        load_checkpoint(tmp_path / "plain.pt")
    (tmp_path / "model.json").write_text('{"learner": {}}')
    with pytest.raises(ValueError, match="torch.load"):
        load_checkpoint(tmp_path / "model.json")
    torch.save([1, 2], tmp_path / "list.pt")
    with pytest.raises(ValueError, match="type builtins.list"):
        load_checkpoint(tmp_path / "list.pt")
    path = save_checkpoint(tmp_path / "c" / "x.pt", {"algorithm": "ppo", "config": {}, "actor": {}, "state": {},
                                                     "obs_norm": {}, "frames": 1, "update": 1})
    assert load_checkpoint(path)["format_version"] == FORMAT_VERSION
    assert [p.name for p in path.parent.iterdir()] == ["x.pt"]  # no temporary left behind
    torch.save({"kind": CHECKPOINT_KIND, "format_version": 99}, tmp_path / "future.pt")
    with pytest.raises(ValueError, match="format_version 99"):
        load_checkpoint(tmp_path / "future.pt")




def test_defaults_are_the_test_states_the_recipes_report_on(evaluate, capsys):
    """Bug: evaluate.py always drew 16 states of seed 0, while a feeder's or a user's network reports on 4
    (per_network_eval.yaml), and draw_initial_states(16, 0) holds none of draw_initial_states(4, 0): its figures
    were on other states than summary.json["test"]'s."""
    from anm_torchrl.baselines import make_baseline
    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy
    from anm_torchrl.training.factory import make_true_env

    assert evaluate.test_protocol(None, "anm6_easy") == (16, 0, 3000, 0.995)
    assert evaluate.test_protocol(None, "case33bw") == (4, 0, 3000, 0.995)
    ckpt = {"config": {"eval": {"test_episodes": 3, "test_seed": 7, "max_steps": 50, "test_max_steps": None}}}
    assert evaluate.test_protocol(ckpt, "case33bw") == (3, 7, 50, 0.995)
    # a run's own eval.gamma (evaluate.py re-scored a run of eval.gamma=0.9 with 0.995: -20.5 against its -4.9)
    ckpt["config"]["eval"]["gamma"] = 0.9
    assert evaluate.test_protocol(ckpt, "case33bw")[3] == 0.9
    out = evaluate.main(["policy=do_nothing", "network=case33bw", "steps=2"])
    env = make_true_env(4, network="case33bw", seed=0)
    assert out["episodes"] == 4 and out["seed"] == 0
    states = draw_initial_states(4, 0, env.sim, env.init)
    want = evaluate_policy(make_baseline("do_nothing", env.sim), states, max_steps=2, gamma=0.995, env=env)
    assert out["per_episode"]["discounted_return"] == pytest.approx(want.discounted_returns.tolist(), rel=1e-12)
    capsys.readouterr()


def test_a_moved_network_file_is_judged_by_the_checkpoints_network_key(evaluate, tmp_path):
    """A checkpoint trained on a network file that has moved since is evaluated with network=<its new path>: the
    network's key decides (load_actor refuses another network by it); it was refused by the path."""
    from types import SimpleNamespace

    ckpt = {"config": {"network": str(tmp_path / "old" / "feeder.npz")}, "network_key": "k"}
    cfg = SimpleNamespace(network=str(tmp_path / "new" / "feeder.npz"))
    assert evaluate.network_of(cfg, ckpt) == cfg.network
    with pytest.raises(SystemExit, match="trained on network="):  # no key (an older checkpoint): the path decides
        evaluate.network_of(cfg, {"config": ckpt["config"]})
    with pytest.raises(SystemExit, match="trained on network="):  # a registered name is never a file's
        evaluate.network_of(SimpleNamespace(network="case33bw"), ckpt)


def test_render_draws_the_random_baselines_seeded_stream(evaluate, tmp_path, monkeypatch, capsys):
    """render=true draws with a fresh baseline: the evaluation advanced the random baseline's generator, and the
    figure showed other actions than the episode reported; with several episodes its title says it is a draw."""
    import anm_torchrl.render

    seen = {}

    def fake_render(policy, env, state, steps, out_dir, stem, title):
        seen.update(policy=policy, title=title)
        return {}

    monkeypatch.setattr(anm_torchrl.render, "render_episode", fake_render)
    evaluate.main(["policy=random", "steps=3", "episodes=2", "render=true", f"render_dir={tmp_path}"])
    fresh = torch.Generator().manual_seed(0)
    assert torch.equal(seen["policy"].generator.get_state(), fresh.get_state())
    assert "(a draw of its own, random seed 0)" in seen["title"]
    capsys.readouterr()
