"""The gap study: every controller against the perfect-foresight optimum, on the same test states.

Its command line is :mod:`anm_torchrl.cli.gap` (``python -m anm_torchrl.cli.gap --help``).

Rows (``--rows``, comma-separated): ``optimal`` (:class:`~anm_torchrl.baselines.optimal.OptimalPolicy`),
``acmpc_<N>`` (AC-MPC, perfect forecast; ``acmpc_<N>_cold``: every solve from N simulated do-nothing steps instead
of the previous solution shifted, to measure that warm start; ``acmpc_<N>_free``: the free storage split applied
without the pinned re-solve, the controller before that fix), ``mpc_<N>`` (gym-anm's DC-OPF MPC, perfect forecast, β = 0.92),
``do_nothing``, ``optimal<K>_then_do_nothing`` (the K-step optimum, then do-nothing: a lower bound of the
optimum when the full horizon is too costly). Every row is evaluated by :func:`~anm_torchrl.evaluation.evaluate_policy` on the
network's true env (``--network``; ``ANM6Env`` for ANM6-Easy, else ``ANMEnv`` of the registered network) from the
states ``draw_initial_states(episodes, seed, sim, init)`` (the env's reset distribution; seed 0: the PPO recipe's
test states), deterministic, T = ``steps``, γ = 0.995; ``--only`` restricts a row to some of those states (the row
records their indices). ``stability`` re-solves the first states' optimum from the do-nothing and a random warm
start. An existing ``--out`` record of the same protocol keeps its other rows. The record also holds, per state,
the optimum's IPOPT status, KKT residuals, rounds, solve times and its float64 replay through the env; per
AC-MPC row its IPOPT statuses and CPU seconds per solve.

**Loss, % of the optimum's** = 100 · (mean return of the row) / (mean return of the optimum on the same states):
100 % is optimal, 200 % loses twice as much. It is a ratio of means over the states a row covers (a row measured
on fewer states is compared with the optimum on those states only). ``--combine`` builds the published table
(:mod:`anm_torchrl.experiments.gap_table`) from gap records and the PPO rows of
``results/reproduction/test_returns.json`` (same protocol, checked), and ``--readme`` rewrites the
``<!-- optimum:gap -->`` block of the named pages from it.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import re
import time
from pathlib import Path

import numpy as np
import torch

from anm_torchrl.artifacts import atomic_write
from anm_torchrl.evaluation import EVAL_GAMMA
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.strict_json import json_text

log = logging.getLogger(__name__)

DEFAULT_ROWS = ("optimal", "acmpc_16", "acmpc_64", "mpc_16", "mpc_64", "do_nothing")
MPC_MARGIN = 0.92
# an MPC row's name: controller, horizon N and AC-MPC variant (one home for the suffixes _policy, _label and
# _order read)
MPC_VARIANT = r"(_cold|_free)?"
MPC_ROW = re.compile(r"(acmpc|mpc)_(\d+)" + MPC_VARIANT)


ANM6 = ANM6_EASY


def _policy(name: str, sim, steps: int):
    from anm_torchrl.baselines import make_baseline

    if name == "optimal":
        return make_baseline("optimal", sim, horizon=steps)
    if name == "do_nothing":
        return make_baseline("do_nothing", sim)
    m = MPC_ROW.fullmatch(name)
    if m is None or (m.group(3) and m.group(1) == "mpc"):
        raise ValueError(f"unknown row {name!r}; expected optimal, do_nothing, acmpc_<N>[_cold|_free] or mpc_<N>")
    if m.group(1) == "acmpc":
        return make_baseline("acmpc", sim, horizon=int(m.group(2)), forecast="perfect",
                             warm_start=m.group(3) != "_cold", pin_direction=m.group(3) != "_free")
    return make_baseline("mpc_perfect", sim, horizon=int(m.group(2)), safety_margin=MPC_MARGIN, gamma=EVAL_GAMMA)


def machine() -> dict:
    """The machine a row was measured on: platform, CPUs, load average, torch threads."""
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
        opt = solve_optimal(sim, s, k, EVAL_GAMMA)
        acts = np.concatenate([opt.setpoints, warm_start_actions(sim, opt.states[-1], steps - k, "do_nothing")])
        rep = replay_in_env(acts, s, EVAL_GAMMA, env=true_env(network, 1))
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
    from anm_torchrl.evaluation import evaluate_policy

    m = re.fullmatch(r"optimal(\d+)_then_do_nothing", name)
    if m:
        return optimum_then_do_nothing(sim, states, steps, int(m.group(1)), network)
    pol = _policy(name, sim, steps)
    t0, c0, load0 = time.perf_counter(), time.process_time(), os.getloadavg()[0]
    res = evaluate_policy(pol, states, max_steps=steps, gamma=EVAL_GAMMA, env=true_env(network, len(states)))
    row = {"discounted_return": res.discounted_returns.tolist(), "return": res.returns.tolist(),
           "terminated": res.terminated.tolist(), "mean_discounted_return": float(res.discounted_returns.mean()),
           "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
           "load_avg_1min": [load0, os.getloadavg()[0]]}
    if name.startswith("acmpc"):
        row.update(_acmpc_stats(pol))
    if name == "optimal":
        plans = []
        for plan, s in zip(pol.plans, states):
            env = replay_in_env(plan.setpoints, s.numpy(), EVAL_GAMMA, env=true_env(network, 1))
            plans.append({**plan.summary(), "env_replay_return": env["discounted_return"],
                          "env_replay_gap": abs(env["discounted_return"] - plan.discounted_return)
                          / abs(plan.discounted_return), "env_replay_terminated": env["terminated"]})
        row["plans"] = plans
    return row


def stability(sim, states: torch.Tensor, steps: int, n: int, seed: int) -> list[dict]:
    """The optimum of the first ``n`` states from the DC-MPC, do-nothing and a random warm start."""
    from anm_torchrl.baselines.nlp_model import ACHorizonNLP
    from anm_torchrl.baselines.optimal import WARM_STARTS, solve_optimal

    nlp = ACHorizonNLP(sim, steps, EVAL_GAMMA)
    out = []
    for i in range(n):
        rec = {}
        for ws in WARM_STARTS:
            r = solve_optimal(sim, states[i].numpy(), steps, EVAL_GAMMA, warm_start=ws, seed=seed, nlp=nlp)
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
        nlp = ACHorizonNLP(sim, steps, EVAL_GAMMA, form)
        build = time.perf_counter() - t0
        r = solve_optimal(sim, state.numpy(), steps, EVAL_GAMMA, warm_start="do_nothing", nlp=nlp)
        out[form] = {"discounted_return": r.discounted_return, "build_s": build,
                     "iterations": [x["iterations"] for x in r.rounds],
                     "solve_s": [x["solve_time_s"] for x in r.rounds], "cpu_s": time.process_time() - c0,
                     "wall_s": time.perf_counter() - t0, "load_avg_1min": os.getloadavg()[0]}
    return out


def covered(row: dict, episodes: int) -> list[int]:
    """Indices of the protocol's states a row was measured on (all of them unless ``--only`` was used)."""
    return list(row.get("episode_index", range(episodes)))


PER_EPISODE = ("discounted_return", "return", "terminated")


def merge_rows(a: dict, b: dict, episodes: int) -> dict:
    """One row from two measurements of it on disjoint states (``--only`` chunks): per-episode lists joined in
    state order, each chunk's own fields kept under ``chunks``."""
    ia, ib = covered(a, episodes), covered(b, episodes)
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
    opt_by_state = dict(zip(covered(opt, n), opt["discounted_return"])) if opt else {}
    out = []
    for name, r in rows.items():
        idx, ret = covered(r, n), np.asarray(r["discounted_return"])
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


def write_record(path: Path, rec: dict) -> None:
    """Write a gap record atomically (:func:`~anm_torchrl.artifacts.atomic_write`), creating its folder."""
    atomic_write(path, (json_text(rec, indent=1) + "\n").encode())


def measure(network: str, episodes: int, seed: int, steps: int, out: Path, command: str, *, rows: list[str],
            only: list[int] = (), drop: list[str] = (), merge: list[str] = (), formulations: int = 0,
            stability_states: int = 0) -> dict:
    """The gap study's measurement (``python -m anm_torchrl.cli.gap``, which passes its options here): ``rows`` on
    ``episodes`` states of ``seed`` (``only``: some of them), T = ``steps``, into the record ``out`` (its other rows
    kept, ``drop`` removed first; ``merge``: records of the same protocol merged instead of measuring), written after
    every row; ``command`` is appended to its ``commands``.

    Raises:
        ValueError: an ``only`` index outside the states, ``out`` or a ``merge`` record of another protocol, or a
            ``drop`` row ``out`` does not hold.
    """
    from anm_torchrl.evaluation import draw_initial_states
    from anm_torchrl.networks import simulator as network_simulator

    sim, env = network_simulator(network), true_env(network, 1)
    states = draw_initial_states(episodes, seed, sim, env.init)
    # "states" names the draw as the committed records do (from when the protocol lived in training/): a record
    # key compared on --out and --merge, so it stays verbatim
    protocol = {"network": network, "episodes": episodes, "seed": seed, "steps": steps,
                "gamma": EVAL_GAMMA, "states": "training.evaluation.draw_initial_states(episodes, seed)"}
    if network != ANM6:  # ANM6-Easy's records predate this key (gym-anm's reset distribution)
        protocol.update(init=env.init, states="training.evaluation.draw_initial_states(episodes, seed, sim, init)")
    only = list(only)
    if any(not 0 <= i < episodes for i in only):
        raise ValueError(f"--only {only}: indices must lie in [0, {episodes})")
    out = Path(out)
    rec = json.loads(out.read_text()) if out.exists() else {}
    if rec and rec.get("protocol") != protocol:
        raise ValueError(f"{out} holds protocol {rec.get('protocol')}, this run {protocol}: use another --out")
    rec.setdefault("rows", {})
    rec["protocol"] = protocol
    for name in drop:
        if name not in rec["rows"]:
            raise ValueError(f"--drop {name}: {out} has no such row (rows: {sorted(rec['rows'])})")
        del rec["rows"][name]
    for path in merge:
        other = json.loads(Path(path).read_text())
        if other.get("protocol") != protocol:
            raise ValueError(f"--merge: {path} holds protocol {other.get('protocol')}, this run {protocol}")
        for name, row in other["rows"].items():
            rec["rows"][name] = merge_rows(rec["rows"][name], row, episodes) if name in rec["rows"] else row
        rec.update({k: other[k] for k in ("stability", "formulations") if k in other})
        rec.setdefault("commands", []).extend(other.get("commands", []))
    for name in ([] if merge else rows):
        log.info("row %s ...", name)
        row = evaluate_row(name, sim, states[only] if only else states, steps, network)
        rec["rows"][name] = {**row, **({"episode_index": only} if only else {}), "machine": machine()}
        log.info("row %s: %s", name, rec["rows"][name]["discounted_return"])
        write_record(out, rec)
    if formulations:
        rec["formulations"] = {**compare_formulations(sim, states[0], formulations), "machine": machine()}
    if stability_states:
        rec["stability"] = {"episodes": stability(sim, states, steps, stability_states, seed), "machine": machine()}
    rec["table"] = table(rec["rows"], episodes)
    rec.setdefault("commands", []).append(command)
    write_record(out, rec)
    return rec
