"""Validation passes in a second process (``eval.background``, :mod:`anm_torchrl.training.validation`): the same
runs as validation in the training process, value for value (curve, best.pt, early stop, test figures), and clear
errors when the second process fails or the option is wrong."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch

from tests.test_recipes_ppo import PPO, TINY, run

torch.set_num_threads(1)


def _without_seconds(d: dict) -> dict:
    return {k: v for k, v in d.items() if k != "seconds"}


def test_background_validation_gives_the_run_of_inline_validation(tmp_path):
    """Two tiny PPO runs, validation after every update with a patience of 2 (so the run stops early: the second
    process's pass that ends the patience is waited for), in a second process and in the training process."""
    from anm_torchrl.training.checkpoint import load_checkpoint

    runs = {}
    for mode in ("true", "false"):
        run_dir = tmp_path / mode
        proc = run(PPO, *TINY, "collector.total_frames=640", "eval.patience=2", "seed=1", f"eval.background={mode}",
                   f"hydra.run.dir={run_dir}", cwd=tmp_path)
        runs[mode] = (run_dir, json.loads((run_dir / "summary.json").read_text()), proc.stdout + proc.stderr)
    (bg_dir, bg, bg_log), (in_dir, inline, in_log) = runs["true"], runs["false"]
    assert "validation passes run in a second process" in bg_log
    assert "validation passes run in a second process" not in in_log
    assert inline["stopped_early"] and inline["updates"] < 20, "the case must exercise the early stop"
    for key in ("stopped_early", "updates", "frames"):
        assert bg[key] == inline[key], key
    assert [{k: v for k, v in p.items() if k != "wall_s"} for p in bg["curve"]] == \
        [{k: v for k, v in p.items() if k != "wall_s"} for p in inline["curve"]]
    assert _without_seconds(bg["best_eval"]) == _without_seconds(inline["best_eval"])
    for name in ("best", "last"):
        assert _without_seconds(bg["test"][name]) == _without_seconds(inline["test"][name]), name
        a, b = (load_checkpoint(d / "checkpoints" / f"{name}.pt") for d in (bg_dir, in_dir))
        assert (a["frames"], a["update"], a["evals_since_best"]) == (b["frames"], b["update"], b["evals_since_best"])
        assert all(torch.equal(a["actor"][k], b["actor"][k]) for k in b["actor"]), name
        assert all(torch.equal(a["state"]["optimizer"]["state"][i]["exp_avg"], b["state"]["optimizer"]["state"][i]
                               ["exp_avg"]) for i in b["state"]["optimizer"]["state"]), name
        assert _without_seconds(a["best_eval"]) == _without_seconds(b["best_eval"])


def _small_case():
    from anm_torchrl.evaluation import draw_initial_states
    from anm_torchrl.training.factory import make_true_env
    from anm_torchrl.training.models import make_ppo_models

    env = make_true_env(2, "cpu", seed=1, network="anm6_easy")
    actor = make_ppo_models(env)[0]
    return actor, draw_initial_states(2, 1, env.sim, env.init), env


def test_background_pass_equals_inline_pass_and_keeps_its_weights():
    """A pass evaluates the weights as they were submitted, even when the caller changes them at once."""
    from anm_torchrl.training.validation import NICENESS, BackgroundValidation, InlineValidation

    actor, states, env = _small_case()
    background = BackgroundValidation(actor, states, env, max_steps=20, gamma=0.99)
    try:
        weights = actor.state_dict()
        background.submit(weights, "first")
        with torch.no_grad():
            for p in actor.parameters():
                p.add_(0.5)  # training goes on while the pass runs
        background.submit(actor.state_dict(), "second")
        assert background.pending == 2
        got = background.results(wait=True)
        assert background.pending == 0 and [tag for tag, _ in got] == ["first", "second"]
        # off the training's critical path: the second process yields the CPUs to the training (NICENESS)
        own = os.getpriority(os.PRIO_PROCESS, 0)
        assert os.getpriority(os.PRIO_PROCESS, background.proc.pid) == min(19, own + NICENESS)
    finally:
        background.close()
    inline = InlineValidation(actor, states, env, max_steps=20, gamma=0.99)
    inline.submit(None, "second")
    (_, expected), = inline.results()
    assert _without_seconds(got[1][1]) == _without_seconds(expected)
    assert got[0][1]["discounted_return"] != expected["discounted_return"]


def test_a_failed_validation_process_names_its_error():
    from anm_torchrl.training.validation import BackgroundValidation

    actor, states, env = _small_case()
    background = BackgroundValidation(actor, torch.cat([states, states]), env, max_steps=5, gamma=0.99)
    try:
        background.submit(actor.state_dict(), 0)
        with pytest.raises(RuntimeError, match="the validation process failed .*does not match 4 initial states"):
            background.results(wait=True)
    finally:
        background.close()


def test_background_choice():
    from anm_torchrl.training.validation import use_background

    from anm_torchrl.provenance import usable_cpus

    assert use_background(True, "cpu", 1, 10) and not use_background(False, "cpu", 1, 3000)
    assert not use_background("auto", "cuda", 1, 3000)
    assert not use_background("auto", "cpu", 10_000, 3000)  # not 20,000 CPUs here
    assert not use_background("auto", "cpu", 1, 10)  # a pass shorter than starting the process
    assert use_background("auto", "cpu", 1, 3000) == (usable_cpus() >= 2)
    with pytest.raises(ValueError, match="eval.background must be auto, true or false; got 'sometimes'"):
        use_background("sometimes", "cpu", 1, 3000)


def test_the_temp_folder_is_removed(tmp_path, monkeypatch):
    import tempfile

    from anm_torchrl.training.validation import BackgroundValidation

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    actor, states, env = _small_case()
    BackgroundValidation(actor, states, env, max_steps=5, gamma=0.99).close()
    assert list(Path(tmp_path).iterdir()) == []


def test_ctrl_c_with_a_pass_in_the_second_process(tmp_path):
    """SIGINT to the training process while the second process runs: the run ends as without it (exit 130,
    last.pt and summary.json marked interrupted), every submitted pass recorded, no process or folder left behind."""
    from tests.test_recipes_ppo import ENV, interrupt_run

    run_dir, tmp = tmp_path / "interrupted", tmp_path / "tmp"
    tmp.mkdir()
    interrupt_run(run_dir, "update 2, 64 frames", "eval.background=true", env={**ENV, "TMPDIR": str(tmp)})
    summary = json.loads((run_dir / "summary.json").read_text())
    assert [p["update"] for p in summary["curve"]] == list(range(1, len(summary["curve"]) + 1))
    assert list(tmp.glob("anm_torchrl_validation_*")) == []  # its folder (setup file, stderr) is removed
    running = [c for c in Path("/proc").glob("[0-9]*/cmdline") if str(tmp) in _reads(c)]
    assert running == []


def _reads(path: Path) -> str:
    try:
        return path.read_bytes().decode(errors="replace")
    except OSError:  # the process ended meanwhile
        return ""


def test_background_curve_points_carry_the_time_of_their_policy(tmp_path, monkeypatch):
    """Bug: with validation in a second process, a curve point's wall_s was taken when its result was read, at the
    next validation point (one iteration late), so the last two points of a run were ~0 s apart. Each iteration is
    stretched by 0.6 s here: consecutive points must be at least that far apart."""
    import time

    from anm_torchrl.training import protocol
    from anm_torchrl.training.algorithms import ppo as ppo_module
    from anm_torchrl.training.network_defaults import compose_recipe_config

    cfg, defaults = compose_recipe_config([*TINY, "collector.total_frames=256", "eval.interval=1",
                                           "eval.background=true", "logger.backend=null"])
    iterate = ppo_module.PPO.iterate

    def slow(self, remaining):
        out = iterate(self, remaining)
        time.sleep(0.6)
        return out

    monkeypatch.setattr(ppo_module.PPO, "iterate", slow)
    curve = protocol.train(cfg, tmp_path / "run", network_defaults=defaults)["curve"]
    assert len(curve) >= 3
    gaps = [b["wall_s"] - a["wall_s"] for a, b in zip(curve, curve[1:])]
    assert min(gaps) > 0.5, gaps
