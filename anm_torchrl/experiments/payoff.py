"""The study "when does a surrogate pay off?" (issue 13 item 5): cost per transition against bus count, the PINN's
accuracy against bus count, and PPO's time to a fixed fraction of do-nothing's loss.

Three parts, each optional (``cfg["parts"]``):

* ``cost`` — per registered network (6 → 115 buses) and batch size, in ONE run: gym-anm 2.0.1's generic env
  (batch 1; :func:`~anm_torchrl.benchmarks.env_networks.bench_gym_generic`), ``ANMEnv`` on the numba and the
  torch backend, and every surrogate spec whose model exists for that network (PINN, XGBoost, MLP ``dnn``...;
  a missing one is a row with its reason). Each measurement is ``rand_action`` + ``step_and_maybe_reset`` after a
  warm-up (construction, model load, first reset and step) timed apart. The machine is shared: every row carries
  the 1-minute load average read just before it, and the ratio to the numba backend at the same network and
  batch (measured next to it) is the figure to compare across rows. ``crossover``: per surrogate and batch, the
  smallest bus count at which it is cheaper per transition than the cheaper exact backend (None: never, over the
  networks measured). A spec ``{name: xgb, dataset: ..., path: <a booster trained with a round cap>, capped: true}``
  times that booster as a *lower bound* of the uncapped one's cost (:func:`capped_bound`; rows carry
  ``lower_bound``): it settles the comparison where it already costs more than the exact backend.
* ``accuracy`` — the PINN's accuracy and training time against bus count, read from the record of the generic
  PINN (``accuracy_record``, default ``results/pinn/pinn_generic_accuracy.json``); never trained here.
* ``ppo`` — PPO (:func:`~anm_torchrl.training.protocol.train`, the recipe's loop) on ``network`` with each
  training env (``none``: the true simulator; a surrogate spec), seeds ``seeds``, a wall-clock cap
  (``timeout_s``): the time (wall, training only, frames) to first reach a return ≥ ``threshold_fraction`` ×
  do-nothing's return on the same validation states (returns are < 0: 0.5 = half of do-nothing's loss), runs that never reach it censored at their length
  (:mod:`.time_to_return`), a surrogate's training time added when given (``surrogate_train_s``: network → label →
  seconds). Runs made earlier by the same code may be reused (``reuse``: label → list of ``run_ppo`` record files;
  the seeds they do not cover are run).
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Any

from anm_torchrl.experiments.common import RunContext, label, make_env_or_reason
from anm_torchrl.experiments.io import read_json, result, write_json

log = logging.getLogger(__name__)

PARTS = ("cost", "accuracy", "ppo")
EXACT = ("numba", "torch")
ACCURACY_RECORD = Path(__file__).resolve().parents[2] / "results" / "pinn" / "pinn_generic_accuracy.json"


def _load() -> float:
    return os.getloadavg()[0]


def _row(network: str, n_bus: int, impl: str, batch: int, warm: float | None, rate: float | None,
         load: float, **extra) -> dict[str, Any]:
    us = None if not rate else 1e6 / rate
    return {"network": network, "n_bus": n_bus, "impl": impl, "batch": batch, "warm_s": warm,
            "transitions_per_s": rate, "us_per_transition": us, "load_avg_1min": load, **extra}


def surrogate_row(spec: dict, network: str, n_bus: int, batch: int, min_time: float, min_steps: int,
                  seed: int) -> dict[str, Any]:
    """One surrogate env's warm-up and rate on ``network`` at ``batch`` (a reason instead when it has no model)."""
    from anm_torchrl.benchmarks.timing import time_env_steps

    load = _load()
    if spec["name"] == "pinn":  # time an existing model only: never train one inside a timing loop
        spec = {"train_if_missing": False, **spec}
    spec = dict(spec)
    bound = capped_bound(spec) if spec.pop("capped", False) else None
    env, why = make_env_or_reason(spec, 1, network=network)
    if env is None:
        return _row(network, n_bus, label(spec), batch, None, None, load, reason=why)
    del env

    def make():
        env, err = make_env_or_reason(spec, batch, seed=seed, network=network)
        if env is None:
            raise RuntimeError(err)
        return env

    warm, steps_per_s = time_env_steps(make, min_time, min_steps, seed)
    return _row(network, n_bus, label(spec), batch, warm, batch * steps_per_s, load,
                **({"lower_bound": bound} if bound else {}))


def capped_bound(spec: dict) -> str:
    """For a spec ``{name: xgb, dataset, path, capped: true}``: why its model's cost per transition is a lower
    bound of the uncapped model's (:func:`~anm_torchrl.surrogates._xgb.capped_prefix_reason`); its rows carry this
    as ``lower_bound``. For a network where the early-stopped booster takes hours to train (SimBench: 80-115 s per
    round on 2 cores), a capped one answers whether XGBoost can be cheaper than the exact simulator.

    Raises:
        ValueError: not an XGBoost spec with a ``path``, or a model that bounds nothing.
    """
    from anm_torchrl.surrogates._xgb import capped_prefix_reason
    from anm_torchrl.surrogates.regressors.defaults import DEFAULT_PARAMS
    from anm_torchrl.surrogates.regressors.io import read_surrogate_meta

    if spec.get("name") != "xgb" or not spec.get("path"):
        raise ValueError(f"capped: true needs an xgb spec with the capped model's path, got {spec}")
    path = Path(spec["path"])
    meta = read_surrogate_meta(path)
    try:
        return capped_prefix_reason(meta["params"], meta["train_info"], DEFAULT_PARAMS["xgb"])
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from err


def _predicted_step_s(rows: list[dict], network: str, impl: str, batch: int) -> float | None:
    """Seconds one step of ``impl`` at ``batch`` would take at its cost per transition at the largest smaller batch
    measured (an upper bound: the cost per transition of a batched env falls with the batch); None without one."""
    smaller = [r for r in rows if r["network"] == network and r["impl"] == impl and r["batch"] < batch
               and r["us_per_transition"]]
    if not smaller:
        return None
    return max(smaller, key=lambda r: r["batch"])["us_per_transition"] * 1e-6 * batch


def cost_rows(networks: list[str], batches: list[int], surrogates: list[dict], min_time: float, min_steps: int,
              gym_steps: int, seed: int = 0, backends: tuple[str, ...] = EXACT, max_step_s: float = 30.0
              ) -> list[dict[str, Any]]:
    """Rows of :func:`_row` for every network × implementation × batch (see the module docstring). A batched row
    whose step is predicted (:func:`_predicted_step_s`) to exceed ``max_step_s`` is skipped, with the prediction."""
    from anm_torchrl.benchmarks.env_networks import bench_anm_env, bench_gym_generic, load_case

    rows: list[dict[str, Any]] = []
    for name in networks:
        case = load_case(name)
        n_bus = int(case["network"]["bus"].shape[0])
        if gym_steps > 0:
            load = _load()
            r = bench_gym_generic(case, gym_steps, seed)
            rows.append(_row(name, n_bus, "gym_anm", 1, r["warm"], r["rate"], load))
        for b in sorted(batches):
            for impl, measure in ([(f"anm_env_{k}", lambda b, k=k: bench_anm_env(case, b, k, min_time, min_steps,
                                                                                    seed)) for k in backends]
                                  + [(label(sp), sp) for sp in surrogates]):
                pred = _predicted_step_s(rows, name, impl, b) if b > 1 else None
                if pred is not None and pred > max_step_s:
                    rows.append(_row(name, n_bus, impl, b, None, None, _load(),
                                     skipped=f"one step predicted {pred:.0f} s > max_step_s {max_step_s:g}"))
                elif callable(measure):
                    load = _load()
                    r = measure(b)
                    rows.append(_row(name, n_bus, impl, b, r["warm"], r["rate"], load))
                else:
                    rows.append(surrogate_row(measure, name, n_bus, b, min_time, min_steps, seed))
            log.info("payoff cost: %s batch %d done", name, b)
    for r in rows:  # ratio to numba at the same network and batch, measured in the same run
        ref = next((q for q in rows if q["network"] == r["network"] and q["batch"] == r["batch"]
                    and q["impl"] == "anm_env_numba" and q["us_per_transition"]), None)
        r["x_numba"] = (r["us_per_transition"] / ref["us_per_transition"]
                        if ref is not None and r["us_per_transition"] else None)
    return rows


def crossover(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (surrogate, batch): the smallest bus count where its cost per transition is below the cheaper exact
    backend's (``n_bus`` None: never over the networks measured), and the bus counts it was measured at."""
    exact = {f"anm_env_{b}" for b in EXACT}
    out = []
    for impl in sorted({r["impl"] for r in rows if r["impl"] not in exact and r["impl"] != "gym_anm"}):
        for batch in sorted({r["batch"] for r in rows}):
            measured, first = [], None
            for r in sorted((r for r in rows if r["impl"] == impl and r["batch"] == batch and r["us_per_transition"]),
                            key=lambda r: r["n_bus"]):
                best = min((q["us_per_transition"] for q in rows if q["network"] == r["network"]
                            and q["batch"] == batch and q["impl"] in exact and q["us_per_transition"]), default=None)
                if best is None or (r.get("lower_bound") and r["us_per_transition"] < best):
                    continue  # a lower bound below the exact cost does not say which is cheaper
                measured.append(r["n_bus"])
                if first is None and r["us_per_transition"] < best:
                    first = r["n_bus"]
            out.append({"impl": impl, "batch": batch, "crossover_n_bus": first, "measured_n_bus": measured})
    return out


def accuracy_part(path: str | Path | None) -> dict[str, Any]:
    """The generic PINN's accuracy-vs-bus-count record, or why it is not available."""
    p = Path(path) if path else ACCURACY_RECORD
    if not p.is_file():
        return {"available": False, "reason": f"{p} not found (the generic PINN's record has not landed)"}
    rec = read_json(p)
    return {"available": True, "file": str(p), "status": rec.get("status"), "data": rec.get("data", rec)}


def reread_accuracy(dst: str | Path, src: str | Path | None = None) -> dict:
    """Replace the ``pinn_accuracy`` part of the payoff record ``dst`` in place by :func:`accuracy_part` of ``src``
    (default the generic PINN's record), e.g. after one of its networks was re-measured."""
    rec = read_json(dst)
    rec["data"]["pinn_accuracy"] = accuracy_part(src)
    rec["data"]["parts"] = list(dict.fromkeys([*rec["data"].get("parts", []), "accuracy"]))
    write_json(dst, rec)
    return rec


def do_nothing_return(network: str, base: dict[str, Any]) -> dict[str, Any]:
    """Do-nothing's metrics on the PPO runs' validation states (same seed, count, length, network)."""
    from anm_torchrl.baselines import make_baseline
    from anm_torchrl.experiments.ppo_runs import eval_protocol
    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy
    from anm_torchrl.training.factory import make_true_env

    ev = eval_protocol({**base, "network": network})
    env = make_true_env(int(ev.num_episodes), seed=int(ev.seed), network=network)
    states = draw_initial_states(int(ev.num_episodes), int(ev.seed), env.sim, env.init)
    res = evaluate_policy(make_baseline("do_nothing", sim=env.sim), states, max_steps=int(ev.max_steps),
                          gamma=float(ev.gamma), env=env)
    return {**res.metrics(), "seconds": res.wall_time, "episodes": int(ev.num_episodes),
            "max_steps": int(ev.max_steps), "eval_seed": int(ev.seed)}


def test_baselines(network: str, base: dict[str, Any], specs: list) -> dict[str, Any]:
    """Baselines (``do_nothing``, ``{name: mpc_perfect, horizon: 16}``...) on the PPO runs' TEST states and test
    protocol (``eval.test_seed``, ``eval.test_episodes``, ``eval.test_max_steps`` or ``eval.max_steps``,
    ``eval.gamma``): label -> metrics, wall and CPU seconds."""
    from anm_torchrl.baselines import make_baseline
    from anm_torchrl.experiments.ppo_runs import eval_protocol
    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy
    from anm_torchrl.training.factory import make_true_env

    ev = eval_protocol({**base, "network": network})
    n, steps = int(ev.test_episodes), int(ev.max_steps if ev.test_max_steps is None else ev.test_max_steps)
    env = make_true_env(n, seed=int(ev.test_seed), network=network)
    states = draw_initial_states(n, int(ev.test_seed), env.sim, env.init)
    out = {}
    for spec in [{"name": x} if isinstance(x, str) else dict(x) for x in specs]:
        kw = {k: v for k, v in spec.items() if k != "name"}
        cpu0, load = time.process_time(), _load()
        res = evaluate_policy(make_baseline(spec["name"], sim=env.sim, **kw), states, max_steps=steps,
                              gamma=float(ev.gamma), env=env)
        out[label(spec) + "".join(f"_{k}{v}" for k, v in kw.items())] = {
            **res.metrics(), "seconds": res.wall_time, "cpu_s": time.process_time() - cpu0, "load_avg_1min": load,
            "episodes": n, "max_steps": steps, "test_seed": int(ev.test_seed), "gamma": float(ev.gamma)}
    return out


def surrogate_model_ids(network: str, specs: list[dict]) -> dict[str, Any]:
    """The default-cache PINN file a ``pinn`` spec without ``path`` uses on ``network``: its network key (the cache
    folder) and the file's SHA-256, so a record says which model the runs were trained on."""
    import hashlib

    from anm_torchrl.networks import simulator as network_simulator
    from anm_torchrl.surrogates.pinn.cache import default_path
    from anm_torchrl.training.factory import network_arguments

    out = {}
    for spec in specs:
        if spec["name"] != "pinn":
            continue
        f = Path(spec["path"]) if spec.get("path") else default_path(network_simulator(**network_arguments(network)))
        out[label(spec)] = {"file": str(f), "network_key": f.parent.name if not spec.get("path") else None,
                            "sha256": hashlib.sha256(f.read_bytes()).hexdigest() if f.is_file() else None}
    return out


def ppo_part(cfg: dict[str, Any], out_dir: Path) -> dict[str, Any]:
    """PPO time to ``threshold_fraction`` × do-nothing's return on ``network`` (see the module docstring), each
    run's CPU seconds, and the baselines of ``test_baselines`` on the runs' test states (the reported figures:
    ``test_fraction_of_do_nothing`` = a policy's test discounted return / do-nothing's; < 0.5 is "2× better")."""
    from anm_torchrl.experiments.ppo_curves import threshold_columns
    from anm_torchrl.experiments.ppo_runs import last_mean, ppo_overrides, run_ppo, time_to_reach

    network = str(cfg.get("network", "case33bw"))
    base = {**dict(cfg.get("base", {})), "network": network}
    dn = do_nothing_return(network, base)
    baselines = test_baselines(network, base, list(cfg.get("test_baselines") or ["do_nothing"]))
    dn_test = baselines.get("do_nothing", {}).get("discounted_return")
    fraction = float(cfg.get("threshold_fraction", 0.5))
    threshold = fraction * dn["return"]
    reuse = {k: [read_json(f) for f in v] for k, v in (cfg.get("reuse") or {}).items()}
    train_s = dict((cfg.get("surrogate_train_s") or {}).get(network) or {})
    runs, table = {}, []
    for spec in [{"name": n} if isinstance(n, str) else dict(n) for n in cfg.get("envs", ["none"])]:
        lab = label(spec)
        seed_runs = reuse.get(lab, [])
        for r in seed_runs:  # a reused run must have been made with this part's overrides (same states)
            r.setdefault("seed", int(next(o.split("=", 1)[1] for o in r["overrides"] if o.startswith("seed="))))
            want = set(ppo_overrides(spec, r["seed"], base))
            if not want <= set(r["overrides"]):
                raise ValueError(f"ppo.reuse[{lab!r}]: a run lacks overrides {sorted(want - set(r['overrides']))}")
        done = {r["seed"] for r in seed_runs}
        for s in [s for s in cfg.get("seeds", [0]) if s not in done]:  # the seeds no reused run covers
            cpu0 = time.process_time()  # in this process: its CPU time is the run's (one torch thread)
            r = run_ppo(ppo_overrides(spec, s, base), out_dir / "runs" / "payoff" / f"{lab}_s{s}",
                        timeout_s=cfg.get("timeout_s"))
            seed_runs = [*seed_runs, r | {"seed": s, "cpu_s": time.process_time() - cpu0}]
        for r in seed_runs:
            r["time_to_threshold"] = time_to_reach(r["curve"], threshold)
            r["last_return"] = last_mean(r["curve"], "return", 1)
            r["test"] = (r.get("summary") or {}).get("test")
        runs[lab] = seed_runs
        ok = [r for r in seed_runs if r["curve"]]
        first = lambda r, k: ((r.get("summary") or {}).get("test") or {}).get("best", {}).get(k)  # noqa: E731
        test_disc = [first(r, "discounted_return") for r in ok]
        table.append({"env": lab, "network": network, "seeds": [r.get("seed") for r in ok],
                      "frames": [r["curve"][-1]["frames"] for r in ok],
                      "wall_s": [r["curve"][-1]["wall_s"] for r in ok],
                      "best_eval_return": [max(c["return"] for c in r["curve"]) for r in ok],
                      "test_best_return": [first(r, "return") for r in ok],
                      "test_best_discounted_return": test_disc,
                      "test_fraction_of_do_nothing": [None if x is None or not dn_test else x / dn_test
                                                      for x in test_disc],
                      "cpu_s": [r.get("cpu_s") for r in ok],
                      "load_avg_1min": [r.get("load_avg_1min") for r in ok],
                      **threshold_columns(ok, train_s.get(lab, 0.0 if lab == "none" else None))})
    specs = [{"name": n} if isinstance(n, str) else dict(n) for n in cfg.get("envs", ["none"])]
    return {"network": network, "do_nothing": dn, "threshold_fraction": fraction, "threshold": threshold,
            "base": base, "test_baselines": baselines, "surrogate_models": surrogate_model_ids(network, specs),
            "runs": runs, "table": table}


def run(cfg: dict[str, Any], ctx: RunContext) -> dict:
    """cfg keys: ``parts`` (subset of :data:`PARTS`), ``networks`` (default every registered one), ``batch_sizes``,
    ``min_time``, ``min_steps``, ``gym_steps``, ``backends``, ``accuracy_record``, ``ppo`` (see :func:`ppo_part`).
    ``ctx.surrogates``: the specs timed in ``cost`` (those without a model on a network get a reason)."""
    surrogates, out_dir, seed = list(ctx.surrogates), ctx.out_dir, ctx.seed
    from anm_torchrl.networks import list_networks

    parts = list(cfg.get("parts", PARTS))
    bad = [p for p in parts if p not in PARTS]
    if bad:
        raise ValueError(f"payoff.parts: unknown {bad}; expected a subset of {list(PARTS)}")
    t0 = time.perf_counter()
    data: dict[str, Any] = {"parts": parts}
    if "cost" in parts:
        rows = cost_rows(list(cfg.get("networks") or list_networks()), [int(b) for b in cfg.get("batch_sizes", [1, 1024])],
                         surrogates, float(cfg.get("min_time", 1.0)), int(cfg.get("min_steps", 3)),
                         int(cfg.get("gym_steps", 20)), seed, tuple(cfg.get("backends", EXACT)),
                         float(cfg.get("max_step_s", 30.0)))
        data["rows"] = rows
        data["crossover"] = crossover(rows)
    if "accuracy" in parts:
        data["pinn_accuracy"] = accuracy_part(cfg.get("accuracy_record"))
    if "ppo" in parts:
        data["ppo"] = ppo_part(dict(cfg.get("ppo", {})), Path(out_dir))
    data["wall_s"] = time.perf_counter() - t0
    status, reason = _status(data)
    return result("payoff", status, data, reason=reason, config=cfg, seeds={"seed": seed})


def _status(data: dict) -> tuple[str, str | None]:
    """A payoff record's status and reason from its data: "partial" while a cost row lacks a model (or was
    skipped) or the PINN accuracy record is absent; recomputed whenever rows are merged in."""
    missing = [r for r in data.get("rows", []) if r.get("reason") or r.get("skipped")]
    status = "partial" if missing or not data.get("pinn_accuracy", {"available": True})["available"] else "ok"
    return status, None if status == "ok" else (
        f"{len(missing)} cost rows without a model or skipped; PINN accuracy record "
        f"{'present' if data.get('pinn_accuracy', {}).get('available') else 'absent or not asked'}")


def ppo_parts(data: dict) -> list[dict]:
    """The PPO parts of a payoff record's ``data``, one per network: ``ppo_by_network`` (a merged record,
    :func:`merge_ppo`) or the ``ppo`` of a single run."""
    if "ppo_by_network" in data:
        return list(data["ppo_by_network"].values())
    return [data["ppo"]] if data.get("ppo") else []


def merge_ppo(src: str | Path, dst: str | Path, note: str | None = None) -> dict:
    """Put the ``ppo`` part of the payoff record ``src`` (e.g. a ``preset.payoff.parts=[ppo]`` run) into the payoff
    record ``dst`` in place, under ``data.ppo_by_network[<its network>]``, keeping ``dst``'s other parts and other
    networks (a single-run ``data.ppo`` of ``dst`` moves there first); ``meta.ppo_from[<network>]`` says where it
    came from, and ``note`` (how ``src`` was made) replaces ``dst``'s note about that network's former part
    (``meta.notes["ppo_<network>"]``).

    Raises:
        ValueError: ``src`` has no ``ppo`` part.
    """
    new, rec = read_json(src), read_json(dst)
    if "ppo" not in (new.get("data") or {}):
        raise ValueError(f"{src}: no data.ppo to merge (parts {new.get('data', {}).get('parts')})")
    d, meta = rec["data"], rec["meta"]
    notes = meta.setdefault("notes", {})
    if "ppo" in d:  # a single-run ppo part (one network): keyed by its network from now on
        old = d.pop("ppo")
        d["ppo_by_network"] = {old["network"]: old}
        if "ppo_from" in meta and "file" in meta["ppo_from"]:
            meta["ppo_from"] = {old["network"]: meta["ppo_from"]}
        if "ppo" in notes:
            notes[f"ppo_{old['network']}"] = notes.pop("ppo")
    part = new["data"]["ppo"]
    net = part["network"]
    d.setdefault("ppo_by_network", {})[net] = part
    d["parts"] = list(dict.fromkeys([*d.get("parts", []), "ppo"]))
    meta.setdefault("ppo_from", {})[net] = {"file": str(src), "versions": new["meta"].get("versions"),
                                            "config": (new["meta"].get("config") or {}).get("ppo")}
    if note is not None:
        notes[f"ppo_{net}"] = note
    write_json(dst, rec)
    return rec


def merge_cost(src: str | Path, dst: str | Path, networks: list[str], note: str | None = None) -> dict:
    """Replace the cost rows of ``networks`` in the payoff record ``dst`` by those of the record ``src`` (a
    ``preset.payoff.parts=[cost]`` run on them: every implementation of a network is measured in the same run, so
    its ``x_numba`` ratios stay same-run ratios) and recompute the crossover; ``note`` goes to
    ``meta.notes["cost_<network>"]``.

    Raises:
        ValueError: ``src`` lacks rows of one of ``networks``.
    """
    new, rec = read_json(src), read_json(dst)
    rows = (new.get("data") or {}).get("rows") or []
    missing = [n for n in networks if not any(r["network"] == n for r in rows)]
    if missing:
        raise ValueError(f"{src}: no cost rows of {missing}")
    d = rec["data"]
    d["rows"] = [r for r in d["rows"] if r["network"] not in networks] + [r for r in rows if r["network"] in networks]
    d["crossover"] = crossover(d["rows"])
    rec["status"], rec["reason"] = _status(d)
    for n in networks:
        rec["meta"].setdefault("cost_from", {})[n] = {"file": str(src), "versions": new["meta"].get("versions")}
        if note is not None:
            rec["meta"].setdefault("notes", {})[f"cost_{n}"] = note
    write_json(dst, rec)
    return rec

