"""Timing helpers shared by the env benchmarks (:mod:`anm_torchrl.benchmarks.env`,
:mod:`anm_torchrl.benchmarks.env_networks`): warm-up measured apart from the steady state."""

from __future__ import annotations

import time
from collections.abc import Callable

import torch


def _timed(first: Callable[[], None], step: Callable[[], None], min_time: float, min_steps: int
           ) -> tuple[float, float, int]:
    """Run ``first`` once (warm-up), then ``step`` until ``min_time`` s and ``min_steps`` calls have passed.

    Returns (warm-up seconds, steady-state seconds, number of steady-state calls).
    """
    t0 = time.perf_counter()
    first()
    warm = time.perf_counter() - t0
    n, t1 = 0, time.perf_counter()
    while True:
        step()
        n += 1
        elapsed = time.perf_counter() - t1
        if n >= min_steps and elapsed >= min_time:
            return warm, elapsed, n


def time_gym_steps(make: Callable[[], object], n_steps: int, seed: int = 0) -> tuple[float, float]:
    """Warm-up seconds (construction + seeded reset + first step) and steady-state steps/s over ``n_steps``
    ``action_space.sample()`` steps of the gym-anm env ``make()`` builds (reset on termination)."""
    box = {}

    def first():
        env = make()
        env.reset(seed=seed)
        env.action_space.seed(seed)
        env.step(env.action_space.sample())
        box["env"] = env

    def run():
        env = box["env"]
        for _ in range(n_steps):
            if env.step(env.action_space.sample())[2]:
                env.reset()

    warm, elapsed, _ = _timed(first, run, 0.0, 1)
    return warm, n_steps / elapsed


def time_env_steps(make: Callable[[], object], min_time: float, min_steps: int, seed: int = 0
                   ) -> tuple[float, float]:
    """Warm-up seconds (construction + reset + first step) and steady-state steps/s of the env ``make()`` builds,
    stepped with random actions through ``step_and_maybe_reset`` (auto-resets included)."""
    box = {}

    def first():
        env = make()
        torch.manual_seed(seed)
        td = env.reset()
        _, td = env.step_and_maybe_reset(env.rand_action(td))
        box["env"], box["td"] = env, td

    def step():
        env = box["env"]
        _, box["td"] = env.step_and_maybe_reset(env.rand_action(box["td"]))

    warm, elapsed, n = _timed(first, step, min_time, min_steps)
    return warm, n / elapsed


def record_provenance(module: str, argv: list[str] | None) -> dict:
    """The command (``python -m <module> <args>``), machine, versions and UTC date of a benchmark record."""
    import sys
    import time

    from anm_torchrl.provenance import machine_info, versions

    args = sys.argv[1:] if argv is None else argv
    return {"command": " ".join(["python -m", module, *args]), "machine": machine_info(), "versions": versions(),
            "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def write_record(out, record: dict, markdown_lines: list[str]) -> None:
    """``<out>.json`` (the record) and ``<out>.md`` (its table), atomically, creating the folder."""
    from pathlib import Path

    from anm_torchrl.artifacts import atomic_write
    from anm_torchrl.strict_json import json_text

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out.with_suffix(".json"), (json_text(record, indent=1) + "\n").encode())
    atomic_write(out.with_suffix(".md"), ("\n".join(markdown_lines) + "\n").encode())
