"""Throughput of ``ANMEnv`` against network size and batch size, with gym-anm, pandapower and lightsim2grid.

Usage::

    python -m anm_torchrl.benchmarks.env --network all [--batch-sizes 1,256,4096,16384] [--threads 2]
        [--backends numba,torch] [--gym-steps 30] [--pf-runs 20] [--min-time 1.0] [--max-step-s 20]
        [--out results/benchmarks/bench_env_networks]
    python -m anm_torchrl.benchmarks.env --solver-sweep [--sweep-sizes 6,10,16,24,33,50,70,120] [--threads 1]

Networks: every registered network (:func:`anm_torchrl.networks.list_networks`) plus synthetic radial feeders
``radial70`` and ``radial120`` (:func:`synthetic_feeder`) for the sizes no registered feeder covers yet.
Per network, in the same run (these machines are shared: compare ratios, not absolute rates):

* ``gym-anm`` — gym-anm 2.0.1's generic ``ANMEnv`` (a subclass whose ``next_vars`` reads the same profiles),
  one env, ``action_space.sample()`` actions, reset on termination; steps/s.
* ``pandapower runpp`` / ``lightsim2grid ac_pf`` (when installed: in no extra) — one AC power flow of the
  do-nothing injections on an equivalent pandapower network (branches as lines with their p.u. impedance, devices
  as ``sgen``; timing only).
* ``ANMEnv`` (numba | torch) — ``rand_action`` + ``step_and_maybe_reset`` at each batch size (warm-up apart).
  A row is skipped when one step is predicted to take more than ``--max-step-s`` seconds (the torch backend's
  memory is bounded by its Jacobian budget and tree solve, so size alone skips nothing).

``--solver-sweep`` times the numba kernel (``GridSimulator.step``, transitions/s) with the dense LU, the band
LU and the tree block LU (:func:`anm_torchrl.grid.constants.jacobian_ordering`) on synthetic
feeders of growing size (batch ``--sweep-batch``, 128): the crossover sets :data:`anm_torchrl.grid.tree_solve.BANDED_MIN_BUS`.
Writes ``<out>.json`` and ``<out>.md``.
"""

from __future__ import annotations

import argparse
import logging
import platform
import time
from pathlib import Path

import numpy as np
import torch

from anm_torchrl.argtypes import count, index, int_list, name_list, positive_float, run_main
from anm_torchrl.benchmarks.timing import _timed, time_env_steps, time_gym_steps
from anm_torchrl.grid import reset as grid_reset
from anm_torchrl.strict_json import json_text

log = logging.getLogger(__name__)
N_ = np.nan
SYNTHETIC = {"radial70": 70, "radial120": 120}


def synthetic_feeder(n_bus: int, seed: int = 0, T: int = 96) -> tuple[dict, np.ndarray, np.ndarray]:
    """A radial 20 kV feeder of ``n_bus`` buses (main trunk with laterals), gym-anm dict and (T, ·) profiles.

    A load (0.05–0.2 MW peak, Q/P 0.3) on every non-slack bus, a PV unit (1 MW, corners) on every 6th bus, a
    wind unit (2 MW) on every 15th, a 1 MW / 4 MWh storage unit on every 20th; lines 0.004 + 0.008j p.u. per
    segment (baseMVA 10), 12 MVA rating. Profiles: a daily load shape and a solar bell, seeded noise.
    """
    rng = np.random.default_rng(seed)
    bus = [[0, 0, 110, 1.0, 1.0]] + [[i, 1, 20, 1.05, 0.95] for i in range(1, n_bus)]
    branch = [[0, 1, 0.002, 0.02, 0, 40, 1, 0]]  # substation transformer
    for i in range(2, n_bus):
        parent = i - 1 if rng.random() < 0.75 else int(rng.integers(1, i))
        branch.append([parent, i, 0.004, 0.008, 0.0005, 12, N_, N_])
    dev = [[0, 0, 0, N_, 50, -50, 50, -50, *[N_] * 7]]
    for i in range(1, n_bus):
        dev.append([len(dev), i, -1, 0.3, 0, -rng.uniform(0.05, 0.2), *[N_] * 9])
        if i % 6 == 0:
            dev.append([len(dev), i, 2, N_, 1.0, 0, 0.6, -0.6, 0.8, N_, 0.3, -0.3, N_, N_, N_])
        if i % 15 == 0:
            dev.append([len(dev), i, 2, N_, 2.0, 0, 1.0, -1.0, N_, N_, N_, N_, N_, N_, N_])
        if i % 20 == 0:
            dev.append([len(dev), i, 3, N_, 1.0, -1.0, 0.8, -0.8, N_, N_, N_, N_, 4.0, 0.4, 0.92])
    dev_arr = np.array(dev, dtype=np.float64)
    t = np.arange(T) / T
    loads = dev_arr[dev_arr[:, 2] == -1]
    shape = 0.6 + 0.4 * np.sin(2 * np.pi * (t - 0.3)) ** 2
    load_p = loads[:, 5][None, :] * shape[:, None] * rng.uniform(0.9, 1.0, (T, loads.shape[0]))
    gens = dev_arr[dev_arr[:, 2] == 2]
    sun = np.clip(np.sin(np.pi * (t - 0.25) / 0.5), 0, None)
    gen_p_max = gens[:, 4][None, :] * np.where(gens[:, 4] > 1.5, 0.5 + 0.4 * rng.random((T, 1)), sun[:, None])
    network = {"baseMVA": 10.0, "bus": np.array(bus, float), "device": dev_arr, "branch": np.array(branch, float)}
    return network, load_p, gen_p_max


def load_case(name: str) -> dict:
    """``{"name", "network", "load_p", "gen_p_max", "delta_t", "gamma", "lamb", "costs_clipping"}``."""
    if name in SYNTHETIC:
        net, load_p, gen_p_max = synthetic_feeder(SYNTHETIC[name])
        return {"name": name, "network": net, "load_p": load_p, "gen_p_max": gen_p_max, "delta_t": 0.25,
                "gamma": 0.995, "lamb": 100.0, "costs_clipping": (1.0, 100.0)}
    from anm_torchrl.networks import get_network

    c = get_network(name)
    return {"name": name, "network": c.network, "load_p": c.load_p, "gen_p_max": c.gen_p_max,
            "delta_t": c.delta_t, "gamma": c.gamma, "lamb": c.lamb, "costs_clipping": tuple(c.costs_clipping)}


def _env_kwargs(case: dict) -> dict:
    return {k: case[k] for k in ("network", "load_p", "gen_p_max", "delta_t", "gamma", "lamb", "costs_clipping")}


def bench_gym_generic(case: dict, n_steps: int, seed: int = 0) -> dict:
    """gym-anm's generic ``ANMEnv`` on ``case``: steps/s over ``n_steps`` steps after a warm-up step."""
    import warnings

    from gym_anm import ANMEnv as GymANMEnv

    from anm_torchrl.networks.case_file import to_gym_anm
    from anm_torchrl.networks.validation import validate_network

    net = validate_network(case["network"])
    gym_net = to_gym_anm(net)  # gym-anm wants None where a value is missing
    load_p, gen_p_max = np.asarray(case["load_p"]), np.asarray(case["gen_p_max"])
    T = load_p.shape[0]

    class Generic(GymANMEnv):
        def __init__(self):
            super().__init__(gym_net, "state", 1, case["delta_t"], case["gamma"], case["lamb"],
                             aux_bounds=np.array([[0, T - 1]]), costs_clipping=case["costs_clipping"], seed=seed)

        def init_state(self):  # do-nothing injections at a random time index
            sim, s = self.simulator, np.zeros(self.state_N)
            t = int(self.np_random.integers(0, T))
            ids, kinds = list(sim.devices), [sim.devices[d].type for d in sim.devices]
            for k, i in enumerate([j for j, kd in enumerate(kinds) if kd == -1]):
                s[i] = load_p[t, k]
            for k, i in enumerate([j for j, kd in enumerate(kinds) if kd in (1, 2)]):
                s[i] = s[2 * len(ids) + sim.N_des + k] = gen_p_max[t, k]
            for k, d in enumerate([d for d in ids if sim.devices[d].type == 3]):
                s[2 * len(ids) + k] = (sim.devices[d].soc_min + sim.devices[d].soc_max) / 2 * sim.baseMVA
            s[-1] = t
            return s

        def next_vars(self, s_t):
            t = (int(round(s_t[-1])) + 1) % T
            return np.concatenate([load_p[t], gen_p_max[t], [t]])

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        warm, rate = time_gym_steps(Generic, n_steps, seed)
    return {"impl": "gym-anm 2.0.1 generic `ANMEnv`", "batch": 1, "warm": warm, "rate": rate}


def _pandapower_net(case: dict):
    """An equivalent pandapower network of ``case`` at its do-nothing point (row 0 of the profiles)."""
    import pandapower as pp

    from anm_torchrl.networks.validation import validate_network

    net = validate_network(case["network"])
    base = net["baseMVA"]
    pnet = pp.create_empty_network(sn_mva=base)
    for b in net["bus"]:
        pp.create_bus(pnet, vn_kv=b[2])
    pp.create_ext_grid(pnet, bus=0, vm_pu=1.0, va_degree=0.0)
    for br in net["branch"]:  # 1 km lines with the branch's p.u. impedance on the from-bus base (taps ignored)
        z_base = net["bus"][int(br[0]), 2] ** 2 / base
        pp.create_line_from_parameters(pnet, int(br[0]), int(br[1]), length_km=1.0, r_ohm_per_km=br[2] * z_base,
                                       x_ohm_per_km=br[3] * z_base,
                                       c_nf_per_km=br[4] / z_base / (2 * np.pi * 50) * 1e9, max_i_ka=100.0)
    dev = net["device"]
    loads, gens = np.flatnonzero(dev[:, 2] == -1), np.flatnonzero(np.isin(dev[:, 2], (1, 2)))
    for k, r in enumerate(loads):
        p = float(np.clip(case["load_p"][0, k], dev[r, 5], 0))
        pp.create_sgen(pnet, int(dev[r, 1]), p_mw=p, q_mvar=p * dev[r, 3])
    for k, r in enumerate(gens):
        pp.create_sgen(pnet, int(dev[r, 1]), p_mw=float(min(case["gen_p_max"][0, k], dev[r, 4])), q_mvar=0.0)
    return pnet


def bench_power_flows(case: dict, runs: int) -> list[dict]:
    """Seconds per AC power flow: pandapower ``runpp`` and (if importable) lightsim2grid's ``ac_pf``."""
    import warnings

    import pandapower as pp

    pnet = _pandapower_net(case)
    rows = []
    t0 = time.perf_counter()
    pp.runpp(pnet)
    warm = time.perf_counter() - t0
    t1 = time.perf_counter()
    for _ in range(runs):
        pp.runpp(pnet)
    rows.append({"impl": "pandapower 3 `runpp` (one power flow)", "batch": 1, "warm": warm,
                 "rate": runs / (time.perf_counter() - t1)})
    try:
        from lightsim2grid.gridmodel import init_from_pandapower
    except ImportError:
        log.info("lightsim2grid is not installed: its row is left out")
        return rows
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        model = init_from_pandapower(pnet)
        v0 = np.ones(len(pnet.bus), dtype=complex)
        converged = model.ac_pf(v0, 100, 1e-5).size > 0  # an empty V means no convergence
        warm = time.perf_counter() - t0
        reps = max(runs, 200)
        t1 = time.perf_counter()
        for _ in range(reps):
            model.ac_pf(v0, 100, 1e-5)
    rows.append({"impl": f"lightsim2grid `ac_pf` (one power flow{'' if converged else ', NOT converged'})",
                 "batch": 1, "warm": warm,
                 "rate": reps / (time.perf_counter() - t1)})
    return rows


def bench_anm_env(case: dict, batch: int, backend: str, min_time: float, min_steps: int, seed: int = 0) -> dict:
    """``ANMEnv`` on ``case`` at ``batch``: warm-up (construction, reset, first step) and transitions/s."""
    from anm_torchrl.envs import ANMEnv

    def make():
        return ANMEnv(**_env_kwargs(case), num_envs=batch, seed=seed, backend=backend)

    warm, steps_per_s = time_env_steps(make, min_time, min_steps, seed)
    return {"impl": f"`ANMEnv` ({backend})", "batch": batch, "warm": warm, "rate": batch * steps_per_s}


def solver_sweep(sizes: list[int], batch: int, min_time: float) -> list[dict]:
    """numba kernel transitions/s with the dense and the band LU on synthetic feeders of ``sizes`` buses."""
    from anm_torchrl.grid.constants import build_constants
    from anm_torchrl.grid.simulator import GridSimulator
    from anm_torchrl.networks.validation import validate_network

    rows = []
    for n in sizes:
        net, load_p, gen_p_max = synthetic_feeder(n)
        net = validate_network(net)
        rates = {}
        for solver in ("dense", "band", "tree"):
            sim = GridSimulator.from_tables(net, load_p, gen_p_max, 0.25, 0.995, 100.0, (1.0, 100.0),
                                            backend="numba", linear_solver=solver)
            gen = torch.Generator().manual_seed(0)
            state, _ = grid_reset.random_state(sim, batch, gen)
            lo, hi = sim.action_bounds()
            action = lo + torch.rand(batch, lo.numel(), generator=gen, dtype=torch.float64) * (hi - lo)
            box = {}

            def first(sim=sim, state=state, action=action):
                box["s"] = sim.step(state, action)[0]

            def step(sim=sim, state=state, action=action):
                sim.step(state, action)

            _, elapsed, k = _timed(first, step, min_time, 2)
            rates[solver] = batch * k / elapsed
        band = build_constants(sim, "band")
        rows.append({"n_bus": n, "kl": int(band.kl), "dense": rates["dense"], "band": rates["band"],
                     "tree": rates["tree"], "band/dense": rates["band"] / rates["dense"],
                     "tree/dense": rates["tree"] / rates["dense"]})
        log.info("solver sweep %s", rows[-1])
    return rows


def network_rows(case: dict, args) -> list[dict]:
    """Every measurement of one network (see the module docstring)."""
    n_bus = np.asarray(case["network"]["bus"]).shape[0]
    rows = []
    if args.gym_steps > 0:
        rows.append(bench_gym_generic(case, args.gym_steps))
    if args.pf_runs > 0:
        rows.extend(bench_power_flows(case, args.pf_runs))
    for backend in args.backends:
        rate = None
        for b in args.batch_sizes:
            if rate is not None and b / rate > args.max_step_s:
                rows.append({"impl": f"`ANMEnv` ({backend})", "batch": b,
                             "skipped": f"one step predicted {b / rate:.0f} s"})
                continue
            r = bench_anm_env(case, b, backend, args.min_time, args.min_steps)
            rate = r["rate"]
            rows.append(r)
            log.info("%s %s", case["name"], r)
    for r in rows:
        r["network"], r["n_bus"] = case["name"], n_bus
    return rows


def markdown(rows: list[dict]) -> str:
    """One table: network, buses, implementation, batch, warm-up, rate, ratio to gym-anm on that network."""
    gym = {r["network"]: r["rate"] for r in rows if r["impl"].startswith("gym-anm") and "rate" in r}
    lines = ["| network | buses | implementation | batch | warm-up (s) | steady-state transitions/s | vs gym-anm |",
             "|---|---:|---|---:|---:|---:|---:|"]
    for r in rows:
        if "skipped" in r:
            lines.append(f"| {r['network']} | {r['n_bus']} | {r['impl']} | {r['batch']:,} | – | skipped: "
                         f"{r['skipped']} | – |")
            continue
        g = gym.get(r["network"])
        ratio = f"{r['rate'] / g:,.1f}×" if g else "–"
        lines.append(f"| {r['network']} | {r['n_bus']} | {r['impl']} | {r['batch']:,} | {r['warm']:.3f} | "
                     f"{r['rate']:,.0f} | {ratio} |")
    return "\n".join(lines)


def sweep_markdown(rows: list[dict]) -> str:
    lines = ["| buses | band kl = ku | dense LU | band LU | tree block LU | band / dense | tree / dense |",
             "|---:|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['n_bus']} | {r['kl']} | {r['dense']:,.0f} | {r['band']:,.0f} | {r['tree']:,.0f} | "
              f"{r['band/dense']:.2f} | {r['tree/dense']:.2f} |" for r in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description="ANMEnv throughput vs network size, gym-anm, pandapower")
    parser.add_argument("--network", default=None, help="registered name, radial70, radial120, or 'all'")
    parser.add_argument("--solver-sweep", action="store_true", help="dense vs band LU crossover")
    parser.add_argument("--sweep-sizes", type=int_list(2), default=[6, 10, 16, 24, 33, 50, 70, 120])
    parser.add_argument("--sweep-batch", type=count, default=128)
    parser.add_argument("--batch-sizes", type=int_list(1), default=[1, 256, 4096, 16384])
    parser.add_argument("--backends", type=name_list(("numba", "torch")), default=["numba", "torch"])
    parser.add_argument("--gym-steps", type=index, default=30, help="gym-anm steady-state steps (0: skip)")
    parser.add_argument("--pf-runs", type=index, default=20, help="pandapower runpp repetitions (0: skip)")
    parser.add_argument("--min-time", type=positive_float, default=1.0)
    parser.add_argument("--min-steps", type=count, default=2)
    parser.add_argument("--max-step-s", type=positive_float, default=20.0, help="skip rows predicted slower per step")
    parser.add_argument("--threads", type=count, default=1, help="torch.set_num_threads (numba slices too)")
    parser.add_argument("--out", default=None, help="write <out>.json and <out>.md")
    args = parser.parse_args(argv)
    names = []
    if args.network:
        from anm_torchrl.networks import list_networks

        known = [*list_networks(), *SYNTHETIC]
        names = known if args.network == "all" else args.network.split(",")
        unknown = [n for n in names if n not in known]
        if unknown:  # was a warning, an empty table and a record written
            raise ValueError(f"--network: unknown network {unknown[0]!r}; known: {', '.join(known)}, all")
    if args.out:  # now, not after the measurement
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(args.threads)
    record = {"machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} thread(s)",
              "torch": torch.__version__, "numpy": np.__version__, "argv": argv, "time": time.ctime()}
    parts = []
    if args.solver_sweep:
        record["solver_sweep"] = solver_sweep(args.sweep_sizes, args.sweep_batch, args.min_time)
        parts.append(sweep_markdown(record["solver_sweep"]))
    if args.network:
        rows = []
        for name in names:
            rows.extend(network_rows(load_case(name), args))
        record["rows"] = rows
        parts.append(markdown(rows))
    text = "\n\n".join(parts) + (f"\n\n<!-- {record['machine']}, torch {record['torch']}, numpy {record['numpy']}; "
                                 "warm-up = construction + first reset + first step; ratios measured in one run "
                                 "on a shared machine -->")
    print(text)  # noqa: T201  (the benchmark's one table, as the ANM6 benchmark prints its table; before the write)
    if args.out:
        out = Path(args.out)
        out.with_suffix(".json").write_text(json_text(record, indent=1))
        out.with_suffix(".md").write_text(text + "\n")
    return text


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO)
    run_main(main, "anm_torchrl.benchmarks.env")
