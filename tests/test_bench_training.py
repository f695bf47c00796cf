"""The training-loop benchmark (:mod:`anm_torchrl.benchmarks.training`) and PPO's opt-in ``loss.compile``."""

from __future__ import annotations

import math

import pytest
import torch

from anm_torchrl.benchmarks import training


def test_compare_measures_every_row_twice_in_one_run():
    # ppo_epochs=1 stands in for any override: cheap, and it changes the update's work
    record = training.measure("anm6_easy", (8,), ("ppo",), 1, (), ("loss.ppo_epochs=1",))
    assert [(r["variant"], r["num_envs"]) for r in record["rows"]] == [("base", 8), ("compare", 8)]
    assert record["compare"] == ["loss.ppo_epochs=1"]
    for row in record["rows"]:
        for key in ("env_fps", "collect_fps", "update_fps", "loop_fps", "loop_cpu_fps", "warmup_s"):
            assert math.isfinite(row[key]) and row[key] > 0, (row["variant"], key, row[key])
    # the same env timing for both variants: their ratio is read on the same load
    assert record["rows"][0]["env_fps"] == record["rows"][1]["env_fps"]
    text = training.markdown(record)
    assert "rows marked `compare` add loss.ppo_epochs=1" in text
    assert record["machine"]["cpu"] and record["machine"]["cpu"] in text  # a rate says on what machine
    assert "| ppo | 8 | base |" in text and "| ppo | 8 | compare |" in text
    assert f"(PPO {training.STEPS} steps per env per iteration," in text


def test_markdown_without_compare_keeps_the_plain_table():
    record = training.measure("anm6_easy", (8,), ("ppo",), 1)
    assert [r["variant"] for r in record["rows"]] == ["base"]
    text = training.markdown(record)
    assert "variant" not in text and "| ppo | 8 | " in text


def test_shac_is_measured_on_its_model_with_its_network_entry():
    """SHAC's row times its rollout through the exact model (+ the actor's backward) and its critic's update; its
    config is the recipe's for the network (ANM6-Easy's entry: horizon 64), N rows."""
    cfg = training._config("shac", "anm6_easy", 8, [])
    assert cfg.loss.horizon == 64 and cfg.env.num_envs == 8 and cfg.model.dynamics == "exact"
    record = training.measure("anm6_easy", (8,), ("shac",), 1, ("loss.horizon=4",))
    (row,) = record["rows"]
    assert row["algorithm"] == "shac" and row["frames"] == 8 * 4, "one iteration: N rows x horizon model frames"
    for key in ("env_fps", "collect_fps", "update_fps", "loop_fps", "loop_cpu_fps"):
        assert math.isfinite(row[key]) and row[key] > 0, (key, row[key])
    text = training.markdown(record)  # SHAC's iteration is its horizon, not the PPO/SAC batch's steps
    assert "(SHAC its rollout horizon (loss.horizon), 1 thread" in text and "steps per env" not in text
    with pytest.raises(ValueError, match="unknown algorithm 'td3'; choose from"):
        training._config("td3", "anm6_easy", 8, [])


@pytest.mark.slow  # inductor's first compilation: ~35 s on 2 busy cores
# tensordict's own deprecation notice under torch.compile (tensordict/utils.py), not this project's
@pytest.mark.filterwarnings("ignore:torch._dynamo.config.inline_inbuilt_nn_modules is deprecated:FutureWarning")
def test_compiled_ppo_loss_matches_eager():
    """``loss.compile=true`` runs ClipPPOLoss through inductor: the first update's logged losses equal eager's (same
    seed, same batch) to float32 rounding (fused kernels reorder sums: 1e-4 relative)."""
    from anm_torchrl.training.algorithms import get_algorithm

    torch.set_num_threads(1)
    out = {}
    for flag in ("false", "true"):
        cfg = training._config("ppo", "anm6_easy", 8, [f"loss.compile={flag}"])
        torch.manual_seed(0)
        algo = get_algorithm("ppo")(cfg, device=torch.device("cpu"), seed=0, budget=10**6, reward_scale=0.01,
                                    resume=None)
        _, metrics = algo.iterate(10**6)
        algo.close()
        out[flag] = {k: float(v) for k, v in metrics.items() if k.startswith("train/loss")}
    assert out["true"].keys() == out["false"].keys() and out["true"]
    for key, eager in out["false"].items():
        assert math.isfinite(out["true"][key])
        assert out["true"][key] == pytest.approx(eager, rel=1e-4, abs=1e-6), key


def _spin(seconds: float) -> None:
    """Spin ``seconds`` of CPU, then stay alive idle (a finished child is no longer a live one)."""
    import time

    end = time.process_time() + seconds
    while time.process_time() < end:
        pass
    time.sleep(30)


def test_cpu_time_counts_live_worker_processes():
    """SHAC's critic worker is a second process: the CPU clock adds the CPU time of live ``multiprocessing``
    children (here one spinning ~0.3 s), so the CPU frames/s count the whole work."""
    import multiprocessing
    import sys

    if not sys.platform.startswith("linux"):
        pytest.skip("reads /proc")
    child = multiprocessing.get_context("fork").Process(target=_spin, args=(0.3,))
    child.start()
    try:
        import time

        time.sleep(1.0)  # the child spins its 0.3 s of CPU (sharing 2 cores with the bench) and idles
        spent = training._children_cpu()
    finally:
        child.terminate()
        child.join()
    assert 0.2 <= spent <= 0.6, spent  # clock ticks of 10 ms, and the child's start-up


@pytest.mark.parametrize("module, cli", [("training", "bench_training"), ("sb3", "bench_sb3"),
                                         ("surrogates", "bench_surrogates")])
def test_a_benchmark_module_run_by_name_points_to_its_command_line(module, cli):
    """Issue 27 names ``python -m anm_torchrl.benchmarks.training``; the library module alone would exit 0 having
    done nothing."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-m", f"anm_torchrl.benchmarks.{module}"], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 1 and f"python -m anm_torchrl.cli.{cli} (--help" in out.stderr
