"""Run ``recipes/ppo.py`` in a subprocess and read back its ``summary.json`` and CSV logs.

The recipe is the single definition of PPO training here; the experiments only choose overrides. Each run gets
its own Hydra run directory, ``logger.backend=csv`` (files ``logs/*/scalars/<group>/<tag>.csv``, rows
``frames,value``) and no progress bar. A run that fails or times out is recorded with its stderr tail.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
RECIPE = REPO / "recipes" / "ppo.py"


def recipe_available() -> str | None:
    """None if ``recipes/ppo.py`` exists, else the reason."""
    return None if RECIPE.exists() else f"{RECIPE} not found"


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
    """Run the PPO recipe with Hydra ``overrides`` into ``run_dir``.

    Returns ``{"ok", "run_dir", "overrides", "wall_s", "summary", "curve", "error"}``. An existing ``run_dir`` (an
    earlier run of the same experiment cell) is removed first: its logs would otherwise be read back with the new.
    """
    run_dir = Path(run_dir).resolve()
    if run_dir.exists():
        shutil.rmtree(run_dir)
    cmd = [sys.executable, str(RECIPE), *overrides, "logger.backend=csv", "logger.progress=false",
           f"hydra.run.dir={run_dir}"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    rec: dict[str, Any] = {"ok": False, "run_dir": str(run_dir), "overrides": overrides, "command": " ".join(cmd[1:]),
                           "summary": None, "curve": [], "error": None}
    try:
        proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout_s)
        if proc.returncode != 0:
            rec["error"] = f"exit {proc.returncode}: " + proc.stderr[-2000:]
    except subprocess.TimeoutExpired:
        rec["error"] = f"timed out after {timeout_s} s"
    rec["wall_s"] = time.perf_counter() - t0
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
    preset's ``base`` overrides (``{"env.num_envs": 4, ...}``)."""
    out = [f"surrogate={surrogate['name']}", f"seed={seed}"]
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


def time_to_reach(curve: list[dict[str, float]], threshold: float, key: str = "return") -> dict[str, float | None]:
    """First evaluation whose ``key`` ≥ ``threshold``: its frames, wall time and training time (None if never)."""
    for c in curve:
        if c.get(key) is not None and c[key] >= threshold:
            return {"frames": c["frames"], "wall_s": c["wall_s"], "train_s": c["train_s"]}
    return {"frames": None, "wall_s": None, "train_s": None}
