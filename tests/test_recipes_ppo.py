"""Smoke tests of recipes/ppo.py and recipes/evaluate.py (tiny runs in temp dirs) and of the training helpers.

Every recipe run is a subprocess with tiny overrides (4 grids, 8 steps per env, 10-step evaluations), so the file
stays well under two minutes on two cores.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
PPO = ROOT / "recipes" / "ppo.py"
EVALUATE = ROOT / "recipes" / "evaluate.py"
TINY = ["env.num_envs=4", "collector.frames_per_batch=32", "collector.total_frames=64", "eval.max_steps=10",
        "eval.num_episodes=2", "loss.mini_batch_size=16", "loss.ppo_epochs=2", "logger.progress=false"]
EVAL_KEYS = ("return", "discounted_return", "e_loss", "penalty", "steps", "terminated")
RESULT_KEYS = EVAL_KEYS + ("episodes", "env", "policy", "wall_time")


def run(script: Path, *args: str, cwd: Path, check: bool = True) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}
    proc = subprocess.run([sys.executable, str(script), *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=300)
    if check and proc.returncode != 0:
        raise AssertionError(f"{script.name} {' '.join(args)} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n"
                             f"{proc.stderr[-3000:]}")
    return proc


def scalars(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """All TensorBoard scalars of a run directory: tag -> [(step, value)]."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    files = sorted(run_dir.glob("logs/*/events.out.tfevents.*"))
    assert files, f"no TensorBoard event file under {run_dir / 'logs'}"
    acc = EventAccumulator(str(files[0].parent))
    acc.Reload()
    out = {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}
    out["__tensors__"] = acc.Tags()["tensors"]
    return out


def last_json(proc: subprocess.CompletedProcess) -> dict:
    lines = [line for line in proc.stdout.strip().splitlines() if line.strip()]
    assert lines, f"no stdout; stderr:\n{proc.stderr[-2000:]}"
    return json.loads(lines[-1])


@pytest.fixture(scope="module")
def base_run(tmp_path_factory) -> Path:
    """One tiny PPO run on the true simulator: 2 updates of 32 frames, an evaluation after each."""
    run_dir = tmp_path_factory.mktemp("ppo") / "run"
    run(PPO, *TINY, "seed=3", f"hydra.run.dir={run_dir}", cwd=run_dir.parent)
    return run_dir


# ------------------------------------------------------------------------------------------------ ppo.py
def test_ppo_writes_logs_checkpoints_and_summary(base_run):
    tags = scalars(base_run)
    for tag in [f"eval/{k}" for k in ("return", "discounted_return", "e_loss", "penalty")] + [
            "train/loss_objective", "train/loss_critic", "train/loss_entropy", "train/entropy", "train/reward",
            "train/lr", "time/collect", "time/update", "time/eval", "time/fps"]:
        assert tag in tags, f"missing TensorBoard tag {tag}; have {sorted(tags)}"
    assert [s for s, _ in tags["eval/discounted_return"]] == [32, 64]  # evaluated after every update
    for tag in ("train/loss_objective", "train/loss_critic", "eval/discounted_return"):
        assert all(math.isfinite(v) for _, v in tags[tag]), (tag, tags[tag])
    assert any(t.startswith("config") for t in tags["__tensors__"]), "resolved config not logged as text"

    from anm_torchrl.training.checkpoint import CHECKPOINT_KIND, load_checkpoint

    for name in ("best.pt", "last.pt"):
        ckpt = load_checkpoint(base_run / "checkpoints" / name)
        assert ckpt["kind"] == CHECKPOINT_KIND and ckpt["config"]["seed"] == 3
        assert set(ckpt["obs_norm"]) == {"loc", "scale"} and ckpt["obs_norm"]["loc"].shape == (18,)
    last = load_checkpoint(base_run / "checkpoints" / "last.pt")
    assert last["frames"] == 64 and last["update"] == 2 and last["logger_step"] == 64
    assert "optimizer" in last and last["best_eval"] is not None

    summary = json.loads((base_run / "summary.json").read_text())
    assert summary["frames"] == 64 and summary["updates"] == 2
    assert set(EVAL_KEYS) <= set(summary["best_eval"]) and set(EVAL_KEYS) <= set(summary["final_eval"])
    assert summary["config"]["env"]["num_envs"] == 4 and summary["wall_time"] > 0
    assert math.isclose(summary["best_eval"]["discounted_return"], max(v for _, v in tags["eval/discounted_return"]),
                        rel_tol=1e-5)


def test_resume_continues_from_saved_frames(base_run, tmp_path):
    run_dir = tmp_path / "resumed"
    run(PPO, *TINY, "seed=3", "collector.total_frames=96", f"checkpoint.resume={base_run}/checkpoints/last.pt",
        f"hydra.run.dir={run_dir}", cwd=tmp_path)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["frames"] == 96 and summary["updates"] == 3  # one more batch of 32 after 64 saved frames
    assert [s for s, _ in scalars(run_dir)["eval/discounted_return"]] == [96]  # logger step continues
    assert (run_dir / "checkpoints" / "best.pt").is_file() and (run_dir / "checkpoints" / "last.pt").is_file()


def test_multirun_same_seed_gives_same_first_evaluation(tmp_path):
    sweep = tmp_path / "sweep"
    run(PPO, "-m", *TINY, "collector.total_frames=32", "logger.backend=csv", "seed=5,5",
        f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    jobs = sorted(p for p in sweep.iterdir() if (p / "summary.json").exists())
    assert len(jobs) == 2, list(sweep.iterdir())
    first = [json.loads((j / "summary.json").read_text())["final_eval"] for j in jobs]
    assert first[0]["discounted_return"] == first[1]["discounted_return"]
    assert list(jobs[0].glob("logs/*/scalars/eval/discounted_return.csv")), "CSV logger wrote no eval scalars"


@pytest.mark.parametrize("override, message", [
    ("surrogate=foo", "Could not find 'surrogate/foo'"),
    ("logger.backend=foo", "logger.backend must be one of tensorboard, csv or null; got 'foo'"),
    ("env.no_such_key=1", "Key 'no_such_key' is not in struct"),
    ("collector.frames_per_batch=30", "must be a positive multiple of env.num_envs"),
])
def test_bad_override_fails_clearly(override, message, tmp_path):
    proc = run(PPO, *TINY, override, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path, check=False)
    assert proc.returncode != 0
    assert message in proc.stdout + proc.stderr, proc.stderr[-2000:]


def test_resume_from_wrong_kind_fails_clearly(tmp_path):
    bogus = tmp_path / "bogus.pt"
    torch.save({"weights": torch.zeros(3), "epoch": 1}, bogus)
    proc = run(PPO, *TINY, f"checkpoint.resume={bogus}", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path,
               check=False)
    assert proc.returncode != 0
    assert "is not an anm_torchrl PPO checkpoint" in proc.stderr and "epoch, weights" in proc.stderr


# ------------------------------------------------------------------------------------------- evaluate.py
def test_evaluate_checkpoint_json(base_run, tmp_path):
    out = last_json(run(EVALUATE, f"checkpoint={base_run}/checkpoints/best.pt", "steps=20", "episodes=2",
                        cwd=tmp_path))
    assert set(RESULT_KEYS) <= set(out) and out["policy"] == "ppo" and out["env"] == "anm6"
    assert out["episodes"] == 2 and 0 < out["steps"] <= 20 and math.isfinite(out["discounted_return"])


def test_evaluate_baseline_json_and_bad_checkpoint(tmp_path):
    out = last_json(run(EVALUATE, "policy=do_nothing", "steps=20", "episodes=2", cwd=tmp_path))
    assert set(RESULT_KEYS) <= set(out) and out["policy"] == "do_nothing" and out["steps"] == 20
    assert out["terminated"] == 0.0 and out["return"] <= out["discounted_return"] < 0

    bogus = tmp_path / "surrogate.pt"
    torch.save({"kind": "anm_torchrl.surrogate.xgb", "model": torch.zeros(2)}, bogus)
    proc = run(EVALUATE, f"checkpoint={bogus}", "steps=5", cwd=tmp_path, check=False)
    assert proc.returncode != 0 and "kind='anm_torchrl.surrogate.xgb'" in proc.stderr
    proc = run(EVALUATE, "policy=do_nothing", "no_such_option=1", cwd=tmp_path, check=False)
    assert proc.returncode != 0 and "unknown option" in proc.stderr


def test_evaluate_gym_anm_json(base_run, tmp_path):
    pytest.importorskip("gym_anm")
    out = last_json(run(EVALUATE, f"checkpoint={base_run}/checkpoints/last.pt", "env=gym_anm", "steps=5",
                        "episodes=1", "progress=false", cwd=tmp_path))
    assert set(RESULT_KEYS) <= set(out) and out["env"] == "gym_anm" and out["steps"] == 5


# ------------------------------------------------------------------------------------------- helpers
def test_gym_anm_and_anm6_evaluations_agree():
    pytest.importorskip("gym_anm")
    torch.set_num_threads(1)
    from anm_torchrl.baselines import make_baseline
    from anm_torchrl.training.evaluation import draw_initial_states, evaluate_policy, evaluate_policy_gym_anm

    states = draw_initial_states(2, seed=11)
    policy = make_baseline("do_nothing")
    ours = evaluate_policy(policy, states, max_steps=6)
    ref = evaluate_policy_gym_anm(policy, states, max_steps=6)
    torch.testing.assert_close(ours.discounted_returns, ref.discounted_returns, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(ours.penalty, ref.penalty, rtol=1e-5, atol=1e-5)


def test_episode_metrics_stop_at_first_termination():
    from anm_torchrl.training.evaluation import episode_metrics

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
    with pytest.raises(ValueError, match=r"not an anm_torchrl PPO checkpoint.*keys \[state_dict\]"):
        load_checkpoint(tmp_path / "plain.pt")
    (tmp_path / "model.json").write_text('{"learner": {}}')
    with pytest.raises(ValueError, match="torch.load"):
        load_checkpoint(tmp_path / "model.json")
    torch.save([1, 2], tmp_path / "list.pt")
    with pytest.raises(ValueError, match="type builtins.list"):
        load_checkpoint(tmp_path / "list.pt")
    path = save_checkpoint(tmp_path / "c" / "x.pt", {"config": {}, "actor": {}, "critic": {}, "obs_norm": {},
                                                     "frames": 1, "update": 1})
    assert load_checkpoint(path)["format_version"] == FORMAT_VERSION
    assert not list(path.parent.glob("*.tmp"))
    torch.save({"kind": CHECKPOINT_KIND, "format_version": 99}, tmp_path / "future.pt")
    with pytest.raises(ValueError, match="format_version 99"):
        load_checkpoint(tmp_path / "future.pt")


@pytest.mark.slow
def test_multiprocess_collector(tmp_path):
    """collector.num_workers=2: TorchRL's multi-process collector (worker start-up takes several seconds)."""
    run_dir = tmp_path / "mp"
    run(PPO, *TINY, "collector.num_workers=2", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["frames"] == 64 and math.isfinite(summary["final_eval"]["discounted_return"])


def test_wall_clock_budget_stops_the_run(tmp_path):
    run_dir = tmp_path / "budget"
    run(PPO, *TINY, "collector.total_frames=320", "collector.max_minutes=0.0001", "logger.backend=null",
        f"hydra.run.dir={run_dir}", cwd=tmp_path)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["out_of_time"] and summary["updates"] == 1 and summary["frames"] == 32
    assert (run_dir / "checkpoints" / "last.pt").is_file()
