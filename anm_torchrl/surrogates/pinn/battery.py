"""The PINN on random networks: does it build from physics alone, and is it accurate, on any valid network?

Per seed, a network of :func:`battery_case` (:mod:`anm_torchrl.networks.random`; the size class and the
topology follow the seed: ``seed % 3`` → 5–15 / 16–40 / 41–80 buses, ``(seed // 3) % 2`` → radial / meshed),
then what ``make_env(surrogate="pinn", network=...)`` does: the ``default`` preset for the network (``feeder``
off ANM6-Easy, :func:`.presets.network_preset_name`) trained by :func:`.cache.train_and_save` (here into
``--model-dir``, never the user's cache), then the chain of :func:`.load.load_pinn` (models in ``--model-dir``). Recorded per network:

* ``accepted`` / ``acceptance_failures``: the preset's acceptance bar (:func:`.presets.check_acceptance`);
* ``pq_rel_mae_max`` / ``pq_rel_mae_mean``: next-state P/Q MAE of the generators and storage units relative to
  their ratings (largest / mean over devices; fraction, target ≤ 0.01), ``vmag_mae_pu`` (target ≤ 1e-3) and
  ``terminal_agreement`` (share of transitions whose ``terminated`` equals the exact env's non-convergence;
  target ≥ 0.99) on ``--n-random`` random transitions (:func:`.evaluate.random_transitions`, seed 12345, the
  metrics of :mod:`.generic_accuracy`);
* ``reward_mae`` and ``reward_rel_mae``: the reward's MAE, and over the true rewards' mean |r|, on the same
  transitions (target ≤ 0.05),
  and ``absolute_bar`` / ``box_only``: the k that rule v2 (absolute bar alone) / rule v3 (box points alone) picks
  and the reward error at that k (what the loss-relative bar and the env-like points of rule v4, :mod:`.refine`,
  buy);
* ``train_wall_s`` (target ≤ 600 s), the chosen refinement ``k`` and the box's power-flow solvability;
* ``meets``: each target, ``passed``: all of them and the bar; ``why``: for each failure what it means and what
  to try (:func:`diagnose`).

Command (the record ``results/pinn_battery/``; ``--pb-steps``/``--kkt-steps`` cut the preset's steps)::

    python -m anm_torchrl.surrogates.pinn.battery --seeds 0 1 2 3 4 5 6 7 8 9 10 11 --out results/pinn_battery/

It writes ``battery.json`` (after each network) and ``battery.md`` (a table per size class).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import statistics
import sys
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np
import torch

from anm_torchrl.artifacts import atomic_write
from anm_torchrl.networks.random import SIZE_CLASSES, generate, size_class
from anm_torchrl.strict_json import json_text

log = logging.getLogger(__name__)

TARGETS = {"pq_rel_mae_max": 0.01, "vmag_mae_pu": 1e-3, "terminal_agreement": 0.99, "reward_rel_mae": 0.05,
           "train_wall_s": 600.0}


def battery_case(seed: int):
    """The battery's network of ``seed``: size class ``SIZE_CLASSES[seed % 3]``, bus count drawn in it, meshed when
    ``(seed // 3) % 2 == 1`` (:func:`anm_torchrl.networks.random.generate`)."""
    lo, hi = SIZE_CLASSES[seed % len(SIZE_CLASSES)]
    n_bus = int(np.random.default_rng([seed, 1]).integers(lo, hi + 1))
    return generate(seed, n_bus=n_bus, meshed=(seed // len(SIZE_CLASSES)) % 2 == 1)


#: the seed standing for issue 23's network (:func:`anm_torchrl.networks.random.stiff_transformer_network`)
ISSUE23 = -1


def issue23_case():
    """Issue 23's 9-bus network as a battery case (seed :data:`ISSUE23`)."""
    from anm_torchrl.networks.random import RandomCase, stiff_transformer_network

    net, load_p, gen_p_max = stiff_transformer_network()
    return RandomCase(net, load_p, gen_p_max, {
        "seed": ISSUE23, "attempt": 0, "n_bus": 9, "topology": "radial (issue 23)", "base_mva": 100.0,
        "transformer": {"x_pu": 0.55, "tap": 1.03, "shift_deg": 0.0, "rating_mva": 120.0}, "n_branch": 8})


def terminal_agreement(m: dict[str, Any]) -> float:
    """Share of transitions whose PINN ``terminated`` equals the simulator's non-convergence, from
    :func:`.evaluate.evaluate_pinn`'s rates and precision: 1 − (FP + FN) / n."""
    rate_pinn, rate_sim = m["terminal_rate_pinn"], m["terminal_rate_sim"]
    prec = m["terminal_precision"]
    tp = prec * rate_pinn if rate_pinn > 0 and not math.isnan(prec) else 0.0
    return 1.0 - (rate_pinn - tp) - (rate_sim - tp)


def box_solvable(sim, points: int = 2048, seed: int = 0) -> float:
    """Share of scrambled-Sobol points of the power-balance training box (:func:`.power_balance.
    bus_injection_box`) where Newton–Raphson converges: the refinement rule needs ≥ 0.99."""
    from anm_torchrl.grid.powerflow import newton_raphson
    from anm_torchrl.surrogates.pinn.power_balance import bus_injection_box

    lo, hi, qlo, qhi = (x[1:] for x in bus_injection_box(sim))
    n = lo.numel()
    u = torch.quasirandom.SobolEngine(2 * n, scramble=True, seed=seed).draw(points).double()
    p = lo + u[:, :n] * (hi - lo)
    q = qlo + u[:, n:] * (qhi - qlo)
    zero = p.new_zeros(points, 1)
    pf = newton_raphson(sim.net.y_bus, torch.complex(torch.cat([zero, p], 1), torch.cat([zero, q], 1)))
    return float(pf.converged.double().mean())


def diagnose(entry: dict[str, Any]) -> list[str]:
    """What each failure of ``entry`` means and what to try (empty: it passed)."""
    why = []
    if entry.get("error"):
        return [f"the build raised {entry['error']}: see 'traceback'; a network make_env refuses is named there"]
    if not entry["accepted"]:
        refine = entry.get("refine") or {}
        if refine and not refine.get("met"):
            solv = entry.get("box_solvable")
            why.append(f"no k <= {refine.get('k_max')} Newton steps brings the box's residual quantile to the bar "
                       f"(after k: {refine.get('residual_q_pu')}); {100 * (1 - solv):.1f} % of the injection box has "
                       "no power flow" + (" (> 1 %: the devices' ratings exceed what the network can carry; lower "
                                          "them or strengthen the lines)" if solv is not None and solv < 0.99 else
                                          "; train the power balance longer (power_balance.max_steps)"))
        for f in entry["acceptance_failures"]:
            if not f.startswith("power_balance.refine"):
                why.append(f"acceptance: {f}; train that module longer (<module>.max_steps) or use the default "
                           "preset's full steps")
    meets = entry["meets"]
    if not meets["vmag_mae_pu"]:
        why.append(f"|V| MAE {entry['vmag_mae_pu']:.2e} > 1e-3 p.u.: train the power balance longer or check that "
                   f"the refinement met its rule (k = {entry.get('refine_steps')})")
    if not meets["pq_rel_mae_max"]:
        why.append(f"device P/Q MAE {entry['pq_rel_mae_max']:.2%} of a rating > 1 %: the KKT-NN projections "
                   "(generator/storage max_steps) or the slack/flows of an inaccurate power balance")
    if not meets["terminal_agreement"]:
        why.append(f"terminal agreement {entry['terminal_agreement']:.2%} < 99 % (PINN flags "
                   f"{entry['terminal_rate_pinn']:.2%}, env {entry['terminal_rate_sim']:.2%}): the residual p99 "
                   f"{entry.get('pf_residual_p99')} vs the 0.005 p.u. threshold: a more accurate power balance")
    if not meets.get("reward_rel_mae", True):  # (entries measured before the target have no verdict on it)
        why.append(f"reward MAE {entry['reward_rel_mae']:.2%} of the rewards' mean |r| > 5 %: the slack injection "
                   f"(the power balance's residual, k = {entry.get('refine_steps')}) or the penalty's inputs")
    if not meets["train_wall_s"]:
        why.append(f"training took {entry['train_wall_s']:.0f} s > 600 s: cut max_steps (the quick preset) or "
                   "train on a less loaded machine")
    return why


def measure(seed: int, model_dir: Path, n_random: int = 4000, overrides: dict[str, Any] | None = None,
            eval_seed: int = 12345) -> dict[str, Any]:
    """One battery entry (module docstring; ``seed`` :data:`ISSUE23`: issue 23's network); never raises: a build
    error is recorded with its traceback."""
    from anm_torchrl.networks import simulator
    from anm_torchrl.surrogates.pinn import cache
    from anm_torchrl.surrogates.pinn import train as tr
    from anm_torchrl.surrogates.pinn.load import load_pinn
    from anm_torchrl.surrogates.pinn.evaluate import evaluate_pinn, random_transitions

    case = issue23_case() if seed == ISSUE23 else battery_case(seed)
    entry: dict[str, Any] = {"seed": seed, "size_class": size_class(case.meta["n_bus"]), **case.meta}
    try:
        sim = simulator(case.network, case.load_p, case.gen_p_max)
        entry["box_solvable"] = box_solvable(sim)
        name = tr.network_preset_name("default", sim)
        cfg = tr.preset(name, **(overrides or {}))
        file = model_dir / f"seed{seed}" / "pinn.safetensors"
        t0 = time.perf_counter()
        _, report = cache.train_and_save(cfg, sim, path=file)
        entry["train_wall_s"] = time.perf_counter() - t0
        chain = load_pinn(sim, path=file, train_if_missing=False)
        transitions = random_transitions(sim, n_random, eval_seed)
        m = evaluate_pinn(chain, sim, *transitions)
        pb = report["power_balance"]
        entry.update({
            "preset": name, "overrides": overrides or {}, "accepted": report["accepted"],
            "acceptance_failures": report["acceptance_failures"], "refine": pb.get("refine"),
            "refine_steps": chain[4].module.refine_steps, "val_vmag_mae": pb.get("val_vmag_mae"),
            "pq_rel_mae_max": m["next_pq_rel_mae_max"], "pq_rel_mae_mean": m["next_pq_rel_mae_mean"],
            "vmag_mae_pu": m["vmag_mae_pu"], "pf_residual_p99": m["pf_residual_p99"],
            "terminal_rate_sim": m["terminal_rate_sim"], "terminal_rate_pinn": m["terminal_rate_pinn"],
            "terminal_agreement": terminal_agreement(m), "n_random": n_random,
            "reward_mae": m["reward_mae"], "reward_rel_mae": m["reward_rel_mae"],
            "module_time_s": {k: report[k].get("time_s") for k in tr.MODULES},
        })
        entry.update(earlier_rule_entries(chain, sim, entry["refine"], m, transitions))
        entry["meets"] = {k: (entry[k] is not None and (entry[k] >= b if k == "terminal_agreement" else
                                                        entry[k] <= b)) for k, b in TARGETS.items()}
        entry["passed"] = bool(entry["accepted"] and all(entry["meets"].values()))
    except Exception as err:  # noqa: BLE001 - the battery records why a network fails to build
        entry.update({"error": f"{type(err).__name__}: {err}", "traceback": traceback.format_exc(), "passed": False})
    entry["why"] = diagnose(entry)
    return entry


def earlier_rule_entries(chain, sim, record: dict[str, Any] | None, m: dict[str, Any],
                         transitions: tuple) -> dict[str, dict[str, Any] | None]:
    """What today's rule (:mod:`.refine`) buys over the earlier ones, on ``transitions`` (those ``m`` was measured
    on): ``absolute_bar``, the k that rule v2's absolute bar alone picks from the record's box quantiles, and
    ``box_only``, the k that rule v3 picks (the box's quantiles against its loss-relative bar, with the box's losses
    at the chosen k), each with the reward error at that k (None: no rule record)."""
    from anm_torchrl.surrogates.pinn.refine import rule_met

    if not record or not record.get("residual_q_pu"):
        return {"absolute_bar": None, "box_only": None}
    qs = [math.inf if q is None else q for q in record["residual_q_pu"]]
    loss = record.get("loss_median_pu")
    k_v2 = next((i + 1 for i, q in enumerate(qs) if rule_met(q)), len(qs))
    k_v3 = next((i + 1 for i, q in enumerate(qs) if rule_met(q, loss)), len(qs))
    return {"absolute_bar": _reward_at(chain, sim, k_v2, m, transitions),
            "box_only": _reward_at(chain, sim, k_v3, m, transitions)}


def _reward_at(chain, sim, k: int, m: dict[str, Any], transitions: tuple) -> dict[str, Any]:
    """``{"k", "reward_rel_mae"}`` of ``chain`` run with ``k`` refinement steps on ``transitions`` (``m``'s figure
    where ``k`` is the chain's own)."""
    from anm_torchrl.surrogates.pinn.evaluate import evaluate_pinn

    pb = chain[4].module
    if k == pb.refine_steps:
        return {"k": k, "reward_rel_mae": m["reward_rel_mae"]}
    k_own = pb.refine_steps
    pb.set_refine_steps(k)
    try:
        return {"k": k, "reward_rel_mae": evaluate_pinn(chain, sim, *transitions)["reward_rel_mae"]}
    finally:
        pb.set_refine_steps(k_own)


def _fmt(x: Any, spec: str) -> str:
    return "—" if x is None else format(x, spec)


def _pct(x: float | None) -> str:
    return "—" if x is None else f"{100 * x:.3g}"


def _at_k(a: dict[str, Any] | None) -> str:
    return "—" if not a else f"{a['k']}: {_pct(a['reward_rel_mae'])}"


def summary(record: dict[str, Any]) -> str:
    """One markdown row per size class: networks (radial / meshed), passed, the worst P/Q MAE (% of a rating),
    |V| MAE (p.u.) and terminal agreement, training time (median / max, s) and the refinement k range."""
    lines = ["| buses | networks (radial / meshed) | pass | P/Q MAE max % (worst) | \\|V\\| MAE p.u. (worst) | "
             "term. agree % (worst) | reward err % (worst) | train s (median / max) | k |",
             "|---|---|---:|---:|---:|---:|---:|---:|---|"]
    for lo, hi in SIZE_CLASSES:
        rows = [e for e in record["networks"] if e["size_class"] == f"{lo}-{hi}"]
        ok = [e for e in rows if not e.get("error")]
        if not rows:
            continue
        n_mesh = sum(e["topology"].startswith("meshed") for e in rows)
        if not ok:
            lines.append(f"| {lo}–{hi} | {len(rows) - n_mesh} / {n_mesh} | 0 / {len(rows)} | "
                         "— | — | — | — | — | — |")
            continue
        t = sorted(e["train_wall_s"] for e in ok)
        ks = sorted({e["refine_steps"] for e in ok})
        lines.append(f"| {lo}–{hi} | {len(rows) - n_mesh} / {n_mesh} | {sum(e['passed'] for e in rows)} / {len(rows)} | "
                     f"{100 * max(e['pq_rel_mae_max'] for e in ok):.3f} | {max(e['vmag_mae_pu'] for e in ok):.2e} | "
                     f"{100 * min(e['terminal_agreement'] for e in ok):.2f} | "
                     f"{_pct(max((e.get('reward_rel_mae') for e in ok), key=lambda x: -1 if x is None else x))} | "
                     f"{statistics.median(t):.0f} / {t[-1]:.0f} | "
                     f"{ks[0]}–{ks[-1]} |")
    return "\n".join(lines) + "\n"


def markdown(record: dict[str, Any]) -> str:
    """The battery's tables, one per size class, and a summary line per class."""
    lines = [f"# PINN battery on random networks ({record['created']})", "",
             f"Command: `{record['command']}`", "",
             f"Machine: {record['machine']['cpus']} CPUs, {record['machine']['platform']}, torch "
             f"{record['machine']['torch']} ({record['machine']['torch_threads']} thread)", "",
             "Targets: device P/Q MAE ≤ 1 % of its rating (largest over devices), |V| MAE ≤ 1e-3 p.u., terminal "
             "agreement ≥ 99 %, reward MAE ≤ 5 % of the rewards' mean |r|, training ≤ 600 s, and the preset's "
             "acceptance bar. 'k (v2)' / 'k (v3)': the Newton steps that rule v2's absolute bar alone / rule v3's "
             "box points alone pick, and the reward error there (today's rule v4 meets its bar on the box and on "
             "env-like injections).", "", summary(record)]
    for lo, hi in SIZE_CLASSES:
        cls = f"{lo}-{hi}"
        rows = [e for e in record["networks"] if e["size_class"] == cls]
        if not rows:
            continue
        n_pass = sum(e["passed"] for e in rows)
        lines += [f"## {lo}–{hi} buses: {n_pass} / {len(rows)} pass", "",
                  "| seed | buses | topology | base MVA | X_tr p.u. | tap | k | accepted | P/Q MAE max (mean) % | "
                  "\\|V\\| MAE p.u. | term. agree % | reward err % | k (v2): reward err % | k (v3): reward err % | "
                  "train s | pass |",
                  "|---:|---:|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---|"]
        for e in rows:
            tr_ = e["transformer"]
            if e.get("error"):
                lines.append(f"| {e['seed']} | {e['n_bus']} | {e['topology']} | {e['base_mva']:.3g} | "
                             f"{tr_['x_pu']:.3f} | {tr_['tap']:.3f} | — | error | "
                             "— | — | — | — | — | — | — | no |")
                continue
            pq = f"{100 * e['pq_rel_mae_max']:.3f} ({100 * e['pq_rel_mae_mean']:.3f})" \
                if e["pq_rel_mae_max"] is not None else "—"
            lines.append(f"| {e['seed']} | {e['n_bus']} | {e['topology']} | {e['base_mva']:.3g} | {tr_['x_pu']:.3f} | "
                         f"{tr_['tap']:.3f} | {e['refine_steps']} | {'yes' if e['accepted'] else 'no'} | {pq} | "
                         f"{_fmt(e['vmag_mae_pu'], '.2e')} | {100 * e['terminal_agreement']:.2f} | "
                         f"{_pct(e.get('reward_rel_mae'))} | {_at_k(e.get('absolute_bar'))} | "
                         f"{_at_k(e.get('box_only'))} | "
                         f"{e['train_wall_s']:.0f} | {'yes' if e['passed'] else 'no'} |")
        lines.append("")
        for e in rows:
            for w in e["why"]:
                lines.append(f"* seed {e['seed']}: {w}")
        lines.append("")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """CLI (module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", required=True, help=f"{ISSUE23}: issue 23's 9-bus network")
    ap.add_argument("--out", required=True, help="folder of battery.json / battery.md (models under models/)")
    ap.add_argument("--n-random", type=int, default=4000, help="random transitions per network")
    ap.add_argument("--pb-steps", type=int, help="power_balance.max_steps (default: the preset's)")
    ap.add_argument("--kkt-steps", type=int, help="generator and storage max_steps (default: the preset's)")
    ap.add_argument("--model-dir", default="outputs/pinn_battery", help="where the trained models are saved")
    ap.add_argument("--merge", action="store_true", help="keep the entries of an existing battery.json (others)")
    args = ap.parse_args(argv)
    for flag, value in (("--pb-steps", args.pb_steps), ("--kkt-steps", args.kkt_steps)):
        if value is not None and value < 1:  # 0 was taken for "not given": the preset's full step count
            ap.error(f"{flag} must be >= 1, got {value}")
    torch.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    overrides: dict[str, Any] = {}
    if args.pb_steps is not None:
        overrides["power_balance"] = {"max_steps": args.pb_steps}
    if args.kkt_steps is not None:
        overrides["generator"] = overrides["storage"] = {"max_steps": args.kkt_steps}
    command = "python -m anm_torchrl.surrogates.pinn.battery " + " ".join(argv if argv is not None else sys.argv[1:])
    entries: dict[int, dict] = {}
    if args.merge and (out / "battery.json").is_file():
        entries = {e["seed"]: e for e in json.loads((out / "battery.json").read_text())["networks"]}
    record: dict[str, Any] = {}
    for seed in args.seeds:
        log.info("battery seed %d", seed)
        e = measure(seed, Path(args.model_dir), args.n_random, overrides)
        e["command"] = command
        entries[seed] = e
        log.info("seed %d: %s buses, passed %s %s", seed, e["n_bus"], e["passed"], e["why"])
        commands = " && ".join(dict.fromkeys(x["command"] for x in entries.values()))
        record = {"description": __doc__.split("\n")[0], "targets": TARGETS, "command": commands,
                  "created": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                  "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "torch": torch.__version__,
                              "torch_threads": torch.get_num_threads(), "python": platform.python_version(),
                              "loadavg": list(os.getloadavg())},
                  "networks": sorted(entries.values(), key=lambda x: (x["n_bus"], x["seed"]))}
        # atomic: a later --merge reads this file back, and a cut write would lose every earlier entry
        atomic_write(out / "battery.json", (json_text(record, indent=2) + "\n").encode())
        atomic_write(out / "battery.md", markdown(record).encode())
    return record


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO)
    main()
