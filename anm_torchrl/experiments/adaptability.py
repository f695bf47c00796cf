"""Beyond the paper: surrogates under changed demand / generation profiles, without retraining.

A copy of the simulator gets its load series and/or renewable-potential series scaled, or both series shifted in
time (``scaled_simulator``; the device limits still clip them, as in gym-anm). The true env and every surrogate
env run on that copy: every loader receives the changed simulator (``load_surrogate(kind, sim=...)``), so the PINN's
physics and the data-driven models' foresight features read the new series; what a data-driven model cannot
follow is what its training data did not cover. The measure is the one-step (teacher-forced) MAE of
:mod:`.rollout_error` along random-agent (and expert) episodes, per scenario; the ``base`` scenario (factors 1,
no shift) is the reference.
"""

from __future__ import annotations

from typing import Any

from anm_torchrl.experiments.common import RunContext
from anm_torchrl.experiments import rollout_error
from anm_torchrl.experiments.io import result


def run(cfg: dict[str, Any], ctx: RunContext) -> dict:
    """cfg keys: ``scenarios`` (list of {name, load, gen, shift}: scale factors of the load and renewable-potential
    series, and a shift of both series by ``shift`` time steps), plus :func:`rollout_error.measure`'s keys."""
    surrogates, seed = list(ctx.surrogates), ctx.seed
    scenarios = cfg.get("scenarios") or [{"name": "base", "load": 1.0, "gen": 1.0},
                                          {"name": "load_x1.2", "load": 1.2, "gen": 1.0},
                                          {"name": "gen_x0.8", "load": 1.0, "gen": 0.8}]
    sub = {**cfg, "free_running": bool(cfg.get("free_running", False))}
    rows, not_available = [], {}
    for sc in scenarios:
        sim = rollout_error.scaled_simulator(sc.get("load", 1.0), sc.get("gen", 1.0), shift=sc.get("shift", 0))
        rec = rollout_error.measure(sub, surrogates, seed=seed, sim=sim, name="adaptability", include_true=False)
        not_available.update(rec["data"].get("not_available", {}))
        for agent, a in rec["data"].get("agents", {}).items():
            for lab, r in a["surrogates"].items():
                rows.append({"scenario": sc["name"], "load": sc.get("load", 1.0), "gen": sc.get("gen", 1.0),
                             "shift": sc.get("shift", 0), "agent": agent, "policy": a["policy"], "surrogate": lab,
                             "one_step_mae": r["one_step"]["mae"],
                             "free_running_mae": r.get("free_running", {}).get("mae")})
    if not rows:
        return result("adaptability", "not available",
                      reason="no surrogate available: " + "; ".join(f"{k}: {v}" for k, v in not_available.items()),
                      config=cfg, seed=seed)
    return result("adaptability", "ok" if not not_available else "partial",
                  {"rows": rows, "scenarios": scenarios, "not_available": not_available}, config=cfg, seed=seed)
