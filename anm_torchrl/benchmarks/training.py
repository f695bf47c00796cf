"""Where a training iteration's time goes: the env alone, collection with the policy, the update, the whole loop.

For every batch size N and algorithm, in one run (ratios compare, seconds do not: these machines are shared):

* ``env``: ``ANMEnv`` stepped under uniformly random actions over the box (TorchRL ``rollout``, terminated
  envs reset in place), frames/s;
* ``collect``: the algorithm's own collector with its policy (one batch of ``collector.frames_per_batch``);
  SHAC: its rollout of ``loss.horizon`` steps through its model (``model.dynamics``, the exact differentiable
  simulator by default) and the actor's backward pass through it;
* ``update``: its update on that batch (PPO: GAE + epochs of minibatches; SAC: the replay steps; SHAC: the critic's
  epochs on the rollout's TD(λ) targets);
* ``loop``: collect + update, i.e. what ``recipes/ppo.py`` / ``recipes/sac.py`` / ``recipes/shac.py`` do between
  evaluations. SHAC's frames are model transitions (none of the true env's).

Every algorithm runs its recipe's config for the network (its per-network entry applied, as the recipe does), with
``env.num_envs`` = N (and PPO's and SAC's ``collector.frames_per_batch`` = N x 16) set. Each is reported as frames/s
of wall time and of CPU time (one torch thread per process: CPU time is the work done, whatever else the machine
runs; SHAC's critic worker, a second process, counted in it), after one warm-up iteration. The ``loop / env``
column is the issue's target (≥ 0.5).
"""

from __future__ import annotations

import time
from pathlib import Path

import torch

from anm_torchrl.strict_json import json_text
from anm_torchrl.training.factory import make_env

STEPS = 16  # steps per env per iteration (PPO, SAC): frames_per_batch = N x STEPS
#: algorithm -> (its recipe's config name, its metrics' seconds of collection and of the update)
ALGORITHMS = {"ppo": ("config", "time/collect", "time/update"), "sac": ("sac", "time/collect", "time/update"),
              "shac": ("shac", "time/rollout", "time/update")}


#: keys the benchmark sets from its own options
BENCH_KEYS = ("network", "env.num_envs", "collector.frames_per_batch")


def _config(algorithm: str, network: str, n_envs: int, overrides: list[str]):
    """``algorithm``'s recipe config on ``network`` with N envs, its network entry applied to the keys not set here."""
    from hydra.errors import HydraException

    from anm_torchrl.overrides import parse_override
    from anm_torchrl.training.algorithms import check_algorithm_config
    from anm_torchrl.training.network_defaults import compose_recipe_config

    if algorithm not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {algorithm!r}; choose from {sorted(ALGORITHMS)}")
    given = {parse_override(o).key: o for o in overrides}
    own = [o for key, o in given.items() if key in BENCH_KEYS]
    if own:  # the rows are labelled by --network and --envs; an override of them measured another batch
        raise ValueError(f"--override {own[0]}: the benchmark sets {', '.join(BENCH_KEYS)} itself (--network, --envs)")
    over = [f"network={network}", f"env.num_envs={n_envs}",
            *([f"collector.frames_per_batch={n_envs * STEPS}"] if algorithm != "shac" else []),
            *(["collector.init_random_frames=0"] if algorithm == "sac" else []), *overrides]  # time the actor's frames
    try:
        cfg = compose_recipe_config(over, ALGORITHMS[algorithm][0])[0]
    except HydraException as err:
        raise ValueError(f"--override: {str(err).strip().splitlines()[0]}") from None
    if algorithm == "ppo" and "loss.mini_batch_size" not in given:  # one minibatch per epoch on a small batch
        cfg.loss.mini_batch_size = min(int(cfg.loss.mini_batch_size), n_envs * STEPS)
    check_algorithm_config(cfg)  # what the recipe would refuse is not measured either
    return cfg


def _children_cpu() -> float:
    """CPU seconds of this process's live ``multiprocessing`` children (SHAC's critic worker), read from
    ``/proc/<pid>/stat`` (utime + stime; 0 where there is no /proc)."""
    import multiprocessing
    import os

    total = 0.0
    for child in multiprocessing.active_children():
        try:
            fields = Path(f"/proc/{child.pid}/stat").read_text().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except (OSError, ValueError, IndexError):
            continue
    return total


def _clock():
    """(wall s, CPU s of this process and its live worker processes)."""
    return time.perf_counter(), time.process_time() + _children_cpu()


def time_env(network: str, n_envs: int, steps: int = STEPS, repeats: int = 3) -> dict[str, float]:
    """frames/s (wall, CPU) of the true env under random actions, ``steps`` per env, best of ``repeats``."""
    env = make_env("none", network=network, num_envs=n_envs, seed=0, max_steps=1000)
    env.rollout(2, break_when_any_done=False)  # warm-up (numba compile, caches)
    best = (0.0, 0.0)
    for _ in range(repeats):
        w0, c0 = _clock()
        env.rollout(steps, break_when_any_done=False)
        w1, c1 = _clock()
        n = n_envs * steps
        best = max(best, (n / (w1 - w0), n / max(c1 - c0, 1e-9)))
    return {"wall_fps": best[0], "cpu_fps": best[1]}


def time_algorithm(algorithm: str, network: str, n_envs: int, iterations: int = 3,
                   overrides: list[str] | None = None) -> dict[str, float]:
    """frames/s (wall and CPU) of collection, update and the loop of ``algorithm`` at ``n_envs`` envs."""
    from anm_torchrl.training.algorithms import get_algorithm

    cfg = _config(algorithm, network, n_envs, list(overrides or []))
    algo = get_algorithm(algorithm)(cfg, device=torch.device("cpu"), seed=0, budget=10**12,
                                    reward_scale=0.01, resume=None)
    w0 = time.perf_counter()
    algo.iterate(10**12)  # warm-up (numba caches, torch.compile's compilation)
    warmup_s = time.perf_counter() - w0
    frames = 0
    wall = {"collect": 0.0, "update": 0.0}
    _, collect_key, update_key = ALGORITHMS[algorithm]
    w0, c0 = _clock()
    for _ in range(iterations):
        n, metrics = algo.iterate(10**12)
        frames += n
        wall["collect"] += float(metrics[collect_key])
        wall["update"] += float(metrics[update_key])
    w1, c1 = _clock()
    algo.close()
    return {"frames": frames, "collect_fps": frames / wall["collect"], "update_fps": frames / wall["update"],
            "loop_fps": frames / (w1 - w0), "loop_cpu_fps": frames / max(c1 - c0, 1e-9),
            "update_share": wall["update"] / (w1 - w0), "warmup_s": warmup_s}


def measure(network: str = "anm6_easy", batch_sizes=(256, 1024, 4096), algorithms=tuple(ALGORITHMS),
            iterations: int = 3, overrides: tuple[str, ...] = (), compare: tuple[str, ...] = ()) -> dict:
    """Every row of the table (one dict per (algorithm, N)), measured in this one run; ``overrides`` (Hydra
    ``key=value``) apply to every algorithm's config. With ``compare`` (more overrides), every row is measured
    twice, without and with them, one after the other (``row["variant"]``: ``"base"`` or ``"compare"``), so their
    ratio is read on the same load."""
    torch.set_num_threads(1)
    variants = {"base": list(overrides), **({"compare": [*overrides, *compare]} if compare else {})}
    rows = []
    for n in batch_sizes:
        env = time_env(network, n)
        for algorithm in algorithms:
            for variant, over in variants.items():
                row = time_algorithm(algorithm, network, n, iterations, over)
                rows.append({"algorithm": algorithm, "num_envs": n, "variant": variant, "env_fps": env["wall_fps"],
                             "env_cpu_fps": env["cpu_fps"], **row,
                             "loop_over_env": row["loop_fps"] / env["wall_fps"],
                             "loop_over_env_cpu": row["loop_cpu_fps"] / env["cpu_fps"]})
    import os

    from anm_torchrl.provenance import machine_info

    return {"network": network, "steps_per_env": STEPS, "threads": 1, "iterations": iterations,
            "overrides": list(overrides), "compare": list(compare), "load_avg_1min": os.getloadavg()[0],
            "torch": torch.__version__, "machine": machine_info(), "rows": rows}


def markdown(record: dict) -> str:
    """The table of :func:`measure`'s record."""
    compare = record.get("compare")
    cpu = (record.get("machine") or {}).get("cpu")  # records before 2026-12-06 do not name their CPU
    algorithms = {r["algorithm"] for r in record["rows"]}
    batched = [a.upper() for a in ("ppo", "sac") if a in algorithms]  # collect steps_per_env steps per env
    iterations = [f"{' and '.join(batched)} {record['steps_per_env']} steps per env per iteration"] if batched else []
    if "shac" in algorithms:
        iterations.append("SHAC its rollout horizon (loss.horizon)")
    per_iteration = ", ".join(iterations)
    lines = [f"Training loop throughput on {record['network']} ({per_iteration}, 1 thread, load "
             f"{record['load_avg_1min']:.1f}" + (f", {cpu}" if cpu else "")
             + (f"; overrides: {' '.join(record['overrides'])}" if record.get("overrides") else "")
             + (f"; rows marked `compare` add {' '.join(compare)}" if compare else "")
             + "); frames/s of wall time (CPU time)" + ("; warm-up: the first iteration's seconds" if compare else ""),
             "", "| algorithm | envs |" + (" variant | warm-up |" if compare else "")
             + " env alone | collect | update | loop | loop / env |",
             "|---|---:|" + ("---|---:|" if compare else "") + "---:|---:|---:|---:|---:|"]
    for r in record["rows"]:
        variant = f" {r['variant']} | {r['warmup_s']:.1f} s |" if compare else ""  # a compare record has both
        lines.append(f"| {r['algorithm']} | {r['num_envs']:,} |{variant} {r['env_fps']:,.0f} "
                     f"({r['env_cpu_fps']:,.0f}) | {r['collect_fps']:,.0f} | {r['update_fps']:,.0f} | "
                     f"{r['loop_fps']:,.0f} ({r['loop_cpu_fps']:,.0f}) | {r['loop_over_env']:.2f} "
                     f"({r['loop_over_env_cpu']:.2f}) |")
    return "\n".join(lines) + "\n"


def write(record: dict, out: str | Path) -> None:
    """``<out>.json`` and ``<out>.md``, atomically."""
    from anm_torchrl.artifacts import atomic_write

    out = Path(out)
    atomic_write(out.with_suffix(".json"), json_text(record, indent=2).encode())
    atomic_write(out.with_suffix(".md"), markdown(record).encode())


if __name__ == "__main__":  # run by name, this library module would otherwise exit 0 having done nothing
    raise SystemExit("the training-loop benchmark's command line is python -m anm_torchrl.cli.bench_training "
                     "(--help lists its options)")
