"""The published gap table: a gap record (:mod:`anm_torchrl.experiments.gap`) combined with the PPO rows measured on
the same test states, rendered as a Markdown block per network into README and the docs.

``python -m anm_torchrl.cli.gap --combine rec.json [--test-returns ...|--ppo ...] --readme <pages>
--out results/gap/optimal_gap_table[_<network>].json`` calls :func:`combine` and :func:`update_pages`.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from anm_torchrl.experiments.formatting import marked_block, replace_marked_blocks
from anm_torchrl.experiments.gap import ANM6, MPC_MARGIN, MPC_ROW, MPC_VARIANT, covered, table
from anm_torchrl.experiments.records import current_path

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
    return marked_block(*block_markers(network))


README_BLOCK = readme_block(ANM6)


def _label(name: str) -> str:
    k = re.fullmatch(r"optimal(\d+)_then_do_nothing", name)
    if k:
        return f"the {k.group(1)}-step optimum, then do-nothing (a lower bound of the optimum)"
    m = MPC_ROW.fullmatch(name)
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
    m = re.fullmatch(r"(optimal\d+_then_do_nothing|acmpc|mpc)_?(\d*)" + MPC_VARIANT, row)
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
        by_state = dict(zip(covered(r, n), r["discounted_return"])) if r else {}
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
    """Another network: the PPO rows of the payoff study's PPO part (``data.ppo`` of
    ``results/payoff/inputs/ppo_<network>.json``), whose test states must be the gap record's: same network, seed,
    count, T and γ, and the same do-nothing return on them (1e-9 relative; a different state draw would change it)."""
    from anm_torchrl.experiments.ppo_runs import aggregate

    dn = ppo["test_baselines"].get("do_nothing") or {}
    want = {"network": pr["network"], "episodes": n, "test_seed": int(pr["seed"]), "max_steps": int(pr["steps"]),
            "gamma": float(pr["gamma"])}
    got = {"network": ppo["network"], **{k: dn.get(k) for k in ("episodes", "test_seed", "max_steps", "gamma")}}
    if got != want:
        raise ValueError(f"combine: the PPO record's test protocol {got} differs from the gap record's {want}")
    mine = gap_rows.get("do_nothing")
    if mine is None or covered(mine, n) != list(range(n)):
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
            record: str = "results/gap/optimal_gap_table.json") -> dict:
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
    if opt is None or len(covered(opt, n)) != n:
        raise ValueError("combine: the gap record needs an 'optimal' row on all of its states")
    opt_mean = float(np.mean(opt["discounted_return"]))
    # the states every gap row covers: there all of them compare on equal terms
    common = sorted(set.intersection(*(set(covered(r, n)) for r in rows_in.values())))
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
        src = {"file": "results/reproduction/test_returns.json",
               "git_commit": (meta.get("versions") or {}).get("git_commit"),
               "date": meta.get("date")}
    if ppo is not None:
        rows += _payoff_ppo_rows(ppo["data"]["ppo"], rows_in, pr, n, opt_mean, gain)
        src = {"file": f"results/payoff/inputs/ppo_{pr['network']}.json",
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
    src = f"_From `{current_path(table_rec.get('record', 'results/gap/optimal_gap_table.json'))}`"
    ps = table_rec.get("ppo_source")
    if ps:
        what = "PPO and β = 0.96 rows" if ps["file"].endswith("test_returns.json") else "PPO rows"
        src += f" ({what}: `{current_path(ps['file'])}`, git commit `{str(ps['git_commit'])[:7]}`)"
    return "\n".join(lines) + "\n\n" + src + "._\n"


def update_pages(pages: list[str | Path], table_rec: dict) -> None:
    """Rewrite the network's gap block (:func:`readme_block`) of every page; a page without it is an error."""
    replace_marked_blocks(pages, *block_markers(network_of(table_rec["protocol"])), render_block(table_rec))

