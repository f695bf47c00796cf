"""The gap table: every classical controller against the perfect-foresight optimum, on the same test states.

    python -m anm_torchrl.baselines.optimal --episodes 4 --seed 0 --steps 3000 --out results/optimal_gap.json
    python -m anm_torchrl.baselines.optimal --rows acmpc_16 --out results/optimal_gap.json   # add a row

Rows (``--rows``, comma-separated): ``optimal`` (:class:`~anm_torchrl.baselines.optimal.OptimalPolicy`),
``acmpc_<N>`` (AC-MPC, perfect forecast), ``mpc_<N>`` (gym-anm's DC-OPF MPC, perfect forecast, β = 0.92),
``do_nothing``. Every row is evaluated by :func:`~anm_torchrl.training.evaluation.evaluate_policy` on ``ANM6Env``
from the states ``draw_initial_states(episodes, seed)`` (seed 0: the PPO recipe's test states), deterministic,
T = ``steps``, γ = 0.995. ``stability`` re-solves the first states' optimum from the do-nothing and a random warm
start. An existing ``--out`` record of the same protocol keeps its other rows (rows can be measured in separate
runs). The record also holds, per state, the optimum's IPOPT status, KKT residuals, rounds, solve times and its
float64 replay through ``ANM6Env``; and each row's loss as a percentage of the optimum's
(``loss_pct_of_optimum`` = 100 · return / optimum's return: 100 % is optimal, 200 % loses twice as much).
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


def _policy(name: str, sim, steps: int):
    from anm_torchrl.baselines import make_baseline

    if name == "optimal":
        return make_baseline("optimal", sim, horizon=steps)
    if name == "do_nothing":
        return make_baseline("do_nothing", sim)
    m = re.fullmatch(r"(acmpc|mpc)_(\d+)", name)
    if m is None:
        raise ValueError(f"unknown row {name!r}; expected optimal, do_nothing, acmpc_<N> or mpc_<N>")
    if m.group(1) == "acmpc":
        return make_baseline("acmpc", sim, horizon=int(m.group(2)), forecast="perfect")
    return make_baseline("mpc_perfect", sim, horizon=int(m.group(2)), safety_margin=MPC_MARGIN, gamma=GAMMA)


def _machine() -> dict:
    return {"platform": platform.platform(), "cpus": os.cpu_count(), "load_avg_1_5_15": list(os.getloadavg()),
            "torch_threads": torch.get_num_threads()}


def evaluate_row(name: str, sim, states: torch.Tensor, steps: int) -> dict:
    """One row: per-episode discounted returns and timings of policy ``name`` on ``ANM6Env``."""
    from anm_torchrl.baselines.optimal import replay_in_env
    from anm_torchrl.training.evaluation import evaluate_policy

    pol = _policy(name, sim, steps)
    t0, c0, load0 = time.perf_counter(), time.process_time(), os.getloadavg()[0]
    res = evaluate_policy(pol, states, max_steps=steps, gamma=GAMMA)
    row = {"discounted_return": res.discounted_returns.tolist(), "return": res.returns.tolist(),
           "terminated": res.terminated.tolist(), "mean_discounted_return": float(res.discounted_returns.mean()),
           "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
           "load_avg_1min": [load0, os.getloadavg()[0]]}
    if name.startswith("acmpc"):
        row["solve_time_s"] = {"mean": float(np.mean(pol.solve_times)), "max": float(np.max(pol.solve_times)),
                               "count": len(pol.solve_times)}
    if name == "optimal":
        plans = []
        for plan, s in zip(pol.plans, states):
            env = replay_in_env(plan.setpoints, s.numpy(), GAMMA, sim)
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


def table(rows: dict) -> list[dict]:
    """Mean return and loss as % of the optimum's per row (empty percentages without an ``optimal`` row), best
    first."""
    opt = np.asarray(rows["optimal"]["discounted_return"]) if "optimal" in rows else None
    out = []
    for name, r in rows.items():
        ret = np.asarray(r["discounted_return"])
        pct = 100.0 * ret / opt if opt is not None else None
        out.append({"policy": name, "mean_discounted_return": float(ret.mean()),
                    "loss_pct_of_optimum": None if pct is None else float(np.mean(pct)),
                    "loss_pct_of_optimum_per_episode": None if pct is None else pct.tolist()})
    return sorted(out, key=lambda t: -t["mean_discounted_return"])


def markdown(rec: dict) -> str:
    """The gap table of a record as Markdown: per row the mean return, per-episode returns and loss vs optimum."""
    rec = {**rec, "table": table(rec["rows"])}
    lines = ["| policy | discounted return (mean) | per episode | loss, % of the optimum's |", "|---|---|---|---|"]
    for t in rec["table"]:
        per = ", ".join(f"{v:.4f}" for v in rec["rows"][t["policy"]]["discounted_return"])
        pct = "–" if t["loss_pct_of_optimum"] is None else f"{t['loss_pct_of_optimum']:.1f} %"
        lines.append(f"| {t['policy']} | {t['mean_discounted_return']:.4f} | {per} | {pct} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m anm_torchrl.baselines.optimal", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=4, help="number of test states (default 4)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the test states (default 0, the test seed)")
    ap.add_argument("--steps", type=int, default=3000, help="episode length T (default 3000)")
    ap.add_argument("--rows", default=",".join(DEFAULT_ROWS), help="comma-separated rows (default: all)")
    ap.add_argument("--stability", type=int, default=0,
                    help="re-solve the optimum of this many first states from every warm start (default 0)")
    ap.add_argument("--formulations", type=int, default=0,
                    help="time polar vs rectangular voltages on the first state over this many steps (default 0: no)")
    ap.add_argument("--merge", nargs="*", default=[],
                    help="records of the same protocol (e.g. rows measured in parallel runs) whose rows are merged "
                         "into --out")
    ap.add_argument("--markdown", action="store_true", help="print the record's table as Markdown and exit")
    ap.add_argument("--out", required=True, help="JSON record (rows of an existing record are kept)")
    args = ap.parse_args(argv)
    if args.markdown:
        sys.stdout.write(markdown(json.loads(Path(args.out).read_text())) + "\n")
        return {}
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    torch.set_num_threads(1)
    from anm_torchrl.grid.simulator import anm6_easy_simulator
    from anm_torchrl.training.evaluation import draw_initial_states

    sim = anm6_easy_simulator()
    states = draw_initial_states(args.episodes, args.seed, sim)
    protocol = {"network": "anm6_easy", "episodes": args.episodes, "seed": args.seed, "steps": args.steps,
                "gamma": GAMMA, "states": "training.evaluation.draw_initial_states(episodes, seed)"}
    out = Path(args.out)
    rec = json.loads(out.read_text()) if out.exists() else {}
    if rec and rec.get("protocol") != protocol:
        raise SystemExit(f"{out} holds protocol {rec.get('protocol')}, this run {protocol}: use another --out")
    rec.setdefault("rows", {})
    rec["protocol"] = protocol
    for path in args.merge:
        other = json.loads(Path(path).read_text())
        if other.get("protocol") != protocol:
            raise SystemExit(f"--merge: {path} holds protocol {other.get('protocol')}, this run {protocol}")
        rec["rows"].update(other["rows"])
        rec.update({k: other[k] for k in ("stability", "formulations") if k in other})
        rec.setdefault("commands", []).extend(other.get("commands", []))
    for name in [r for r in args.rows.split(",") if r and not args.merge]:
        log.info("row %s ...", name)
        rec["rows"][name] = {**evaluate_row(name, sim, states, args.steps), "machine": _machine()}
        log.info("row %s: %s", name, rec["rows"][name]["discounted_return"])
        _write(out, rec)
    if args.formulations:
        rec["formulations"] = {**compare_formulations(sim, states[0], args.formulations), "machine": _machine()}
    if args.stability:
        rec["stability"] = {"episodes": stability(sim, states, args.steps, args.stability, args.seed),
                            "machine": _machine()}
    rec["table"] = table(rec["rows"])
    rec.setdefault("commands", []).append("python -m anm_torchrl.baselines.optimal " + " ".join(
        argv if argv is not None else sys.argv[1:]))
    _write(out, rec)
    return rec


def _write(path: Path, rec: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(rec, indent=1) + "\n")
    os.replace(tmp, path)
