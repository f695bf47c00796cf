"""When a differentiable model pays off: true-env frames, model frames and wall time until a policy reaches a share
of the perfect-foresight optimum, for SHAC through the exact simulator, SHAC through the PINN, PPO and SAC, in one
campaign (issue 26, item 3).

Every cell is a recipe's documented command at its defaults with only ``seed`` set, plus the measurement keys
(run in-process through the recipe's own config and :func:`anm_torchrl.training.protocol.train`, one worker process
per cell, ``--jobs`` at a time; the record names the equivalent command line):
``eval.track_test=true`` evaluates the network's gap-table test states (the leaderboard's: ``protocol.episodes``
states of seed ``protocol.seed``, T = ``protocol.steps``, γ = ``protocol.gamma``) at every validation point, as
a measurement only (``best.pt`` is still chosen on the validation states; the tracking's time is kept out of the
curve's wall time). A threshold is a discounted return on those states:

* ANM6-Easy: a loss ratio to the optimum, R ≥ r · R_opt (R_opt < 0), r = 1.5 and 1.1;
* a feeder: a share of the optimum's gain over do-nothing, R ≥ R_dn + s (R_opt − R_dn), s = 90 % and 97 %.

A run's time to a threshold is its first validation point whose tracked test return reaches it; a run that never
does is censored at its end (Kaplan–Meier median over seeds, :mod:`.time_to_return`). SHAC through the PINN adds the
PINN's training (``recipes/train_pinn.py`` wall time, measured once in the campaign) to every one of its times.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

from anm_torchrl.experiments.cells import RECIPES, run_cells, shown, tested_states
from anm_torchrl.experiments.formatting import replace_marked_blocks
from anm_torchrl.experiments.leaderboard import ANM6, gap_table_path, reference_returns
from anm_torchrl.experiments.ppo_runs import time_to_reach
from anm_torchrl.experiments.time_to_return import censored_summary

log = logging.getLogger(__name__)

#: the clocks of a time to a threshold (a curve point's keys)
CLOCKS = ("wall_s", "frames", "true_env_frames")

#: method -> (recipe, its overrides, label); ``{pinn}`` is the campaign's PINN file
METHODS: dict[str, tuple[str, tuple[str, ...], str]] = {
    "shac_exact": ("shac.py", ("model=exact",), "SHAC through the exact simulator's gradients"),
    "shac_pinn": ("shac.py", ("model=pinn", "surrogate=pinn", "surrogate.path={pinn}"),
                  "SHAC through the PINN's gradients (PINN training counted)"),
    "ppo": ("ppo.py", ("surrogate=none",), "PPO on the true env"),
    "sac": ("sac.py", (), "SAC on the true env"),
}


def thresholds(network: str, gap_table: dict) -> list[dict[str, Any]]:
    """The study's thresholds on ``network``'s gap-table states: ``[{"name", "kind", "level", "return"}]``."""
    opt, dn = reference_returns(network, gap_table)
    if network == ANM6:
        return [{"name": f"{r}× the optimum's loss", "kind": "loss_ratio", "level": r, "return": r * opt}
                for r in (1.5, 1.1)]
    return [{"name": f"{s:.0%} of the optimum's gain", "kind": "gain_share", "level": s, "return": dn + s * (opt - dn)}
            for s in (0.90, 0.97)]


def cell_command(method: str, network: str, seed: int, run_dir: Path, protocol: dict, pinn: Path | None,
                 overrides: tuple[str, ...] = ()) -> list[str]:
    """The recipe command of one cell (its defaults, ``seed``, the tracking of the gap-table states, then
    ``overrides``: keys every cell of a campaign shares, e.g. a smaller budget for a smoke test)."""
    recipe, method_keys, _ = METHODS[method]
    return [sys.executable, str(RECIPES / recipe), f"network={network}", f"seed={seed}",
            *(k.format(pinn=pinn) for k in method_keys), "eval.track_test=true",
            f"eval.test_episodes={protocol['episodes']}", f"eval.test_seed={protocol['seed']}",
            f"eval.test_max_steps={protocol['steps']}", "logger.progress=false", *overrides, f"hydra.run.dir={run_dir}"]


def train_pinn(network: str, folder: Path) -> float:
    """Train ``network``'s default PINN preset into ``folder`` (unless there, trained on the same network data with
    the same preset) and return its training wall time (s), measured once and kept in ``folder/study_pinn.json``.
    One torch thread, as the recipes' ``threads`` default (the training's second process takes this one's count:
    two processes of two threads on two cores ran ~5x slower)."""
    import torch

    from anm_torchrl.grid.identity import network_key
    from anm_torchrl.networks import simulator
    from anm_torchrl.surrogates.pinn import cache, presets

    sim = simulator(network)
    cfg = presets.preset_for("default", sim)
    made = {"network": network, "network_key": network_key(sim), "preset": json.loads(json.dumps(cfg.to_dict()))}
    marker = folder / "study_pinn.json"
    if marker.is_file() and (folder / "pinn.safetensors").is_file():
        kept = json.loads(marker.read_text())
        if all(kept.get(k) == v for k, v in made.items()):
            return float(kept["wall_s"])
        log.info("%s was trained on other network data or another preset: trained again", folder)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        t0 = time.perf_counter()
        cache.train_and_save(cfg, sim, path=folder / "pinn.safetensors")
        wall = time.perf_counter() - t0
    finally:
        torch.set_num_threads(threads)
    marker.write_text(json.dumps({**made, "wall_s": wall}) + "\n")
    return wall


def read_run(run_dir: Path, protocol: dict) -> dict[str, Any]:
    """A finished cell: its curve (validation and tracked test returns), budget and test figures."""
    s = json.loads((run_dir / "summary.json").read_text())
    cell = json.loads((run_dir / "study_cell.json").read_text())
    test = s["test"]
    got = tested_states(s)
    want = {k: protocol[k] for k in got}
    if got != want or not s.get("curve") or any("test" not in p for p in s["curve"]):
        raise ValueError(f"{run_dir}: not a study cell (tracked test states {got}, the gap table's {want})")
    return {"run_dir": str(run_dir), "algorithm": s["algorithm"], "seed": int(s["config"]["seed"]),
            "curve": s["curve"], "frames": s.get("model_frames", s["frames"]), "true_env_frames": s["frames"],
            "budget_unit": s.get("budget_unit", "frames"), "wall_s": s["curve"][-1]["wall_s"],
            "stopped_early": s["stopped_early"], "test_best": test["best"]["discounted_return"],
            **{k: cell[k] for k in ("command", "process_wall_s", "load_avg_1min") if k in cell}}


def summarize(runs: list[dict], levels: list[dict], offset_s: float) -> list[dict[str, Any]]:
    """Per threshold, the censored summaries (wall time, frames of the budget's unit) over ``runs``."""
    out = []
    for th in levels:
        cells = [{"time_to_threshold": time_to_reach(r["curve"], th["return"], key="test", clocks=CLOCKS),
                  "curve": r["curve"]} for r in runs]
        out.append({"threshold": th["name"], "wall_s": censored_summary(cells, "wall_s", offset_s=offset_s),
                    "frames": censored_summary(cells, "frames"),
                    "per_seed": [c["time_to_threshold"] for c in cells]})
    return out


def kept_rows(keep: dict[str, Any] | None, network: str, protocol: dict, seeds: list[int], methods: list[str],
              overrides: tuple[str, ...], source: str) -> list[dict[str, Any]]:
    """The method rows of an earlier record ``keep`` (read from ``source``) that this campaign does not re-make
    (methods not in ``methods``), each marked ``kept_from``; none without ``keep``.

    Raises:
        ValueError: ``keep`` is not a record of this study, or of another network, test states, seeds or shared
            overrides (a kept row would then not compare with the re-made ones).
    """
    if keep is None:
        return []
    if not isinstance(keep.get("methods"), list):
        raise ValueError(f"{source}: not a record of the gradient study (no 'methods' list)")
    for key, want in (("network", network), ("protocol", protocol), ("seeds", seeds), ("overrides", list(overrides))):
        if keep.get(key) != want:
            raise ValueError(f"{source}: its {key} {keep.get(key)!r} is not this campaign's {want!r}; "
                             f"its rows cannot be kept")
    return [{**row, "kept_from": source} for row in keep["methods"] if row.get("method") not in methods]


def campaign(network: str, methods: list[str], seeds: list[int], runs_dir: Path, jobs: int = 2,
             overrides: tuple[str, ...] = (), keep: dict[str, Any] | None = None,
             keep_source: str = "the kept record") -> dict[str, Any]:
    """Run (or reuse) every cell, then the record: thresholds, per method its runs and time-to-threshold.

    ``keep``: an earlier record of this campaign (read from ``keep_source``); its rows of the methods not in
    ``methods`` are kept (marked ``kept_from``), so one method's cells are re-made after its defaults change without
    running the others again.
    """
    unknown = sorted(set(methods) - set(METHODS))
    if unknown:
        raise ValueError(f"unknown methods {unknown}; choose from {sorted(METHODS)}")
    gap = json.loads(gap_table_path(network).read_text())
    protocol, levels = gap["protocol"], thresholds(network, gap)
    kept = kept_rows(keep, network, protocol, seeds, methods, tuple(overrides), keep_source)
    runs_dir = Path(runs_dir).resolve()
    pinn_dir = runs_dir / f"pinn_{network}"
    pinn_s = train_pinn(network, pinn_dir) if "shac_pinn" in methods else 0.0
    cells = [(m, s, runs_dir / f"{network}_{m}_s{s}") for m in methods for s in seeds]
    commands = {d: cell_command(m, network, s, d, protocol, pinn_dir / "pinn.safetensors", tuple(overrides))
                for m, s, d in cells}
    t0 = time.perf_counter()
    failed = [o for o in run_cells(commands, jobs) if o["error"]]
    rows = []
    for m in methods:
        runs = [read_run(d, protocol) for mm, _, d in cells if mm == m and (d / "summary.json").is_file()]
        offset = pinn_s if m == "shac_pinn" else 0.0
        first = next(commands[d] for mm, _, d in cells if mm == m)
        rows.append({"method": m, "label": METHODS[m][2], "command": shown(first), "pinn_training_s": offset or None,
                     "runs": runs, "thresholds": summarize(runs, levels, offset)})
    rows = sorted(rows + kept, key=lambda r: list(METHODS).index(r["method"]))
    return {"what": __doc__.split("\n\n")[0].replace("\n", " "), "network": network, "protocol": protocol,
            "optimum": reference_returns(network, gap)[0],
            "thresholds": levels, "seeds": seeds, "jobs": jobs, "overrides": list(overrides),
            "invocation_wall_s": time.perf_counter() - t0, "failed": failed, "methods": rows,
            **({"kept_from": keep_source} if keep is not None else {}),
            "machine": {"cpus": os.cpu_count(), "threads_per_run": 1, "concurrent_runs": jobs}}


def _t(x: float | None, unit: str = "s") -> str:
    if x is None:
        return "–"
    return f"{x:,.0f} s" if unit == "s" else f"{x / 1e6:.2f}M" if x >= 1e5 else f"{x:,.0f}"


def markdown(record: dict) -> str:
    """The study's table of ``record`` (one network)."""
    p = record["protocol"]
    lines = [f"{record['network']}: {p['episodes']} test states (seed {p['seed']}), T = {p['steps']:,}, "
             f"γ = {p['gamma']}; optimum {record['optimum']:.4g}; {len(record['seeds'])} seeds, "
             f"{record['jobs']} runs at a time on {record['machine']['cpus']} cores. Median (Kaplan–Meier) over "
             "seeds; `–`: fewer than half reached it.",
             "", "| method | threshold | reached | median wall time | median frames (unit) | best.pt test return |",
             "|---|---|---:|---:|---:|---:|"]
    for row in record["methods"]:
        unit = "model" if any(r["budget_unit"] != "frames" for r in row["runs"]) else "true-env"
        best = [r["test_best"] for r in row["runs"]]
        best_s = f"{sum(best) / len(best):.4g}" if best else "–"
        for th in row["thresholds"]:
            w, f = th["wall_s"], th["frames"]
            lines.append(f"| {row['label']} | {th['threshold']} | {w['reached']}/{w['runs']} | {_t(w['median'])} | "
                         f"{_t(f['median'], 'f')} ({unit}) | {best_s} |")
    loads = [x for row in record["methods"] for r in row["runs"] for x in r.get("load_avg_1min", [])]
    pinn = [row["pinn_training_s"] for row in record["methods"] if row.get("pinn_training_s")]
    notes = []
    if pinn:
        notes.append(f"The PINN's training ({pinn[0]:,.0f} s, `recipes/train_pinn.py`, once) is added to every time "
                     "of SHAC through the PINN.")
    if loads:
        notes.append(f"1-minute load average at the cells' starts and ends: {min(loads):.1f}–{max(loads):.1f}.")
    kept = [row["label"] for row in record["methods"] if row.get("kept_from")]
    if kept:
        notes.append(f"Kept from an earlier campaign of this record (`--keep`, not re-run with the others): "
                     f"{'; '.join(kept)}.")
    lines += ["", " ".join(notes)] if notes else []
    return "\n".join(lines) + "\n"


def _times(ratio: float, fewer: str, more: str, same: str) -> str:
    """``ratio`` (PPO's / SHAC's) in words: ``fewer`` or ``more`` formatted with the factor (≥ 1, two significant
    digits), ``same`` where the factor would print as 1."""
    factor = ratio if ratio >= 1 else 1 / ratio
    if f"{factor:.2g}" == "1":
        return same
    return (fewer if ratio >= 1 else more).format(f"{factor:.2g}")


def verdict(records: list[dict]) -> str:
    """The generated verdict over the networks' records: where SHAC reached each threshold with fewer transitions
    and less wall time than PPO, and where not."""
    out = []
    for rec in records:
        by = {row["method"]: row for row in rec["methods"]}
        if "ppo" not in by:
            continue
        for i, th in enumerate(rec["thresholds"]):
            ppo = by["ppo"]["thresholds"][i]
            for m in ("shac_exact", "shac_pinn"):
                if m not in by:
                    continue
                sh = by[m]["thresholds"][i]
                head = f"{rec['network']}, {th['name']}: {by[m]['label']}"
                if sh["frames"]["median"] is None:
                    out.append(f"{head}: reached by fewer than half its runs ({sh['frames']['reached']}/"
                               f"{sh['frames']['runs']}); PPO {ppo['frames']['reached']}/{ppo['frames']['runs']}.")
                elif ppo["frames"]["median"] is None:
                    out.append(f"{head}: reached ({sh['frames']['reached']}/{sh['frames']['runs']}, median "
                               f"{_t(sh['wall_s']['median'])}, {_t(sh['frames']['median'], 'f')} model frames, 0 "
                               f"true-env frames); PPO did not within its budget ({ppo['frames']['reached']}/"
                               f"{ppo['frames']['runs']}).")
                else:
                    fewer = _times(ppo["frames"]["median"] / sh["frames"]["median"], "{}× fewer transitions",
                                   "{}× more transitions", "as many transitions")
                    faster = _times(ppo["wall_s"]["median"] / sh["wall_s"]["median"], "{}× faster in wall time",
                                    "PPO {}× faster in wall time", "as fast in wall time")
                    out.append(f"{head}: median {_t(sh['frames']['median'], 'f')} model frames and "
                               f"{_t(sh['wall_s']['median'])} against PPO's {_t(ppo['frames']['median'], 'f')} "
                               f"true-env frames and {_t(ppo['wall_s']['median'])}: {fewer}, {faster}.")
        out += ppo_best_lines(rec)
    return "\n".join(f"- {x}" for x in out) + "\n"


def ppo_best_lines(rec: dict) -> list[str]:
    """Issue 26's transitions target on one network's record: the frames each SHAC method and PPO itself took to
    reach PPO's best return (the mean of PPO's ``best.pt`` test returns), read off the tracked test curves."""
    by = {row["method"]: row for row in rec["methods"]}
    if not by.get("ppo", {}).get("runs"):
        return []
    best = sum(r["test_best"] for r in by["ppo"]["runs"]) / len(by["ppo"]["runs"])
    level = [{"name": "PPO's best", "return": best}]
    ppo = summarize(by["ppo"]["runs"], level, 0.0)[0]["frames"]
    out = []
    for m in ("shac_exact", "shac_pinn"):
        if m not in by:
            continue
        sh = summarize(by[m]["runs"], level, 0.0)[0]["frames"]
        head = (f"{rec['network']}, PPO's best return ({best:.4g}, the mean of its best.pt test returns): "
                f"{by[m]['label']} reached it in {sh['reached']}/{sh['runs']} runs")
        if sh["median"] is None:
            out.append(f"{head}, fewer than half (PPO's own runs: {ppo['reached']}/{ppo['runs']}).")
        elif ppo["median"] is None:
            out.append(f"{head}, median {_t(sh['median'], 'f')} model frames; PPO's own runs reached it in "
                       f"{ppo['reached']}/{ppo['runs']}, fewer than half.")
        else:
            out.append(f"{head}, median {_t(sh['median'], 'f')} model frames against PPO's "
                       f"{_t(ppo['median'], 'f')} true-env frames ({ppo['reached']}/{ppo['runs']} runs): "
                       + _times(ppo["median"] / sh["median"], "{}× fewer transitions", "{}× more transitions",
                                "as many transitions") + " (issue 26's target: 10× fewer).")
    return out


MARKERS = ("<!-- gradients:begin (generated by anm_torchrl.experiments.gradient_study from "
           "results/gradient_study/*.json) -->", "<!-- gradients:end -->")


def render(records: list[dict]) -> str:
    """The docs block: the verdict, then each network's table."""
    parts = ["## When does a differentiable model pay off? (issue 26, item 3)", "",
             "True-env frames, model frames and wall time to reach a share of the optimum on the leaderboard's test "
             "states, one campaign per network (`python -m anm_torchrl.cli.gradient_study --network <n>`; "
             "`anm_torchrl/experiments/gradient_study.py` says how a time is measured). Frames compare exactly; wall "
             "times only roughly, since the cells of a campaign ran at different machine loads (each cell's load "
             "average is in the record).", "", verdict(records)]
    for rec in records:
        parts += [markdown(rec), f"_From `results/gradient_study/{rec['network']}.json`._", ""]
    return "\n".join(parts)


def update_page(page: str | Path, records: list[dict]) -> None:
    """Replace the gradients block of ``page`` with :func:`render` of ``records``.

    Raises:
        ValueError: ``page`` has no such block (nothing is written).
    """
    replace_marked_blocks([page], *MARKERS, render(records))
