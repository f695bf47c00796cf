"""The torch backend's Newton–Raphson with the dense batched LU against the block-tree solve, on radial networks.

For each network and batch size: the wall time of one batched ``powerflow.newton_raphson`` on the injections of
random transitions (:func:`anm_torchrl.surrogates.pinn.evaluate.random_transitions`), with every step solved
densely and with every step on the tree (``tree_solve``), and the largest |ΔV| between the two; measured in one
run, 1 thread. The ratio sets :data:`anm_torchrl.grid.tree_solve.TREE_WORK`.

    python -m anm_torchrl.benchmarks.tree_solve --networks case33bw simbench_mv_semiurb --rows 1 16 256 1024 \\
        --out results/benchmarks/torch_tree_solve
"""

from __future__ import annotations

import argparse
import logging
import time
from contextlib import contextmanager

import torch

log = logging.getLogger(__name__)


@contextmanager
def _forced(tree: bool):
    """Every batch solved on the tree (radial networks) or every batch dense, within the block."""
    import anm_torchrl.grid.tree_solve as ts

    saved = ts.TREE_WORK, ts.BANDED_MIN_BUS
    ts.TREE_WORK, ts.BANDED_MIN_BUS = (0.0, 0) if tree else (float("inf"), 1 << 30)
    try:
        yield
    finally:
        ts.TREE_WORK, ts.BANDED_MIN_BUS = saved


def _time(fn, repeats: int) -> float:
    fn()  # warm-up
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - t0) / repeats


def measure(network: str, rows: list[int], seed: int = 1) -> list[dict]:
    """One row per batch size: dense and tree wall time (ms) of one batched power flow, their ratio, max |ΔV|."""
    from anm_torchrl.grid.powerflow import newton_raphson
    from anm_torchrl.grid.tree_solve import bus_forest
    from anm_torchrl.networks import simulator
    from anm_torchrl.surrogates.pinn.evaluate import random_transitions

    sim = simulator(network, backend="torch")
    forest = bus_forest(sim.net.y_bus)
    if forest is None:
        raise ValueError(f"{network} is meshed: the tree solve is for radial networks")
    state, action = random_transitions(sim, max(rows), seed=seed)
    _, trn = sim.step(state, action)
    s_all = torch.complex(trn.p_dev @ sim.net.incidence, trn.q_dev @ sim.net.incidence)
    s_all[:, 0] = 0
    out = []
    for n in rows:
        s = s_all[:n]
        repeats = max(1, 64 // n)
        with _forced(False):
            dense_s, dense = _time(lambda: newton_raphson(sim.net.y_bus, s), repeats), newton_raphson(sim.net.y_bus, s)
        with _forced(True):
            tree_s, tree = _time(lambda: newton_raphson(sim.net.y_bus, s), repeats), newton_raphson(sim.net.y_bus, s)
        out.append({"network": network, "n_bus": int(sim.net.n_bus), "depth": len(forest.levels), "rows": n,
                    "dense_ms": 1e3 * dense_s, "tree_ms": 1e3 * tree_s, "dense_over_tree": dense_s / tree_s,
                    "max_abs_dv": float((dense.v - tree.v).abs().max()),
                    "same_convergence": bool((dense.converged == tree.converged).all())})
        log.info("%s", out[-1])
    return out


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--networks", nargs="+", default=["case33bw", "simbench_mv_semiurb"])
    p.add_argument("--rows", type=int, nargs="+", default=[1, 16, 256, 1024])
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(1)
    rows = [r for name in args.networks for r in measure(name, args.rows)]
    from anm_torchrl.benchmarks.timing import record_provenance, write_record

    record = {"rows": rows, **record_provenance("anm_torchrl.benchmarks.tree_solve", argv)}
    if args.out:
        lines = ["torch backend: one batched Newton-Raphson power flow, dense batched LU against the block-tree solve "
                 "(1 thread, one run)", "", "| network | buses / depth | rows | dense ms | tree ms | dense / tree "
                 "| max \\|ΔV\\| p.u. |", "|---|---|---:|---:|---:|---:|---:|"]
        lines += [f"| {r['network']} | {r['n_bus']} / {r['depth']} | {r['rows']:,} | {r['dense_ms']:.2f} | "
                  f"{r['tree_ms']:.2f} | {r['dense_over_tree']:.2f} | {r['max_abs_dv']:.1e} |" for r in rows]
        write_record(args.out, record, lines)
    return record


if __name__ == "__main__":
    main()
