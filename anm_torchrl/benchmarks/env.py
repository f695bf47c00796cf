"""Transitions per second of the true simulator against batch size (and network size), and of gym-anm.

Usage::

    python -m anm_torchrl.benchmarks.env [--batch-sizes 1,16,256,1024,4096,16384] [--gym-steps 200]
                                         [--min-time 2.0] [--device cpu] [--threads 1] [--no-gym]
                                         [--backends auto|numba|torch|numba,torch]
    python -m anm_torchrl.benchmarks.env --network <name|all> [...]   # any network: see env_networks.py
    python -m anm_torchrl.benchmarks.env --solver-sweep [...]          # dense vs band LU crossover
    python benchmarks/before_after.py [...]                            # ANM6Env vs an earlier commit, interleaved

Without ``--network``: the ANM6-Easy table below.

Prints one markdown table. Every row separates the warm-up (construction, first reset and first step, where
lazy initialisation happens) from the steady state (further steps, timed until ``--min-time`` seconds and at
least ``--min-steps`` steps have passed).

* ``gym-anm`` — gym-anm 2.0.1 ``ANM6Easy``, one env, ``action_space.sample()`` actions (seeded), reset on
  termination; measured in the same run so the ratio is on the same machine and load.
* ``ANM6Env`` — the TorchRL env: ``env.rand_action`` then ``env.step_and_maybe_reset`` (what a collector does:
  terminated envs are reset in place).
* ``GridSimulator.step`` — the raw batched physics (uniform actions over the box, no TorchRL, no resets;
  terminated rows continue from their zero state).

The ratio column is steady-state transitions/s divided by gym-anm's steps/s.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from anm_torchrl.argtypes import count, index, int_list, name_list, positive_float, run_main
from anm_torchrl.benchmarks.timing import _timed, time_env_steps, time_gym_steps
from anm_torchrl.grid import reset as grid_reset

DEFAULT_BATCH_SIZES = (1, 16, 256, 1024, 4096, 16384)
BACKENDS = ("auto", "numba", "torch")  # the physics backends ANM6Env takes


def bench_gym_anm(n_steps: int, seed: int = 0) -> dict:
    """gym-anm single-env steps/s (``n_steps`` steady-state steps after reset + 1 warm-up step)."""
    import warnings

    from gym_anm.envs import ANM6Easy

    warnings.filterwarnings("ignore", module="gym_anm")
    warm, rate = time_gym_steps(ANM6Easy, n_steps, seed)
    return {"impl": "gym-anm 2.0.1 (`ANM6Easy.step`)", "batch": 1, "warm": warm, "rate": rate}


def bench_env(batch: int, min_time: float, min_steps: int, device: str, seed: int = 0, backend: str = "auto") -> dict:
    """``ANM6Env`` at batch ``batch``: warm-up and transitions/s."""
    from anm_torchrl.envs import ANM6Env

    used = []  # the backend "auto" resolved to

    def make() -> ANM6Env:
        env = ANM6Env(num_envs=batch, device=device, seed=seed, backend=backend)
        used.append(env.sim.backend)
        return env

    warm, steps_per_s = time_env_steps(make, min_time, min_steps, seed)
    return {"impl": f"`ANM6Env` ({used[-1]}; `rand_action` + `step_and_maybe_reset`)", "batch": batch,
            "warm": warm, "rate": batch * steps_per_s}


def bench_grid(batch: int, min_time: float, min_steps: int, device: str, seed: int = 0, backend: str = "auto") -> dict:
    from anm_torchrl.networks import ANM6_EASY
    from anm_torchrl.networks import simulator as network_simulator

    gen = torch.Generator(device=device).manual_seed(seed)
    box = {}

    def actions():
        return box["low"] + torch.rand(batch, box["low"].numel(), generator=gen, dtype=torch.float64,
                                       device=device) * (box["high"] - box["low"])

    def first():
        sim = network_simulator(ANM6_EASY, device=device, backend=backend)
        box["low"], box["high"] = sim.action_bounds()
        state = grid_reset.gym_anm_reset(sim, batch, gen)
        state = state[0] if isinstance(state, tuple) else state
        box["sim"], box["state"] = sim, sim.step(state, actions())[0]

    def step():
        box["state"] = box["sim"].step(box["state"], actions())[0]

    warm, elapsed, n = _timed(first, step, min_time, min_steps)
    return {"impl": f"`GridSimulator.step` ({box['sim'].backend}; raw physics)", "batch": batch, "warm": warm,
            "rate": batch * n / elapsed}


def markdown_table(rows: list[dict], gym_rate: float | None) -> str:
    lines = ["| implementation | batch size | warm-up (s) | steady-state transitions/s | ratio vs gym-anm |",
             "|---|---:|---:|---:|---:|"]
    for r in rows:
        ratio = f"{r['rate'] / gym_rate:,.1f}×" if gym_rate else "–"
        lines.append(f"| {r['impl']} | {r['batch']:,} | {r['warm']:.3f} | {r['rate']:,.0f} | {ratio} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> str:
    """ANM6-Easy table, or the network / solver-sweep tables of :mod:`anm_torchrl.benchmarks.env_networks`."""
    import sys

    argv = sys.argv[1:] if argv is None else argv
    if any(a.startswith(("--network", "--solver-sweep")) for a in argv):
        from anm_torchrl.benchmarks.env_networks import main as networks_main

        return networks_main(argv)
    return anm6_main(argv)


def anm6_main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(
        description="ANM6Env / GridSimulator throughput vs gym-anm",
        # the other tables take their own options: --network NAME [--out ...] or --solver-sweep, listed by --help
        epilog="Other networks: python -m anm_torchrl.benchmarks.env --network <name> --help; the linear-solver sweep: "
               "python -m anm_torchrl.benchmarks.env --solver-sweep --help")
    parser.add_argument("--batch-sizes", type=int_list(1), default=list(DEFAULT_BATCH_SIZES),
                        help="comma-separated batch sizes")
    parser.add_argument("--gym-steps", type=index, default=200, help="gym-anm steady-state steps (0: skip)")
    parser.add_argument("--no-gym", action="store_true", help="skip gym-anm")
    parser.add_argument("--min-time", type=positive_float, default=2.0,
                        help="seconds of steady state per measurement")
    parser.add_argument("--min-steps", type=count, default=3, help="at least this many batched steps")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=count, default=1, help="torch.set_num_threads")
    parser.add_argument("--skip-grid", action="store_true", help="skip the raw GridSimulator rows")
    parser.add_argument("--backends", type=name_list(BACKENDS), default=["auto"],
                        help="comma-separated physics backends to measure: auto, numba, torch (e.g. numba,torch)")
    args = parser.parse_args(argv)
    from anm_torchrl.training.recipe_errors import check_device

    check_device(args.device, "--device")
    torch.set_num_threads(args.threads)
    batches = args.batch_sizes

    rows = []
    gym_rate = None
    if args.gym_steps > 0 and not args.no_gym:
        try:
            g = bench_gym_anm(args.gym_steps)
            rows.append(g)
            gym_rate = g["rate"]
        except ImportError:
            pass
    backends = args.backends
    for backend in backends:
        for b in batches:
            rows.append(bench_env(b, args.min_time, args.min_steps, args.device, backend=backend))
    if not args.skip_grid:
        for backend in backends:
            for b in batches:
                rows.append(bench_grid(b, args.min_time, args.min_steps, args.device, backend=backend))
    table = markdown_table(rows, gym_rate)
    print(table)
    print(f"\n<!-- torch {torch.__version__}, {torch.get_num_threads()} thread(s), device {args.device}, "
          f"numpy {np.__version__}; warm-up = construction + first reset + first step -->")
    return table


if __name__ == "__main__":
    run_main(main, "anm_torchrl.benchmarks.env")
