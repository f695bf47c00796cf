"""Inference time per transition (paper Fig. 6) and its scaling with the batch size — the honest speed table.

For every implementation — gym-anm 2.0.1 itself, the batched true simulator ``ANM6Env``, the raw
``GridSimulator.step`` and every available surrogate env — on the same machine, in the same run:

``anm6env`` runs on the simulator's default backend (the compiled numba loop on the CPU), ``anm6env_torch`` on
its batched-torch backend.

* ``batch 1``: ``n_transitions`` single-env steps, each timed; the median (and quartiles) per transition;
* ``batched``: ``n_transitions`` grids stepped in one call, ``repeats`` times; median time / batch size;
* ``scaling``: per-transition time against the batch size (``batch_sizes``).

Random actions (uniform over the action box); terminated envs are reset in place (``step_and_maybe_reset``),
as a collector does. The first call (construction, lazy initialisation) is excluded as warm-up.
"""

from __future__ import annotations

import os
import statistics
import time
import warnings
from typing import Any

import torch

from anm_torchrl.experiments.common import RunContext, label, make_env_or_reason
from anm_torchrl.experiments.io import result
from anm_torchrl.grid import reset as grid_reset


def _quantiles(xs: list[float]) -> dict[str, float]:
    xs = sorted(xs)
    q = lambda p: xs[min(int(p * (len(xs) - 1) + 0.5), len(xs) - 1)]  # noqa: E731
    return {"median": statistics.median(xs), "q25": q(0.25), "q75": q(0.75), "mean": statistics.fmean(xs),
            "n": len(xs)}


def time_gym_anm(n_steps: int, seed: int = 0) -> dict[str, Any]:
    """Per-step seconds of gym-anm's ``ANM6Easy.step`` (one env, sampled actions)."""
    from gym_anm.envs import ANM6Easy

    warnings.filterwarnings("ignore", module="gym_anm")
    env = ANM6Easy()
    env.reset(seed=seed)
    env.action_space.seed(seed)
    env.step(env.action_space.sample())  # warm-up
    times = []
    for _ in range(n_steps):
        a = env.action_space.sample()
        t0 = time.perf_counter()
        _, _, term, _, _ = env.step(a)
        times.append(time.perf_counter() - t0)
        if term:
            env.reset()
    return _quantiles(times)


def time_env(env, n_steps: int, seed: int = 0) -> list[float]:
    """Seconds of each of ``n_steps`` calls of ``env.step_and_maybe_reset`` (after one warm-up call)."""
    torch.manual_seed(seed)
    td = env.reset()
    _, td = env.step_and_maybe_reset(env.rand_action(td))
    times = []
    for _ in range(n_steps):
        td = env.rand_action(td)
        t0 = time.perf_counter()
        _, td = env.step_and_maybe_reset(td)
        times.append(time.perf_counter() - t0)
    return times


def time_grid(batch: int, n_steps: int, seed: int = 0) -> list[float]:
    """Seconds of each of ``n_steps`` raw ``GridSimulator.step`` calls on ``batch`` grids."""
    from anm_torchrl.networks import ANM6_EASY
    from anm_torchrl.networks import simulator as network_simulator

    sim = network_simulator(ANM6_EASY)
    gen = torch.Generator().manual_seed(seed)
    lo, hi = sim.action_bounds()
    state = grid_reset.gym_anm_reset(sim, batch, gen)
    state = state[0] if isinstance(state, tuple) else state

    def act():
        return lo + torch.rand(batch, lo.numel(), generator=gen, dtype=torch.float64) * (hi - lo)

    state = sim.step(state, act())[0]
    times = []
    for _ in range(n_steps):
        a = act()
        t0 = time.perf_counter()
        state = sim.step(state, a)[0]
        times.append(time.perf_counter() - t0)
    return times


def run(cfg: dict[str, Any], ctx: RunContext) -> dict:
    """Run the speed experiment; ``cfg`` keys: ``n_transitions``, ``gym_steps``, ``repeats``, ``batch_sizes``.

    The record's ``load_avg_1min`` is the machine's 1-minute load average before and after the timings: other
    processes on a shared machine stretch every time here.
    """
    surrogates, seed = list(ctx.surrogates), ctx.seed
    load_before = os.getloadavg()[0]
    n = int(cfg.get("n_transitions", 1000))
    repeats = int(cfg.get("repeats", 5))
    batch_sizes = [int(b) for b in cfg.get("batch_sizes", [1, 10, 100, 1000])]
    rows, scaling, missing = [], [], {}

    gym_steps = int(cfg.get("gym_steps", n))
    if gym_steps > 0:
        try:
            q = time_gym_anm(gym_steps, seed)
            rows.append({"impl": "gym_anm", "mode": "batch 1", "batch": 1, **q, "s_per_transition": q["median"]})
        except Exception as err:  # noqa: BLE001
            missing["gym_anm"] = f"{type(err).__name__}: {err}"

    q = _quantiles(time_grid(1, n, seed))
    rows.append({"impl": "grid_sim", "mode": "batch 1", "batch": 1, **q, "s_per_transition": q["median"]})
    for b in sorted(set(b for b in batch_sizes if b > 1) | {n}):
        q = _quantiles([t / b for t in time_grid(b, repeats, seed)])
        if b == n:
            rows.append({"impl": "grid_sim", "mode": "batched", "batch": b, **q, "s_per_transition": q["median"]})
        if b in batch_sizes:
            scaling.append({"impl": "grid_sim", "batch": b, "s_per_transition": q["median"]})
    if 1 in batch_sizes:
        scaling.append({"impl": "grid_sim", "batch": 1, "s_per_transition": next(r["median"] for r in rows if r["impl"] == "grid_sim" and r["batch"] == 1)})

    from anm_torchrl.networks import ANM6_EASY
    from anm_torchrl.networks import simulator as network_simulator

    # ANM6Env on its default backend (numba on the CPU) and on the batched-torch backend, then every surrogate
    envs = [("anm6env", {"name": "none"}, None), ("anm6env_torch", {"name": "none"}, "torch")]
    for name, spec, backend in envs + [(label(s), s, None) for s in surrogates]:
        sim = network_simulator(ANM6_EASY, backend=backend) if backend else None
        env, reason = make_env_or_reason(spec, 1, seed, sim=sim)
        if env is None:
            missing[name] = reason
            continue
        q = _quantiles(time_env(env, n, seed))
        rows.append({"impl": name, "mode": "batch 1", "batch": 1, **q, "s_per_transition": q["median"]})
        scaling.append({"impl": name, "batch": 1, "s_per_transition": q["median"]})
        for b in sorted(set(b for b in batch_sizes if b > 1) | {n}):
            env, reason = make_env_or_reason(spec, b, seed, sim=sim)
            q = _quantiles([t / b for t in time_env(env, repeats, seed)])
            if b == n:
                rows.append({"impl": name, "mode": "batched", "batch": b, **q, "s_per_transition": q["median"]})
            if b in batch_sizes:
                scaling.append({"impl": name, "batch": b, "s_per_transition": q["median"]})

    ref = {r["mode"]: r["s_per_transition"] for r in rows if r["impl"] == "gym_anm"}.get("batch 1")
    for r in rows:
        r["speedup_vs_gym_anm"] = ref / r["s_per_transition"] if ref else None
    status = "ok" if not missing else "partial"
    return result("speed", status, {"table": rows, "scaling": scaling, "not_available": missing,
                                    "n_transitions": n, "repeats": repeats,
                                    "load_avg_1min": [load_before, os.getloadavg()[0]]}, config=cfg, seed=seed)
