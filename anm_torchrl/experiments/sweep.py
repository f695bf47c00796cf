"""Structural sweep of PPO on the PINN surrogate: number of envs × buffer size (paper Figs. 10–11).

buffer = steps per env between updates, so ``collector.frames_per_batch = n_envs × buffer``. Every cell trains
with the same frame budget (once per seed) and is evaluated on the true simulator; recorded: the mean evaluation
return over the last ``last_k`` evaluations (mean and std over seeds) and the training wall time, then Pearson
correlations between n_envs, buffer, mean return and training time, and the best cell. The same grid runs as a
Hydra multirun::

    python recipes/ppo.py -m surrogate=pinn env.num_envs=10,100 collector.frames_per_batch=300,3000

(there frames_per_batch is the product; the experiment pairs them itself). If the PINN surrogate is not
available the sweep runs on ``fallback`` (default the true simulator) and says so.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from anm_torchrl.experiments.common import RunContext, label, make_env_or_reason
from anm_torchrl.experiments.io import result
from anm_torchrl.experiments.ppo_runs import aggregate, last_mean, ppo_overrides, run_ppo

VARS = ("n_envs", "buffer", "mean_return", "train_time_s")


def pearson(x: list[float], y: list[float]) -> float | None:
    """Pearson correlation (None with < 3 points or a constant series)."""
    pts = [(a, b) for a, b in zip(x, y) if a is not None and b is not None]
    if len(pts) < 3:
        return None
    mx = sum(a for a, _ in pts) / len(pts)
    my = sum(b for _, b in pts) / len(pts)
    sxy = sum((a - mx) * (b - my) for a, b in pts)
    sx = math.sqrt(sum((a - mx) ** 2 for a, _ in pts))
    sy = math.sqrt(sum((b - my) ** 2 for _, b in pts))
    return sxy / (sx * sy) if sx > 0 and sy > 0 else None


def run(cfg: dict[str, Any], ctx: RunContext) -> dict:
    """cfg keys: ``surrogate`` (spec), ``fallback`` (spec or null), ``n_envs`` (list), ``buffer`` (list),
    ``seeds`` (list; default ``[seed]``: every cell is trained once per seed and its numbers are seed means),
    ``base`` (overrides), ``last_k``, ``timeout_s``, ``eval_every_frames`` (optional: evaluate every this many
    frames in every cell, so cells with small batches are not dominated by evaluation; default every update).
    Every cell runs with ``ctx.threads``; a ``pinn`` surrogate is the run's PINN (``ctx.surrogates``)."""
    out_dir, seed = ctx.out_dir, ctx.seed
    cfg = {**cfg, "base": {**cfg.get("base", {}), "threads": int(ctx.threads)}}
    if cfg.get("surrogate", {}).get("name") == "pinn":
        cfg["surrogate"] = next((s for s in ctx.surrogates if s["name"] == "pinn"), cfg["surrogate"])
    spec = dict(cfg.get("surrogate", {"name": "pinn"}))
    note = None
    env, why = make_env_or_reason(spec, 1)
    if env is None:
        fb = cfg.get("fallback")
        if not fb:
            return result("sweep", "not available", reason=f"{label(spec)}: {why}", config=cfg)
        note = f"{label(spec)} not available ({why}); swept on {label(fb)} instead"
        spec = dict(fb)
    rows = []
    seeds = [int(x) for x in cfg.get("seeds", [seed])]
    last_k = int(cfg.get("last_k", 10))
    for n in cfg.get("n_envs", [10, 100]):
        for b in cfg.get("buffer", [30, 300]):
            over = {**cfg.get("base", {}), "env.num_envs": int(n), "collector.frames_per_batch": int(n) * int(b)}
            if "loss.mini_batch_size" in over:  # at most one batch (the recipe refuses more; it used to cap it)
                over["loss.mini_batch_size"] = min(int(over["loss.mini_batch_size"]), int(n) * int(b))
            if cfg.get("eval_every_frames"):
                over["eval.interval"] = max(1, round(int(cfg["eval_every_frames"]) / (int(n) * int(b))))
            recs = [run_ppo(ppo_overrides(spec, s, over), Path(out_dir) / "runs" / "sweep" / f"n{n}_b{b}_s{s}",
                            timeout_s=cfg.get("timeout_s")) for s in seeds]
            per_seed = [last_mean(r["curve"], "return", last_k) for r in recs]
            ret = aggregate(per_seed)
            rows.append({"n_envs": int(n), "buffer": int(b), "frames_per_batch": int(n) * int(b),
                         "seeds": ret["n"], "mean_return": ret["mean"],
                         "mean_return_std": ret["std"] if ret["n"] > 1 else None,
                         "mean_return_per_seed": per_seed,
                         "mean_discounted_return": aggregate([last_mean(r["curve"], "discounted_return", last_k)
                                                              for r in recs])["mean"],
                         "train_time_s": aggregate([(r["summary"] or {}).get("wall_time") for r in recs])["mean"],
                         "train_time_no_eval_s": aggregate([r["curve"][-1]["train_s"] for r in recs
                                                            if r["curve"]])["mean"],
                         "frames": aggregate([r["curve"][-1]["frames"] for r in recs if r["curve"]])["mean"],
                         "evaluations": aggregate([len(r["curve"]) for r in recs if r["curve"]])["mean"],
                         "error": "; ".join(str(r["error"]) for r in recs if r["error"]) or None,
                         "run_dirs": [r["run_dir"] for r in recs]})
    corr = {a: {b: pearson([r[a] for r in rows], [r[b] for r in rows]) for b in VARS} for a in VARS}
    valid = [r for r in rows if r["mean_return"] is not None]
    best = max(valid, key=lambda r: r["mean_return"]) if valid else None
    status = "ok" if valid and note is None and len(valid) == len(rows) else ("partial" if valid else "error")
    return result("sweep", status, {"surrogate": label(spec), "note": note, "grid": rows, "correlation": corr,
                                    "seeds": seeds,
                                    "best": best, "command": "python recipes/ppo.py -m surrogate=" + spec["name"] +
                                    " env.num_envs=" + ",".join(map(str, cfg.get("n_envs", []))) +
                                    " collector.frames_per_batch=<n_envs x buffer>"},
                  reason=None if valid else "no sweep run produced evaluations", config=cfg, seed=seed)
