"""The leaderboard of a network: trained controllers (any algorithm, any training env) next to the optimum, the MPC
baselines and do-nothing, every row on the **same** test states as the network's gap table.

The baseline rows come from the committed gap table (``results/gap/optimal_gap_table[_<network>].json``: the
perfect-foresight AC optimum, AC-MPC, DC-MPC, do-nothing on ``protocol.episodes`` states of seed
``protocol.seed``, T = ``protocol.steps``, γ = ``protocol.gamma``). A trained row is a training run directory
(``summary.json`` + ``checkpoints/best.pt``, chosen on that run's validation states): its ``best.pt`` is evaluated
here on the gap table's states with the same protocol, so every number of a row is measured on identical
episodes. Runs of one (algorithm, training env) are one row: mean and spread over seeds, true-env training frames
(a surrogate-trained run used 0; SHAC's model transitions are shown beside them), wall time (surrogate training
included when it happened in the run).

Columns: discounted return; loss ratio to the optimum (returns < 0: R / R_opt, 1 is optimal); share of the
optimum's gain over do-nothing, 100 (R − R_dn) / (R_opt − R_dn).
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path

from anm_torchrl.evaluation import draw_initial_states, evaluate_policy
from anm_torchrl.experiments.formatting import replace_marked_blocks
from anm_torchrl.experiments.records import RESULTS

ANM6 = "anm6_easy"


def gap_table_path(network: str) -> Path:
    """The committed gap table of ``network``."""
    name = "optimal_gap_table.json" if network == ANM6 else f"optimal_gap_table_{network}.json"
    return RESULTS / "gap" / name


def baseline_rows(gap_table: dict) -> list[dict]:
    """The gap table's rows measured on all of its states (partial rows, e.g. AC-MPC on state #0 only, are left
    out: they do not compare)."""
    n = int(gap_table["protocol"]["episodes"])
    return [{"policy": r["policy"], "row": r["row"], "discounted_return": r["discounted_return"], "seeds": None,
             "frames": None, "wall_s": None, "source": "gap table"}
            for r in gap_table["rows"] if r.get("states") == n and r.get("source") == "gap"]


def reference_returns(network: str, gap_table: dict) -> tuple[float, float]:
    """The optimum's and do-nothing's discounted returns in ``network``'s gap table (rows on all its states).

    Raises:
        ValueError: the table lacks either row on all its states.
    """
    by = {r["row"]: r["discounted_return"] for r in baseline_rows(gap_table)}
    if "optimal" not in by or "do_nothing" not in by:
        raise ValueError(f"the gap table of {network!r} has no optimum or do-nothing row on all its states")
    return by["optimal"], by["do_nothing"]


def against_optimum(ret: float, opt: float, dn: float) -> tuple[float | None, float]:
    """(loss ratio, gain %) of the discounted return ``ret`` against the optimum's ``opt`` and do-nothing's ``dn``:
    ``ret / opt`` where both are losses (``opt`` < 0, else None), and the share of the optimum's gain over
    do-nothing in %."""
    return (ret / opt if opt < 0 else None), 100 * (ret - dn) / (opt - dn)


def evaluate_run(run_dir: str | Path, protocol: dict) -> dict:
    """``best.pt`` of a training run evaluated on the gap table's states; with the run's frames and wall time (s,
    without the seconds a study spent tracking the test states during training)."""
    from anm_torchrl.training.checkpoint import load_actor, load_checkpoint
    from anm_torchrl.training.factory import make_true_env

    run_dir = Path(run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    track_s = float(summary.get("track_seconds", 0.0))  # a study's test tracking (eval.track_test), not training
    ckpt = load_checkpoint(run_dir / "checkpoints" / "best.pt")
    network = ckpt["config"].get("network", ANM6)
    if network != protocol.get("network", ANM6):
        raise ValueError(f"{run_dir} was trained on {network!r}, the table is of {protocol.get('network', ANM6)!r}")
    n, seed = int(protocol["episodes"]), int(protocol["seed"])
    env = make_true_env(n, network=network, seed=seed)
    states = draw_initial_states(n, seed, env.sim, env.init)
    actor = load_actor(ckpt, env=make_true_env(1, network=network))
    result = evaluate_policy(actor, states, max_steps=int(protocol["steps"]), gamma=float(protocol["gamma"]), env=env)
    surrogate = ckpt["config"]["surrogate"]["name"]
    if (ckpt["config"].get("model") or {}).get("dynamics") == "pinn":  # SHAC through the PINN (surrogate unread)
        surrogate = "pinn"
    warm = summary.get("warm_start") or {}  # a teacher trained first (warm_start.algorithm); its time is in wall_time
    return {"run_dir": str(run_dir), "algorithm": ckpt["algorithm"], "surrogate": surrogate,
            "warm_start": warm.get("algorithm"), "warm_start_model_frames": warm.get("model_frames"),
            "seed": int(ckpt["config"]["seed"]), "discounted_return": float(result.discounted_returns.mean()),
            "per_episode": result.discounted_returns.tolist(), "best_frames": int(ckpt["frames"]),
            "frames": int(summary["frames"]), "true_env_frames": int(summary["frames"]) if surrogate == "none" else 0,
            "model_frames": summary.get("model_frames"),  # SHAC: transitions of the model it differentiates
            "wall_s": float(summary["wall_time"]) - track_s, "track_s": track_s,  # the recipe's own time
            "stopped_early": bool(summary["stopped_early"])}


def group_of(run: dict) -> tuple[str, str, str]:
    """A run's row: (algorithm, training env, the algorithm of its warm start or "")."""
    return run["algorithm"], run["surrogate"], run.get("warm_start") or ""


def trained_rows(runs: list[dict]) -> list[dict]:
    """One row per (algorithm, training env): mean over its seeds, with the spread."""
    groups: dict[tuple[str, str, str], list[dict]] = {}
    for r in runs:
        groups.setdefault(group_of(r), []).append(r)
    rows = []
    for (algorithm, surrogate, warm), rs in sorted(groups.items()):
        values = [r["discounted_return"] for r in rs]
        model_frames = [r.get("model_frames") or r.get("warm_start_model_frames") for r in rs]
        model_frames = [m for m in model_frames if m is not None]
        if model_frames and not warm:  # trained through a differentiable model's gradients, not on sampled rewards
            where = "the exact simulator" if surrogate == "none" else f"the {surrogate} surrogate"
            policy = f"{algorithm.upper()} through {where}'s gradients"
        else:
            where = "the true env" if surrogate == "none" else f"the {surrogate} surrogate"
            policy = f"{algorithm.upper()} trained on {where}"
        if warm:  # the teacher's model transitions are the row's model frames
            policy += f", started from {warm.upper()} through its gradients"
        rows.append({"policy": policy, "row": f"{algorithm}_{surrogate}" + (f"_from_{warm}" if warm else ""),
                     "model_frames": statistics.fmean(model_frames) if model_frames else None,
                     "discounted_return": statistics.fmean(values),
                     "std_over_seeds": statistics.stdev(values) if len(values) > 1 else None,
                     "seeds": sorted(r["seed"] for r in rs), "per_seed": values,
                     "frames": statistics.fmean(r["true_env_frames"] for r in rs),
                     "wall_s": statistics.fmean(r["wall_s"] for r in rs), "source": "runs"})
    return rows


def kept_runs(record: dict, protocol: dict, source: str) -> list[dict]:
    """The evaluated runs of an earlier leaderboard ``record`` (read from ``source``) of the same protocol, each
    naming ``kept_from`` (:func:`build` drops those of the groups it re-runs).

    Raises:
        ValueError: ``record`` was measured on another protocol (network, states, T, γ) than ``protocol``.
    """
    if record.get("protocol") != protocol:
        raise ValueError(f"{source} was measured on protocol {record.get('protocol')}, not the gap table's "
                         f"{protocol}: its runs cannot be kept")
    return [{**r, "kept_from": r.get("kept_from", source)} for r in record.get("runs", [])]


def build(network: str, run_dirs: list[str | Path], gap_table: dict | None = None,
          keep: dict | None = None, keep_source: str = "the kept record") -> dict:
    """The leaderboard record of ``network``: baseline rows, trained rows, ratios. ``keep``: an earlier record (read
    from ``keep_source``) whose runs of the (algorithm, training env) groups not in ``run_dirs`` are kept
    (:func:`kept_runs`): a row re-made without re-training the others; a group given again is replaced, not merged."""
    gap_table = gap_table if gap_table is not None else json.loads(gap_table_path(network).read_text())
    protocol = gap_table["protocol"]
    # the earlier record first: a wrong one fails before the runs' evaluations (minutes), not after them
    earlier = kept_runs(keep, protocol, keep_source) if keep is not None else []
    runs = [evaluate_run(d, protocol) for d in run_dirs]
    replaced = {group_of(r) for r in runs}
    runs = [r for r in earlier if group_of(r) not in replaced] + runs
    opt, dn = reference_returns(network, gap_table)
    rows = baseline_rows(gap_table) + trained_rows(runs)
    for r in rows:
        r["loss_ratio"], r["gain_pct"] = against_optimum(r["discounted_return"], opt, dn)
    rows.sort(key=lambda r: -r["discounted_return"])
    return {"network": network, "protocol": protocol, "rows": rows, "runs": runs,
            "gap_table": str(gap_table_path(network).relative_to(RESULTS.parent))}


def markdown(record: dict) -> str:
    """The leaderboard as a Markdown table."""
    p = record["protocol"]
    lines = [f"{record['network']}: {p['episodes']} test states (seed {p['seed']}), T = {p['steps']:,}, "
             f"γ = {p['gamma']}; trained rows: `best.pt` (chosen on validation states) evaluated on these states",
             "", "| policy | discounted return | loss / optimum | gain share | true-env frames | wall time | seeds |",
             "|---|---:|---:|---:|---:|---:|---|"]
    # feeders' returns are O(0.1) (line losses): two decimals would show the optimum and PPO alike
    dec = 2 if max(abs(r["discounted_return"]) for r in record["rows"]) >= 10 else 4
    for r in record["rows"]:
        spread = f" ± {r['std_over_seeds']:.{dec}f}" if r.get("std_over_seeds") is not None else ""
        ratio = f"{r['loss_ratio']:.3f}×" if r["loss_ratio"] is not None else "–"
        frames = f"{r['frames']:,.0f}" if r["frames"] is not None else "–"
        if r.get("model_frames") is not None:
            frames += f" ({r['model_frames']:,.0f} model)"
        wall = f"{r['wall_s']:,.0f} s" if r["wall_s"] is not None else "–"
        seeds = ", ".join(map(str, r["seeds"])) if r["seeds"] else "–"
        lines.append(f"| {r['policy']} | {r['discounted_return']:.{dec}f}{spread} | {ratio} | {r['gain_pct']:.2f} % | "
                     f"{frames} | {wall} | {seeds} |")
    return "\n".join(lines) + "\n"


def block_markers(network: str) -> tuple[str, str]:
    """The markers of a network's leaderboard block in README and the docs."""
    return f"<!-- leaderboard:{network} -->", f"<!-- /leaderboard:{network} -->"


def update_pages(pages: list[str | Path], record: dict) -> None:
    """Replace the network's leaderboard block of every page with :func:`markdown` of ``record``; every page is
    checked for the block before any is written.

    Raises:
        ValueError: a page without the block (nothing is written then).
    """
    body = markdown(record) + f"\n_From `results/leaderboard/{record['network']}.json`._\n"
    replace_marked_blocks(pages, *block_markers(record["network"]), body)
