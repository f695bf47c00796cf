"""Peak memory and speed of the torch backend on a large random feeder: block-tree solve, dense LU under the
Jacobian budget, and the dense LU without it (the solve of before both).

Each row runs in a fresh spawned process (its peak resident set is its own): ``ANMEnv(backend="torch")`` on the random
radial network of ``seed`` with ``n_bus`` buses (:func:`anm_torchrl.networks.random.generate`), a reset and
``steps`` random steps of ``num_envs`` envs, in one of the modes ``auto`` (the backend as shipped: the block-tree
solve of :mod:`anm_torchrl.grid.tree_solve` on a radial network), ``dense`` (the dense LU with
``powerflow.JACOBIAN_BUDGET_BYTES`` at ``--budget`` MiB) or ``dense-unbounded`` (no budget). Reports
transitions/s of the steps and the process's peak RSS. ``--mmap-threshold-mib 0 8`` repeats each row with glibc's
``MALLOC_MMAP_THRESHOLD_`` at 8 MiB (0: glibc's default, a threshold that rises with use): on the dense path the peak
grows from step to step as the heap fragments, and a fixed threshold keeps it flat at a cost in step time.

    python -m anm_torchrl.benchmarks.torch_memory --n-bus 320 --envs 256 1024 \\
        --modes auto dense dense-unbounded --out results/benchmarks/torch_backend_memory
"""

from __future__ import annotations

import argparse
import itertools
import logging
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor, TimeoutError

log = logging.getLogger(__name__)


MODES = ("auto", "dense", "dense-unbounded")


def measure_one(n_bus: int, seed: int, num_envs: int, mode: str, budget_mib: int, steps: int) -> dict:
    """One row, in this process: transitions/s of ``steps`` random steps and this process's peak RSS (MiB)."""
    import resource

    import torch

    import anm_torchrl.grid.powerflow as pf
    import anm_torchrl.grid.tree_solve as ts
    from anm_torchrl.envs import ANMEnv
    from anm_torchrl.networks.random import generate

    torch.set_num_threads(1)
    if mode != "auto":
        ts.TREE_WORK = float("inf")
    pf.JACOBIAN_BUDGET_BYTES = budget_mib * 2**20 if mode != "dense-unbounded" else 1 << 62
    case = generate(seed, n_bus=n_bus, meshed=False)
    env = ANMEnv(network=case.network, load_p=case.load_p, gen_p_max=case.gen_p_max, num_envs=num_envs,
                 backend="torch", seed=seed)
    td = env.reset()
    t0, peaks = time.perf_counter(), []
    for _ in range(steps):
        td = env.rand_step(td)["next"]
        peaks.append(round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))
    wall = time.perf_counter() - t0
    return {"n_bus": n_bus, "seed": seed, "num_envs": num_envs, "mode": mode, "budget_mib": budget_mib, "steps": steps,
            "transitions_per_s": steps * num_envs / wall, "peak_rss_mib": resource.getrusage(
                resource.RUSAGE_SELF).ru_maxrss / 1024, "peak_rss_mib_per_step": peaks,
            "malloc_mmap_threshold_env": os.environ.get("MALLOC_MMAP_THRESHOLD_")}


def measure_row(args: argparse.Namespace, n_env: int, mode: str, mmap_mib: int) -> dict:
    """:func:`measure_one` in a fresh spawned process (its peak resident set is the row's own), with glibc's mmap
    threshold at ``mmap_mib`` MiB (0: its default); a row that fails or runs over ``args.timeout`` says so."""
    old = os.environ.pop("MALLOC_MMAP_THRESHOLD_", None)
    if mmap_mib:  # read by glibc when the child starts: the spawned process inherits it
        os.environ["MALLOC_MMAP_THRESHOLD_"] = str(mmap_mib * 2**20)
    try:
        with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
            future = pool.submit(measure_one, args.n_bus, args.seed, n_env, mode, args.budget, args.steps)
            try:
                return future.result(timeout=args.timeout)
            except TimeoutError:
                return {"num_envs": n_env, "mode": mode, "error": f"over {args.timeout:.0f} s"}
            except Exception as err:  # noqa: BLE001 (a row that fails, e.g. out of memory, is reported as such)
                return {"num_envs": n_env, "mode": mode, "error": f"{type(err).__name__}: {err}"}
    finally:
        os.environ.pop("MALLOC_MMAP_THRESHOLD_", None)
        if old is not None:
            os.environ["MALLOC_MMAP_THRESHOLD_"] = old


def main(argv: list[str] | None = None) -> dict:
    """CLI: every (envs, mode) row in its own process; writes ``<out>.json`` and ``<out>.md`` if ``--out``."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n-bus", type=int, default=320)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--envs", type=int, nargs="+", default=[256, 1024])
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    p.add_argument("--budget", type=int, default=256, help="MiB, the dense mode's Jacobian budget")
    p.add_argument("--steps", type=int, default=2)
    p.add_argument("--timeout", type=float, default=1800, help="seconds per row (a row over it is reported so)")
    p.add_argument("--mmap-threshold-mib", type=int, nargs="+", default=[0],
                   help="glibc MALLOC_MMAP_THRESHOLD_ of the row's process, MiB (0: glibc's default)")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    rows = []
    for n_env, mode, mmap in itertools.product(args.envs, args.modes, args.mmap_threshold_mib):
        row = {**measure_row(args, n_env, mode, mmap), "mmap_threshold_mib": mmap or None}
        log.info("%s", row)
        rows.append(row)
    from anm_torchrl.benchmarks.timing import record_provenance, write_record

    record = {"rows": rows, **record_provenance("anm_torchrl.benchmarks.torch_memory", argv)}
    if args.out:
        lines = [f"torch backend, random radial network of {args.n_bus} buses (seed {args.seed}), {args.steps} random "
                 "steps after a reset, one process per row, 1 thread", "",
                 "| envs | Newton solve | glibc mmap threshold | transitions/s | peak RSS "
                 "| peak after each step (MiB) |",
                 "|---:|---|---|---:|---:|---|"]
        names = {"auto": "block tree (as shipped)", "dense": f"dense LU, {args.budget} MiB Jacobian budget",
                 "dense-unbounded": "dense LU, unbounded (before)"}
        for r in rows:
            mmap = f"{r['mmap_threshold_mib']} MiB" if r.get("mmap_threshold_mib") else "default"
            lines.append(f"| {r['num_envs']:,} | {names[r['mode']]} | {mmap} | " + (
                f"{r['transitions_per_s']:.1f} | {r['peak_rss_mib']:,.0f} MiB | "
                f"{', '.join(f'{x:,}' for x in r['peak_rss_mib_per_step'])} |" if "error" not in r
                else f"– | failed: {r['error']} | |"))
        write_record(args.out, record, lines)
    return record


if __name__ == "__main__":
    main()
