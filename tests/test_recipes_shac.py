"""Smoke test of recipes/shac.py (model=exact) through the shared training protocol, tiny budget: the run
directory PPO's runs have, the model-frame budget (true-env training frames 0), finite losses under their tags,
evaluate.py loading the checkpoint, and SHAC's config errors naming the key."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest

from tests.test_recipes_ppo import EVAL_KEYS, ROOT, run, scalars

SHAC = ROOT / "recipes" / "shac.py"
TINY_SHAC = ["env.num_envs=4", "loss.horizon=8", "collector.total_frames=64", "eval.interval=1", "eval.max_steps=10",
             "eval.num_episodes=2", "eval.test_episodes=2", "model.actor_cells=[16]", "model.critic_cells=[16]",
             "loss.critic_epochs=2", "loss.critic_batch_size=16", "logger.interval=1", "logger.progress=false"]


@pytest.fixture(scope="module")
def shac_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("shac") / "run"
    run(SHAC, "model=exact", *TINY_SHAC, f"hydra.run.dir={run_dir}", cwd=run_dir.parent)
    return run_dir


def test_shac_writes_the_protocols_run_directory(shac_run, evaluate_recipe):
    from anm_torchrl.training.checkpoint import load_checkpoint

    summary = json.loads((shac_run / "summary.json").read_text())
    assert summary["algorithm"] == "shac" and summary["updates"] == 2  # 2 x (4 envs x 8 steps)
    assert summary["budget_unit"] == "model_frames" and summary["model_frames"] == 64 and summary["frames"] == 0
    assert set(EVAL_KEYS) <= set(summary["best_eval"]) and not summary["interrupted"]
    assert all(math.isfinite(summary["test"][c]["discounted_return"]) for c in ("best", "last"))
    last = load_checkpoint(shac_run / "checkpoints" / "last.pt")
    assert last["algorithm"] == "shac" and {"critic", "target_critic", "actor_optimizer"} <= set(last["state"])
    tags = scalars(shac_run)
    for tag in ("train/loss_actor", "train/loss_critic", "train/grad_norm", "train/reward", "train/model_frames",
                "eval/discounted_return", "test/best/discounted_return", "time/fps"):
        assert tag in tags, tag
        assert all(math.isfinite(v) for _, v in tags[tag]), (tag, tags[tag])
    out = evaluate_recipe.main([f"checkpoint={shac_run / 'checkpoints' / 'best.pt'}", "steps=5", "episodes=2"])
    assert out["policy"] == "shac" and out["episodes"] == 2 and math.isfinite(out["discounted_return"])


@pytest.mark.parametrize("override, message", [
    ("loss.horizon=0", "loss.horizon must be an integer >= 1, got 0"),
    ("model.dynamics=mlp", "model.dynamics must be one of exact, pinn; got 'mlp'"),
    ("loss.noise=yes", "loss.noise must be true or false, got 'yes'"),
    ("optim.anneal_lr=1", "optim.anneal_lr must be true or false, got 1"),
    ("optim.actor_ema=1.5", "optim.actor_ema must be in [0, 1], got 1.5"),
    ("optim.anneal_start=1", "optim.anneal_start must be in [0, 1), got 1"),
    ("env.stagger=1", "env.stagger must be true or false, got 1"),
    ("env.stagger=true env.max_steps=null", "env.stagger=true needs a time limit (env.max_steps)"),
    ("env.short_rows=1.0", "env.short_rows must be in [0, 1), got 1.0"),
    ("env.short_rows=0.5 env.short_steps=0", "env.short_steps must be an integer >= 1, got 0"),
    ("env.short_rows=0.5 env.max_steps=null", "env.short_rows > 0 needs a time limit (env.max_steps)"),
    ("loss.critic_worker=1", "loss.critic_worker must be true or false, got 1"),
    ("env.power_flow=gpu", "env.power_flow must be one of torch, numba; got 'gpu'"),
    ("env.device=cuda", "env.power_flow=numba (the default) runs the exact model's power flow on the CPU; with "
                        "env.device=cuda add env.power_flow=torch"),
    # ANM6-Easy's exact-model entry sets the worker: it failed inside the run (a traceback, a run directory left)
    ("env.device=cuda env.power_flow=torch loss.critic_worker=true", "loss.critic_worker=true runs SHAC's critic "
     "in a CPU process; with env.device=cuda add loss.critic_worker=false"),
])
def test_shac_config_errors_name_the_key(override, message):
    from recipe_utils import compose

    from anm_torchrl.training.algorithms import check_algorithm_config

    cfg = compose("shac", [*TINY_SHAC, *override.split()])
    with pytest.raises(ValueError, match=re.escape(message)):
        check_algorithm_config(cfg)


def _tiny_shac(*overrides: str):
    import torch
    from recipe_utils import compose

    from anm_torchrl.training.algorithms import get_algorithm

    cfg = compose("shac", [*TINY_SHAC, *overrides])
    return get_algorithm("shac")(cfg, device=torch.device("cpu"), seed=0, budget=64, reward_scale=1.0, resume=None)


@pytest.mark.parametrize("noise", [False, True])
def test_shac_rollouts_take_the_deterministic_action_unless_noise_is_asked(noise):
    """Without noise the actor's loss does not depend on torch's random stream (the rollout acts with the mean that
    evaluation scores) and no noise scale is logged; with ``loss.noise=true`` the sampled actions change it."""
    import torch

    losses = []
    for draw in (1, 2):
        torch.manual_seed(0)  # the same initial networks
        algo = _tiny_shac(f"loss.noise={str(noise).lower()}")
        torch.manual_seed(draw)  # the stream the rollout's samples would come from
        _, metrics = algo.iterate(64)
        losses.append(float(metrics["train/loss_actor"]))
        assert (float(metrics["train/action_scale"]) > 0) == noise
    assert (losses[0] != losses[1]) == noise, losses


@pytest.mark.parametrize("anneal", [False, True])
def test_shac_anneals_both_learning_rates_linearly_over_the_budget_when_asked(anneal):
    """``optim.anneal_lr=true``: each iteration sets the actor's and the critic's Adam lr to the configured value
    times the share of ``collector.total_frames`` still to run (1 at the first iteration, 0 once spent)."""
    algo = _tiny_shac(f"optim.anneal_lr={str(anneal).lower()}", "optim.actor_lr=0.001", "optim.critic_lr=0.002")
    frames, _ = algo.iterate(64)  # budget 64: the first iteration starts the schedule at its full value
    assert [algo.actor_optim.param_groups[0]["lr"], algo.critic_optim.param_groups[0]["lr"]] == [0.001, 0.002]
    assert frames < 64, "a second iteration is needed to see the decay"
    algo.iterate(64 - frames)
    left = 1.0 - frames / 64 if anneal else 1.0
    assert algo.actor_optim.param_groups[0]["lr"] == pytest.approx(0.001 * left)
    assert algo.critic_optim.param_groups[0]["lr"] == pytest.approx(0.002 * left)


def test_a_late_anneal_keeps_the_rate_until_its_start():
    """``anneal_start=s``: the full rate until s x the budget, then a linear decay reaching 0 at the budget."""
    import torch

    from anm_torchrl.training.algorithms.base import anneal_lr

    optim = torch.optim.Adam([torch.zeros(1, requires_grad=True)], lr=1.0)
    got = []
    for frames in (0, 50, 60, 80, 100, 120):
        anneal_lr(optim, 0.5, frames, 100, start=0.6)
        got.append(optim.param_groups[0]["lr"])
    assert got == pytest.approx([0.5, 0.5, 0.5, 0.25, 0.0, 0.0])


@pytest.mark.parametrize("ema", [0.0, 0.25])
def test_shac_evaluates_a_running_average_of_the_actor_when_asked(ema):
    """``optim.actor_ema=w``: the rollouts train ``learner``; ``actor`` (what the protocol evaluates and saves)
    moves by ``w`` towards it after each actor step, and ``learner`` is saved to resume. 0: one actor."""
    import torch

    torch.manual_seed(0)
    algo = _tiny_shac(f"optim.actor_ema={ema}")
    start = [p.detach().clone() for p in algo.actor.parameters()]
    algo.iterate(64)
    if ema == 0:
        assert algo.learner is algo.actor and "learner" not in algo.state_dict()
        return
    moved = False
    for p0, p_avg, p in zip(start, algo.actor.parameters(), algo.learner.parameters()):
        torch.testing.assert_close(p_avg, p0 + ema * (p - p0), rtol=0, atol=1e-7)  # float32 lerp round-off
        moved |= not torch.equal(p, p0)
    assert moved
    saved = algo.state_dict()["learner"]
    assert all(torch.equal(saved[k], v) for k, v in algo.learner.state_dict().items())


@pytest.mark.parametrize("stagger", [False, True])
def test_staggered_rows_end_their_episodes_at_different_iterations(stagger):
    """With ``env.stagger`` the rows' first episodes are cut after 1..max_steps steps, so their resets spread over
    the iterations; without it every row is reset at the same iteration (all rows start together)."""
    import torch

    torch.manual_seed(0)
    algo = _tiny_shac("env.num_envs=16", "env.max_steps=24", f"env.stagger={str(stagger).lower()}")
    ends = []
    for _ in range(6):  # 6 iterations x 8 steps: 48 steps, every row ends its first episode
        before = algo.steps.clone()
        algo.iterate(10 ** 6)
        ends.append(algo.steps < before + 8)  # a row reset during the iteration counts fewer steps
    ends = torch.stack(ends)  # [iteration, row]
    first = ends.float().argmax(0)
    assert bool(ends.any(0).all())
    if stagger:
        assert first.unique().numel() >= 3, first
    else:
        assert first.unique().tolist() == [2], first  # 24 steps = 3 iterations of 8


def test_short_rows_end_their_episodes_after_short_steps():
    """``env.short_rows`` gives the last round(share x num_envs) rows episodes of ``env.short_steps`` steps; the
    others keep ``env.max_steps`` (here 16 rows: 4 short rows of 8 steps, 12 of 100)."""
    import torch

    torch.manual_seed(0)
    algo = _tiny_shac("env.num_envs=16", "env.max_steps=100", "env.short_rows=0.25", "env.short_steps=8")
    assert algo.max_steps.tolist() == [100] * 12 + [8] * 4
    resets = torch.zeros(16, dtype=torch.long)
    for _ in range(4):  # 4 iterations x 8 steps: the short rows end an episode every iteration, the others never
        before = algo.steps.clone()
        algo.iterate(10 ** 6)
        resets += (algo.steps < before + 8).long()
    assert resets.tolist() == [0] * 12 + [4] * 4
    # their fresh states come from a pool of whole reset batches (16 rows each), handed out once each
    first, second = algo._fresh(torch.arange(10))[0], algo._fresh(torch.arange(10))[0]
    assert first.shape == second.shape == (10, algo.state.shape[1])
    assert not any(torch.equal(a, b) for a in first for b in second)


def _weights(module) -> list:
    """A module's (or a state dict's) tensors, copied."""
    import torch

    state = module.state_dict() if isinstance(module, torch.nn.Module) else module
    return [v.detach().clone() for v in state.values()]


def test_the_critic_worker_gives_the_sequential_updates():
    """``loss.critic_worker=true``: each iteration's critic update runs in the worker process while the actor's
    backward pass runs, and is loaded back before the next rollout, so training is the sequential order's. With
    deterministic rollouts and one minibatch per critic epoch (no random stream read in either process's order),
    actor, critic, target critic and the checkpoint's optimiser state match the in-process run to float32
    round-off (the minibatch's samples summed in another order); close() ends the process."""
    import torch

    keys = ("loss.noise=false", "loss.critic_batch_size=64")  # 32 frames per iteration: one minibatch
    states = {}
    for worker in (False, True):
        torch.manual_seed(0)
        algo = _tiny_shac(*keys, f"loss.critic_worker={str(worker).lower()}")
        for _ in range(3):
            _, metrics = algo.iterate(10 ** 6)
            assert math.isfinite(float(metrics["train/loss_critic"]))
        state = algo.state_dict()
        assert {int(s["step"]) for s in state["critic_optimizer"]["state"].values()} == {3 * 2}  # 2 epochs each
        states[worker] = (_weights(algo.actor) + _weights(state["critic"]) + _weights(state["target_critic"]) +
                          [s["exp_avg"] for s in state["critic_optimizer"]["state"].values()])
        if worker:
            proc = algo.worker._proc
            algo.close()
            assert not proc.is_alive()
    for a, b in zip(states[False], states[True]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


def test_the_critic_worker_is_repeatable():
    """Two runs of the same seed with the worker give the same weights (its minibatch shuffles are seeded)."""
    import torch

    runs = []
    for _ in range(2):
        torch.manual_seed(0)
        algo = _tiny_shac("loss.critic_worker=true")
        for _ in range(2):
            algo.iterate(10 ** 6)
        runs.append(_weights(algo.actor) + _weights(algo.critic))
        algo.close()
    assert all(torch.equal(a, b) for a, b in zip(*runs))


def test_shac_with_the_critic_worker_and_the_torch_power_flow_runs_the_recipe(tmp_path):
    """The recipe end to end with the critic worker and the exact model's power flow in torch ops (the reference
    path; the compiled one is the default the other recipe tests run): the run directory and finite critic losses
    under their tag."""
    run_dir = tmp_path / "run"
    run(SHAC, "model=exact", *TINY_SHAC, "loss.critic_worker=true", "env.power_flow=torch",
        "collector.total_frames=96", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["model_frames"] == 96 and summary["updates"] == 3 and not summary["interrupted"]
    tags = scalars(run_dir)
    assert len(tags["train/loss_critic"]) == 3 and all(math.isfinite(v) for _, v in tags["train/loss_critic"])


def test_checkpoints_with_the_forward_keys_first_home_still_load():
    """The runs of ANM6-Easy's exact-model leaderboard row were made with ``model.power_flow`` (now
    ``env.power_flow``): the actor is built from the model keys ``make_ppo_models`` takes, without it."""
    from anm_torchrl.training.algorithms.shac import actor_options

    config = {"model": {"dynamics": "exact", "power_flow": "numba", "actor_cells": [8], "time_features": True}}
    assert actor_options(config) == {"actor_cells": [8], "time_features": True}


def test_a_dead_critic_worker_is_named():
    """If the worker process dies, the training process says so instead of waiting or failing on a pipe error."""
    import torch

    torch.manual_seed(0)
    algo = _tiny_shac("loss.critic_worker=true")
    algo.iterate(10 ** 6)
    algo.worker._proc.kill()
    algo.worker._proc.join()
    with pytest.raises(RuntimeError, match=r"SHAC's critic worker process ended \(exit code -9\)"):
        algo.iterate(10 ** 6)
    algo.close()


def test_a_signal_to_the_whole_group_leaves_the_critic_worker_running():
    """Ctrl-C in a terminal (and ``timeout``, a scheduler's group kill) signals the worker too: it inherited the
    run's handler and died with a KeyboardInterrupt, and the training process, finishing its iteration, failed on
    the dead worker with no summary. The worker ignores both signals; the run's own handler decides."""
    import os
    import signal

    import torch

    from anm_torchrl.training.signals import graceful, stop_requested, stop_signals

    torch.manual_seed(0)
    with stop_signals():
        algo = _tiny_shac("loss.critic_worker=true")
        try:
            with graceful():
                algo.iterate(10 ** 6)
                for sig in (signal.SIGINT, signal.SIGTERM):
                    os.kill(algo.worker._proc.pid, sig)
                os.kill(os.getpid(), signal.SIGINT)  # the training process's own: a request to stop
                _, metrics = algo.iterate(10 ** 6)  # the iteration in flight finishes with the worker
            assert algo.worker._proc.is_alive() and stop_requested() == "SIGINT"
            assert math.isfinite(float(metrics["train/loss_critic"]))
        finally:
            algo.close()


def test_the_critic_worker_says_where_it_cannot_run(monkeypatch):
    import multiprocessing

    monkeypatch.setattr(multiprocessing, "get_all_start_methods", lambda: ["spawn"])
    with pytest.raises(ValueError, match="loss.critic_worker=true needs the 'fork' start method"):
        _tiny_shac("loss.critic_worker=true")


@pytest.mark.parametrize("network", ["anm6_easy", "case33bw", "cigre_mv", "simbench_mv_semiurb", "my_feeder.npz"])
def test_the_exact_model_solves_in_the_compiled_kernel_by_default_on_every_network(network):
    """The leaderboards' SHAC rows and the unseen-networks column were made with the compiled power flow
    (``env.power_flow: numba``, recipes/conf/env/shac.yaml); no network's entry may switch it back silently. A
    network file that is not a registered name gets the ``default`` entry (its name is only read, not loaded)."""
    from anm_torchrl.training.network_defaults import compose_recipe_config

    cfg, _ = compose_recipe_config([f"network={network}"], "shac")
    assert cfg.model.dynamics == "exact" and cfg.env.power_flow == "numba"


def test_shac_names_a_pinn_that_terminates_far_too_often(monkeypatch, caplog):
    """PPO's surrogate env names a model ending more than one step in ten; SHAC through the PINN (no surrogate env)
    said nothing while a smoke PINN ended every step of its rollouts."""
    import logging

    import torch
    from recipe_utils import compose

    from anm_torchrl.surrogates.pinn import chain
    from anm_torchrl.training import factory
    from anm_torchrl.training.algorithms.shac import PINNModel
    from anm_torchrl.training.factory import make_true_env

    monkeypatch.setattr(factory, "load_surrogate_in_home", lambda *a, **k: torch.nn.Linear(1, 1))
    monkeypatch.setattr(chain, "run_chain", lambda c, td: {
        "next_state": td["state"].clone(), "reward": torch.zeros(td["state"].shape[0]),
        "terminated": torch.ones(td["state"].shape[0], dtype=torch.bool)})
    env = make_true_env(4, seed=0)
    model = PINNModel(env, compose("shac", ["model=pinn"]))
    state = env.reset()["state"]
    with caplog.at_level(logging.WARNING, logger="anm_torchrl.envs.surrogate"):
        for _ in range(25):
            model(state, torch.zeros(4, 6))
    warned = [r.getMessage() for r in caplog.records if "termination" in r.getMessage()]
    assert len(warned) == 1 and "(the PINN) ended 100 % of its first 80 steps" in warned[0], warned
