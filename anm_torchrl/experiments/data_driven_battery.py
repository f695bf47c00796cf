"""The data-driven surrogates on the PINN battery's random networks, through the entry a user calls.

For each battery network (:func:`anm_torchrl.surrogates.pinn.battery.battery_case`, the same seeds as
``results/pinn_battery/battery.json``) and each kind, the surrogate is built exactly as ``make_env(<kind>,
network=<dict>, load_p=..., gen_p_max=...)`` builds it with nothing trained (:mod:`anm_torchrl.surrogates.
regressors.first_use`: the recipe's default dataset of 100,000 generative rows, default hyper-parameters, its
terminal classifier; timed, dataset generation included), in a fresh artifact home. It is then scored on the
battery's held-out random transitions (:func:`anm_torchrl.surrogates.pinn.evaluate.random_transitions`, seed 12345,
``--n-random`` of them) with the PINN battery's metrics: next-state P/Q MAE of every generator and storage unit
relative to its rating (largest over devices), reward MAE, and the share of transitions whose ``terminated``
agrees with the simulator's non-convergence. The PINN's figures of the same network are copied beside them from
the battery record (``--pinn-record``). No |V| for these models: they predict the state, not the voltages.

Command (the record ``results/pinn_battery/data_driven.{json,md}``)::

    python -m anm_torchrl.cli.data_driven_battery --seeds 6 4 2 --kinds lr dt xgb dnn \\
        --out results/pinn_battery/data_driven
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict

from anm_torchrl.provenance import machine_info, versions
from anm_torchrl.strict_json import json_text

PINN_RECORD = Path(__file__).resolve().parents[2] / "results" / "pinn_battery" / "battery.json"
TARGET_PQ = 0.01  # of each device's rating: the PINN battery's target (issue 23)


@torch.no_grad()
def score(model, sim, state: torch.Tensor, action: torch.Tensor) -> dict[str, float | None]:
    """The battery's metrics of a transition model on (state, action) rows against ``sim.step``."""
    from anm_torchrl.surrogates.pinn.evaluate import relative_pq

    n = state.shape[0]
    t0 = time.perf_counter()
    out = model(TensorDict({"state": state, "action": action.to(torch.float32)}, [n]))
    model_s = time.perf_counter() - t0
    nxt, tr = sim.step(state, action)
    ok, term = tr.converged, out.get("terminated").reshape(-1).bool()
    both = ok & ~term
    sl = sim.state_slices()
    pred = out.get("next_state").to(torch.float64)
    pq = torch.cat([pred[:, sl["dev_p"]], pred[:, sl["dev_q"]]], 1)
    pq_ref = torch.cat([nxt[:, sl["dev_p"]], nxt[:, sl["dev_q"]]], 1)
    rel = relative_pq(sim, pq[both] - pq_ref[both])
    return {"n": n, "pq_rel_mae_max": rel["next_pq_rel_mae_max"], "pq_rel_mae_mean": rel["next_pq_rel_mae_mean"],
            "slack_pq_rel_mae": rel["slack_pq_rel_mae"],
            "reward_mae": float((out.get("reward").reshape(-1).double() - tr.reward)[both].abs().mean()),
            "terminal_rate_sim": float((~ok).double().mean()), "terminal_rate_model": float(term.double().mean()),
            "terminal_agreement": float((term == ~ok).double().mean()), "time_us": 1e6 * model_s / n}


def measure(seed: int, kinds: list[str], n_random: int, n_jobs: int, eval_seed: int = 12345) -> dict[str, Any]:
    """One network's entry: per kind, the first-use build time and its scores."""
    from anm_torchrl.networks import simulator
    from anm_torchrl.surrogates import load_surrogate
    from anm_torchrl.surrogates.pinn.battery import ISSUE23, battery_case, issue23_case
    from anm_torchrl.surrogates.pinn.evaluate import random_transitions

    case = issue23_case() if seed == ISSUE23 else battery_case(seed)
    sim = simulator(case.network, case.load_p, case.gen_p_max)
    state, action = random_transitions(sim, n_random, eval_seed)
    entry: dict[str, Any] = {"seed": seed, "n_bus": case.meta["n_bus"], "topology": case.meta["topology"],
                             "base_mva": case.meta["base_mva"], "kinds": {}}
    old = os.environ.get("ANM_TORCHRL_HOME")
    with tempfile.TemporaryDirectory(prefix="anm_dd_") as home:
        os.environ["ANM_TORCHRL_HOME"] = home  # a new user's empty cache: everything is built here
        try:
            for kind in kinds:
                t0 = time.perf_counter()
                model = load_surrogate(kind, sim=sim, n_jobs=n_jobs, progress=False)
                build_s = time.perf_counter() - t0
                info = model.meta.get("trained_on_first_use", {})
                m = score(model, sim, state, action)
                entry["kinds"][kind] = {**m, "build_s": build_s, **{k: info.get(k) for k in
                                        ("dataset_seconds", "fit_seconds", "terminal_seconds", "rows")},
                                        "meets_pq": m["pq_rel_mae_max"] is not None and m["pq_rel_mae_max"] <= TARGET_PQ}
        finally:
            if old is None:
                os.environ.pop("ANM_TORCHRL_HOME", None)
            else:
                os.environ["ANM_TORCHRL_HOME"] = old
    return entry


def pinn_figures(record: Path, seed: int) -> dict[str, Any] | None:
    """The PINN battery's figures of network ``seed`` (None: not in the record)."""
    if not record.is_file():
        return None
    for e in json.loads(record.read_text())["networks"]:
        if e["seed"] == seed:
            return {k: e.get(k) for k in ("pq_rel_mae_max", "pq_rel_mae_mean", "terminal_agreement", "train_wall_s",
                                          "vmag_mae_pu", "reward_mae", "passed")}
    return None


def markdown(rec: dict[str, Any]) -> str:
    """The record as a table: one row per network and model, the PINN's row first."""
    head = ("| network (seed) | buses | model | P/Q MAE max (% of rating) | reward MAE | terminal agreement | "
            "build time (s) |\n|---|---:|---|---:|---:|---:|---:|")
    rows = []
    for e in rec["networks"]:
        name = f"{e['topology']} ({e['seed']})"
        p = e.get("pinn")
        if p:
            reward = "–" if p.get("reward_mae") is None else f"{p['reward_mae']:.2e}"  # (records before it: none)
            rows.append(f"| {name} | {e['n_bus']} | PINN (battery record) | {100 * p['pq_rel_mae_max']:.4f} | "
                        f"{reward} | {100 * p['terminal_agreement']:.2f} % | {p['train_wall_s']:.0f} |")
        for kind, m in e["kinds"].items():
            pq = "–" if m["pq_rel_mae_max"] is None else f"{100 * m['pq_rel_mae_max']:.3f}"
            rows.append(f"| {name} | {e['n_bus']} | {kind} | {pq} | {m['reward_mae']:.2e} | "
                        f"{100 * m['terminal_agreement']:.2f} % | {m['build_s']:.0f} |")
    return (f"Data-driven surrogates built on first use (`make_env(<kind>, network=<dict>)`, 100,000 generative rows) "
            f"on the PINN battery's networks, scored on {rec['n_random']} held-out random transitions (seed 12345; "
            f"the PINN's row from `{rec.get('pinn_refreshed', {}).get('record', 'results/pinn_battery/battery.json')}`"
            f", same transitions). Target of the PINN battery: "
            f"P/Q MAE ≤ 1 % of each device's rating. Build time includes the dataset. Machine: "
            f"{rec['machine'].get('cpu', '?')}, {rec['machine'].get('usable_cores', '?')} usable cores.\n\n{head}\n"
            + "\n".join(rows) + "\n")


def refresh_pinn(out: str | Path, pinn_record: str | Path = PINN_RECORD) -> dict[str, Any]:
    """Re-read the PINN's figures of the record ``<out>.json`` from ``pinn_record`` (the PINN battery re-measured;
    the data-driven figures are kept as measured), note it in the record, rewrite ``<out>.json`` and ``<out>.md``.

    Raises:
        FileNotFoundError: no ``<out>.json`` or no ``pinn_record``.
    """
    stem = Path(out)
    rec = json.loads(stem.with_suffix(".json").read_text())
    if not Path(pinn_record).is_file():
        raise FileNotFoundError(f"no PINN battery record at {pinn_record}")
    for e in rec["networks"]:
        e["pinn"] = pinn_figures(Path(pinn_record), e["seed"])
    rec["pinn_refreshed"] = {"record": str(pinn_record), "created": json.loads(Path(pinn_record).read_text()).get(
        "created"), "command": f"python -m anm_torchrl.cli.data_driven_battery --refresh-pinn --out {out}"}
    stem.with_suffix(".json").write_text(json_text(rec, indent=1) + "\n")
    stem.with_suffix(".md").write_text(markdown(rec))
    return rec


def run(seeds: list[int], kinds: list[str], out: str | Path, n_random: int = 4000, n_jobs: int = 2,
        pinn_record: str | Path = PINN_RECORD) -> dict[str, Any]:
    """Measure every seed, write ``<out>.json`` and ``<out>.md``, return the record."""
    t0 = time.perf_counter()
    nets = []
    for seed in seeds:
        e = measure(seed, kinds, n_random, n_jobs)
        e["pinn"] = pinn_figures(Path(pinn_record), seed)
        nets.append(e)
    rec = {"what": "data-driven surrogates built on first use on random networks, beside the PINN",
           "n_random": n_random, "eval_seed": 12345, "kinds": kinds, "n_jobs": n_jobs, "networks": nets,
           "wall_s": time.perf_counter() - t0, "machine": machine_info(), "versions": versions(),
           "command": "python -m anm_torchrl.cli.data_driven_battery --seeds " + " ".join(map(str, seeds))
                      + " --kinds " + " ".join(kinds) + f" --n-random {n_random} --out {out}"}
    stem = Path(out)
    stem.parent.mkdir(parents=True, exist_ok=True)
    stem.with_suffix(".json").write_text(json_text(rec, indent=1) + "\n")
    stem.with_suffix(".md").write_text(markdown(rec))
    return rec
