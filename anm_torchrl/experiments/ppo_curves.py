"""PPO training curves against frames and wall time on the true simulator (paper Fig. 12 / §5.4 "training time").

For every training env — the true simulator ``none``, the original package ``gym_anm`` and every available
surrogate — and every seed, the PPO recipe's loop (:func:`~anm_torchrl.training.protocol.train`) trains a
policy and evaluates it on the true simulator after every update (deterministic policy, fixed initial states). Baselines (do-nothing, random, MPC when it fits the time
budget) are evaluated once on the same initial states and drawn as horizontal lines.

Derived numbers: the mean evaluation return over the last ``last_k`` evaluations, the best one, the wall time of
the run, and the time (wall and frames) to first reach a fixed return ``threshold`` (default: a fraction of the
do-nothing baseline's return on the same states) over seeds, runs that never reach it censored at their run length
(:mod:`.time_to_return`), both without and with the surrogate's own training time (``surrogate_train_s``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from anm_torchrl.experiments.common import RunContext, label, make_env_or_reason
from anm_torchrl.experiments.io import result
from anm_torchrl.experiments.ppo_runs import (aggregate, eval_protocol, last_mean, ppo_overrides, run_ppo,
                                              time_to_reach)
from anm_torchrl.experiments.time_to_return import censored_summary


def evaluate_baselines(names: list[str], num_episodes: int, max_steps: int, eval_seed: int = 0,
                       budget_s: float | None = None) -> dict[str, Any]:
    """Evaluation metrics of each baseline on the recipe's evaluation protocol; unavailable ones get a reason."""
    out: dict[str, Any] = {}
    try:
        from anm_torchrl.baselines import make_baseline
        from anm_torchrl.evaluation import draw_initial_states, evaluate_policy
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


TRAINING_FREE = ("none", "gym_anm")  # envs with no surrogate to train first


def threshold_columns(seed_runs: list[dict], train_s: float | None) -> dict[str, Any]:
    """Time to the return threshold over seeds (Kaplan–Meier median, censored runs at their length): wall time
    without and with the surrogate's training ``train_s`` (s; None = not measured), frames, runs that reached it."""
    wall, frames = censored_summary(seed_runs, "wall_s"), censored_summary(seed_runs, "frames")
    with_training = censored_summary(seed_runs, "wall_s", offset_s=train_s) if train_s is not None else {}
    return {"threshold_reached": wall["reached"], "threshold_runs": wall["runs"],
            "threshold_wall_s": wall["median"], "threshold_wall_s_mean": wall["restricted_mean"],
            "threshold_censored_at_s": wall["censored_at"], "threshold_frames": frames["median"],
            "surrogate_train_s": train_s, "threshold_wall_with_training_s": with_training.get("median"),
            "threshold_wall_with_training_s_mean": with_training.get("restricted_mean")}


def reused_runs(reuse: dict[str, Any], threshold: float | None) -> dict[str, list[dict]]:
    """The runs of ``reuse["envs"]`` taken from an earlier ``ppo_curves`` record (``reuse["from"]``) instead of
    training them again, each marked with that record's git commit and date; they must have been evaluated on the
    same states with the same threshold (checked: the earlier record's threshold equals this run's)."""
    from anm_torchrl.experiments.io import read_json

    rec = read_json(reuse["from"])
    old = rec["data"].get("threshold")
    # same states => same do-nothing return up to the simulator's float64 round-off (parity with gym-anm is ~1e-8
    # relative per reward), summed over 8,000 steps: 1e-6 relative separates that from other states (~10 % apart)
    if threshold is None or old is None or abs(old - threshold) > 1e-6 * abs(threshold):
        raise ValueError(f"reuse.from={reuse['from']}: its threshold {old} differs from "
                         f"this run's {threshold}; reused runs must be evaluated on the same states")
    origin = {"git_commit": (rec["meta"].get("versions") or {}).get("git_commit"), "file": str(reuse["from"])}
    missing = [e for e in reuse["envs"] if e not in rec["data"]["runs"]]
    if missing:
        raise ValueError(f"reuse.envs {missing} not in {reuse['from']} (it holds {sorted(rec['data']['runs'])})")
    return {e: [{**r, "reused_from": origin} for r in rec["data"]["runs"][e]] for e in reuse["envs"]}


def run(cfg: dict[str, Any], ctx: RunContext) -> dict:
    """cfg keys: ``envs`` (extra env specs before the surrogates, default none + gym_anm), ``base`` (Hydra
    overrides for every run), ``per_env`` (label -> extra overrides, e.g. a smaller budget for gym_anm),
    ``baselines``, ``baseline_budget_s``, ``threshold`` (null = ``threshold_scale`` × the do-nothing return; scale 0.1
    = a tenth of do-nothing's loss), ``last_k``, ``timeout_s``, ``only`` (surrogate labels), ``reuse``
    (``{from: <earlier ppo_curves.json>, envs: [labels]}``: take those envs' runs from that record),
    ``per_env_seeds`` (label -> seeds, default ``seeds``), ``surrogate_train_s``
    (label -> seconds the surrogate took to train; ``ctx.surrogate_train_s``, measured by the caller; unknown labels
    count as not measured). Every run uses ``ctx.threads``, the seeds ``ctx.seeds`` and the surrogates
    ``ctx.surrogates``."""
    cfg = {**cfg, "base": {**cfg.get("base", {}), "threads": int(ctx.threads)},
           "surrogate_train_s": dict(ctx.surrogate_train_s)}
    surrogates, out_dir, seeds = list(ctx.surrogates), Path(ctx.out_dir), [int(s) for s in ctx.seeds]
    base = dict(cfg.get("base", {}))
    ev = eval_protocol(base)  # the PPO runs' validation protocol
    baselines = evaluate_baselines(list(cfg.get("baselines", ["do_nothing", "random", "mpc_perfect"])),
                                   int(ev.num_episodes), int(ev.max_steps), int(ev.seed), cfg.get("baseline_budget_s"))
    threshold = cfg.get("threshold")
    if threshold is None and baselines.get("do_nothing", {}).get("available"):
        threshold = float(cfg.get("threshold_scale", 1.0)) * baselines["do_nothing"]["return"]
    specs = [{"name": n} if isinstance(n, str) else dict(n) for n in cfg.get("envs", ["none", "gym_anm"])]
    only = cfg.get("only")  # optional list of surrogate labels to train on (others are skipped, not "missing")
    specs += [s for s in surrogates if not only or label(s) in only]
    runs, not_available, table = {}, {}, []
    last_k = int(cfg.get("last_k", 10))
    train_s = dict(cfg.get("surrogate_train_s") or {})
    reuse = dict(cfg.get("reuse") or {})
    earlier = reused_runs(reuse, threshold) if reuse else {}
    for spec in specs:
        lab = label(spec)
        if lab in earlier:
            seed_runs = earlier[lab]
        else:
            env, why = make_env_or_reason(spec, 1)
            if env is None:
                not_available[lab] = why
                continue
            del env
            extra = dict(cfg.get("per_env", {}).get(lab, {}))
            seed_runs = [run_ppo(ppo_overrides(spec, seed, {**base, **extra}),
                                 out_dir / "runs" / "ppo_curves" / f"{lab}_s{seed}", timeout_s=cfg.get("timeout_s"))
                         | {"seed": seed} for seed in cfg.get("per_env_seeds", {}).get(lab, seeds)]
        for rec in seed_runs:
            rec["last_mean_return"] = last_mean(rec["curve"], "return", last_k)
            rec["best_return"] = max((c["return"] for c in rec["curve"]), default=None)
            rec["time_to_threshold"] = time_to_reach(rec["curve"], threshold) if threshold is not None else None
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
            **threshold_columns(ok, train_s.get(lab, 0.0 if lab in TRAINING_FREE else None)),
        })
    status = "ok" if not not_available else ("partial" if any(r["seeds"] for r in table) else "not available")
    return result("ppo_curves", status, {"runs": runs, "table": table, "baselines": baselines,
                                         "threshold": threshold, "not_available": not_available, "seeds": seeds},
                  reason=None if status != "not available" else str(not_available), config=cfg, seeds=seeds)
