"""Smoke tests of recipes/sac.py through the shared training protocol (tiny runs in temp dirs): the run directory
PPO's runs have, finite SAC losses under their tags, the exact frame budget across the random warm-up, resume,
evaluate.py loading a SAC checkpoint, and the protocol refusing to resume another algorithm's checkpoint."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from tests.test_recipes_ppo import EVAL_KEYS, PPO, ROOT, TINY, run, scalars

SAC = ROOT / "recipes" / "sac.py"
TINY_SAC = ["env.num_envs=4", "collector.frames_per_batch=32", "collector.total_frames=96",
            "collector.init_random_frames=32", "eval.interval=1", "eval.max_steps=10", "eval.num_episodes=2",
            "eval.test_episodes=2", "replay.batch_size=16", "replay.samples_per_frame=1", "model.actor_cells=[16]",
            "model.critic_cells=[16]", "logger.interval=1", "logger.progress=false"]


@pytest.fixture(scope="module")
def sac_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("sac") / "run"
    run(SAC, *TINY_SAC, "collector.total_frames=80", f"hydra.run.dir={run_dir}", cwd=run_dir.parent)
    return run_dir


def test_sac_writes_the_protocols_run_directory(sac_run):
    from anm_torchrl.training.checkpoint import load_checkpoint

    summary = json.loads((sac_run / "summary.json").read_text())
    assert summary["algorithm"] == "sac" and summary["frames"] == 80 and summary["updates"] == 3  # 32 + 32 + 16
    assert set(EVAL_KEYS) <= set(summary["best_eval"]) and not summary["interrupted"]
    assert all(math.isfinite(summary["test"][c]["discounted_return"]) for c in ("best", "last"))
    last = load_checkpoint(sac_run / "checkpoints" / "last.pt")
    assert last["algorithm"] == "sac" and last["frames"] == 80 and {"loss", "optimizers"} <= set(last["state"])
    assert set(last["state"]["optimizers"]) == {"actor", "qvalue", "alpha"}
    tags = scalars(sac_run)
    for tag in ("train/loss_actor", "train/loss_qvalue", "train/loss_alpha", "train/alpha", "train/buffer_size",
                "eval/discounted_return", "test/best/discounted_return", "time/fps"):
        assert tag in tags, tag
        assert all(math.isfinite(v) for _, v in tags[tag]), (tag, tags[tag])
    assert [v for _, v in tags["train/buffer_size"]] == [32, 64, 80]  # every kept frame is stored once


def test_sac_resumes_and_evaluate_loads_it(sac_run, tmp_path, evaluate_recipe, capsys):
    resumed = tmp_path / "resumed"
    run(SAC, *TINY_SAC, f"checkpoint.resume={sac_run / 'checkpoints' / 'last.pt'}", f"hydra.run.dir={resumed}",
        cwd=tmp_path)
    summary = json.loads((resumed / "summary.json").read_text())
    assert summary["frames"] == 96 and summary["updates"] == 4  # from 80 frames, 3 updates: one more batch of 16
    out = evaluate_recipe.main([f"checkpoint={sac_run / 'checkpoints' / 'best.pt'}", "steps=5", "episodes=2"])
    assert out["policy"] == "sac" and out["episodes"] == 2 and math.isfinite(out["discounted_return"])


def test_resuming_another_algorithms_checkpoint_is_refused(sac_run, tmp_path):
    proc = run(PPO, *TINY, f"checkpoint.resume={sac_run / 'checkpoints' / 'last.pt'}",
               f"hydra.run.dir={tmp_path / 'ppo'}", cwd=tmp_path, check=False)
    assert proc.returncode != 0 and "it was trained by 'sac', this run is 'ppo'" in proc.stderr


@pytest.mark.parametrize("override, message", [
    ("replay.batch_size=0", "replay.batch_size must be an integer >= 1, got 0"),
    ("replay.size=8", "replay.size (8) must be >= collector.frames_per_batch (32)"),
    ("loss.tau=0", "loss.tau must be in (0, 1], got 0"),
    ("loss.alpha_init=-1", "loss.alpha_init must be > 0, got -1"),
    ("collector.num_workers=2", "collector.num_workers must be 1 for sac (one collector process), got 2"),
    ("collector.sync=false", "collector.sync must be true for sac (collection and updates take turns), got False"),
])
def test_sac_config_errors_name_the_key(override, message):
    from hydra import compose, initialize_config_dir

    from anm_torchrl.training.algorithms import check_algorithm_config

    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "conf"), version_base="1.3"):
        cfg = compose(config_name="sac", overrides=[*TINY_SAC, override])
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        check_algorithm_config(cfg)


def test_the_replay_buffer_stores_only_what_the_loss_reads():
    """A stored frame holds SACLoss's keys only: every collected key (gym-anm's float64 state and next state, grid
    diagnostics) made a frame 17 kB on the 115-bus feeder, a 1M-frame buffer 17 GB, and two runs swapped a 24 GB
    machine to a halt. Keys only, so training is unchanged (the losses were compared bit for bit before and after)."""
    import torch
    from recipe_utils import compose

    from anm_torchrl.training.algorithms import get_algorithm

    # 4 envs x 16 steps per iteration: one random warm-up iteration
    cfg = compose("sac", ["network=anm6_easy", "env.num_envs=4", "collector.frames_per_batch=64",
                          "collector.init_random_frames=64", "replay.batch_size=8"])
    algo = get_algorithm("sac")(cfg, device=torch.device("cpu"), seed=0, budget=64, reward_scale=1.0, resume=None)
    try:
        algo.iterate(64)
        stored = set(algo.buffer.sample().keys(True, True))
    finally:
        algo.close()
    assert stored - {"index"} == set(algo.loss_module.in_keys), stored  # "index": the sampler's, if it adds one
    assert "state" not in stored and ("next", "state") not in stored


def test_the_target_entropy_is_per_dimension_of_the_box_scaled_to_unit_half_width():
    """SAC's target counts nats in the box scaled to [-1, 1]: ANM6-Easy keeps its tuned total (-1 nat per MW-unit
    dimension, -6, the same float32 the loss stores), and a network of small devices gets the same noise relative
    to its box; in MW units CIGRE MV's target was above what a uniform action over its box has (unreachable)."""
    import torch
    from torchrl.data import Bounded

    from anm_torchrl.training.algorithms.sac import box_target_entropy
    from anm_torchrl.training.factory import make_true_env

    default = -4.510698737319501  # recipes/conf/loss/sac.yaml
    anm6 = make_true_env(2, network="anm6_easy").full_action_spec["action"]
    assert torch.tensor(box_target_entropy(anm6, default), dtype=torch.float32).item() == -6.0
    cigre = make_true_env(1, network="cigre_mv").full_action_spec["action"]
    half = (cigre.space.high - cigre.space.low)[0].double() / 2
    uniform = float(half.log().sum() + math.log(2) * half.numel())  # a uniform action's entropy over the box, nats
    assert -1.0 * half.numel() > uniform  # the former target: out of reach
    target = box_target_entropy(cigre, default)
    assert target < uniform and math.isclose(target - half.log().sum().item(), default * half.numel())
    # a single-value dimension is written at its value by the actor, not sampled: no entropy of its own
    flat = Bounded(low=torch.tensor([0.0, 1.0]), high=torch.tensor([2.0, 1.0]), shape=(2,))
    assert box_target_entropy(flat, default) == default
    empty = Bounded(low=torch.tensor([1.0, 1.0]), high=torch.tensor([1.0, 1.0]), shape=(2,))
    with pytest.raises(ValueError, match=r"dimension\(s\) \[0, 1\] have half-width \[0.0, 0.0\]"):
        box_target_entropy(empty, default)
    inverted = Bounded(low=torch.tensor([0.0, 1.0]), high=torch.tensor([2.0, 0.5]), shape=(2,))
    with pytest.raises(ValueError, match=r"dimension\(s\) \[1\] have half-width \[-0.25\]"):
        box_target_entropy(inverted, default)


def test_the_actor_and_temperature_wait_for_optim_actor_delay_frames():
    """Until ``optim.actor_delay_frames`` frames are collected only the Q networks step (the actor keeps its
    do-nothing start and the temperature its initial value); the first batch past it steps all three."""
    import torch
    from recipe_utils import compose

    from anm_torchrl.training.algorithms import get_algorithm

    cfg = compose("sac", ["network=case33bw", "env.num_envs=4", "collector.frames_per_batch=32",
                          "collector.init_random_frames=0", "replay.batch_size=16", "model.actor_cells=[16]",
                          "model.critic_cells=[16]", "optim.actor_delay_frames=64"])
    algo = get_algorithm("sac")(cfg, device=torch.device("cpu"), seed=0, budget=96, reward_scale=1.0, resume=None)

    def snapshot():
        q = algo.loss_module.qvalue_network_params.flatten_keys()
        return ([p.detach().clone() for p in algo.actor.parameters()], [p.detach().clone() for p in q.values()],
                algo.loss_module.log_alpha.detach().clone())

    def same(a, b):
        return all(torch.equal(x, y) for x, y in zip(a, b))

    try:
        actor0, q0, alpha0 = snapshot()
        for remaining in (96, 64):  # 32 and 64 frames collected: not past the delay
            algo.iterate(remaining)
        actor1, q1, alpha1 = snapshot()
        assert same(actor0, actor1) and torch.equal(alpha0, alpha1)
        assert not same(q0, q1)
        algo.iterate(32)  # 96 frames: past it
        actor2, _, alpha2 = snapshot()
        assert not same(actor1, actor2) and not torch.equal(alpha1, alpha2)
    finally:
        algo.close()



def test_replay_samples_per_frame_is_kept_on_average():
    """``replay.samples_per_frame`` x frames is what the updates draw: a fraction of a minibatch carries over (every
    iteration was rounded up to a whole minibatch: 1 sample per frame drew 48 per 32 frames at minibatches of 48)."""
    import torch
    from recipe_utils import compose

    from anm_torchrl.training.algorithms import get_algorithm

    cfg = compose("sac", ["network=case33bw", "env.num_envs=4", "collector.frames_per_batch=32",
                          "collector.init_random_frames=0", "replay.batch_size=48", "replay.samples_per_frame=1",
                          "model.actor_cells=[16]", "model.critic_cells=[16]"])
    algo = get_algorithm("sac")(cfg, device=torch.device("cpu"), seed=0, budget=96, reward_scale=1.0, resume=None)
    drawn = []
    sample = algo.buffer.sample
    algo.buffer.sample = lambda: drawn.append(1) or sample()
    try:
        counts = []
        for remaining in (96, 64, 32):
            before = len(drawn)
            _, metrics = algo.iterate(remaining)
            counts.append(len(drawn) - before)
            assert ("train/loss_qvalue" in metrics) == (counts[-1] > 0)
        assert counts == [0, 1, 1]  # 32, 64, 96 samples due: 0, 1 (16 left), 1 (0 left) minibatches of 48
    finally:
        algo.close()


def test_a_resumed_run_takes_the_configs_discount_and_entropy_target(sac_run):
    """SACLoss keeps its discount and entropy target as buffers in the checkpoint: a resumed run with other values
    trained with the checkpoint's while summary.json and the resume warning named the new ones."""
    import torch
    from recipe_utils import compose

    from anm_torchrl.training.algorithms import get_algorithm
    from anm_torchrl.training.checkpoint import load_checkpoint

    overrides = [o for o in TINY_SAC if not o.startswith("collector.total_frames")]
    cfg = compose("sac", [*overrides, "loss.gamma=0.9", "loss.target_entropy_per_dim=-1.0"])
    fresh = get_algorithm("sac")(cfg, device=torch.device("cpu"), seed=0, budget=0, reward_scale=1.0, resume=None)
    algo = get_algorithm("sac")(cfg, device=torch.device("cpu"), seed=0, budget=0, reward_scale=1.0,
                                resume=load_checkpoint(sac_run / "checkpoints" / "last.pt"))
    try:
        assert float(algo.loss_module.value_estimator.gamma) == pytest.approx(0.9)
        assert float(algo.loss_module.target_entropy) == pytest.approx(float(fresh.loss_module.target_entropy))
    finally:
        algo.close()
        fresh.close()


def test_do_nothing_start_on_gym_anms_own_env():
    """``sac.py surrogate=gym_anm`` (SAC's default do-nothing start) failed with a traceback: gym-anm's own env has
    no simulator to read do-nothing from; ANM6-Easy's action is the same policy there."""
    import torch

    from anm_torchrl.training.algorithms.ppo import model_options

    options = model_options({"model": {"init_action": "do_nothing"}, "surrogate": {"name": "gym_anm"}})
    do_nothing = torch.tensor([30.0, 50, 0, 0, 0, 0], dtype=torch.float64)  # PV and wind at their caps, Q and storage 0
    torch.testing.assert_close(options["init_action"].double(), do_nothing)
    assert model_options({"model": {"init_action": "do_nothing"}, "surrogate": {"name": "none"}})["init_action"] \
        == "do_nothing"
