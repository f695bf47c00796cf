"""Random valid gym-anm networks with daily profiles, deterministic by seed (the PINN battery, backend tests).

:func:`generate` draws a distribution network the way such grids are built: a slack at 132 kV, a 132/33 kV
transformer (tap 0.95–1.05, phase shift 0–6°, X ≤ 0.6 p.u. on the base), 33 kV lines in ohms converted to p.u.
on a base of 1–100 MVA, on bigger networks an 11 kV sub-feeder behind its own 33/11 kV transformer; radial
(a random tree with long laterals) or meshed (1–3 tie lines between feeder buses); every device type: loads
(Q/P 0.1–0.5), a classical generator (sometimes), PV and wind (capability corners present or absent), several
storage units (SOC_MIN > 0 on some, own efficiency). Profiles: one day at 15 min (T = 96): loads follow
residential / commercial shapes with noise, PV a clear-sky bell with clouds, wind a smooth random walk,
classical generators their PMAX.

A draw is kept only when it passes :func:`.validation.validate_network` and the exact Newton–Raphson converges
(1e-5 p.u.) on (a) the do-nothing operating point of every profile row, with every |V| in [0.85, 1.15] p.u.,
and (b) the four extreme corners of the devices' injection box (every bus at its lowest / highest P with its
lowest / highest Q: the box a PINN is trained on, :func:`anm_torchrl.grid.devices.bus_injection_box`); otherwise the next sub-draw of the same seed is tried (``attempt`` in the metadata), so
a seed always gives the same network.

:func:`small_random_network` is the backend tests' generator (4–14 buses, 100 MVA; the draws those tests
were written against). :func:`stiff_transformer_network` is the 9-bus network of issue 23 (132/33 kV, tap 1.03,
X = 0.55 p.u. on 100 MVA) on which the flat-start chord refinement of the PINN failed its rule.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from anm_torchrl.networks.validation import validate_network

N_ = np.nan
T_DAY = 96  # 15-min steps of one day (delta_t = 0.25 h)
SIZE_CLASSES = ((5, 15), (16, 40), (41, 80))


@dataclasses.dataclass
class RandomCase:
    """A generated network: ``network`` (gym-anm dict as a user writes it: lists, NaN where a value is missing;
    what ``make_env(network=...)`` takes), ``load_p`` (T, n_load) MW (≤ 0),
    ``gen_p_max`` (T, n_gen) MW (non-slack generators in device-id order) and ``meta`` (seed, attempt, bus count,
    topology, base, device counts, transformer data)."""

    network: dict
    load_p: np.ndarray
    gen_p_max: np.ndarray
    meta: dict[str, Any]


def small_random_network(rng: np.random.Generator) -> tuple[dict, np.ndarray, np.ndarray]:
    """A random valid gym-anm network dict and its profiles (T = 12), 4–14 buses (``tests/test_backends.py``)."""
    n_bus = int(rng.integers(4, 15))
    bus = [[0, 0, 132, 1.0, 1.0]] + [[i, 1, 33, 1.1, 0.9] for i in range(1, n_bus)]
    branch = []
    for i in range(1, n_bus):  # a random tree, then maybe a loop
        f = int(rng.integers(0, i))
        tap, shift = (rng.uniform(0.95, 1.05), rng.uniform(0, 10)) if rng.random() < 0.2 else (N_, N_)
        branch.append([f, i, rng.uniform(0.005, 0.04), rng.uniform(0.01, 0.08), rng.choice([0, 0.002]),
                       rng.choice([N_, 30.0]), tap, shift])
    if n_bus > 4 and rng.random() < 0.5:
        a, b = sorted(rng.choice(np.arange(1, n_bus), 2, replace=False))
        if not any({r[0], r[1]} == {a, b} for r in branch):
            branch.append([a, b, 0.03, 0.06, 0, 20, N_, N_])
    dev = [[0, 0, 0, N_, 200, -200, 200, -200, N_, N_, N_, N_, N_, N_, N_]]
    kinds = rng.choice([-1, 1, 2, 3], size=int(rng.integers(1, 2 * n_bus)), p=[0.4, 0.15, 0.25, 0.2])
    for k in kinds:
        d, b = len(dev), int(rng.integers(1, n_bus))
        if k == -1:
            dev.append([d, b, -1, rng.uniform(0, 0.4), N_, -rng.uniform(2, 10), *[N_] * 9])
        elif k in (1, 2):
            pmax, qmax = rng.uniform(5, 20), rng.uniform(3, 10)
            corner = [0.7 * pmax, N_, 0.5 * qmax, -0.5 * qmax] if rng.random() < 0.5 else [N_] * 4
            dev.append([d, b, int(k), N_, pmax, 0, qmax, -qmax, *corner, N_, N_, N_])
        else:
            pmax, qmax, soc_max = rng.uniform(3, 10), rng.uniform(2, 8), rng.uniform(5, 20)
            corner = [0.6 * pmax, -0.6 * pmax, 0.5 * qmax, -0.5 * qmax] if rng.random() < 0.5 else [N_] * 4
            dev.append([d, b, 3, N_, pmax, -pmax, qmax, -qmax, *corner, soc_max, rng.uniform(0, 0.3) * soc_max,
                        rng.uniform(0.7, 1.0)])
    net = validate_network({"baseMVA": 100, "bus": bus, "device": dev, "branch": branch})
    n_load = int((net["device"][:, 2] == -1).sum())
    n_gen = int(np.isin(net["device"][:, 2], (1, 2)).sum())
    return net, -rng.uniform(0, 10, (12, n_load)), rng.uniform(0, 25, (12, n_gen))


def stiff_transformer_network(scale: float = 3.0) -> tuple[dict, np.ndarray, np.ndarray]:
    """Issue 23's 9-bus network: 132/33 kV transformer (tap 1.03, X = 0.55 p.u., R = 0.01 p.u. on 100 MVA) feeding
    two 33 kV feeders; 4 loads (12·``scale`` MW peak in all), a classical generator without capability corners
    (8·``scale`` MW), a PV plant (6 MW, corners) and two storage units (SOC_MIN > 0) at the feeders' ends.

    At the default ``scale`` (36 MW of peak load through the transformer; do-nothing |V| ≥ 0.84 p.u.) the
    flat-start chord refinement (rule v1) meets no k ≤ 8 while damped Newton (v2) meets k ≤ 4, from the same
    untrained power-balance network (``tests/test_pinn_refine.py``).

    Returns the dict as given to ``make_env`` (NaN: missing), ``load_p`` (96, 4) and ``gen_p_max`` (96, 2) MW.
    """
    c = float(scale)
    bus = [[0, 0, 132, 1.04, 1.04]] + [[i, 1, 33, 1.1, 0.9] for i in range(1, 9)]
    z = 33.0 ** 2 / 100.0  # ohm base at 33 kV, 100 MVA
    line = lambda f, t, km: [f, t, 0.3 * km / z, 0.35 * km / z, 0.0, 20.0 * c, N_, N_]  # noqa: E731
    branch = [[0, 1, 0.01, 0.55, 0.0, 40.0 * c, 1.03, 0.0],
              line(1, 2, 4), line(2, 3, 3), line(3, 4, 5), line(4, 5, 4),  # feeder A: 1-2-3-4-5
              line(1, 6, 5), line(6, 7, 4), line(7, 8, 6)]  # feeder B: 1-6-7-8
    peaks = c * np.array([4, 3, 3, 2.0])
    dev = [[0, 0, 0, N_, N_, N_, N_, N_, N_, N_, N_, N_, N_, N_, N_],
           *[[1 + i, b, -1, qp, 0, -pk, *[N_] * 9] for i, (b, qp, pk) in enumerate(zip((3, 4, 6, 7),
                                                                                    (0.3, 0.25, 0.3, 0.2), peaks))],
           [5, 2, 1, N_, 8 * c, 0, 5 * c, -5 * c, *[N_] * 7],  # classical generator, no corners
           [6, 8, 2, N_, 6, 0, 3, -3, 4.5, N_, 1.5, -1.5, N_, N_, N_],  # PV with corners
           [7, 5, 3, N_, 3 * c, -3 * c, 2 * c, -2 * c, *[N_] * 4, 10 * c, 1.0 * c, 0.9],  # storage, feeder A's end
           [8, 8, 3, N_, 2 * c, -2 * c, 1.5 * c, -1.5 * c, *[N_] * 4, 6 * c, 0.6 * c, 0.92]]  # feeder B's end
    net = {"baseMVA": 100, "bus": bus, "device": dev, "branch": branch}
    validate_network(net)
    t = np.arange(T_DAY) * 0.25
    load_p = -_residential(t)[:, None] * peaks
    gen_p_max = np.stack([np.full(T_DAY, 8.0 * c), 6.0 * _pv(t, np.ones(T_DAY))], 1)
    return net, load_p, gen_p_max


def _residential(t: np.ndarray) -> np.ndarray:
    """Residential daily load shape (T,) in [0.3, 1]: night trough, morning and evening peaks; ``t`` in hours."""
    s = 0.45 + 0.25 * np.exp(-((t - 8.0) / 1.5) ** 2) + 0.55 * np.exp(-((t - 19.0) / 2.0) ** 2)
    return np.clip(s / s.max(), 0.3, 1.0)


def _commercial(t: np.ndarray) -> np.ndarray:
    """Commercial daily load shape (T,) in [0.3, 1]: a plateau 8–18 h."""
    s = 0.35 + 0.65 / (1 + np.exp(-(t - 8.0) * 2)) / (1 + np.exp((t - 18.0) * 2))
    return np.clip(s / s.max(), 0.3, 1.0)


def _pv(t: np.ndarray, clouds: np.ndarray) -> np.ndarray:
    """PV potential shape (T,) in [0, 1]: a clear-sky bell from 6 to 20 h times a cloud factor."""
    return np.clip(np.sin(np.pi * (t - 6.0) / 14.0), 0.0, None) ** 1.5 * clouds


def _smooth_walk(rng: np.random.Generator, n: int, lo: float, hi: float) -> np.ndarray:
    """A smooth random series (n,) in [lo, hi] (wind, clouds)."""
    x = np.cumsum(rng.normal(0, 1, n))
    x = np.convolve(x, np.ones(8) / 8, mode="same")
    x = (x - x.min()) / max(x.max() - x.min(), 1e-9)
    return lo + (hi - lo) * x


def _tree(rng: np.random.Generator, first: int, n: int, root: int) -> list[tuple[int, int]]:
    """Edges of a random tree on buses ``first..first+n-1`` hanging from ``root``: each new bus attaches to one of
    the last few buses (long laterals, as real feeders), sometimes to any earlier one (branching)."""
    nodes, edges = [root], []
    for b in range(first, first + n):
        parent = nodes[-1 - int(rng.integers(0, min(3, len(nodes))))] if rng.random() < 0.75 else \
            nodes[int(rng.integers(0, len(nodes)))]
        edges.append((parent, b))
        nodes.append(b)
    return edges


def _draw(rng: np.random.Generator, n_bus: int, meshed: bool) -> tuple[dict, np.ndarray, np.ndarray, dict]:
    """One candidate network dict, its profiles and metadata (validated, not yet checked by the power flow)."""
    base = float(rng.choice([1.0, 10.0, 100.0])) if rng.random() < 0.6 else float(10 ** rng.uniform(0, 2))
    n_feed = n_bus - 1  # buses behind the slack
    sub = n_bus >= 20 and rng.random() < 0.6  # an 11 kV sub-feeder behind a 33/11 kV transformer
    n_sub = int(rng.integers(4, max(5, n_feed // 3))) if sub else 0
    n33 = n_feed - n_sub
    kv = [132.0] + [33.0] * n33 + [11.0] * n_sub
    # total peak load ~ 0.3 MW per bus, a few MW to ~25 MW; the transformer sized for it
    p_tot = float(rng.uniform(0.2, 0.4) * n_feed + rng.uniform(1, 4))
    s_tr = p_tot * rng.uniform(1.4, 2.2)
    x_tr = min(0.6, float(rng.uniform(0.08, 0.16) * base / s_tr))
    tap, shift = float(rng.uniform(0.95, 1.05)), float(rng.choice([0.0, rng.uniform(0, 6)]))
    branch = [[0, 1, x_tr / rng.uniform(8, 20), x_tr, 0.0, round(s_tr, 3), tap, shift]]
    edges = _tree(rng, 2, n33 - 1, 1)
    if sub:
        j = int(rng.integers(1, n33 + 1))  # the 33 kV bus the sub-feeder's transformer hangs from
        s_sub = p_tot * rng.uniform(0.5, 0.9)
        x_sub = min(0.6, float(rng.uniform(0.06, 0.1) * base / s_sub))
        branch.append([j, n33 + 1, x_sub / 10, x_sub, 0.0, round(s_sub, 3), float(rng.uniform(0.97, 1.03)),
                       float(rng.choice([0.0, 30.0 * rng.integers(0, 2)]))])
        edges += _tree(rng, n33 + 2, n_sub - 1, n33 + 1)
    km_scale = 4.0 / max(1.0, math.sqrt(n_feed / 8))  # shorter sections on bigger feeders
    def line(f: int, t: int) -> list[float]:  # noqa: E306
        z = kv[t] ** 2 / base
        km = rng.uniform(0.3, 1.0) * km_scale * (0.4 if kv[t] == 11.0 else 1.0)
        r, x = rng.uniform(0.1, 0.35) * km, rng.uniform(0.3, 0.4) * km
        return [f, t, r / z, x / z, float(rng.choice([0.0, 9e-5 * km * z])), round(
            p_tot * rng.uniform(0.6, 1.5), 3), N_, N_]
    branch += [line(f, t) for f, t in edges]
    if meshed:  # tie lines between buses of the same voltage level that are not already neighbours
        pairs = {frozenset(b[:2]) for b in branch}
        lv = np.arange(2, 1 + n33) if n33 > 3 else np.arange(1, 1 + n33)
        n_ties, tries = int(rng.integers(1, 4)), 0
        while tries < n_ties or (len(pairs) == n_bus - 1 and tries < 50):  # a tree has n_bus - 1 branches
            tries += 1  # n_ties draws; more only while none closed a loop
            a, b = (int(v) for v in rng.choice(lv, 2, replace=False))
            if frozenset((a, b)) not in pairs:
                pairs.add(frozenset((a, b)))
                branch.append(line(a, b))
    bus = [[0, 0, 132.0, 1.0, 1.0]] + [[i, 1, kv[i], 1.1, 0.9] for i in range(1, n_bus)]
    dev: list[list[float]] = [[0, 0, 0, N_, N_, N_, N_, N_, N_, N_, N_, N_, N_, N_, N_]]
    load_buses = [b for b in range(2, n_bus) if rng.random() < 0.8] or [n_bus - 1]
    w = rng.dirichlet(np.ones(len(load_buses)))
    kinds = {"commercial": [], "residential": []}
    for b, share in zip(load_buses, w):
        kinds["commercial" if rng.random() < 0.3 else "residential"].append(len(dev))
        dev.append([len(dev), b, -1, float(rng.uniform(0.1, 0.5)), 0.0, -round(p_tot * share, 4), *[N_] * 9])
    ends = [b for b in range(2, n_bus) if all(e[0] != b for e in branch[1:])] or [n_bus - 1]  # leaves
    gens: list[tuple[int, str, float]] = []  # (device id, kind, PMAX)
    if rng.random() < 0.6:  # a classical generator (CHP, diesel): no capability corners
        pmax = float(p_tot * rng.uniform(0.15, 0.35))
        gens.append((len(dev), "classical", pmax))
        dev.append([len(dev), int(rng.integers(2, n_bus)), 1, N_, pmax, 0.0, 0.6 * pmax, -0.6 * pmax, *[N_] * 7])
    for _ in range(int(rng.integers(1, 2 + n_bus // 8))):  # renewables
        pmax = float(p_tot * rng.uniform(0.05, 0.25))
        qmax = pmax * rng.uniform(0.3, 0.6)
        corner = [0.7 * pmax, N_, 0.5 * qmax, -0.5 * qmax] if rng.random() < 0.5 else [N_] * 4
        gens.append((len(dev), "pv" if rng.random() < 0.6 else "wind", pmax))
        dev.append([len(dev), int(rng.integers(2, n_bus)), 2, N_, pmax, 0.0, qmax, -qmax, *corner, N_, N_, N_])
    n_des = int(rng.integers(2, 3 + n_bus // 15))
    for i in range(n_des):  # storage, preferably at the feeders' ends
        pmax = float(p_tot * rng.uniform(0.03, 0.12))
        qmax = pmax * rng.uniform(0.5, 1.0)
        soc_max = pmax * rng.uniform(2, 4)
        corner = [0.7 * pmax, -0.7 * pmax, 0.6 * qmax, -0.6 * qmax] if rng.random() < 0.5 else [N_] * 4
        soc_min = soc_max * rng.uniform(0.05, 0.2) if i == 0 or rng.random() < 0.5 else 0.0
        b = int(rng.choice(ends)) if rng.random() < 0.7 else int(rng.integers(2, n_bus))
        dev.append([len(dev), b, 3, N_, pmax, -pmax, qmax, -qmax, *corner, soc_max, soc_min,
                    float(rng.uniform(0.85, 0.98))])
    raw = {"baseMVA": base, "bus": bus, "device": dev, "branch": branch}
    net = validate_network(raw)
    t = np.arange(T_DAY) * 0.25
    load_p = np.zeros((T_DAY, sum(len(v) for v in kinds.values())))
    dev_arr = net["device"]
    load_ids = [int(i) for i in dev_arr[dev_arr[:, 2] == -1, 0]]
    for j, d in enumerate(load_ids):
        shape = _commercial(t) if d in kinds["commercial"] else _residential(t)
        noise = np.clip(1 + rng.normal(0, 0.04, T_DAY), 0.85, 1.0)
        load_p[:, j] = dev_arr[d, 5] * np.clip(shape * noise, 0, 1)
    cols = []
    for _, kind, pmax in gens:
        if kind == "classical":
            cols.append(np.full(T_DAY, pmax))
        elif kind == "pv":
            cols.append(pmax * _pv(t, _smooth_walk(rng, T_DAY, 0.5, 1.0)))
        else:
            cols.append(pmax * _smooth_walk(rng, T_DAY, 0.05, 0.95))
    gen_p_max = np.stack(cols, 1)
    meta = {"n_bus": n_bus, "topology": "meshed" if meshed else "radial", "base_mva": base,
            "transformer": {"x_pu": x_tr, "tap": tap, "shift_deg": shift, "rating_mva": s_tr},
            "sub_feeder_buses": n_sub, "peak_load_mw": p_tot, "n_load": len(load_ids),
            "n_gen": len(gens), "n_classical": sum(k == "classical" for _, k, _ in gens), "n_des": n_des,
            "n_branch": len(branch)}
    return raw, load_p, gen_p_max, meta


def check_power_flow(net: dict, load_p: np.ndarray, gen_p_max: np.ndarray,
                     v_range: tuple[float, float] = (0.85, 1.15)) -> str | None:
    """Why a network dict (as given to ``make_env``) is not kept (None: it is): the do-nothing power flow of a profile row, or an extreme corner
    of the injection box, does not converge, or a do-nothing |V| leaves ``v_range`` (p.u.)."""
    import torch

    from anm_torchrl.grid.powerflow import newton_raphson
    from anm_torchrl.networks.pf_check import do_nothing_injections
    from anm_torchrl.networks.resolve import simulator
    from anm_torchrl.grid.devices import bus_injection_box

    sim = simulator(net, load_p, gen_p_max)
    net = validate_network(net)
    inc = sim.net.incidence.numpy()
    base = float(net["baseMVA"])
    pq = [do_nothing_injections(net, lp, gp) for lp, gp in zip(load_p, gen_p_max)]
    p = np.stack([a for a, _ in pq]) @ inc / base
    q = np.stack([b for _, b in pq]) @ inc / base
    pf = newton_raphson(sim.net.y_bus, torch.complex(torch.as_tensor(p), torch.as_tensor(q)))
    if not bool(pf.converged.all()):
        return f"do-nothing power flow does not converge at {int((~pf.converged).sum())} of {len(p)} profile rows"
    vm = pf.v.abs()
    if float(vm.min()) < v_range[0] or float(vm.max()) > v_range[1]:
        return f"do-nothing |V| in [{float(vm.min()):.3f}, {float(vm.max()):.3f}] p.u., outside {v_range}"
    p_lo, p_hi, q_lo, q_hi = bus_injection_box(sim.net)
    corners = torch.stack([torch.complex(a, b) for a in (p_lo, p_hi) for b in (q_lo, q_hi)])
    pf = newton_raphson(sim.net.y_bus, corners)
    if not bool(pf.converged.all()):
        return f"{int((~pf.converged).sum())} of the 4 extreme corners of the injection box have no power flow"
    return None


def generate(seed: int, n_bus: int | None = None, meshed: bool | None = None, max_attempts: int = 200
             ) -> RandomCase:
    """The random network of ``seed`` (module docstring).

    Args:
        seed: the seed; the same seed (and arguments) always gives the same network.
        n_bus: bus count in 5..400 (None: drawn from 5..80, the battery's range, by the seed; larger ones serve
            scaling benchmarks).
        meshed: tie lines (None: drawn, half of the seeds).
        max_attempts: sub-draws tried before giving up.

    Raises:
        ValueError: ``n_bus`` outside 5..400, or no valid draw in ``max_attempts`` (naming the last reason).
    """
    rng0 = np.random.default_rng([seed, 0])
    n_bus = int(rng0.integers(5, 81)) if n_bus is None else int(n_bus)
    meshed = bool(rng0.random() < 0.5) if meshed is None else bool(meshed)
    if not 5 <= n_bus <= 400:
        raise ValueError(f"n_bus must lie in 5..400, got {n_bus}")
    why = None
    for attempt in range(max_attempts):
        rng = np.random.default_rng([seed, n_bus, int(meshed), attempt])
        try:
            net, load_p, gen_p_max, meta = _draw(rng, n_bus, meshed)
        except ValueError as err:  # validation refused the draw
            why = str(err)
            continue
        why = check_power_flow(net, load_p, gen_p_max)
        if why is None:
            return RandomCase(net, load_p, gen_p_max, {"seed": seed, "attempt": attempt, **meta})
    raise ValueError(f"no valid random network for seed {seed} ({n_bus} buses, meshed={meshed}) in {max_attempts} "
                     f"draws; last reason: {why}")


def size_class(n_bus: int) -> str:
    """The battery's size class of a bus count, e.g. ``"5-15"``."""
    for lo, hi in SIZE_CLASSES:
        if lo <= n_bus <= hi:
            return f"{lo}-{hi}"
    raise ValueError(f"n_bus {n_bus} is outside the size classes {SIZE_CLASSES}")
