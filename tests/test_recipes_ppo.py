"""Smoke tests of recipes/ppo.py (tiny runs in temp dirs): what a run writes (logs, checkpoints, summary with the
validation/test split), exact frame budgets, resume, multirun, bad overrides, Ctrl-C.

Every recipe run is a subprocess with tiny overrides (4 grids, 8 steps per env, 10-step evaluations), so the file
stays around two minutes on two shared cores.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
PPO = ROOT / "recipes" / "ppo.py"
TINY = ["env.num_envs=4", "collector.frames_per_batch=32", "collector.total_frames=64", "eval.max_steps=10",
        "eval.interval=1", "eval.num_episodes=2", "eval.test_episodes=3", "loss.mini_batch_size=16",
        "loss.ppo_epochs=2", "logger.progress=false"]
EVAL_KEYS = ("return", "discounted_return", "e_loss", "penalty", "steps", "terminated")
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}


def run(script: Path, *args: str, cwd: Path, check: bool = True) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, str(script), *args], cwd=cwd, env=ENV, capture_output=True, text=True,
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
    out["__images__"] = {tag: [e.step for e in acc.Images(tag)] for tag in acc.Tags()["images"]}
    return out


@pytest.fixture(scope="module")
def base_run(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """One tiny PPO run on the true simulator: 80 frames = 2 batches of 32 + 16 frames of a third batch (the
    budget is exact), a validation evaluation after each update, a test evaluation of best.pt and last.pt."""
    run_dir = tmp_path_factory.mktemp("ppo") / "run"
    proc = run(PPO, *TINY, "collector.total_frames=80", "seed=3", "eval.render_interval=2", f"hydra.run.dir={run_dir}",
               cwd=run_dir.parent)
    return run_dir, proc


# ------------------------------------------------------------------------------------------------ ppo.py
def test_ppo_writes_logs_checkpoints_and_summary(base_run):
    base_run, proc = base_run
    assert f"run directory: {base_run}" in proc.stdout
    tags = scalars(base_run)
    for tag in [f"eval/{k}" for k in ("return", "discounted_return", "e_loss", "penalty")] + [
            "train/loss_objective", "train/loss_critic", "train/explained_variance", "train/clip_fraction",
            "train/kl_approx", "train/grad_norm", "train/reward",
            "train/lr", "time/collect", "time/update", "time/eval", "time/fps"] + [
            f"test/{c}/{k}" for c in ("best", "last") for k in EVAL_KEYS]:
        assert tag in tags, f"missing TensorBoard tag {tag}; have {sorted(tags)}"
    assert "train/loss_entropy" not in tags  # loss.entropy_coeff = 0: no (sampled) entropy estimate is computed
    assert [s for s, _ in tags["eval/discounted_return"]] == [32, 64, 80]  # after every update; exact budget
    for tag in ("train/loss_objective", "train/loss_critic", "eval/discounted_return"):
        assert all(math.isfinite(v) for _, v in tags[tag]), (tag, tags[tag])
    assert any(t.startswith("config") for t in tags["__tensors__"]), "resolved config not logged as text"
    assert tags["__images__"] == {"eval/episode": [64]}, "eval.render_interval=2: a figure at evaluation 2 only"

    from anm_torchrl.training.checkpoint import CHECKPOINT_KIND, load_checkpoint

    for name in ("best.pt", "last.pt"):
        ckpt = load_checkpoint(base_run / "checkpoints" / name)
        assert ckpt["kind"] == CHECKPOINT_KIND and ckpt["config"]["seed"] == 3
        assert set(ckpt["obs_norm"]) == {"loc", "scale"} and ckpt["obs_norm"]["loc"].shape == (18,)
    last = load_checkpoint(base_run / "checkpoints" / "last.pt")
    assert last["frames"] == 80 and last["update"] == 3 and last["logger_step"] == 80
    assert last["algorithm"] == "ppo" and "optimizer" in last["state"] and last["best_eval"] is not None

    summary = json.loads((base_run / "summary.json").read_text())
    assert summary["frames"] == 80 and summary["updates"] == 3 and not summary["interrupted"]
    assert set(EVAL_KEYS) <= set(summary["best_eval"]) and set(EVAL_KEYS) <= set(summary["final_eval"])
    assert summary["config"]["env"]["num_envs"] == 4 and summary["wall_time"] > 0
    assert math.isclose(summary["best_eval"]["discounted_return"], max(v for _, v in tags["eval/discounted_return"]),
                        rel_tol=1e-5)


def test_summary_separates_validation_from_test_states(base_run):
    """Model selection on the validation states (eval.seed), reported figures on other states (eval.test_seed)."""
    base_run, _ = base_run
    summary = json.loads((base_run / "summary.json").read_text())
    val, test = summary["validation"], summary["test"]
    assert (val["seed"], val["num_episodes"], test["seed"], test["num_episodes"]) == (1, 2, 0, 3)

    from anm_torchrl.evaluation import draw_initial_states

    s_val, s_test = draw_initial_states(2, val["seed"]), draw_initial_states(3, test["seed"])
    assert not (s_val[:, None, :] == s_test[None, :, :]).all(-1).any(), "a validation state is also a test state"
    best = summary["best_eval"]
    assert test["best"]["frames"] == best["frames"] and test["last"]["frames"] == 80
    for name in ("best", "last"):
        assert set(EVAL_KEYS) <= set(test[name]) and math.isfinite(test[name]["discounted_return"])
        logged = scalars(base_run)[f"test/{name}/discounted_return"]
        assert logged[-1][0] == 80 and math.isclose(logged[-1][1], test[name]["discounted_return"], rel_tol=1e-5)
    # the same policy scores differently on other states: the test figures are not the validation figures
    assert test["best"]["discounted_return"] != best["discounted_return"]


def test_the_summary_compares_best_with_doing_nothing_and_says_when_it_is_worse(base_run):
    """do-nothing on the same validation states (its discounted return to the last digit of an independent pass),
    and one warning line when best.pt scores below it: the user would otherwise take a policy worse than no
    controller for a trained one."""
    import torch

    from anm_torchrl.baselines import make_baseline
    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy
    from anm_torchrl.training.factory import make_true_env

    base_run, proc = base_run
    summary = json.loads((base_run / "summary.json").read_text())
    val = summary["validation"]
    env = make_true_env(val["num_episodes"], seed=val["seed"])
    states = draw_initial_states(val["num_episodes"], val["seed"], env.sim, env.init)
    expected = evaluate_policy(make_baseline("do_nothing", sim=env.sim), states, max_steps=val["max_steps"],
                               gamma=val["gamma"], env=env).metrics()["discounted_return"]
    assert val["do_nothing_discounted_return"] == expected and torch.isfinite(torch.tensor(expected))
    worse = summary["best_eval"]["discounted_return"] < expected
    assert ("best.pt is worse than doing nothing on the validation states" in proc.stderr + proc.stdout) == worse
    # the run's last log line puts the two side by side (README: "it ends by comparing best.pt with doing nothing")
    assert f"(do-nothing on the same validation states: {expected:.4g})" in proc.stderr + proc.stdout


def test_ppo_on_another_network(tmp_path, evaluate_recipe):
    """``python recipes/ppo.py network=case33bw surrogate=none``: trains and evaluates on the 33-bus feeder's true
    env, states from its reset distribution; evaluate.py takes the network from the checkpoint."""
    run_dir = tmp_path / "case33bw"
    run(PPO, *TINY, "network=case33bw", "surrogate=none", "eval.test_max_steps=12", f"hydra.run.dir={run_dir}",
        cwd=tmp_path)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["frames"] == 64 and summary["config"]["network"] == "case33bw"
    # case33bw's own defaults (recipes/conf/per_network/ppo.yaml) apply to every key not on the command line
    defaults = summary["network_defaults"]
    assert defaults["entry"] == "case33bw" and defaults["applied"]["model.init_action"] == "do_nothing"
    assert summary["config"]["model"]["init_action"] == "do_nothing" and summary["config"]["env"]["max_steps"] == 200
    assert defaults["kept"]["env.num_envs"] == 4 and summary["test"]["best"]["steps"] == 12
    assert all(math.isfinite(summary["test"][c]["discounted_return"]) for c in ("best", "last"))

    from anm_torchrl.training.checkpoint import load_checkpoint
    from anm_torchrl.training.factory import make_true_env

    env = make_true_env(1, network="case33bw")
    n_obs = env.observation_spec["observation"].shape[-1]
    assert n_obs != 18 and load_checkpoint(run_dir / "checkpoints" / "best.pt")["obs_norm"]["loc"].shape == (n_obs,)
    out = evaluate_recipe.main([f"checkpoint={run_dir}/checkpoints/best.pt", "steps=10", "episodes=2"])
    assert out["network"] == "case33bw" and out["steps"] == 10 and math.isfinite(out["discounted_return"])
    with pytest.raises(SystemExit, match="trained on network='case33bw', not 'anm6_easy'"):
        evaluate_recipe.main([f"checkpoint={run_dir}/checkpoints/best.pt", "network=anm6_easy"])


def test_resume_continues_from_saved_frames(base_run, tmp_path):
    base_run, _ = base_run
    run_dir = tmp_path / "resumed"
    run(PPO, *TINY, "seed=3", "collector.total_frames=112", f"checkpoint.resume={base_run}/checkpoints/last.pt",
        f"hydra.run.dir={run_dir}", cwd=tmp_path)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["frames"] == 112 and summary["updates"] == 4  # one more batch of 32 after 80 saved frames
    assert [s for s, _ in scalars(run_dir)["eval/discounted_return"]] == [112]  # logger step continues
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


@pytest.mark.parametrize("override, message", [  # every range check: tests/test_config_checks.py
    ("surrogate=foo", "Could not find 'surrogate/foo'"),
    ("env.no_such_key=1", "Key 'no_such_key' is not in struct"),
    ("collector.total_frames=-5", "collector.total_frames must be an integer >= 1, got -5"),
])
def test_bad_override_fails_clearly(override, message, tmp_path):
    proc = run(PPO, *TINY, override, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path, check=False)
    assert proc.returncode != 0
    assert message in proc.stdout + proc.stderr, proc.stderr[-2000:]
    if "must be" in message:  # our range checks: one line, no traceback, no run directory left behind
        assert proc.stderr.strip() == f"ppo.py: {message}", proc.stderr[-2000:]
        assert not (tmp_path / "run").exists()


def test_help_lists_only_this_recipes_groups(tmp_path):
    out = run(PPO, "--help", cwd=tmp_path).stdout
    assert "surrogate: dnn, dt, gym_anm, lr, none, pinn, rf, xgb (now: none)" in out
    for group in ("collector:", "eval:", "loss:", "model:", "optim:"):
        assert f"\n{group} " in out, group
    assert "preset" not in out and "pinn_preset" not in out  # other recipes' groups


def test_resume_with_another_activation_fails(ppo_checkpoint, tmp_path):
    proc = run(PPO, *TINY, "model.activation=relu", f"checkpoint.resume={ppo_checkpoint}",
               f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path, check=False)
    assert proc.returncode != 0
    assert "model.activation: checkpoint 'tanh', this run 'relu'" in proc.stderr, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and not (tmp_path / "run").exists()  # one line, before the run

def interrupt_run(run_dir: Path, marker: str, *args: str, env: dict | None = None, sig=signal.SIGINT,
                  status: int = 130, group: bool = False) -> str:
    """Run ``ppo.py`` (TINY, an endless budget, ``args``) into ``run_dir``, send ``sig`` once a line of its output
    holds ``marker`` (``group``: to its whole process group, as a terminal's Ctrl-C does); check exit status
    ``status``, ``summary.json`` marked interrupted and ``last.pt`` at its frames; returns the output."""
    proc = subprocess.Popen([sys.executable, str(PPO), *TINY, "collector.total_frames=1000000", "eval.patience=null",
                             *args, f"hydra.run.dir={run_dir}"], cwd=run_dir.parent, env=env or ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=group)
    lines = []
    for line in proc.stdout:
        lines.append(line)
        if marker in line:
            if group:
                os.killpg(proc.pid, sig)
            else:
                proc.send_signal(sig)
            break
    out, _ = proc.communicate(timeout=120)
    out = "".join(lines) + out
    assert proc.returncode == status, out[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["interrupted"] and 32 <= summary["frames"] < 1000000
    assert summary["validation"]["do_nothing_discounted_return"] is None  # no extra pass after a Ctrl-C

    from anm_torchrl.training.checkpoint import load_checkpoint

    assert load_checkpoint(run_dir / "checkpoints" / "last.pt")["frames"] == summary["frames"]
    return out


def test_ctrl_c_ends_the_run_cleanly(tmp_path):
    """SIGINT after the first evaluation: exit status 130, last.pt and summary.json marked interrupted."""
    run_dir = tmp_path / "interrupted"
    out = interrupt_run(run_dir, "update 1, 32 frames")
    assert f"run directory: {run_dir}" in out


def test_sigterm_ends_the_run_as_ctrl_c_does(tmp_path):
    """SIGTERM (``kill``, a scheduler's preemption) after the first evaluation: exit status 143 (128 + 15), last.pt
    and summary.json marked interrupted, as after a Ctrl-C; before, the run died without its summary."""
    run_dir = tmp_path / "terminated"
    out = interrupt_run(run_dir, "update 1, 32 frames", sig=signal.SIGTERM, status=143)
    assert "interrupted (Ctrl-C or SIGTERM) after" in out


def test_ctrl_c_to_the_process_group_with_collector_workers(tmp_path):
    """A terminal's Ctrl-C reaches the collector workers too: they ignore it, the training process finishes its
    iteration, closes them and ends as interrupted (exit 130, summary.json, last.pt)."""
    run_dir = tmp_path / "workers"
    out = interrupt_run(run_dir, "update 1, 32 frames", "collector.num_workers=2", group=True)
    assert "stopping after this iteration" in out


def test_resume_from_wrong_kind_fails_clearly(tmp_path):
    bogus = tmp_path / "bogus.pt"
    torch.save({"weights": torch.zeros(3), "epoch": 1}, bogus)
    proc = run(PPO, *TINY, f"checkpoint.resume={bogus}", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path,
               check=False)
    assert proc.returncode != 0
    assert "is not an anm_torchrl training checkpoint" in proc.stderr and "epoch, weights" in proc.stderr


@pytest.mark.slow
def test_multiprocess_collector(tmp_path):
    """collector.num_workers=2: TorchRL's multi-process collector (worker start-up takes several seconds)."""
    run_dir = tmp_path / "mp"
    run(PPO, *TINY, "collector.num_workers=2", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["frames"] == 64 and math.isfinite(summary["final_eval"]["discounted_return"])


def test_async_collection_in_one_worker_process(tmp_path):
    """collector.sync=false with one worker: TorchRL's AsyncCollector collects the next batch in another process
    while this one updates; the budget stays exact (80 frames: the third batch cut) and the run is written whole."""
    run_dir = tmp_path / "async"
    run(PPO, *TINY, "collector.sync=false", "collector.total_frames=80", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["frames"] == 80 and summary["updates"] == 3
    assert math.isfinite(summary["final_eval"]["discounted_return"])
    assert (run_dir / "checkpoints" / "best.pt").is_file() and (run_dir / "checkpoints" / "last.pt").is_file()
    logged = scalars(run_dir)
    assert all(math.isfinite(v) for _, v in logged["train/loss_objective"]) and len(logged["train/loss_objective"]) == 3


def test_one_async_worker_is_torchrl_async_collector_and_keeps_the_thread_count():
    """One worker with collector.sync=false is TorchRL's AsyncCollector (every other test runs the in-process one);
    TorchRL would set this process's torch threads to the cores its workers leave, and raise them at shutdown."""
    from torchrl.collectors import AsyncCollector

    from anm_torchrl.training.algorithms.ppo import PPO as PPOAlgorithm
    from anm_torchrl.training.network_defaults import compose_recipe_config

    # two threads: TorchRL's own choice would be 2 - 1 worker = 1 while running
    cfg = compose_recipe_config([*TINY, "collector.sync=false", "threads=2"], "config")[0]
    before = torch.get_num_threads()
    torch.set_num_threads(int(cfg.threads))
    try:
        algo = PPOAlgorithm(cfg, device=torch.device("cpu"), seed=0, budget=64, reward_scale=0.01, resume=None)
        try:
            assert isinstance(algo.collector, AsyncCollector) and algo.collector.num_workers == 1
            assert torch.get_num_threads() == int(cfg.threads)
        finally:
            algo.close()
        assert torch.get_num_threads() == int(cfg.threads)
    finally:
        torch.set_num_threads(before)


def test_wall_clock_budget_stops_the_run(tmp_path):
    run_dir = tmp_path / "budget"
    run(PPO, *TINY, "collector.total_frames=320", "collector.max_minutes=0.0001", "logger.backend=null",
        f"hydra.run.dir={run_dir}", cwd=tmp_path)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["out_of_time"] and summary["updates"] == 1 and summary["frames"] == 32
    assert (run_dir / "checkpoints" / "last.pt").is_file()


def test_budget_mask_keeps_the_first_frames_in_time_order():
    """The last batch of a run is cut to the budget: every env's step t before any env's step t + 1."""
    from anm_torchrl.training.algorithms.ppo import budget_mask

    assert budget_mask(torch.Size([4, 8]), 32) is None and budget_mask(torch.Size([4, 8]), 99) is None
    keep = budget_mask(torch.Size([2, 3, 4]), 10)  # [workers, envs per worker, T]: 6 envs, 4 steps
    assert keep.shape == (2, 3, 4) and int(keep.sum()) == 10
    per_step = keep.reshape(6, 4).sum(0).tolist()
    assert per_step == [6, 4, 0, 0]  # all 6 envs at t = 0, the first 4 at t = 1


def test_same_seed_ends_in_identical_weights(tmp_path):
    """A whole run — collection, GAE, minibatches, Adam, evaluations — is deterministic: two runs of one seed end
    in bit-identical actor weights and optimiser state (issue 25)."""
    from anm_torchrl.training.checkpoint import load_checkpoint

    ckpts = []
    for k in range(2):
        run_dir = tmp_path / f"run{k}"
        run(PPO, *TINY, "seed=7", "logger.backend=csv", f"hydra.run.dir={run_dir}", cwd=tmp_path)
        ckpts.append(load_checkpoint(run_dir / "checkpoints" / "last.pt"))

    def tensors(x, prefix=""):
        if isinstance(x, torch.Tensor):
            yield prefix, x
        elif isinstance(x, dict):
            for k, v in x.items():
                yield from tensors(v, f"{prefix}.{k}")
        elif isinstance(x, (list, tuple)):
            for i, v in enumerate(x):
                yield from tensors(v, f"{prefix}[{i}]")

    a, b = (dict(tensors({"actor": c["actor"], "state": c["state"]})) for c in ckpts)
    assert a.keys() == b.keys() and len(a) > 4
    assert any(".weight" in k for k in a)
    changed = [k for k in a if not torch.equal(a[k], b[k])]
    assert not changed, changed[:5]


def test_a_surrogate_run_counts_no_true_env_frames(tmp_path, base_run):
    """Bug: PPO on a surrogate reported its surrogate frames as true-env frames in every curve point (the README's
    main job: "0 true-env frames"); summary.json now says both, and the true-env run's two counts agree."""
    from anm_torchrl.networks import simulator
    from anm_torchrl.surrogates.pinn import cache
    from anm_torchrl.surrogates.pinn.presets import preset
    from anm_torchrl.training.network_defaults import compose_recipe_config
    from anm_torchrl.training.protocol import train

    torch.set_num_threads(1)
    pinn = cache.train_and_save(preset("smoke"), simulator("anm6_easy"), path=tmp_path / "pinn" / "pinn.safetensors",
                                overwrite_cache=True, jobs=1)[0]
    cfg, defaults = compose_recipe_config([*TINY, "surrogate=pinn", f"surrogate.path={pinn}", "logger.backend=null"])
    summary = train(cfg, tmp_path / "run", network_defaults=defaults)
    assert summary["frames"] == 64 and summary["true_env_frames"] == 0
    assert summary["curve"] and all(p["true_env_frames"] == 0 for p in summary["curve"])
    true_run = json.loads((base_run[0] / "summary.json").read_text())
    assert true_run["true_env_frames"] == true_run["frames"] > 0
