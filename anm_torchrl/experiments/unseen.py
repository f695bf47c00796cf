"""Networks nobody tuned: the documented training commands, at their defaults, on random networks a user could bring.

A network is a spec ``SEED:BUSES:radial|meshed`` of :func:`anm_torchrl.networks.random.generate` (every device
type, daily profiles), written to ``<runs_dir>/<name>.npz`` with
:func:`~anm_torchrl.networks.user.save_network`, as a user saves theirs; or a network file (``<path>.npz``, e.g. a
SimBench grid written by ``python -m anm_torchrl.cli.import_network``), copied there. On each one:

* the baselines on the test states every recipe reports on (the per-network protocol's ``default`` entry: the
  ``eval.test_*`` keys of the PPO recipe's config for that file), the perfect-foresight AC optimum and do-nothing,
  by the gap study's measurement (:func:`.gap.measure`, what ``python -m anm_torchrl.cli.gap --network <file>
  --rows optimal,do_nothing ...`` runs; the record names that command), one process per network, ``jobs`` at a
  time;
* each algorithm's recipe with nothing on its command line but the network and the seed
  (``python recipes/<ppo|shac|sac>.py network=<file> seed=<s>``: the ``default`` per-network entry; and the main job,
  ``python recipes/ppo.py network=<file> surrogate=pinn``, its PINN trained on first use), as cells of
  :mod:`.cells`; a cell's score is its ``best.pt`` (chosen on its validation states) on the test states, read from
  its ``summary.json`` after checking that the states are the baselines'.

Shares of the optimum's gain over do-nothing, ``100 (R − R_dn) / (R_opt − R_dn)``, as the leaderboards'.
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import os
import statistics
import sys
import time
import traceback
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from anm_torchrl.experiments.cells import RECIPES, cell_config, run_cells, shown, tested_states
from anm_torchrl.experiments.formatting import replace_marked_blocks
from anm_torchrl.experiments.leaderboard import against_optimum

log = logging.getLogger(__name__)

#: a column -> (its recipe, the keys its documented command sets besides the network, label)
RECIPE: dict[str, tuple[str, tuple[str, ...], str]] = {
    "ppo": ("ppo.py", (), "PPO"),
    "shac": ("shac.py", (), "SHAC"),
    "sac": ("sac.py", (), "SAC"),
    # the main job on a user's network: the PINN trained on first use (counted in the run's wall time)
    "ppo_pinn": ("ppo.py", ("surrogate=pinn",), "PPO on the PINN"),
}
MARKERS = ("<!-- unseen:networks -->", "<!-- /unseen:networks -->")


def parse_spec(spec: str) -> tuple[int, int, bool] | Path:
    """``"SEED:BUSES:radial|meshed"`` -> (seed, bus count, meshed); a network file's path (``.npz``, e.g. written by
    ``python -m anm_torchrl.cli.import_network``) -> that path.

    Raises:
        ValueError: another form, or a network file that does not exist, naming the spec.
    """
    if spec.endswith(".npz"):
        if not Path(spec).is_file():
            raise ValueError(f"network spec {spec!r}: no such network file")
        return Path(spec)
    parts = spec.split(":")
    if len(parts) != 3 or parts[2] not in ("radial", "meshed") or not all(p.isdigit() for p in parts[:2]):
        raise ValueError(f"network spec {spec!r}: expected SEED:BUSES:radial|meshed, e.g. 9101:18:radial, or a "
                         "network file (.npz)")
    return int(parts[0]), int(parts[1]), parts[2] == "meshed"


def write_network(spec: str, folder: Path) -> tuple[Path, dict[str, Any]]:
    """The random network of ``spec`` saved as ``folder/random<seed>_<buses>_<topology>.npz``; (path, its meta with
    the simulator's ``network_key``). An existing file of another network (the generator changed) is replaced."""
    from anm_torchrl.grid.identity import network_key
    from anm_torchrl.networks import simulator
    from anm_torchrl.networks.random import generate
    from anm_torchrl.networks.user import save_network

    parsed = parse_spec(spec)
    if isinstance(parsed, Path):
        return _copy_network(parsed, folder)
    seed, n_bus, meshed = parsed
    case = generate(seed, n_bus=n_bus, meshed=meshed)
    path = folder / f"random{seed}_{n_bus}_{'meshed' if meshed else 'radial'}.npz"
    folder.mkdir(parents=True, exist_ok=True)
    old = network_key(simulator(str(path))) if path.is_file() else None
    save_network(path, case.network, case.load_p, case.gen_p_max)
    key = network_key(simulator(str(path)))
    if old not in (None, key):
        log.warning("%s held another network (the generator changed): replaced; its runs are trained again", path)
    meta = {k: v for k, v in case.meta.items() if k in ("seed", "n_bus", "topology", "n_load", "n_gen", "n_des",
                                                         "n_classical", "n_branch", "peak_load_mw")}
    # the generator's n_gen counts classical and renewable generators, n_des its storage units
    return path, {**meta, "n_renewable": meta["n_gen"] - meta["n_classical"], "n_storage": meta.pop("n_des"),
                  "network_key": key}


def _copy_network(src: Path, folder: Path) -> tuple[Path, dict[str, Any]]:
    """A user's network file copied to ``folder`` (its name kept); (path, its meta as :func:`write_network`'s)."""
    import shutil

    from anm_torchrl.grid.identity import network_key
    from anm_torchrl.networks import simulator
    from anm_torchrl.networks.user import load_network_file

    case = load_network_file(src)  # checked as every recipe checks it
    path = folder / src.name
    folder.mkdir(parents=True, exist_ok=True)
    if path.resolve() != src.resolve():
        shutil.copyfile(src, path)
    kind = case.network["device"][:, 2]
    meta = {"n_bus": int(case.network["bus"].shape[0]), "topology": "file", "n_load": int((kind == -1).sum()),
            "n_classical": int((kind == 1).sum()), "n_renewable": int((kind == 2).sum()),
            "n_storage": int((kind == 3).sum()), "n_branch": int(case.network["branch"].shape[0]),
            "source": case.source}
    return path, {**meta, "network_key": network_key(simulator(str(path)))}


def reported_states(path: Path, overrides: tuple[str, ...] = ()) -> dict[str, Any]:
    """The test states every recipe reports on for the network file ``path`` (the PPO recipe's config with the
    network's per-network entry and ``overrides``): episodes, seed, steps, gamma."""
    cfg, _ = cell_config([sys.executable, str(RECIPES / "ppo.py"), f"network={path}", *overrides])
    ev = cfg.eval
    steps = ev.test_max_steps if ev.test_max_steps is not None else ev.max_steps
    return {"episodes": int(ev.test_episodes), "seed": int(ev.test_seed), "steps": int(steps), "gamma": float(ev.gamma)}


def baselines_command(path: Path, protocol: dict, out: Path) -> str:
    """The gap study's command line that measures the baselines of ``path`` on ``protocol``'s states into ``out``."""
    return (f"python -m anm_torchrl.cli.gap --network {path} --rows optimal,do_nothing --episodes "
            f"{protocol['episodes']} --seed {protocol['seed']} --steps {protocol['steps']} --out {out}")


def _baselines_done(out: Path, path: Path, protocol: dict, key: str) -> bool:
    if not out.is_file():
        return False
    rec = json.loads(out.read_text())
    p = rec.get("protocol", {})
    same = (p.get("network") == str(path) and rec.get("network_key") == key
            and all(p.get(k) == v for k, v in protocol.items()))
    return same and {"optimal", "do_nothing"} <= set(rec.get("rows", {}))


def _solve_baselines(path: Path, protocol: dict, out: Path, key: str) -> float:
    """Worker: the gap study's measurement of the optimum and do-nothing (:func:`.gap.measure`, as its command line
    does); its record gets the network's key (a later study reuses it only for the same network). Returns the wall
    time (s)."""
    import torch

    from anm_torchrl.experiments.gap import measure, write_record

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    rec = measure(str(path), protocol["episodes"], protocol["seed"], protocol["steps"], out,
                  baselines_command(path, protocol, out), rows=["optimal", "do_nothing"])
    write_record(out, {**rec, "network_key": key})
    return time.perf_counter() - t0


def solve_baselines(todo: dict[Path, tuple[Path, dict, str]], jobs: int) -> list[dict[str, Any]]:
    """Measure the baselines of every ``out -> (network file, protocol, network key)`` in ``todo``, ``jobs`` at a
    time, each in a fresh process; how each went (``error`` holds a failure's traceback)."""
    if not todo:
        return []
    outcomes = []
    ctx = multiprocessing.get_context("spawn")  # no forked torch state; one network per process
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, max_tasks_per_child=1) as pool:
        futures = {out: pool.submit(_solve_baselines, path, protocol, out, key)
                   for out, (path, protocol, key) in todo.items()}
        for out, fut in futures.items():
            try:
                outcomes.append({"record": str(out), "wall_s": fut.result(), "error": None})
            except Exception as err:  # noqa: BLE001 - a failed network is reported, the others go on
                outcomes.append({"record": str(out), "error": "".join(traceback.format_exception(err))[-2000:]})
    return outcomes


def cell_dir(runs_dir: Path, path: Path, algorithm: str, seed: int) -> Path:
    """The run directory of the cell of ``algorithm`` and ``seed`` on the network file ``path``."""
    return runs_dir / f"{path.stem}_{algorithm}_s{seed}"


def cell_command(algorithm: str, path: Path, seed: int, run_dir: Path, overrides: tuple[str, ...] = ()) -> list[str]:
    """A cell: the recipe's documented command on the network file (its ``default`` entry; ``surrogate=pinn`` for
    ``ppo_pinn``), ``seed``, then ``overrides`` (a smoke test's smaller budget)."""
    recipe, keys, _ = RECIPE[algorithm]
    return [sys.executable, str(RECIPES / recipe), f"network={path}", *keys, f"seed={seed}",
            "logger.progress=false", *overrides, f"hydra.run.dir={run_dir}"]


def read_cell(run_dir: Path, protocol: dict) -> dict[str, Any]:
    """A finished cell's score on the test states (its ``best.pt``), budget and time.

    Raises:
        ValueError: the run's test states are not ``protocol``'s.
    """
    s = json.loads((run_dir / "summary.json").read_text())
    got = tested_states(s)
    if got != protocol:
        raise ValueError(f"{run_dir}: tested on {got}, the baselines on {protocol}")
    surrogate = s["config"]["surrogate"]["name"]
    return {"run_dir": str(run_dir), "seed": int(s["config"]["seed"]),
            "discounted_return": s["test"]["best"]["discounted_return"],
            "validation_best": s["best_eval"]["discounted_return"], "frames": int(s["frames"]),
            "surrogate": surrogate, "true_env_frames": int(s["frames"]) if surrogate == "none" else 0,
            "model_frames": s.get("model_frames"), "wall_s": float(s["wall_time"]),
            "stopped_early": bool(s["stopped_early"])}


def kept_network(keep: dict[str, Any] | None, net: dict[str, Any], source: str) -> dict[str, Any] | None:
    """The row of ``net``'s spec in an earlier record ``keep`` (from ``source``), or None.

    Raises:
        ValueError: the row is another network (its key) or was scored on other test states.
    """
    row = next((r for r in (keep or {}).get("networks", []) if r.get("spec") == net["spec"]), None)
    if row is not None and (row.get("network_key") != net["meta"]["network_key"]
                            or row.get("protocol") != net["protocol"]):
        raise ValueError(f"{source}: {net['spec']} there is network {row.get('network_key')} on the states "
                         f"{row.get('protocol')}, here network {net['meta']['network_key']} on {net['protocol']}: "
                         f"its rows cannot be kept")
    return row


def study(specs: list[str], algorithms: list[str], seeds: list[int], runs_dir: Path, jobs: int = 2,
          overrides: tuple[str, ...] = (), keep: dict[str, Any] | None = None,
          keep_source: str = "the kept record") -> dict[str, Any]:
    """Write every network, solve (or reuse) its baselines, train (or reuse) every cell, then the record.

    ``keep``: an earlier record of this study (read from ``keep_source``); a network of it keeps its baselines when
    they are not on disk, and every algorithm of it not in ``algorithms`` keeps its cells (marked ``kept_from``),
    so one algorithm's column can be re-made after its defaults change without solving the optimum again.
    """
    unknown = sorted(set(algorithms) - set(RECIPE))
    if unknown:
        raise ValueError(f"unknown algorithms {unknown}; choose from {sorted(RECIPE)}")
    if keep is not None and not (isinstance(keep, dict) and isinstance(keep.get("networks"), list)):
        raise ValueError(f"{keep_source}: not a record of this study (no 'networks' list)")
    runs_dir = Path(runs_dir).resolve()
    t0 = time.perf_counter()
    nets = []
    for spec in specs:
        path, meta = write_network(spec, runs_dir)
        protocol = reported_states(path, overrides)
        nets.append({"spec": spec, "path": path, "meta": meta, "protocol": protocol,
                     "gap": path.with_suffix(".gap.json")})
        nets[-1]["kept"] = kept_network(keep, nets[-1], keep_source)
    todo = {n["gap"]: (n["path"], n["protocol"], n["meta"]["network_key"]) for n in nets
            if not _baselines_done(n["gap"], n["path"], n["protocol"], n["meta"]["network_key"])
            and (n["kept"] or {}).get("optimum") is None}
    for out in todo:
        out.unlink(missing_ok=True)  # another network or protocol: the gap command would refuse to extend it
    failed = [o for o in solve_baselines(todo, jobs) if o["error"]]
    # a cell of a replaced network file is trained again: its marker's network key differs (cells.finished)
    commands = {d: cell_command(a, n["path"], s, d, tuple(overrides))
                for n in nets for a in algorithms for s in seeds
                for d in [cell_dir(runs_dir, n["path"], a, s)]}
    failed += [o for o in run_cells(commands, jobs) if o["error"]]
    # the kept record's columns in its order, the re-made ones where they were, new ones last
    kept_columns = [a for a in (keep or {}).get("algorithms", []) if a in RECIPE and a not in algorithms]
    order = (keep or {}).get("algorithms", []) + algorithms
    columns = sorted(kept_columns + algorithms, key=order.index)
    rows = [_network_row(n, algorithms, columns, seeds, runs_dir, commands, keep_source) for n in nets]
    return {"what": __doc__.split("\n\n")[0].replace("\n", " "), "algorithms": columns, "seeds": seeds,
            **({"kept_from": keep_source} if keep is not None else {}),
            "jobs": jobs, "overrides": list(overrides), "networks": rows, "failed": failed,
            "invocation_wall_s": time.perf_counter() - t0,
            "machine": {"cpus": os.cpu_count(), "threads_per_run": 1, "concurrent_runs": jobs}}


def _network_row(net: dict, algorithms: list[str], columns: list[str], seeds: list[int], runs_dir: Path,
                 commands: dict[Path, list[str]], keep_source: str) -> dict[str, Any]:
    row = {"spec": net["spec"], "file": net["path"].name, **net["meta"], "protocol": net["protocol"],
           "optimum": None, "do_nothing": None, "optimum_wall_s": None, "algorithms": []}
    kept = net.get("kept") or {}
    if kept.get("optimum") is not None and not net["gap"].is_file():
        row.update({k: kept.get(k) for k in ("optimum", "do_nothing", "optimum_wall_s", "baselines_command")},
                   baselines_kept_from=keep_source)
    if net["gap"].is_file():
        rec = json.loads(net["gap"].read_text())
        rows = rec.get("rows", {})
        if {"optimal", "do_nothing"} <= set(rows):
            row.update(optimum=rows["optimal"]["mean_discounted_return"],
                       do_nothing=rows["do_nothing"]["mean_discounted_return"],
                       optimum_wall_s=rows["optimal"]["wall_s"], baselines_command=rec["commands"][-1])
    for a in columns:
        if a not in algorithms:
            entry = next((e for e in kept.get("algorithms", []) if e["algorithm"] == a), {"algorithm": a, "runs": []})
            row["algorithms"].append({**entry, "kept_from": keep_source})
            continue
        dirs = [cell_dir(runs_dir, net["path"], a, s) for s in seeds]
        runs = [read_cell(d, net["protocol"]) for d in dirs if (d / "summary.json").is_file()]
        entry = {"algorithm": a, "command": shown(commands[dirs[0]]).replace(str(net["path"]), net["path"].name),
                 "runs": runs}
        if runs:
            values = [r["discounted_return"] for r in runs]
            entry.update(discounted_return=statistics.fmean(values),
                         std_over_seeds=statistics.stdev(values) if len(values) > 1 else None,
                         wall_s=statistics.fmean(r["wall_s"] for r in runs),
                         frames=statistics.fmean(r["frames"] for r in runs), surrogate=runs[0]["surrogate"],
                         true_env_frames=statistics.fmean(r["true_env_frames"] for r in runs),
                         model_frames=(statistics.fmean(r["model_frames"] for r in runs)
                                       if all(r["model_frames"] is not None for r in runs) else None))
            if row["optimum"] is not None:
                def gain(ret: float) -> float:
                    return against_optimum(ret, row["optimum"], row["do_nothing"])[1]

                entry["gain_pct"] = gain(entry["discounted_return"])
                entry["gain_pct_per_seed"] = [gain(v) for v in values]
        row["algorithms"].append(entry)
    return row


def markdown(record: dict) -> str:
    """The study as a Markdown table: one line per network, each algorithm's test return and gain share."""
    algos = record["algorithms"]
    p = record["networks"][0]["protocol"]
    kinds = ("random networks (`SEED:BUSES:topology`, `anm_torchrl.networks.random.generate`) saved as a user's "
             "files" if all(n.get("topology") != "file" for n in record["networks"]) else
             "networks given as files (random specs `SEED:BUSES:topology` saved as a user's files, and network files)")
    intro = [f"{kinds[0].upper()}{kinds[1:]}; {p['episodes']} test states (seed {p['seed']}), T = {p['steps']:,}, "
             f"γ = {p['gamma']}; each "
             f"algorithm's `best.pt` (chosen on its validation states) after "
             + ", ".join(f"`{' '.join(['python', f'recipes/{RECIPE[a][0]}', 'network=<file>', *RECIPE[a][1]])}`"
                         for a in algos)
             + f" (seeds {', '.join(map(str, record['seeds']))}); in parentheses the share of the optimum's gain over "
             f"do-nothing", ""]
    head = ["network", "buses", "loads / classical / renewable / storage", "do-nothing", "optimum"]
    head += [RECIPE[a][2] for a in algos]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * 3 + "---:|" * (2 + len(algos))]
    for n in record["networks"]:
        cells = [f"`{n['file'] if n.get('topology') == 'file' else n['spec']}`", str(n["n_bus"]),
                 f"{n['n_load']} / {n['n_classical']} / {n['n_renewable']} / {n['n_storage']}",
                 _num(n["do_nothing"]), _num(n["optimum"])]
        for a in n["algorithms"]:
            if "discounted_return" not in a:
                cells.append("–")
                continue
            gain = f" ({a['gain_pct']:.1f} %)" if a.get("gain_pct") is not None else ""
            if a["model_frames"] is not None:  # SHAC: 0 true-env frames
                frames = f"{a['model_frames']:,.0f} model frames"
            elif a["surrogate"] != "none":  # trained on a surrogate: 0 true-env frames
                frames = f"{a['frames']:,.0f} {a['surrogate'].upper()} frames"
            else:
                frames = f"{a['frames']:,.0f} frames"
            cells.append(f"{_num(a['discounted_return'])}{gain}, {frames}, {a['wall_s']:,.0f} s")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(intro + lines) + "\n"


def _num(x: float | None) -> str:
    return "–" if x is None else f"{x:.4f}"


def update_page(page: str | Path, record: dict, source: str) -> None:
    """Rewrite the study's block of ``page`` with :func:`markdown` of ``record`` (read from ``source``).

    Raises:
        ValueError: the page has no block (nothing is written then).
    """
    replace_marked_blocks([page], *MARKERS, markdown(record) + f"\n_From `{source}`._\n")
