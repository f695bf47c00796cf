"""The experiment ``test_returns`` (record ``test_returns.json``): returns on the held-out **test** states, PPO
trained on each env and the baselines, under one protocol.

PPO runs train with the recipe's loop (:func:`~anm_torchrl.training.protocol.train`): validation states
(``eval.seed``) choose ``best.pt`` and the early stop, and the loop evaluates ``best.pt`` and ``last.pt`` once on
the test states (``eval.test_seed``, ``summary.json["test"]``). The baselines (do-nothing, random, MPC …) are
evaluated here on the same test states (:func:`~anm_torchrl.evaluation.draw_initial_states` with the test
seed and count), deterministic, T = ``max_steps``, discount ``gamma``. Every figure the README's PPO table shows
comes from this record.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from anm_torchrl.experiments.common import RunContext, label
from anm_torchrl.experiments.io import result
from anm_torchrl.experiments.ppo_runs import aggregate, ppo_overrides, run_ppo


def evaluate_baseline(name: str, kwargs: dict[str, Any], states, max_steps: int, gamma: float) -> dict[str, Any]:
    """Metrics of baseline ``name`` (built with ``kwargs``) from the initial ``states`` (E, 18) on the true env."""
    from anm_torchrl.baselines import make_baseline
    from anm_torchrl.evaluation import evaluate_policy

    t0 = time.perf_counter()
    res = evaluate_policy(make_baseline(name, **kwargs), states, max_steps=max_steps, gamma=gamma)
    return {**res.metrics(), "episodes": res.num_episodes, "seconds": time.perf_counter() - t0}


def reused_rows(paths: list[str], protocol: dict[str, Any]) -> tuple[list[dict], dict[str, list[dict]]]:
    """The rows (baselines and PPO) and PPO runs of earlier ``test_returns`` records at ``paths``, not measured
    again, each row marked with its record's git commit; every record's protocol (states, T, γ) must equal
    ``protocol``."""
    from anm_torchrl.experiments.io import read_json

    rows, runs = [], {}
    for path in paths:
        rec = read_json(path)
        if rec["data"].get("protocol") != protocol:
            raise ValueError(f"reuse: {path} was measured with protocol {rec['data'].get('protocol')}, this run "
                             f"with {protocol}")
        origin = {"file": str(path), "git_commit": (rec["meta"].get("versions") or {}).get("git_commit")}
        rows += [{**r, "reused_from": origin} for r in rec["data"]["rows"]]
        runs.update(rec["data"].get("runs", {}))
    return rows, runs


def run(cfg: dict[str, Any], ctx: RunContext) -> dict:
    """cfg keys: ``test_episodes``, ``test_seed``, ``max_steps``, ``gamma`` (the protocol, shared by every row);
    ``baselines`` (list of ``{name, kwargs}``); ``reuse`` (earlier records of the same protocol whose rows are
    taken instead of measuring them again, e.g. the MPC's slow episodes); ``ppo`` (``envs``: env labels, ``seeds``, ``base``: Hydra overrides
    of every run, ``per_env``: label -> extra overrides, ``timeout_s``). Surrogate envs take their spec (e.g. a
    PINN ``path``) from ``ctx.surrogates``; ``none`` is the true simulator. PPO runs use ``ctx.threads``."""
    ppo = cfg.get("ppo", {})
    cfg = {**cfg, "ppo": {**ppo, "base": {**ppo.get("base", {}), "threads": int(ctx.threads)}}}
    surrogates, out_dir = list(ctx.surrogates), ctx.out_dir
    n, seed = int(cfg["test_episodes"]), int(cfg["test_seed"])
    max_steps, gamma = int(cfg["max_steps"]), float(cfg["gamma"])
    protocol = {"eval.test_episodes": n, "eval.test_seed": seed, "eval.max_steps": max_steps, "eval.gamma": gamma}
    from anm_torchrl.evaluation import draw_initial_states

    states = draw_initial_states(n, seed)
    protocol_rec = {"test_episodes": n, "test_seed": seed, "max_steps": max_steps, "gamma": gamma}
    rows, runs = reused_rows(list(cfg.get("reuse") or []), protocol_rec)
    not_available: dict[str, str] = {}
    for b in cfg.get("baselines", []):
        b = {"name": b} if isinstance(b, str) else dict(b)
        lab = b.get("label", b["name"])
        try:
            rows.append({"policy": lab, "trained_on": None, "seeds": None,
                         **evaluate_baseline(b["name"], dict(b.get("kwargs") or {}), states, max_steps, gamma)})
        except Exception as err:  # noqa: BLE001 - one baseline failing is recorded, the others still run
            not_available[lab] = f"{type(err).__name__}: {err}"
    p = cfg.get("ppo") or {}
    by_label = {label(s): s for s in surrogates}
    for env_label in p.get("envs", []):
        spec = by_label.get(env_label, {"name": env_label})
        over = {**p.get("base", {}), **protocol, **p.get("per_env", {}).get(env_label, {})}
        recs = []
        for s in p.get("seeds", [0]):
            rec = run_ppo(ppo_overrides(spec, int(s), over), Path(out_dir) / "runs" / "test_returns" /
                          f"{env_label}_s{s}", timeout_s=p.get("timeout_s"))
            recs.append({k: rec[k] for k in ("ok", "error", "wall_s", "summary", "command")} | {"seed": int(s)})
        runs[env_label] = recs
        tests = [(r["summary"] or {}).get("test") or {} for r in recs]
        if not any("best" in t for t in tests):
            not_available[f"ppo_{env_label}"] = "; ".join(str(r["error"])[:300] for r in recs) or "no test figures"
            continue
        for which in ("best", "last"):
            disc = aggregate([t.get(which, {}).get("discounted_return") for t in tests])
            ret = aggregate([t.get(which, {}).get("return") for t in tests])
            rows.append({"policy": f"ppo_{which}", "trained_on": env_label, "seeds": disc["n"],
                         "discounted_return": disc["mean"], "discounted_return_std": disc["std"],
                         "return": ret["mean"], "episodes": n,
                         "frames": aggregate([(r["summary"] or {}).get("frames") for r in recs])["mean"],
                         "seconds": aggregate([(r["summary"] or {}).get("wall_time") for r in recs])["mean"]})
    status = "ok" if not not_available else ("partial" if rows else "not available")
    return result("test_returns", status, {"rows": rows, "runs": runs, "not_available": not_available,
                                           "protocol": protocol_rec},
                  reason=None if rows else str(not_available), config=cfg)
