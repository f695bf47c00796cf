"""The gap table: every controller against the perfect-foresight optimum, on the same test states.

    python -m anm_torchrl.baselines.optimal --episodes 8 --seed 0 --steps 3000 --rows optimal --out rec.json
    python -m anm_torchrl.baselines.optimal --episodes 8 --seed 0 --steps 3000 --rows acmpc_64 --only 0,1 \
        --out part.json                                            # a costly row on some of the states
    python -m anm_torchrl.baselines.optimal --episodes 8 --seed 0 --steps 3000 --merge part.json --out rec.json
    python -m anm_torchrl.baselines.optimal --combine rec.json --test-returns results/test_returns.json \
        --readme README.md docs/OPTIMAL.md --out results/optimal_gap_table.json   # the published table

Rows (``--rows``, comma-separated): ``optimal`` (:class:`~anm_torchrl.baselines.optimal.OptimalPolicy`),
``acmpc_<N>`` (AC-MPC, perfect forecast; ``acmpc_<N>_cold``: every solve from N simulated do-nothing steps instead
of the previous solution shifted, to measure that warm start; ``acmpc_<N>_free``: the free storage split applied
without the pinned re-solve, the controller before that fix), ``mpc_<N>`` (gym-anm's DC-OPF MPC, perfect forecast, β = 0.92),
``do_nothing``, ``optimal<K>_then_do_nothing`` (the K-step optimum, then do-nothing: a lower bound of the
optimum when the full horizon is too costly). Every row is evaluated by :func:`~anm_torchrl.training.evaluation.evaluate_policy` on the
network's true env (``--network``; ``ANM6Env`` for ANM6-Easy, else ``ANMEnv`` of the registered network) from the
states ``draw_initial_states(episodes, seed, sim, init)`` (the env's reset distribution; seed 0: the PPO recipe's
test states), deterministic, T = ``steps``, γ = 0.995; ``--only`` restricts a row to some of those states (the row
records their indices). ``stability`` re-solves the first states' optimum from the do-nothing and a random warm
start. An existing ``--out`` record of the same protocol keeps its other rows. The record also holds, per state,
the optimum's IPOPT status, KKT residuals, rounds, solve times and its float64 replay through the env; per
AC-MPC row its IPOPT statuses and CPU seconds per solve.

**Loss, % of the optimum's** = 100 · (mean return of the row) / (mean return of the optimum on the same states):
100 % is optimal, 200 % loses twice as much. It is a ratio of means over the states a row covers (a row measured
on fewer states is compared with the optimum on those states only). ``--combine`` builds the published table from
gap records and the PPO rows of ``results/test_returns.json`` (same protocol, checked), and ``--readme`` rewrites
the ``<!-- optimum:gap -->`` block of the named pages from it.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import re
import sys
import time
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger(__name__)

DEFAULT_ROWS = ("optimal", "acmpc_16", "acmpc_64", "mpc_16", "mpc_64", "do_nothing")
GAMMA = 0.995
MPC_MARGIN = 0.92
# an MPC row's name: controller, horizon N and AC-MPC variant (one home for the suffixes _policy, _label and
# _order read)
_MPC_VARIANT = r"(_cold|_free)?"
_MPC_ROW = re.compile(r"(acmpc|mpc)_(\d+)" + _MPC_VARIANT)


ANM6 = "anm6_easy"


def _policy(name: str, sim, steps: int):
    from anm_torchrl.baselines import make_baseline

    if name == "optimal":
        return make_baseline("optimal", sim, horizon=steps)
    if name == "do_nothing":
        return make_baseline("do_nothing", sim)
    m = _MPC_ROW.fullmatch(name)
    if m is None or (m.group(3) and m.group(1) == "mpc"):
        raise ValueError(f"unknown row {name!r}; expected optimal, do_nothing, acmpc_<N>[_cold|_free] or mpc_<N>")
    if m.group(1) == "acmpc":
        return make_baseline("acmpc", sim, horizon=int(m.group(2)), forecast="perfect",
                             warm_start=m.group(3) != "_cold", pin_direction=m.group(3) != "_free")
    return make_baseline("mpc_perfect", sim, horizon=int(m.group(2)), safety_margin=MPC_MARGIN, gamma=GAMMA)


def _machine() -> dict:
    return {"platform": platform.platform(), "cpus": os.cpu_count(), "load_avg_1_5_15": list(os.getloadavg()),
            "torch_threads": torch.get_num_threads()}


def true_env(network: str, n: int):
    """The network's true env with batch size ``n`` (``ANM6Env`` for ANM6-Easy, else ``ANMEnv``), as PPO's."""
    from anm_torchrl.training.factory import make_true_env

    return make_true_env(n, "cpu", seed=0, network=None if network == ANM6 else network)


def _acmpc_stats(pol) -> dict:
    """IPOPT statuses, iterations and CPU seconds of every AC-MPC solve of a row; pinned-direction re-solves and
    states off the previous plan (SoC more than ``soc_tol`` from it)."""
    infos = pol.infos
    statuses = [i[k] for i in infos for k in ("status", "warm_status", "pinned_status") if i[k]]
    cpu = np.array([i["cpu_time"] for i in infos])
    warm = np.array([i["warm"] for i in infos])
    return {"solves": len(infos), "solve_time_s": {"mean": float(np.mean(pol.solve_times)),
                                                   "max": float(np.max(pol.solve_times))},
            "cpu_s_per_solve": {"mean": float(cpu.mean()), "max": float(cpu.max()),
                                "warm_mean": float(cpu[warm].mean()) if warm.any() else None,
                                "cold_mean": float(cpu[~warm].mean()) if (~warm).any() else None},
            "iterations_mean": float(np.mean([i["iterations"] for i in infos])),
            "warm_started": int(warm.sum()),
            "warm_start_failed": sum(1 for i in infos if i["warm_status"] not in (None, "Solve_Succeeded")),
            "not_solve_succeeded": sum(1 for x in statuses if x != "Solve_Succeeded"),
            "statuses": {x: statuses.count(x) for x in sorted(set(statuses))},
            "fallbacks": sum(1 for i in infos if i["fallback"]),
            "pinned_resolves": sum(1 for i in infos if i["pinned"]),
            "pinned_failed": sum(1 for i in infos if i["pinned_failed"]),
            "pinned_iterations_mean": float(np.mean([i["pinned_iterations"] for i in infos if i["pinned"]] or [0])),
            "max_overlap_applied": max((i["overlap_applied"] for i in infos if i["overlap_applied"] is not None),
                                       default=None),
            "off_plan": sum(1 for i in infos if i["off_plan"]),
            "max_soc_off_plan_mwh": max((i["soc_off_plan"] for i in infos if i["soc_off_plan"] is not None),
                                        default=None)}


def optimum_then_do_nothing(sim, states: torch.Tensor, steps: int, k: int, network: str = ANM6) -> dict:
    """A feasible ``steps``-step plan per state: the ``k``-step optimum, then do-nothing; its return (float64
    set-points replayed in the network's true env) is a lower bound of the ``steps``-step optimum, cheap when the
    full horizon is not.
    """
    from anm_torchrl.baselines.optimal import replay_in_env, solve_optimal, warm_start_actions

    if not 0 < k < steps:
        raise ValueError(f"optimum_then_do_nothing: k must lie in (0, {steps}), got {k}")
    t0, c0, load0 = time.perf_counter(), time.process_time(), os.getloadavg()[0]
    rets, undiscounted, terms, plans = [], [], [], []
    for s in states.numpy():
        opt = solve_optimal(sim, s, k, GAMMA)
        acts = np.concatenate([opt.setpoints, warm_start_actions(sim, opt.states[-1], steps - k, "do_nothing")])
        rep = replay_in_env(acts, s, GAMMA, env=true_env(network, 1))
        rets.append(rep["discounted_return"])
        undiscounted.append(float(rep["rewards"].sum()))
        terms.append(rep["terminated"])
        plans.append({"k_step_return": opt.discounted_return, "k_step_replay_gap": opt.replay_gap,
                      "statuses": [x["status"] for x in opt.rounds], "cpu_s": opt.cpu_time})
    return {"discounted_return": rets, "return": undiscounted, "terminated": terms,
            "mean_discounted_return": float(np.mean(rets)), "k": k, "plans": plans,
            "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
            "load_avg_1min": [load0, os.getloadavg()[0]]}


def evaluate_row(name: str, sim, states: torch.Tensor, steps: int, network: str = ANM6) -> dict:
    """One row: per-episode discounted returns and timings of policy ``name`` on the network's true env
    (``optimal<K>_then_do_nothing``: :func:`optimum_then_do_nothing`)."""
    from anm_torchrl.baselines.optimal import replay_in_env
    from anm_torchrl.training.evaluation import evaluate_policy

    m = re.fullmatch(r"optimal(\d+)_then_do_nothing", name)
    if m:
        return optimum_then_do_nothing(sim, states, steps, int(m.group(1)), network)
    pol = _policy(name, sim, steps)
    t0, c0, load0 = time.perf_counter(), time.process_time(), os.getloadavg()[0]
    res = evaluate_policy(pol, states, max_steps=steps, gamma=GAMMA, env=true_env(network, len(states)))
    row = {"discounted_return": res.discounted_returns.tolist(), "return": res.returns.tolist(),
           "terminated": res.terminated.tolist(), "mean_discounted_return": float(res.discounted_returns.mean()),
           "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
           "load_avg_1min": [load0, os.getloadavg()[0]]}
    if name.startswith("acmpc"):
        row.update(_acmpc_stats(pol))
    if name == "optimal":
        plans = []
        for plan, s in zip(pol.plans, states):
            env = replay_in_env(plan.setpoints, s.numpy(), GAMMA, env=true_env(network, 1))
            plans.append({**plan.summary(), "env_replay_return": env["discounted_return"],
                          "env_replay_gap": abs(env["discounted_return"] - plan.discounted_return)
                          / abs(plan.discounted_return), "env_replay_terminated": env["terminated"]})
        row["plans"] = plans
    return row


def stability(sim, states: torch.Tensor, steps: int, n: int, seed: int) -> list[dict]:
    """The optimum of the first ``n`` states from the DC-MPC, do-nothing and a random warm start."""
    from anm_torchrl.baselines.nlp_model import ACHorizonNLP
    from anm_torchrl.baselines.optimal import WARM_STARTS, solve_optimal

    nlp = ACHorizonNLP(sim, steps, GAMMA)
    out = []
    for i in range(n):
        rec = {}
        for ws in WARM_STARTS:
            r = solve_optimal(sim, states[i].numpy(), steps, GAMMA, warm_start=ws, seed=seed, nlp=nlp)
            rec[ws] = {"discounted_return": r.discounted_return, "exact_return": r.exact_return,
                       "warm_return": r.warm_return, "wall_time": r.wall_time,
                       "iterations": [x["iterations"] for x in r.rounds]}
        vals = [v["discounted_return"] for v in rec.values()]
        out.append({"episode": i, "by_warm_start": rec, "max_rel_spread": (max(vals) - min(vals)) / abs(min(vals))})
    return out


def compare_formulations(sim, state: torch.Tensor, steps: int) -> dict:
    """Polar vs rectangular voltages: the optimum of one state over ``steps`` (build, iterations, CPU and wall s)."""
    from anm_torchrl.baselines.nlp_model import ACHorizonNLP
    from anm_torchrl.baselines.optimal import solve_optimal

    out = {"steps": steps}
    for form in ("polar", "rectangular"):
        c0, t0 = time.process_time(), time.perf_counter()
        nlp = ACHorizonNLP(sim, steps, GAMMA, form)
        build = time.perf_counter() - t0
        r = solve_optimal(sim, state.numpy(), steps, GAMMA, warm_start="do_nothing", nlp=nlp)
        out[form] = {"discounted_return": r.discounted_return, "build_s": build,
                     "iterations": [x["iterations"] for x in r.rounds],
                     "solve_s": [x["solve_time_s"] for x in r.rounds], "cpu_s": time.process_time() - c0,
                     "wall_s": time.perf_counter() - t0, "load_avg_1min": os.getloadavg()[0]}
    return out


def _covered(row: dict, episodes: int) -> list[int]:
    """Indices of the protocol's states a row was measured on (all of them unless ``--only`` was used)."""
    return list(row.get("episode_index", range(episodes)))


PER_EPISODE = ("discounted_return", "return", "terminated")


def merge_rows(a: dict, b: dict, episodes: int) -> dict:
    """One row from two measurements of it on disjoint states (``--only`` chunks): per-episode lists joined in
    state order, each chunk's own fields kept under ``chunks``."""
    ia, ib = _covered(a, episodes), _covered(b, episodes)
    if set(ia) & set(ib):
        raise ValueError(f"merge_rows: states {sorted(set(ia) & set(ib))} measured twice")
    order = np.argsort(ia + ib)
    out = {k: [(a[k] + b[k])[i] for i in order] for k in PER_EPISODE}
    out["episode_index"] = sorted(ia + ib)
    out["mean_discounted_return"] = float(np.mean(out["discounted_return"]))
    out["chunks"] = [c for r in (a, b) for c in r.get("chunks", [{k: v for k, v in r.items() if k not in PER_EPISODE}])]
    return out


def _rank(t: dict) -> tuple:
    """Best first: by loss vs the optimum on each row's own states (rows on fewer states compare fairly), then
    rows without one by mean return."""
    pct = t["loss_pct_of_optimum"]
    return (pct is None, pct if pct is not None else 0.0, -t["mean_discounted_return"])


def table(rows: dict, episodes: int | None = None) -> list[dict]:
    """Per row: mean return and loss as % of the optimum's on the states it covers (None without an ``optimal``
    row covering them, or with an optimum whose mean return is ≥ 0: no loss to compare with), best first
    (:func:`_rank`)."""
    n = episodes if episodes is not None else max(len(r["discounted_return"]) for r in rows.values())
    opt = rows.get("optimal")
    opt_by_state = dict(zip(_covered(opt, n), opt["discounted_return"])) if opt else {}
    out = []
    for name, r in rows.items():
        idx, ret = _covered(r, n), np.asarray(r["discounted_return"])
        pct = None
        if idx and all(i in opt_by_state for i in idx):
            ref = float(np.mean([opt_by_state[i] for i in idx]))
            pct = 100.0 * float(ret.mean()) / ref if ref < 0 else None
        out.append({"policy": name, "episode_index": idx, "mean_discounted_return": float(ret.mean()),
                    "loss_pct_of_optimum": pct})
    return sorted(out, key=_rank)


def markdown(rec: dict) -> str:
    """The gap table of a record as Markdown: per row the mean return, per-episode returns and loss vs optimum."""
    lines = ["| policy | states | discounted return (mean) | per episode | loss, % of the optimum's |",
             "|---|---|---|---|---|"]
    for t in table(rec["rows"], rec["protocol"]["episodes"]):
        per = ", ".join(f"{v:.4f}" for v in rec["rows"][t["policy"]]["discounted_return"])
        pct = "–" if t["loss_pct_of_optimum"] is None else f"{t['loss_pct_of_optimum']:.1f} %"
        idx = ",".join(map(str, t["episode_index"]))
        lines.append(f"| {t['policy']} | {idx} | {t['mean_discounted_return']:.4f} | {per} | {pct} |")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------ the published table
LABELS = {"optimal": "perfect-foresight AC optimum", "do_nothing": "do-nothing"}  # other rows: _label
PPO_ROWS = {"none": "PPO trained on the true env", "pinn": "PPO trained on the PINN"}


def network_of(protocol: dict) -> str:
    """The network of a gap record's ``protocol`` (ANM6-Easy's records predate the key)."""
    return protocol.get("network", ANM6)


def block_markers(network: str = ANM6) -> tuple[str, str]:
    """The opening and closing markers of a network's gap block in README and the docs:
    ``<!-- optimum:gap -->`` for ANM6-Easy's table, ``<!-- optimum:gap:<network> -->`` for another's."""
    tag = "optimum:gap" if network == ANM6 else f"optimum:gap:{network}"
    return f"<!-- {tag} -->", f"<!-- /{tag} -->"


def readme_block(network: str = ANM6) -> re.Pattern:
    """A page's gap block of ``network``: groups (opening marker and newline, body, closing marker)."""
    start, end = block_markers(network)
    return re.compile(f"({re.escape(start)}\n)(.*?)({re.escape(end)})", re.S)


README_BLOCK = readme_block(ANM6)


def _label(name: str) -> str:
    k = re.fullmatch(r"optimal(\d+)_then_do_nothing", name)
    if k:
        return f"the {k.group(1)}-step optimum, then do-nothing (a lower bound of the optimum)"
    m = _MPC_ROW.fullmatch(name)
    if m is None:
        return LABELS[name]
    if m.group(3):
        return f"AC-MPC, perfect forecast, N = {m.group(2)}, " + (
            "cold starts" if m.group(3) == "_cold" else "free storage split (before the pinned re-solve)")
    if m.group(1) == "acmpc":
        return f"AC-MPC, perfect forecast, N = {m.group(2)}"
    return f"DC-OPF MPC, perfect forecast, N = {m.group(2)}, β = {MPC_MARGIN}"


def _solver_stats(row: dict) -> dict:
    """AC-MPC rows: solves, IPOPT non-successes, mean CPU s per solve, pinned re-solves (and their failures) and
    states off the previous plan over all chunks of a row ({} otherwise)."""
    parts = [c for c in row.get("chunks", [row]) if "solves" in c]
    if not parts:
        return {}
    n = sum(c["solves"] for c in parts)
    out = {"solves": n, "not_solve_succeeded": sum(c["not_solve_succeeded"] for c in parts),
           "cpu_s_per_solve": sum(c["cpu_s_per_solve"]["mean"] * c["solves"] for c in parts) / n}
    if all("pinned_resolves" in c for c in parts):  # rows measured before the pinned re-solve have none
        out.update({k: sum(c[k] for c in parts) for k in ("pinned_resolves", "pinned_failed", "off_plan")})
    return out


def _order(row: str) -> tuple:
    """The published table's fixed row order (the issue's): optimum, AC-MPC, DC-MPC (larger N first), the β = 0.96
    DC-MPC, PPO on the PINN, PPO on the true env, do-nothing. Not a ranking: rows may cover different states."""
    m = re.fullmatch(r"(optimal\d+_then_do_nothing|acmpc|mpc)_?(\d*)" + _MPC_VARIANT, row)
    groups = {"acmpc": 2, "mpc": 3}
    if m and m.group(1) in groups:
        return groups[m.group(1)], -int(m.group(2)), bool(m.group(3))
    fixed = ["optimal", "optimal_then", "", "", "mpc_perfect_N16", "ppo_best_pinn", "ppo_best_none", "do_nothing"]
    key = "optimal_then" if m else row
    return (fixed.index(key) if key in fixed else len(fixed), 0, False)


def _gain_pct(rows: dict, n: int, ret: float, idx: list[int]) -> float | None:
    """100 · (R − R_do-nothing) / (R_optimum − R_do-nothing), the means over states ``idx``: the share of the
    achievable improvement over do-nothing a row reaches (100 % is optimal, 0 % no better than doing nothing).
    Defined whatever the optimum's sign (case33bw's returns are positive); None without both rows on ``idx``."""
    ref = {}
    for name in ("optimal", "do_nothing"):
        r = rows.get(name)
        by_state = dict(zip(_covered(r, n), r["discounted_return"])) if r else {}
        if not all(i in by_state for i in idx):
            return None
        ref[name] = float(np.mean([by_state[i] for i in idx]))
    span = ref["optimal"] - ref["do_nothing"]
    return 100.0 * (ret - ref["do_nothing"]) / span if span > 0 else None


def _all_states_row(label: str, row: str, source: str, n: int, ret: float, opt_mean: float, gain,
                    std: float | None = None, seeds: int | None = None) -> dict:
    """A row measured on all ``n`` states outside the gap record (PPO: ``ret`` and ``std`` are the mean and
    sample std over ``seeds`` of each seed's mean return)."""
    g, losses = gain(ret), opt_mean < 0
    return {"policy": label, "row": row, "source": source, "states": n, "episode_index": list(range(n)),
            "discounted_return": ret, "std_over_seeds": std, "seeds": seeds,
            "loss_pct_of_optimum": 100.0 * ret / opt_mean if losses else None, "loss_pct_on_common": None,
            "loss_pct_std": 100.0 * std / abs(opt_mean) if losses and std is not None else None,
            "gain_pct_of_optimum": g, "gain_pct_std": None if g is None or std is None else abs(g - gain(ret + std))}


def _test_returns_rows(test_returns: dict, pr: dict, n: int, opt_mean: float, gain) -> list[dict]:
    """ANM6-Easy: the PPO rows and the β = 0.96 DC-MPC row of a ``test_returns`` record (protocol checked)."""
    d = test_returns["data"]
    want = {"test_episodes": n, "test_seed": int(pr["seed"]), "max_steps": int(pr["steps"]), "gamma": float(pr["gamma"])}
    if network_of(pr) != ANM6 or d["protocol"] != want:
        raise ValueError(f"combine: test_returns protocol {d['protocol']} differs from the gap record's {want} "
                         f"(network {pr.get('network')})")
    rows = []
    for r in d["rows"]:
        ret = float(r["discounted_return"])
        if r["policy"] == "mpc_perfect_N16":
            rows.append(_all_states_row("DC-OPF MPC, perfect forecast, N = 16, β = 0.96 (gym-anm-exp's tuned β)",
                                        r["policy"], "test_returns", n, ret, opt_mean, gain))
        elif r["policy"] == "ppo_best" and r.get("trained_on") in PPO_ROWS:
            rows.append(_all_states_row(f"{PPO_ROWS[r['trained_on']]} (`best.pt`, {int(r['frames']):,} frames)",
                                        f"ppo_best_{r['trained_on']}", "test_returns", n, ret, opt_mean, gain,
                                        float(r.get("discounted_return_std") or 0.0), int(r["seeds"])))
    return rows


def _payoff_ppo_rows(ppo: dict, gap_rows: dict, pr: dict, n: int, opt_mean: float, gain) -> list[dict]:
    """Another network: the PPO rows of the payoff study's PPO part (``data.ppo`` of ``results/inputs/ppo_<network>
    .json``), whose test states must be the gap record's: same network, seed, count, T and γ, and the same
    do-nothing return on them (1e-9 relative; a different state draw would change it)."""
    from anm_torchrl.experiments.ppo_runs import aggregate

    dn = ppo["test_baselines"].get("do_nothing") or {}
    want = {"network": pr["network"], "episodes": n, "test_seed": int(pr["seed"]), "max_steps": int(pr["steps"]),
            "gamma": float(pr["gamma"])}
    got = {"network": ppo["network"], **{k: dn.get(k) for k in ("episodes", "test_seed", "max_steps", "gamma")}}
    if got != want:
        raise ValueError(f"combine: the PPO record's test protocol {got} differs from the gap record's {want}")
    mine = gap_rows.get("do_nothing")
    if mine is None or _covered(mine, n) != list(range(n)):
        raise ValueError("combine: checking the PPO record's test states needs a do_nothing row on every state")
    a, b = float(np.mean(mine["discounted_return"])), float(dn["discounted_return"])
    if abs(a - b) > 1e-9 * abs(b):
        raise ValueError(f"combine: do-nothing returns {a!r} (gap record) and {b!r} (PPO record's test states) "
                         "differ: the two records were not measured on the same states")
    rows = []
    for t in ppo["table"]:
        if t["env"] not in PPO_ROWS:
            continue
        vals = t["test_best_discounted_return"]
        if any(v is None for v in vals):
            raise ValueError(f"combine: PPO {t['env']!r} lacks a test return for a seed of {t['seeds']}")
        agg = aggregate(vals)
        lo, hi = min(t["frames"]), max(t["frames"])
        frames = f"{lo:,} frames" if lo == hi else f"{lo:,}–{hi:,} frames"
        rows.append(_all_states_row(f"{PPO_ROWS[t['env']]} (`best.pt`, {frames})", f"ppo_best_{t['env']}", "ppo",
                                    n, agg["mean"], opt_mean, gain, agg["std"], agg["n"]))
    return rows


def combine(gap_rec: dict, test_returns: dict | None = None, ppo: dict | None = None,
            record: str = "results/optimal_gap_table.json") -> dict:
    """The published gap table from a gap record and (optionally) its PPO rows, measured on the same states
    (protocol checked): for ANM6-Easy a ``test_returns`` record (its PPO rows and β = 0.96 DC-MPC row), for
    another network the payoff study's PPO part ``ppo`` (:func:`_payoff_ppo_rows`). ``record``: where the table
    is written (named under the rendered table).

    Rows: ``policy`` (label), ``source``, ``states`` (how many), ``episode_index``, ``discounted_return`` (mean
    over the states; for PPO the mean over seeds of each seed's mean), ``std_over_seeds``, ``seeds``,
    ``loss_pct_of_optimum`` (100 · mean return / the optimum's mean return on the same states; None where the
    optimum's return is ≥ 0) and its ``loss_pct_std`` (PPO: the std over seeds in the same units), and
    ``gain_pct_of_optimum`` (:func:`_gain_pct`).
    """
    if test_returns is not None and ppo is not None:
        raise ValueError("combine: PPO rows come from a test_returns record (ANM6-Easy) or a PPO record, not both")
    pr, rows_in = gap_rec["protocol"], gap_rec["rows"]
    n = int(pr["episodes"])
    opt = rows_in.get("optimal")
    if opt is None or len(_covered(opt, n)) != n:
        raise ValueError("combine: the gap record needs an 'optimal' row on all of its states")
    opt_mean = float(np.mean(opt["discounted_return"]))
    # the states every gap row covers: there all of them compare on equal terms
    common = sorted(set.intersection(*(set(_covered(r, n)) for r in rows_in.values())))
    rows = []
    for t in table(rows_in, n):
        r = rows_in[t["policy"]]
        on_common = table({"optimal": opt, "row": {"discounted_return": [
            dict(zip(t["episode_index"], r["discounted_return"]))[i] for i in common], "episode_index": common}},
            n)
        rows.append({"policy": _label(t["policy"]), "row": t["policy"], "source": "gap",
                     "states": len(t["episode_index"]), "episode_index": t["episode_index"],
                     "discounted_return": t["mean_discounted_return"], "std_over_seeds": None, "seeds": None,
                     "loss_pct_of_optimum": t["loss_pct_of_optimum"], "loss_pct_std": None,
                     "loss_pct_on_common": next(x["loss_pct_of_optimum"] for x in on_common if x["policy"] == "row"),
                     "gain_pct_of_optimum": _gain_pct(rows_in, n, t["mean_discounted_return"], t["episode_index"]),
                     "gain_pct_std": None, **_solver_stats(r)})
    gain = lambda ret: _gain_pct(rows_in, n, ret, list(range(n)))  # noqa: E731  (rows on all n states)
    src = None
    if test_returns is not None:
        rows += _test_returns_rows(test_returns, pr, n, opt_mean, gain)
        meta = test_returns.get("meta", {})
        src = {"file": "results/test_returns.json", "git_commit": (meta.get("versions") or {}).get("git_commit"),
               "date": meta.get("date")}
    if ppo is not None:
        rows += _payoff_ppo_rows(ppo["data"]["ppo"], rows_in, pr, n, opt_mean, gain)
        src = {"file": f"results/inputs/ppo_{pr['network']}.json",
               "git_commit": (ppo.get("meta", {}).get("versions") or {}).get("git_commit")}
    rows.sort(key=lambda r: _order(r["row"]))
    return {"protocol": pr, "optimum_mean": opt_mean, "common_states": common, "rows": rows, "ppo_source": src,
            "record": record}


def _pct(v: float) -> str:
    """A loss percentage: one decimal below 1,000 % (near-optimal rows differ in tenths), none above."""
    return f"{v:.1f} %" if v < 1000 else f"{v:,.0f} %"


def render_block(table_rec: dict) -> str:
    """The Markdown of a network's gap block (README, docs/OPTIMAL.md) from a :func:`combine` record.

    A loss column (ratio to the optimum's loss) appears where the optimum's return is negative; a column on the
    states every measured row covers appears when some rows cover fewer states."""
    pr, common = table_rec["protocol"], table_rec["common_states"]
    partial = len(common) < pr["episodes"]
    losses = table_rec["optimum_mean"] < 0
    digits = 2 if abs(table_rec["optimum_mean"]) >= 10 else 4  # returns of order 1 differ in the third decimal
    on = f"#{', #'.join(map(str, common))}"
    init = f", sim, init='{pr['init']}'" if "init" in pr else ""
    net = network_of(pr)
    lines = [f"{net}: {pr['episodes']} test states (`draw_initial_states({pr['episodes']}, seed={pr['seed']}{init})`, "
             f"numbered #0–#{pr['episodes'] - 1}), T = {pr['steps']:,}, γ = {pr['gamma']}, discounted return on the "
             "true env; gain: the share of the optimum's improvement over do-nothing a row reaches, "
             "100 · (R − R_do-nothing) / (R_optimum − R_do-nothing)"
             + ("; loss as % of the optimum's loss on the same states (ratio of means)" if losses else
                "; no loss column: the optimum's return is positive")
             + "; PPO: mean ± std over seeds"
             + (f"; the last column compares every row measured per state on state{'s' if len(common) > 1 else ''} "
                f"{on} alone" if partial and losses else "") + ":", "",
             "| policy | states | discounted return | gain, % of the optimum's |"
             + (" loss, % of the optimum's |" if losses else "") + (f" on {on} |" if partial and losses else ""),
             "|---|---:|---:|---:|" + ("---:|" if losses else "") + ("---:|" if partial and losses else "")]
    for r in table_rec["rows"]:
        spread = (r["seeds"] or 0) > 1  # a std over one seed says nothing
        ret = f"{r['discounted_return']:.{digits}f}" + (f" ± {r['std_over_seeds']:.{digits}f}" if spread else "")
        gain = "–" if r.get("gain_pct_of_optimum") is None else f"{r['gain_pct_of_optimum']:.1f} %" + (
            f" ± {r['gain_pct_std']:.1f}" if spread else "")
        std = r["loss_pct_std"]
        pct = "–" if r["loss_pct_of_optimum"] is None else _pct(r["loss_pct_of_optimum"]) + (
            (f" ± {std:,.0f}" if std >= 10 else f" ± {std:.1f}") if spread else "")
        states = f"{r['states']}" if r["states"] == pr["episodes"] else \
            f"{r['states']} (#{', #'.join(map(str, r['episode_index']))})"
        seeds = f", {r['seeds']} seed{'s' if r['seeds'] != 1 else ''}" if r["seeds"] else ""
        last = f" {pct} |" if losses else ""
        if partial and losses:
            last += " – |" if r["loss_pct_on_common"] is None else f" {_pct(r['loss_pct_on_common'])} |"
        lines.append(f"| {r['policy']}{seeds} | {states} | {ret} | {gain} |{last}")
    src = f"_From `{table_rec.get('record', 'results/optimal_gap_table.json')}`"
    ps = table_rec.get("ppo_source")
    if ps:
        what = "PPO and β = 0.96 rows" if ps["file"].endswith("test_returns.json") else "PPO rows"
        src += f" ({what}: `{ps['file']}`, git commit `{str(ps['git_commit'])[:7]}`)"
    return "\n".join(lines) + "\n\n" + src + "._\n"


def update_pages(pages: list[str | Path], table_rec: dict) -> None:
    """Rewrite the network's gap block (:func:`readme_block`) of every page; a page without it is an error."""
    body = render_block(table_rec)
    net = network_of(table_rec["protocol"])
    block = readme_block(net)
    texts = {page: page.read_text() for page in map(Path, pages)}
    missing = [str(page) for page, text in texts.items() if not block.search(text)]
    if missing:  # checked on every page before any is written: no page is left half-updated
        raise ValueError(f"{', '.join(missing)}: no {' ... '.join(block_markers(net))} block for {net}")
    for page, text in texts.items():
        page.write_text(block.sub(lambda m: m.group(1) + body + m.group(3), text))


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m anm_torchrl.baselines.optimal", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--network", default=ANM6, help="registered network (default anm6_easy)")
    ap.add_argument("--episodes", type=int, default=4, help="number of test states (default 4)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the test states (default 0, the test seed)")
    ap.add_argument("--steps", type=int, default=3000, help="episode length T (default 3000)")
    ap.add_argument("--rows", default=",".join(DEFAULT_ROWS), help="comma-separated rows (default: all)")
    ap.add_argument("--only", default="", help="comma-separated state indices the rows run on (default: all)")
    ap.add_argument("--stability", type=int, default=0,
                    help="re-solve the optimum of this many first states from every warm start (default 0)")
    ap.add_argument("--formulations", type=int, default=0,
                    help="time polar vs rectangular voltages on the first state over this many steps (default 0: no)")
    ap.add_argument("--merge", nargs="*", default=[],
                    help="records of the same protocol (e.g. rows measured in parallel runs) whose rows are merged "
                         "into --out")
    ap.add_argument("--drop", default="",
                    help="comma-separated rows removed from --out before --merge (to replace them by re-measured "
                         "ones)")
    ap.add_argument("--combine", default="",
                    help="build the published table from this gap record into --out (no evaluation)")
    ap.add_argument("--test-returns", default="", help="with --combine: the test_returns record (ANM6-Easy's PPO rows)")
    ap.add_argument("--ppo", default="",
                    help="with --combine, another network: its payoff PPO record (results/inputs/ppo_<network>.json)")
    ap.add_argument("--readme", nargs="*", default=[],
                    help="with --combine: pages whose <!-- optimum:gap --> block is rewritten")
    ap.add_argument("--markdown", action="store_true", help="print the record's table as Markdown and exit")
    ap.add_argument("--out", required=True, help="JSON record (rows of an existing record are kept)")
    args = ap.parse_args(argv)
    if args.markdown:
        sys.stdout.write(markdown(json.loads(Path(args.out).read_text())) + "\n")
        return {}
    command = "python -m anm_torchrl.baselines.optimal " + " ".join(argv if argv is not None else sys.argv[1:])
    if args.combine:
        tr = json.loads(Path(args.test_returns).read_text()) if args.test_returns else None
        ppo = json.loads(Path(args.ppo).read_text()) if args.ppo else None
        rec = {**combine(json.loads(Path(args.combine).read_text()), tr, ppo, record=args.out), "command": command}
        update_pages(args.readme, rec)  # first: a page without the block refuses the table before it is written
        _write(Path(args.out), rec)
        return rec
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    torch.set_num_threads(1)
    from anm_torchrl.data.generic import simulator_for
    from anm_torchrl.training.evaluation import draw_initial_states

    sim, env = simulator_for(args.network), true_env(args.network, 1)
    states = draw_initial_states(args.episodes, args.seed, sim, env.init)
    protocol = {"network": args.network, "episodes": args.episodes, "seed": args.seed, "steps": args.steps,
                "gamma": GAMMA, "states": "training.evaluation.draw_initial_states(episodes, seed)"}
    if args.network != ANM6:  # ANM6-Easy's records predate this key (gym-anm's reset distribution)
        protocol.update(init=env.init, states="training.evaluation.draw_initial_states(episodes, seed, sim, init)")
    only = [int(i) for i in args.only.split(",") if i]
    if any(not 0 <= i < args.episodes for i in only):
        raise SystemExit(f"--only {only}: indices must lie in [0, {args.episodes})")
    out = Path(args.out)
    rec = json.loads(out.read_text()) if out.exists() else {}
    if rec and rec.get("protocol") != protocol:
        raise SystemExit(f"{out} holds protocol {rec.get('protocol')}, this run {protocol}: use another --out")
    rec.setdefault("rows", {})
    rec["protocol"] = protocol
    for name in [r for r in args.drop.split(",") if r]:
        if name not in rec["rows"]:
            raise SystemExit(f"--drop {name}: {out} has no such row (rows: {sorted(rec['rows'])})")
        del rec["rows"][name]
    for path in args.merge:
        other = json.loads(Path(path).read_text())
        if other.get("protocol") != protocol:
            raise SystemExit(f"--merge: {path} holds protocol {other.get('protocol')}, this run {protocol}")
        for name, row in other["rows"].items():
            rec["rows"][name] = merge_rows(rec["rows"][name], row, args.episodes) if name in rec["rows"] else row
        rec.update({k: other[k] for k in ("stability", "formulations") if k in other})
        rec.setdefault("commands", []).extend(other.get("commands", []))
    for name in [r for r in args.rows.split(",") if r and not args.merge]:
        log.info("row %s ...", name)
        row = evaluate_row(name, sim, states[only] if only else states, args.steps, args.network)
        rec["rows"][name] = {**row, **({"episode_index": only} if only else {}), "machine": _machine()}
        log.info("row %s: %s", name, rec["rows"][name]["discounted_return"])
        _write(out, rec)
    if args.formulations:
        rec["formulations"] = {**compare_formulations(sim, states[0], args.formulations), "machine": _machine()}
    if args.stability:
        rec["stability"] = {"episodes": stability(sim, states, args.steps, args.stability, args.seed),
                            "machine": _machine()}
    rec["table"] = table(rec["rows"], args.episodes)
    rec.setdefault("commands", []).append(command)
    _write(out, rec)
    return rec


def _write(path: Path, rec: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(rec, indent=1) + "\n")
    os.replace(tmp, path)
