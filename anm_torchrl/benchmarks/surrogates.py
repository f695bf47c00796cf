"""Transitions per second of every trained data-driven surrogate env against ``ANM6Env``, at several batch sizes.

Usage::

    python -m anm_torchrl.cli.bench_surrogates [--batch-sizes 1,4096] [--surrogates lr,dt,rf,xgb,dnn]
                                               [--datasets generative,agent] [--min-time 2.0] [--rounds 3]
                                               [--threads 1] [--device cpu]

Each row is ``make_env(<surrogate>, dataset=..., num_envs=batch)`` stepped with ``env.rand_action`` then
``env.step_and_maybe_reset`` (what a collector does: terminated envs are reset in place), after a warm-up
(construction, model loading, first reset and first step). Rounds are interleaved — every env is measured once
per round, in the same order — and the median over rounds is reported, so slow phases of a shared machine hit
all rows alike. The ratio column divides by ``ANM6Env`` (the exact batched simulator) at the same batch size,
measured in the same run. Surrogates that are not trained are listed with the command that trains them.
"""

from __future__ import annotations

import statistics

from anm_torchrl.benchmarks.timing import time_env_steps
from anm_torchrl.surrogates.regressors.defaults import DATASETS, KINDS  # re-exported for the CLI


def _make(kind: str | None, dataset: str | None, batch: int, device: str, seed: int):
    from anm_torchrl.training.factory import make_env

    if kind is None:
        return make_env("none", num_envs=batch, device=device, seed=seed)
    # a benchmark times trained models: a missing one is an error here, never minutes of training
    return make_env(kind, dataset=dataset, num_envs=batch, device=device, seed=seed, train_if_missing=False)


def bench(kind: str | None, dataset: str | None, batch: int, min_time: float, min_steps: int, device: str,
          seed: int = 0) -> dict:
    """Warm-up seconds and steady-state transitions/s of one env (``kind=None``: ``ANM6Env``)."""
    warm, steps_per_s = time_env_steps(lambda: _make(kind, dataset, batch, device, seed), min_time, min_steps, seed)
    return {"warm": warm, "rate": batch * steps_per_s}


def available(kinds, datasets) -> tuple[list[tuple[str, str]], list[str]]:
    """Trained ``(kind, dataset)`` pairs and notes for the missing ones."""
    from anm_torchrl.paths import surrogate_dir
    from anm_torchrl.surrogates.regressors import META_FILE, train_command

    from anm_torchrl.networks import ANM6_EASY, simulator

    sim = simulator(ANM6_EASY)  # the benchmark's surrogates are ANM6-Easy's (surrogate_dir's default folders)
    found, missing = [], []
    for d in datasets:
        for k in kinds:
            if (surrogate_dir(k, d) / META_FILE).is_file():
                found.append((k, d))
            else:
                missing.append(f"{k}/{d}: not trained ({train_command(k, d, sim)})")
    return found, missing


def markdown_table(results: dict, batches: list[int]) -> str:
    head = "| env | trained on | " + " | ".join(f"batch {b:,}: transitions/s (× ANM6Env)" for b in batches) + " |"
    lines = [head, "|---|---|" + "---:|" * len(batches)]
    ref = {b: results[("ANM6Env", "-")][b]["rate"] for b in batches}
    for (name, dataset), per in results.items():
        cells = []
        for b in batches:
            r = per[b]["rate"]
            cells.append(f"{r:,.0f} ({r / ref[b]:.2f}×)")
        lines.append(f"| {name} | {dataset} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def measure(batches: list[int], kinds, datasets, min_time: float, min_steps: int, rounds: int,
            device: str = "cpu") -> tuple[dict, list[str]]:
    """Interleaved rounds over ``ANM6Env`` and every trained ``(kind, dataset)``: per env and batch the median over
    rounds of transitions/s (``"rate"``) and warm-up seconds (``"warm"``), and notes for the untrained ones."""
    found, missing = available(list(kinds), list(datasets))
    envs = [("ANM6Env", "-", None, None)] + [(k, d, k, d) for k, d in found]
    samples: dict = {(name, ds): {b: [] for b in batches} for name, ds, _, _ in envs}
    warm: dict = {(name, ds): {b: [] for b in batches} for name, ds, _, _ in envs}
    for _ in range(rounds):
        for b in batches:
            for name, ds, kind, dataset in envs:
                r = bench(kind, dataset, b, min_time, min_steps, device)
                samples[(name, ds)][b].append(r["rate"])
                warm[(name, ds)][b].append(r["warm"])
    results = {key: {b: {"rate": statistics.median(samples[key][b]), "warm": statistics.median(warm[key][b])}
                     for b in batches} for key in samples}
    return results, missing


if __name__ == "__main__":  # run by name, this library module would otherwise exit 0 having done nothing
    raise SystemExit("the surrogate benchmark's command line is python -m anm_torchrl.cli.bench_surrogates "
                     "(--help lists its options)")
