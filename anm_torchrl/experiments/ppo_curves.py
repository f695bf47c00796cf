"""PPO training curves against frames and wall time on the true simulator (paper Fig. 12 / §5.4 "training time").

For every training env — the true simulator ``none``, the original package ``gym_anm`` and every available
surrogate — and every seed, ``recipes/ppo.py`` trains a policy and evaluates it on the true simulator after every
update (deterministic policy, fixed initial states). Baselines (do-nothing, random, MPC when it fits the time
budget) are evaluated once on the same initial states and drawn as horizontal lines.

Derived numbers: the mean evaluation return over the last ``last_k`` evaluations, the best one, the wall time of
the run, and the time (wall and frames) to first reach a fixed return ``threshold`` (default: the do-nothing
baseline's return on the same states).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from anm_torchrl.experiments.common import label, make_env_or_reason
from anm_torchrl.experiments.io import result
from anm_torchrl.experiments.ppo_runs import (aggregate, last_mean, ppo_overrides, recipe_available, run_ppo,
                                              time_to_reach)


def evaluate_baselines(names: list[str], num_episodes: int, max_steps: int, eval_seed: int = 0,
                       budget_s: float | None = None) -> dict[str, Any]:
    """Evaluation metrics of each baseline on the recipe's evaluation protocol; unavailable ones get a reason."""
    out: dict[str, Any] = {}
    try:
        from anm_torchrl.baselines import make_baseline
        from anm_torchrl.training.evaluation import draw_initial_states, evaluate_policy
    except ImportError as err:
        return {n: {"available": False, "reason": str(err)} for n in names}
    states = draw_initial_states(num_episodes, eval_seed)
    for name in names:
        try:
            policy = make_baseline(name, seed=0) if name == "random" else make_baseline(name)
            steps = max_steps
            if name.startswith("mpc") and budget_s is not None:  # time a few steps first; skip if over budget
                t0 = time.perf_counter()
                evaluate_policy(policy, states, max_steps=3)
                est = (time.perf_counter() - t0) / 3 * max_steps
                if est > budget_s:
                    out[name] = {"available": False, "reason": f"~{est:.0f} s for {max_steps} steps > budget {budget_s} s"}
                    continue
            res = evaluate_policy(policy, states, max_steps=steps)
            out[name] = {"available": True, **res.metrics(), "seconds": res.wall_time}
        except Exception as err:  # noqa: BLE001
            out[name] = {"available": False, "reason": f"{type(err).__name__}: {err}"}
    return out


def run(cfg: dict[str, Any], surrogates: list[dict], out_dir: str | Path, seeds: list[int]) -> dict:
    """cfg keys: ``envs`` (extra env specs before the surrogates, default none + gym_anm), ``base`` (Hydra
    overrides for every run), ``per_env`` (label -> extra overrides, e.g. a smaller budget for gym_anm),
    ``baselines``, ``baseline_budget_s``, ``threshold`` (null = ``threshold_scale`` × the do-nothing return; scale 0.1
    = a tenth of do-nothing's loss), ``last_k``, ``timeout_s``, ``only`` (surrogate labels)."""
    reason = recipe_available()
    if reason:
        return result("ppo_curves", "not available", reason=reason, config=cfg)
    out_dir = Path(out_dir)
    base = dict(cfg.get("base", {}))
    n_ep, max_steps = int(base.get("eval.num_episodes", 16)), int(base.get("eval.max_steps", 3000))
    baselines = evaluate_baselines(list(cfg.get("baselines", ["do_nothing", "random", "mpc_perfect"])), n_ep,
                                   max_steps, int(base.get("eval.seed", 0)), cfg.get("baseline_budget_s"))
    threshold = cfg.get("threshold")
    if threshold is None and baselines.get("do_nothing", {}).get("available"):
        threshold = float(cfg.get("threshold_scale", 1.0)) * baselines["do_nothing"]["return"]
    specs = [{"name": n} if isinstance(n, str) else dict(n) for n in cfg.get("envs", ["none", "gym_anm"])]
    only = cfg.get("only")  # optional list of surrogate labels to train on (others are skipped, not "missing")
    specs += [s for s in surrogates if not only or label(s) in only]
    runs, not_available, table = {}, {}, []
    last_k = int(cfg.get("last_k", 10))
    for spec in specs:
        lab = label(spec)
        env, why = make_env_or_reason(spec, 1)
        if env is None:
            not_available[lab] = why
            continue
        del env
        extra = dict(cfg.get("per_env", {}).get(lab, {}))
        seed_runs = []
        for seed in seeds:
            rec = run_ppo(ppo_overrides(spec, seed, {**base, **extra}), out_dir / "runs" / "ppo_curves" / f"{lab}_s{seed}",
                          timeout_s=cfg.get("timeout_s"))
            rec["seed"] = seed
            rec["last_mean_return"] = last_mean(rec["curve"], "return", last_k)
            rec["best_return"] = max((c["return"] for c in rec["curve"]), default=None)
            rec["time_to_threshold"] = time_to_reach(rec["curve"], threshold) if threshold is not None else None
            seed_runs.append(rec)
        runs[lab] = seed_runs
        ok = [r for r in seed_runs if r["curve"]]
        if not ok:
            not_available[lab] = "; ".join(str(r["error"])[-300:] for r in seed_runs)
        ret = aggregate([r["last_mean_return"] for r in ok])
        table.append({
            "env": lab, "seeds": len(ok), "last_mean_return": ret["mean"], "last_mean_return_std": ret["std"],
            "best_return": aggregate([r["best_return"] for r in ok])["mean"],
            "wall_s": aggregate([(r["summary"] or {}).get("wall_time") for r in ok])["mean"],
            "train_s": aggregate([r["curve"][-1]["train_s"] if r["curve"] else None for r in ok])["mean"],
            "frames": aggregate([r["curve"][-1]["frames"] if r["curve"] else None for r in ok])["mean"],
            "threshold_wall_s": aggregate([(r["time_to_threshold"] or {}).get("wall_s") for r in ok])["mean"],
            "threshold_frames": aggregate([(r["time_to_threshold"] or {}).get("frames") for r in ok])["mean"],
            "reached_threshold": sum(1 for r in ok if (r["time_to_threshold"] or {}).get("frames") is not None),
        })
    status = "ok" if not not_available else ("partial" if any(r["seeds"] for r in table) else "not available")
    return result("ppo_curves", status, {"runs": runs, "table": table, "baselines": baselines,
                                         "threshold": threshold, "not_available": not_available, "seeds": seeds},
                  reason=None if status != "not available" else str(not_available), config=cfg, seeds=seeds)
