"""The payoff study's record in words and tables (:mod:`anm_torchrl.experiments.payoff` measures and merges it):
the cost table with its crossovers, the PINN's accuracy table, the PPO runs' tables and the generated verdicts
that ``docs/RESULTS.md`` and README show."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from anm_torchrl.experiments.payoff import ppo_parts
from anm_torchrl.experiments.records import current_path


def accuracy_table(acc: dict) -> str:
    """Markdown table of the generic PINN's record (:mod:`anm_torchrl.surrogates.pinn.generic_accuracy`): per
    network, the chord-Newton steps after the power balance (:mod:`anm_torchrl.surrogates.pinn.refine`), test-transition
    |V| MAE, power-flow residual and largest device P/Q MAE relative to its rating (random / expert), the terminal
    check's precision/recall on random transitions, and the training's CPU and wall seconds."""
    def pair(e, k, fmt):
        return " / ".join("—" if e["eval"].get(s, {}).get(k) is None else fmt.format(e["eval"][s][k])
                          for s in ("random", "expert"))

    out = ["| network | buses | preset | chord steps | \\|V\\| MAE p.u. (random / expert) | power-flow residual p.u. | "
           "device P/Q MAE / rating (max) | terminal precision / recall (random; sim rate; PINN rate) | "
           "meets targets | train CPU s (wall s, load) |",
           "|---|---:|---|---:|---|---|---|---|---|---|"]
    for e in acc.get("networks", []):
        r = e["eval"].get("random", {})
        meets = all(all(v for v in m.values()) for m in e.get("meets_targets", {}).values())
        out.append(f"| {e['network']} | {e['n_bus']} | {e['preset']} | {_f(e.get('refine_steps'), '{}')} | "
                   f"{pair(e, 'vmag_mae_pu', '{:.1e}')} | {pair(e, 'pf_residual_mean', '{:.1e}')} | "
                   f"{pair(e, 'next_pq_rel_mae_max', '{:.1e}')} | {_f(r.get('terminal_precision'), '{:.2f}')} / "
                   f"{_f(r.get('terminal_recall'), '{:.2f}')} ({_f(r.get('terminal_rate_sim'), '{:.2%}')}; "
                   f"{_f(r.get('terminal_rate_pinn'), '{:.2%}')}) | "
                   f"{'yes' if meets else 'no'} | {e['train_cpu_s']:,.0f} ({e['train_wall_s']:,.0f}, "
                   f"L{e['loadavg_before'][0]:.0f}) |")
    return "\n".join(out)


def readme_pinn_accuracy(res: dict[str, Any]) -> str:
    """README's PINN-accuracy block (``<!-- results:pinn_accuracy -->``, :mod:`.readme_blocks`): the accuracy
    table of the payoff record's ``pinn_accuracy`` part (a copy of ``results/pinn/pinn_generic_accuracy.json``)."""
    rec = res.get("payoff")
    acc = ((rec or {}).get("data") or {}).get("pinn_accuracy") or {}
    if not acc.get("available"):
        return "_(PINN accuracy not measured)_"
    nets = acc["data"].get("networks", [])
    n_rand = sorted({e["eval"]["random"]["n"] for e in nets if "random" in e["eval"]})
    n_exp = sorted({e["eval"]["expert"]["n"] for e in nets if "expert" in e["eval"]})
    head = (f"Held-out test transitions ({'/'.join(f'{n:,}' for n in n_rand)} random, "
            f"{'/'.join(f'{n:,}' for n in n_exp)} MPC-expert; seed 12345), physics-only training with each "
            "network's default preset; chord steps: chosen per network by the rule of "
            "`anm_torchrl/surrogates/pinn/refine.py` (—: not recorded, an entry measured before the rule); terminal "
            "figures on the random set (—: no terminal transition to recall, or none flagged):")
    return (f"{head}\n\n{accuracy_table(acc['data'])}\n\n_From `results/payoff/payoff.json` (its `pinn_accuracy` "
            f"part, read from `{_accuracy_path(acc)}`, whose `command` field reproduces each row)._")


def _accuracy_path(acc: dict) -> str:
    """Where the PINN accuracy record a payoff record's ``pinn_accuracy`` part was read from lives now."""
    return current_path(f"results/{Path(acc['file']).name}")


def cost_verdict(rec: dict) -> str:
    """The cost and accuracy findings of a ``payoff`` record in words (generated; the PPO part is not read):
    the cheapest implementation per network and batch, the crossovers, and which networks' PINN meets the
    accuracy targets."""
    d = rec.get("data") or {}
    rows = [r for r in d.get("rows") or [] if r.get("us_per_transition") and not r.get("lower_bound")]
    out = []
    if rows:
        parts = []
        for b in sorted({r["batch"] for r in rows}):
            best = {}
            for r in rows:
                if r["batch"] == b and (r["network"] not in best
                                        or r["us_per_transition"] < best[r["network"]]["us_per_transition"]):
                    best[r["network"]] = r
            nets = sorted(best.values(), key=lambda r: r["n_bus"])
            parts.append(f"batch {b:,}: " + ", ".join(f"{r['impl']} on {r['network']} ({r['us_per_transition']:,.1f} µs)"
                                                   for r in nets))
            parts[-1] += "".join(f" (undetermined against {q['impl']}, whose lower bound is {q['us_per_transition']:,.1f} µs)"
                                 for q in d.get("rows") or [] if q.get("lower_bound") and q["batch"] == b
                                 and q["us_per_transition"] and q["network"] in best
                                 and q["us_per_transition"] < best[q["network"]]["us_per_transition"])
        out.append("Cheapest per transition — " + "; ".join(parts) + ".")
        cross = [c for c in d.get("crossover", []) if c["crossover_n_bus"]]
        out.append("Crossover: " + ("; ".join(f"{c['impl']} at batch {c['batch']:,} from {c['crossover_n_bus']} buses"
                                             for c in cross) if cross else
                                   "none — no surrogate is cheaper per transition than the cheaper exact backend at "
                                   "any network and batch measured") + ".")
        out.append("For cost alone, a user should " + (
            "train on the exact batched simulator (`make_env(\"none\", network=...)`, numba): on every network and "
            "batch measured it is the cheapest env, and a surrogate needs training before its first step."
            if not cross else "prefer the surrogate only where a crossover is listed above, and count its training "
            "time; elsewhere the exact batched simulator is cheaper."))
    acc = d.get("pinn_accuracy") or {}
    if acc.get("available"):
        nets = acc["data"].get("networks", [])
        ok = [e["network"] for e in nets
              if all(all(v for v in m.values()) for m in e.get("meets_targets", {}).values())]
        miss = [e["network"] for e in nets if e["network"] not in ok]
        out.append(f"The PINN (physics only) meets the |V| ≤ 1e-3 p.u. and device P/Q ≤ 1 % of rating targets on "
                   f"held-out test transitions on {', '.join(ok) or 'no network'}"
                   + (f"; not on {', '.join(miss)}" if miss else "") + ".")
    return " ".join(out)


def _f(x, fmt="{:,.1f}") -> str:
    return "—" if x is None else fmt.format(x)


def markdown(rec: dict) -> str:
    """The study's tables (cost per transition, crossover, PINN accuracy, PPO) from a ``payoff`` record."""
    d, out = rec.get("data") or {}, []
    rows = d.get("rows") or []
    if rows:
        batches = sorted({r["batch"] for r in rows})
        impls = list(dict.fromkeys(r["impl"] for r in rows))
        nets = sorted(dict.fromkeys((r["network"], r["n_bus"]) for r in rows), key=lambda x: x[1])
        cols = [(i, b) for b in batches for i in impls if any(r["impl"] == i and r["batch"] == b for r in rows)]
        out += ["Cost per transition, µs (× numba at the same network and batch; 1-min load average when measured):",
                "", "| network | buses | " + " | ".join(f"{i} b={b:,}" for i, b in cols) + " |",
                "|---|---:|" + "---:|" * len(cols)]
        for net, nb in nets:
            cells = []
            for i, b in cols:
                r = next((r for r in rows if r["network"] == net and r["impl"] == i and r["batch"] == b), None)
                if r is None:
                    cells.append("")
                elif r["us_per_transition"] is None:
                    cells.append("skipped" if r.get("skipped") else "n/a")
                else:
                    ge = "≥ " if r.get("lower_bound") else ""
                    cells.append(f"{ge}{r['us_per_transition']:,.1f} ({ge}{r['x_numba']:.2f}×; "
                                 f"L{r['load_avg_1min']:.0f})")
            out.append(f"| {net} | {nb} | " + " | ".join(cells) + " |")
        # no machine-local paths in the docs: the record keeps the full reason
        reasons = sorted({f"{r['impl']} on {r['network']}: " + re.sub(r"\S*/\S*", "<path>", r["reason"].split(";")[0])
                          for r in rows if r.get("reason")})
        if reasons:
            out += ["", "Not measured (no trained model for that network):", ""] + [f"- {x}" for x in reasons]
        bounds = sorted({f"{r['impl']} on {r['network']}: {r['lower_bound']}" for r in rows if r.get("lower_bound")})
        if bounds:
            out += ["", "≥: a lower bound, not the model's own cost —", ""] + [f"- {x}" for x in bounds]
        out += ["", "Crossover (smallest bus count where the surrogate is cheaper than the cheaper exact backend):", "",
                "| surrogate | batch | crossover buses | measured at buses |", "|---|---:|---:|---|"]
        for c in d.get("crossover", []):
            out.append(f"| {c['impl']} | {c['batch']:,} | {c['crossover_n_bus'] if c['crossover_n_bus'] else 'none'}"
                       f" | {', '.join(map(str, c['measured_n_bus'])) or 'nowhere'} |")
    acc = d.get("pinn_accuracy")
    if acc is not None:
        out += ["", "PINN accuracy vs bus count: " + (f"from `{_accuracy_path(acc)}`." if acc["available"]
                                                     else re.sub(r"\S*/(\S+)", r"\1", acc["reason"]))]
        if acc["available"]:
            out += ["", accuracy_table(acc["data"])]
    for ppo in ppo_parts(d):
        out += ppo_markdown(ppo)
    if ppo_parts(d):
        out += ["", f"**What this means for a user.** {user_verdict(rec)}"]
    return "\n".join(out)


def ppo_markdown(ppo: dict) -> list[str]:
    """Lines of one network's PPO part: the runs' table, the test-state comparison and its verdict."""
    dn = ppo["do_nothing"]
    out = ["", f"PPO on `{ppo['network']}` (validation: {dn['episodes']} states × {dn['max_steps']} steps, seed "
           f"{dn['eval_seed']}); do-nothing return {dn['return']:.4f}; threshold = {ppo['threshold_fraction']} × "
           f"that = {ppo['threshold']:.4f}:", "",
           "| env | seeds | frames | wall s | best eval return | test return (best.pt) | reached | time to "
           "threshold s (KM median) | with surrogate training s | censored at s |",
           "|---|---|---|---|---|---|---:|---:|---:|---|"]
    for t in ppo["table"]:
        out.append(f"| {t['env']} | {t['seeds']} | {t['frames']} | {[round(x) for x in t['wall_s']]} | "
                   f"{[round(x, 4) for x in t['best_eval_return']]} | "
                   f"{[None if x is None else round(x, 4) for x in t['test_best_return']]} | "
                   f"{t['threshold_reached']}/{t['threshold_runs']} | {_f(t['threshold_wall_s'])} | "
                   f"{_f(t.get('threshold_wall_with_training_s'))} | "
                   f"{[round(x) for x in t['threshold_censored_at_s']]} |")
    tb = ppo.get("test_baselines") or {}
    if tb:
        any_tb = next(iter(tb.values()))
        out += ["", f"Test states ({any_tb['episodes']} states × {any_tb['max_steps']:,} steps, seed "
                f"{any_tb['test_seed']}, γ = {any_tb['gamma']}), discounted return and fraction of do-nothing's "
                "(< 0.5: at least 2× better than do-nothing; < 0: a net energy gain):", "",
                "| policy | discounted return | fraction of do-nothing | CPU s |", "|---|---|---|---|"]
        dn_t = (tb.get("do_nothing") or {}).get("discounted_return")
        for name, m in tb.items():
            frac = m["discounted_return"] / dn_t if dn_t else None
            out.append(f"| {name} | {m['discounted_return']:.4f} | {_f(frac, '{:.3f}')} | {m['cpu_s']:.0f} |")
        for t in ppo["table"]:
            if t.get("test_best_discounted_return"):
                out.append(f"| PPO {t['env']} (best.pt, seeds {t['seeds']}) | "
                           f"{[None if x is None else round(x, 4) for x in t['test_best_discounted_return']]} | "
                           f"{[None if x is None else round(x, 3) for x in t['test_fraction_of_do_nothing']]} | "
                           f"{[None if x is None else round(x) for x in t['cpu_s']]} |")
        out += ["", ppo_verdict(ppo)]
    return out


def ppo_verdict(ppo: dict) -> str:
    """The PPO target in words, from a ``ppo`` part: per training env, the seeds whose best.pt is at least 2× better
    than do-nothing on the test states (fraction of do-nothing's discounted loss ≤ 0.5) and the time to the
    validation threshold, surrogate training included."""
    parts = []
    for t in ppo["table"]:
        fr = [x for x in t.get("test_fraction_of_do_nothing") or [] if x is not None]
        if not fr:
            continue
        ok = sum(x <= 0.5 for x in fr)
        wall = t.get("threshold_wall_with_training_s") or t.get("threshold_wall_s")
        when = (f"median time {wall:,.0f} s with the surrogate's training ({_f(t.get('surrogate_train_s'), '{:,.0f}')}"
                " s)" if wall is not None else "no median time (fewer than half the runs reached it; the surrogate's "
                f"training: {_f(t.get('surrogate_train_s'), '{:,.0f}')} s)")
        parts.append(f"PPO {t['env']}: {ok}/{len(fr)} seeds at least 2× better than do-nothing on the test states "
                     f"(fraction of its discounted loss {min(fr):.2f} to {max(fr):.2f}; < 0: a net energy gain), "
                     f"{t['threshold_reached']}/{t['threshold_runs']} reached the validation threshold, {when}")
    return f"Target (issue 13), `{ppo['network']}`: " + "; ".join(parts) + "." if parts else ""


def _ppo_summary(t: dict) -> str:
    """One training env's time to the threshold and test fractions, in words."""
    fr = [x for x in t.get("test_fraction_of_do_nothing") or [] if x is not None]
    med = t.get("threshold_wall_with_training_s")
    train = t.get("surrogate_train_s") or 0.0
    when = (f"reached the threshold in a median {med:,.0f} s" + (f" ({train:,.0f} s of it the surrogate's training)"
                                                               if train else "")
            if med is not None else
            f"{t['threshold_reached']}/{t['threshold_runs']} runs reached the threshold within their "
            f"≤ {max(t['wall_s']):,.0f} s" + (f", after {train:,.0f} s of surrogate training" if train else ""))
    frac = f" (test return {min(fr):.2f} to {max(fr):.2f} × do-nothing's loss)" if fr else ""
    return f"`{t['env']}` {when}{frac}"


def user_verdict(rec: dict) -> str:
    """"What this means for a user", generated from a payoff record: which env is cheapest per transition, where
    the PINN is accurate, and per PPO network whether training on the surrogate reached the threshold sooner than
    on the exact simulator once the surrogate's training is counted (KM medians; censored runs at their length)."""
    d = rec.get("data") or {}
    out = []
    cross = [c for c in d.get("crossover", []) if c["crossover_n_bus"]]
    nets = sorted({(r["n_bus"], r["network"]) for r in d.get("rows") or [] if r.get("us_per_transition")})
    if nets:
        out.append(f"Per transition, no surrogate is cheaper than the exact batched simulator on any network measured "
                   f"({nets[0][0]}–{nets[-1][0]} buses)" if not cross else
                   "Per transition, a surrogate is cheaper than the exact batched simulator only at " +
                   "; ".join(f"{c['impl']} batch {c['batch']:,} from {c['crossover_n_bus']} buses" for c in cross))
    pays = []
    for ppo in ppo_parts(d):
        tab = {t["env"]: t for t in ppo["table"]}
        if "none" not in tab:
            continue
        out.append(f"PPO on `{ppo['network']}`: " + "; ".join(_ppo_summary(t) for t in ppo["table"]))
        ref = tab["none"]
        for lab, t in tab.items():
            if lab == "none":
                continue
            a, b = t.get("threshold_wall_with_training_s"), ref.get("threshold_wall_with_training_s")
            if (a is not None and (b is None or a < b)) or t["threshold_reached"] > ref["threshold_reached"]:
                pays.append(f"`{lab}` on `{ppo['network']}`")
    if pays:
        out.append("Training on a surrogate paid off for " + ", ".join(pays) + "; elsewhere train on the exact "
                   "batched simulator")
    elif ppo_parts(d):
        out.append("On no network measured did training on a surrogate reach the threshold sooner (or more often) "
                   "than on the exact simulator once the surrogate's training is counted" + (
                       ", and no surrogate is cheaper per transition: a user of this package should train on the "
                       "exact batched simulator (`make_env(\"none\", network=...)`, `surrogate=none`)" if not cross
                       else ": the exact batched simulator stays the default (`surrogate=none`); where a surrogate is "
                       "cheaper per transition, its training (for a data-driven one, also its dataset) comes first "
                       "and its transitions are approximate"))
    return ". ".join(out) + "." if out else ""

