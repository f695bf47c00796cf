"""PINN accuracy against bus count on the registered feeders: the record ``results/pinn/pinn_generic_accuracy.json``.

For each network (:func:`anm_torchrl.networks.list_networks`): train a preset from physics alone, its three
modules in three processes (the weights of :func:`.loop.train_pinn`; timed: wall seconds and the CPU seconds of
the three trainings together, one torch thread each, with the load average before and after — the machine may
be shared), store the model (the network's default cache when it passes the preset's acceptance bar, the cache
is empty and the network is not ANM6-Easy, else ``--model-dir/<network>/pinn.safetensors``), then evaluate
the whole chain against the exact simulator on held-out ``random`` and MPC-``expert`` transitions
(:mod:`.evaluate`; never seen in training, other seeds than any validation set). Per network and set: |V| MAE
(p.u.), next-state P/Q MAE of every generator and storage unit relative to its rating (largest and mean over
devices; target ≤ 0.01), the slack's relative to the peak load, the terminal check's precision/recall against
the simulator's non-convergence, inference cost.

Commands (each network in its own process, then one merge; ``--preset default`` is each network's default:
``default`` on ANM6-Easy, ``feeder`` elsewhere)::

    python -m anm_torchrl.surrogates.pinn.generic_accuracy --networks case33bw --preset default \
        --expert-envs 4 --expert-steps 50 --out /tmp/acc_case33bw.json
    python -m anm_torchrl.surrogates.pinn.generic_accuracy --merge /tmp/acc_*.json \
        --out results/pinn/pinn_generic_accuracy.json

One network re-measured into the record (``--replace``: its entry and command replaced)::

    python -m anm_torchrl.surrogates.pinn.generic_accuracy --networks simbench_mv_semiurb --preset default \
        --expert-envs 4 --expert-steps 50 --out /tmp/acc_simbench.json
    python -m anm_torchrl.surrogates.pinn.generic_accuracy --merge results/pinn/pinn_generic_accuracy.json \
        /tmp/acc_simbench.json --replace --out results/pinn/pinn_generic_accuracy.json

A saved model re-evaluated without training (``--model``, its training figures from the record entry whose
training it holds, e.g. after :mod:`.refine` re-chose its chord steps)::

    python -m anm_torchrl.surrogates.pinn.generic_accuracy --networks cigre_mv --preset default \
        --expert-envs 4 --expert-steps 50 --model <file> --training-from results/pinn/pinn_generic_accuracy.json \
        --out /tmp/acc_cigre.json
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import re
import time
from pathlib import Path
from typing import Any

import torch

from anm_torchrl.networks.resolve import is_anm6
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.surrogates.pinn import cache
from anm_torchrl.surrogates.pinn.load import load_pinn
from anm_torchrl.surrogates.pinn.evaluate import evaluate_sets
from anm_torchrl.surrogates.pinn.train import (MODULES, build_modules, check_acceptance, load_modules, module_seed,
                                              network_preset_name, preset, read_pinn_file, save_pinn, train_module)
from anm_torchrl.strict_json import json_text

log = logging.getLogger(__name__)

#: metrics kept in the record, per transition set (the full set is in :func:`.evaluate.evaluate_pinn`)
KEPT = ("n", "terminal_rate_sim", "vmag_mae_pu", "vmag_mae_pb_pu", "pf_residual_mean", "gen_proj_mae_pu",
        "des_proj_mae_pu", "feasible", "next_pq_rel_mae_max", "next_pq_rel_mae_mean", "slack_pq_rel_mae",
        "next_pq_mae_mw", "soc_mae_mwh", "reward_mae", "terminal_precision", "terminal_recall", "terminal_rate_pinn",
        "time_us", "sim_time_us")
TARGETS = {"vmag_mae_pu": 1e-3, "next_pq_rel_mae_max": 0.01}


def measure_network(network: str, preset_name: str = "default", seed: int = 0, n_random: int = 10_000,
                    expert_envs: int = 8, expert_steps: int = 125, eval_seed: int = 12345,
                    model_dir: str | Path = "outputs/pinn_generic", model: str | Path | None = None,
                    training_from: str | Path | None = None) -> dict[str, Any]:
    """Train, store and evaluate the PINN of ``network``; returns its record entry (JSON-ready). ``default``
    stands for the network's own default (:func:`.presets.network_preset_name`: ``feeder`` off ANM6-Easy).

    ``model`` (with ``training_from``, a record of this module): evaluate that saved model instead of training one,
    its training figures taken from ``training_from``'s entry for ``network`` — only when the file holds that
    entry's training (:func:`training_of`): e.g. after :mod:`.refine` re-chose the chord steps of the same weights.
    """
    sim = network_simulator(network)
    preset_name = network_preset_name(preset_name, sim)
    if model is not None:
        file = Path(model)
        train = training_of(file, network, preset_name, seed, training_from)
    else:
        cfg = preset(preset_name, seed=seed)
        load0 = os.getloadavg()
        wall0 = time.perf_counter()
        modules, report, train_cpu = train_modules_in_parallel(network, preset_name, seed)
        train_wall = time.perf_counter() - wall0
        load1 = os.getloadavg()
        file = cache.default_path(sim)
        # a failed model never lands in the cache, an existing one stays, and ANM6-Easy's cache is the default
        # preset's (documented in .presets, used by the paper reproduction)
        if not report["accepted"] or file.exists() or is_anm6(sim):
            file = Path(model_dir) / network / "pinn.safetensors"
        save_pinn(file, modules, cfg, report, sim)
        train = {"accepted": report["accepted"], "acceptance_failures": report["acceptance_failures"],
                 "train_wall_s": train_wall, "train_cpu_s": train_cpu, "loadavg_before": list(load0),
                 "loadavg_after": list(load1),
                 "modules": {m: {k: v for k, v in report[m].items() if isinstance(v, (int, float))} for m in MODULES}}
    chain = load_pinn(sim, path=file, train_if_missing=False)
    modules, _, report = load_modules(file, sim)
    results = evaluate_sets(chain, sim, n_random=n_random, n_expert_envs=expert_envs, expert_steps=expert_steps,
                            seed=eval_seed)
    sets = {name: {k: res[k] for k in KEPT} for name, res in results.items()}
    meets = {name: {k: (s[k] is not None and s[k] <= bound) for k, bound in TARGETS.items()}
             for name, s in sets.items()}
    return {
        "network": network, "n_bus": sim.net.n_bus, "n_dev": sim.net.n_dev, "n_gen": sim.n_gen, "n_des": sim.n_des,
        "n_load": sim.n_load, "preset": preset_name, "seed": seed, "model": str(file), **train,
        "refine_steps": modules["power_balance"].refine_steps, "refine": report["power_balance"].get("refine"),
        "eval": sets, "meets_targets": meets,
    }


def training_of(file: Path, network: str, preset_name: str, seed: int, record: str | Path | None) -> dict[str, Any]:
    """The training fields of ``record``'s entry for ``network``, for the saved model ``file`` evaluated without
    training, plus ``training_from`` saying so.

    Raises:
        ValueError: no ``record``, no entry for ``network``, or the entry is not ``file``'s training: another
            preset or seed, or per-module training figures (steps, times, validation errors) that differ from the
            training report stored in ``file``.
    """
    if record is None:
        raise ValueError("evaluating a saved model (model=...) needs training_from=<record> for its training figures")
    entry = next((e for e in json.loads(Path(record).read_text())["networks"] if e["network"] == network), None)
    if entry is None:
        raise ValueError(f"{record} has no entry for network {network!r}")
    payload = read_pinn_file(file)
    saved = {m: {k: v for k, v in (payload.get("report") or {}).get(m, {}).items() if isinstance(v, (int, float))}
             for m in MODULES}
    got = (payload["config"].get("preset"), payload["config"].get("seed"))
    if got != (preset_name, seed) or (entry["preset"], entry["seed"]) != got or saved != entry["modules"]:
        raise ValueError(f"{file} is not the model of {record}'s {network} entry (preset/seed {got} vs "
                         f"{(entry['preset'], entry['seed'])}, or other per-module training figures): train it instead")
    keys = ("accepted", "acceptance_failures", "train_wall_s", "train_cpu_s", "loadavg_before", "loadavg_after",
            "modules")
    return {**{k: entry[k] for k in keys},
            "training_from": {"record": str(record), "model_sha256": _sha256(file),
                              "note": "not re-trained: the training figures are that entry's, whose training report "
                                      "the model file holds; only the chord steps after the power balance were "
                                      "(re)chosen by the rule of anm_torchrl.surrogates.pinn.refine"}}


def _sha256(file: Path) -> str:
    import hashlib

    return hashlib.sha256(Path(file).read_bytes()).hexdigest()


def _train_one(network: str, preset_name: str, seed: int, name: str) -> tuple[dict, dict, float]:
    """Worker: module ``name`` trained exactly as :func:`.loop.train_pinn` trains it (same initial weights: the
    three modules are built after the same ``manual_seed``; same Sobol seed). Returns its state dict, report and
    the worker's CPU seconds."""
    torch.set_num_threads(1)
    cpu0 = time.process_time()
    sim = network_simulator(network)
    cfg = preset(preset_name, seed=seed)
    torch.manual_seed(cfg.seed)
    modules = build_modules(cfg, sim)
    rep = train_module(name, modules[name], sim, getattr(cfg, name), seed=module_seed(cfg, name))
    return modules[name].state_dict(), rep, time.process_time() - cpu0


def train_modules_in_parallel(network: str, preset_name: str, seed: int) -> tuple[dict, dict, float]:
    """:func:`.loop.train_pinn` with its three independent modules in three processes (the same weights; on a
    shared machine each process gets its own CPU share). Returns the modules, the report (with ``accepted``) and
    the CPU seconds of the three trainings together (comparable with one process training them in turn)."""
    from concurrent.futures import ProcessPoolExecutor
    import multiprocessing

    sim = network_simulator(network)
    cfg = preset(preset_name, seed=seed)
    torch.manual_seed(cfg.seed)
    modules = build_modules(cfg, sim)
    with ProcessPoolExecutor(len(MODULES), mp_context=multiprocessing.get_context("spawn")) as pool:
        jobs = {m: pool.submit(_train_one, network, preset_name, seed, m) for m in MODULES}
        done = {m: j.result() for m, j in jobs.items()}
    report: dict[str, Any] = {}
    for m, (state, rep, _) in done.items():
        modules[m].load_state_dict(state)
        if "refine_steps" in rep:  # chosen in the worker (refine_steps: auto); the chord matrix is not a weight
            modules[m].set_refine_steps(rep["refine_steps"])
        modules[m].eval()
        report[m] = rep
    report["time_s"] = sum(report[m]["time_s"] for m in MODULES)
    report["acceptance_failures"] = check_acceptance(cfg, report)
    report["accepted"] = not report["acceptance_failures"]
    return modules, report, sum(c for _, _, c in done.values())


def record(entries: list[dict[str, Any]], command: str) -> dict[str, Any]:
    """The record: entries sorted by bus count, with the targets, the machine and the command."""
    return {"description": __doc__.split("\n")[0], "targets": TARGETS, "command": command,
            "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "torch": torch.__version__,
                        "torch_threads": torch.get_num_threads()},
            "networks": sorted(entries, key=lambda e: e["n_bus"])}


def merge(parts: list[dict[str, Any]], replace: bool = False) -> dict[str, Any]:
    """One record of the networks of ``parts`` (records of this module), its command the commands that measured
    them; with ``replace``, a later part's network replaces an earlier one's entry and command.

    Raises:
        ValueError: a network measured twice without ``replace``.
    """
    entries: dict[str, dict] = {}
    commands: dict[str, str] = {}
    for part in parts:
        pieces = part["command"].split(" && ")
        for e in part["networks"]:
            name = e["network"]
            if name in entries and not replace:
                raise ValueError(f"the merged records measure network {name!r} twice (--replace to take the later)")
            own = [c for c in pieces if re.search(rf"--networks( \S+)* {re.escape(name)}( |$)", c)]
            entries[name], commands[name] = e, own[0] if len(own) == 1 else part["command"]
    order = sorted(entries, key=lambda n: entries[n]["n_bus"])
    return record(list(entries.values()), " && ".join(dict.fromkeys(commands[n] for n in order)))


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """CLI (module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--networks", nargs="*", default=[], help="registered network names")
    ap.add_argument("--merge", nargs="*", default=[], help="records to merge (their networks), instead of measuring")
    ap.add_argument("--replace", action="store_true", help="with --merge: a later record's network replaces an "
                    "earlier one's entry and command")
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n-random", type=int, default=10_000)
    ap.add_argument("--expert-envs", type=int, default=8)
    ap.add_argument("--expert-steps", type=int, default=125)
    ap.add_argument("--model-dir", default="outputs/pinn_generic", help="where a model failing its bar is saved")
    ap.add_argument("--model", help="evaluate this saved model instead of training (one network; needs "
                    "--training-from)")
    ap.add_argument("--training-from", help="with --model: the record whose entry holds that model's training")
    args = ap.parse_args(argv)
    if bool(args.networks) == bool(args.merge):
        raise ValueError("give either --networks (measure) or --merge (combine records), not both or neither")
    torch.set_num_threads(1)
    if args.merge:
        out = merge([json.loads(Path(f).read_text()) for f in args.merge], replace=args.replace)
    else:
        if args.model is not None and len(args.networks) != 1:
            raise ValueError(f"--model evaluates one network's model; got --networks {args.networks}")
        entries = [measure_network(n, args.preset, args.seed, args.n_random, args.expert_envs, args.expert_steps,
                                   model_dir=args.model_dir, model=args.model, training_from=args.training_from)
                   for n in args.networks]
        model = f" --model {args.model} --training-from {args.training_from}" if args.model is not None else ""
        out = record(entries, "python -m anm_torchrl.surrogates.pinn.generic_accuracy --networks "
                     f"{' '.join(args.networks)} --preset {args.preset} --seed {args.seed} --n-random {args.n_random} "
                     f"--expert-envs {args.expert_envs} --expert-steps {args.expert_steps}{model}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json_text(out, indent=2) + "\n")
    return out


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO)
    main()
