"""Train PPO in-process with the recipe's own loop and read back its ``summary.json`` and CSV logs.

:func:`anm_torchrl.training.protocol.train` is the single definition of PPO training (``recipes/ppo.py`` calls
it too); the experiments only choose Hydra overrides of the recipe's config (``recipes/conf/config.yaml``), composed
here with Hydra's compose API. Each run gets its own run directory, ``logger.backend=csv`` (files
``logs/*/scalars/<group>/<tag>.csv``, rows ``frames,value``) and no progress bar. A run that raises is recorded with
its error; a time budget becomes the recipe's own ``collector.max_minutes`` (the run stops cleanly and says so).
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import time
import traceback
from pathlib import Path
from typing import Any

from anm_torchrl.training.network_defaults import compose_recipe_config


def eval_protocol(base: dict[str, Any]):
    """The ``eval`` group (validation and test protocol) of the PPO runs made with the overrides ``base``
    (``{"network": ..., "eval.num_episodes": 4, ...}``): the recipe's config with the network's entry applied, as
    :func:`run_ppo` trains with, so baselines are scored on the runs' own states."""
    return compose_recipe_config(ppo_overrides({"name": "none"}, 0, base))[0].eval


def _read_scalar(run_dir: Path, tag: str) -> list[tuple[int, float]]:
    files = sorted(run_dir.glob(f"logs/*/scalars/{tag}.csv"))
    rows: list[tuple[int, float]] = []
    for f in files[-1:]:
        for line in f.read_text().splitlines():
            parts = line.strip().split(",")
            if len(parts) >= 2:
                try:
                    rows.append((int(float(parts[0])), float(parts[1])))
                except ValueError:
                    continue
    return rows


def eval_curve(run_dir: str | Path) -> list[dict[str, float]]:
    """Evaluations of a run: frames, cumulative wall time (collect + update + eval, s), training time without the
    evaluations (collect + update, s), ``eval/return`` and ``eval/discounted_return``."""
    run_dir = Path(run_dir)
    ret = dict(_read_scalar(run_dir, "eval/return"))
    disc = dict(_read_scalar(run_dir, "eval/discounted_return"))
    times = {}
    for tag in ("time/collect", "time/update", "time/eval"):
        for step, v in _read_scalar(run_dir, tag):
            times.setdefault(step, {})[tag] = v
    wall = train = 0.0
    out = []
    for step in sorted(times):
        t = times[step]
        train += t.get("time/collect", 0.0) + t.get("time/update", 0.0)
        wall += t.get("time/collect", 0.0) + t.get("time/update", 0.0) + t.get("time/eval", 0.0)
        if step in ret:
            out.append({"frames": step, "wall_s": wall, "train_s": train, "return": ret[step],
                        "discounted_return": disc.get(step)})
    return out


def run_ppo(overrides: list[str], run_dir: str | Path, timeout_s: float | None = None) -> dict[str, Any]:
    """Train PPO with Hydra ``overrides`` of the recipe's config into ``run_dir``.

    Returns ``{"ok", "run_dir", "overrides", "command", "wall_s", "summary", "curve", "error", "load_avg_1min"}``;
    ``load_avg_1min`` is the machine's 1-minute load average before and after the run; ``command`` is the
    equivalent recipe command line. ``timeout_s`` caps the run's wall-clock budget (``collector.max_minutes``).
    An existing ``run_dir`` (an earlier run of the same cell) is removed first: its logs
    would otherwise be read back with the new.
    """
    from anm_torchrl.training import protocol

    run_dir = Path(run_dir).resolve()
    if run_dir.exists():
        shutil.rmtree(run_dir)
    overrides = [*overrides, "logger.backend=csv", "logger.progress=false"]
    rec: dict[str, Any] = {"ok": False, "run_dir": str(run_dir), "overrides": overrides,
                           "command": " ".join(["python recipes/ppo.py", *overrides, f"hydra.run.dir={run_dir}"]),
                           "summary": None, "curve": [], "error": None}
    # machine load (1-min load average, before and after): wall times of runs made at different loads differ
    rec["load_avg_1min"] = [os.getloadavg()[0]]
    t0 = time.perf_counter()
    try:
        cfg, defaults = compose_recipe_config(overrides)  # the network's entry applied, as the recipe does
        if timeout_s is not None:  # the tighter of the run's own budget and the experiment's
            cfg.collector.max_minutes = min(float(cfg.collector.max_minutes or "inf"), float(timeout_s) / 60)
        protocol.train(cfg, run_dir, network_defaults=defaults)
    except Exception as err:  # noqa: BLE001 - one failed cell is recorded, the experiment goes on
        rec["error"] = f"{type(err).__name__}: {err}\n" + traceback.format_exc()[-2000:]
    rec["wall_s"] = time.perf_counter() - t0
    rec["load_avg_1min"].append(os.getloadavg()[0])
    summary = run_dir / "summary.json"
    if summary.exists():
        s = json.loads(summary.read_text())
        s.pop("config", None)
        rec["summary"] = s
        rec["ok"] = rec["error"] is None
    if run_dir.exists():
        rec["curve"] = eval_curve(run_dir)
    return rec


def ppo_overrides(surrogate: dict[str, Any], seed: int, base: dict[str, Any]) -> list[str]:
    """Hydra overrides for one run: the surrogate group (``surrogate=<name>`` + its options), the seed and the
    preset's ``base`` overrides (``{"env.num_envs": 4, ...}``). The experiments compare PPO on each training env
    from fresh networks: ``warm_start.algorithm=null`` (the main job's SHAC warm start on ANM6-Easy, its network
    entry, is not theirs) unless ``base`` sets it."""
    out = [f"surrogate={surrogate['name']}", f"seed={seed}", "warm_start.algorithm=null"]
    out += [f"surrogate.{k}={'null' if v is None else v}" for k, v in surrogate.items() if k != "name"]
    out += [f"{k}={'null' if v is None else v}" for k, v in base.items()]
    return out


def aggregate(xs: list[float | None]) -> dict[str, float | None]:
    """Mean, sample std (0.0 for one value) and count of the values that are not None (seeds of one setting)."""
    xs = [x for x in xs if x is not None]
    if not xs:
        return {"mean": None, "std": None, "n": 0}
    return {"mean": statistics.fmean(xs), "std": statistics.stdev(xs) if len(xs) > 1 else 0.0, "n": len(xs)}


def last_mean(curve: list[dict[str, float]], key: str = "return", k: int = 10) -> float | None:
    """Mean of ``key`` over the last ``k`` evaluations (None without evaluations)."""
    vals = [c[key] for c in curve if c.get(key) is not None][-k:]
    return sum(vals) / len(vals) if vals else None


def time_to_reach(curve: list[dict[str, float]], threshold: float, key: str = "return",
                  clocks: tuple[str, ...] = ("frames", "wall_s", "train_s")) -> dict[str, float | None]:
    """First evaluation whose ``key`` ≥ ``threshold``: its ``clocks`` (by default frames, wall time and training
    time; None if never)."""
    for c in curve:
        if c.get(key) is not None and c[key] >= threshold:
            return {k: c[k] for k in clocks}
    return dict.fromkeys(clocks)
