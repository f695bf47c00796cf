"""Power-flow checks of an imported feeder: pandapower's ``runpp`` against gym-anm's equations on one operating point.

The operating point is "do nothing" at one profile row: loads at their profile (Q = P·Q/P), generators at their
potential (classical ones at PMAX), reactive set-points and storage at 0 — gym-anm's injections without the
projections, so that the comparison tests the conversion of the network, not the devices' polygons.
Needs pandapower and gym-anm (test / ``feeders`` extras).
"""

from __future__ import annotations

import numpy as np

from anm_torchrl._extras import require
from anm_torchrl.networks.case_file import to_gym_anm


def do_nothing_injections(network: dict, load_row: np.ndarray, gen_row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Device (P, Q) in MW/MVAr, device-ID order (slack 0), at one profile row.

    Args:
        network: gym-anm dict (float64 tables, NaN = None).
        load_row: (n_load,) MW load injections (<= 0).
        gen_row: (n_gen,) MW potentials of the non-slack generators.
    """
    dev = network["device"]
    kind = dev[:, 2]
    p, q = np.zeros(len(dev)), np.zeros(len(dev))
    loads, gens = kind == -1, np.isin(kind, (1, 2))
    p[loads] = np.clip(load_row, dev[loads, 5], 0.0)
    q[loads] = p[loads] * dev[loads, 3]
    p[gens] = np.clip(gen_row, 0.0, dev[gens, 4])
    return p, q


def set_pandapower_point(net, res, p: np.ndarray, q: np.ndarray) -> None:
    """Write device injections (MW/MVAr, device-ID order) into the pandapower elements of the conversion."""
    kind = res.network["device"][:, 2]
    net.load.loc[res.load_idx, "p_mw"] = -p[kind == -1]
    net.load.loc[res.load_idx, "q_mvar"] = -q[kind == -1]
    net.load.loc[res.load_idx, "scaling"] = 1.0
    gens = np.flatnonzero(np.isin(kind, (1, 2)))
    for table in ("sgen", "gen"):  # one write per table and column: a row at a time took minutes on an HV grid
        rows = [(i, k) for (t, i, _), k in zip(res.gen_elements, gens) if t == table]
        if rows:
            idx, k = [i for i, _ in rows], np.array([k for _, k in rows])
            net[table].loc[idx, "p_mw"] = p[k]
            net[table].loc[idx, "scaling"] = 1.0
            if table == "sgen":
                net[table].loc[idx, "q_mvar"] = q[k]
    if len(res.storage_idx):
        st = np.flatnonzero(kind == 3)
        net.storage.loc[res.storage_idx, "p_mw"] = -p[st]
        net.storage.loc[res.storage_idx, "q_mvar"] = -q[st]
        net.storage.loc[res.storage_idx, "scaling"] = 1.0


def run_pandapower(net) -> None:
    """``runpp`` with a tolerance far below the 1e-6 p.u. comparison.

    1e-9 MVA (1e-11 stalls on round-off on the SimBench feeder); DC initial angles (a flat start fails behind
    its 150° transformers); no numba (its JIT compile costs more than these small nets' solves).
    """
    pp = require("pandapower")

    pp.runpp(net, calculate_voltage_angles=True, init="dc", trafo_model="pi", tolerance_mva=1e-9,
             max_iteration=50, numba=False)


#: the import check's stopping tolerance on the power mismatch (p.u.), and its floor relative to the round-off of
#: the mismatch itself (float64 eps x the Y-bus's largest row sum |Y|: an HV grid on a 1 MVA base, SimBench's
#: 1-HV-urban--0-sw, has row sums ~1e6 p.u., so 1e-11 was out of reach and a sound net was refused as "not converged")
XTOL = 1e-11
XTOL_ROUNDOFF = 100 * float(np.finfo(np.float64).eps)


def gym_anm_vm(network: dict, p: np.ndarray, q: np.ndarray, xtol: float | None = None) -> tuple[np.ndarray, bool]:
    """|V| (n_bus,) p.u. solved with gym-anm's own Y-bus and Newton–Raphson (``solve_load_flow``).

    Args:
        network: gym-anm dict.
        p, q: device injections (MW/MVAr, device-ID order); the slack device's entries are ignored.
        xtol: stopping tolerance on the power mismatch (p.u.; gym-anm's env uses 1e-5); None: :data:`XTOL`, or
            :data:`XTOL_ROUNDOFF` x the Y-bus's largest absolute row sum where that is larger.

    Returns:
        ``(|V|, converged)`` with gym-anm's convergence rule (finite and mismatch <= xtol).
    """
    require("gym_anm")
    from gym_anm.simulator.simulator import Simulator
    from gym_anm.simulator.solve_load_flow import _construct_v_from_guess, _newton_raphson_sparse

    sim = Simulator(to_gym_anm(network), 0.25, 100.0)
    n_bus = network["bus"].shape[0]
    dev = network["device"]
    bus = dev[:, 1].astype(int)
    keep = dev[:, 2] != 0
    pb = np.bincount(bus[keep], p[keep], minlength=n_bus) / network["baseMVA"]
    qb = np.bincount(bus[keep], q[keep], minlength=n_bus) / network["baseMVA"]
    if xtol is None:
        xtol = max(XTOL, XTOL_ROUNDOFF * float(abs(sim.Y_bus).sum(axis=1).max()))
    guess = np.concatenate([np.zeros(n_bus - 1), np.ones(n_bus - 1)])
    x, _, diff, ok = _newton_raphson_sparse(guess, pb[1:], qb[1:], sim.Y_bus, x_tol=xtol)
    return np.abs(_construct_v_from_guess(x)), bool(ok and diff <= xtol)


def compare_vm(net, res, vm_gym: np.ndarray) -> np.ndarray:
    """|V| difference (pandapower − gym-anm) p.u. of nominal kV at every mapped pandapower bus.

    gym-anm's slack bus carries the folded set-point in its BASE_KV, so |V|·BASE_KV/vn_kv is compared.
    """
    base_kv = res.network["bus"][:, 2]
    buses = np.array(list(res.bus_map))
    g = np.array([res.bus_map[b] for b in buses])
    vm_pp = net.res_bus.vm_pu.loc[buses].to_numpy()
    return vm_pp - vm_gym[g] * base_kv[g] / net.bus.vn_kv.loc[buses].to_numpy()


def do_nothing_sweep(net, res, load_p: np.ndarray, gen_p_max: np.ndarray) -> dict:
    """pandapower power flow of the do-nothing point on every profile row.

    Returns:
        ``vm_min``, ``vm_max`` (p.u., in-service buses), ``loading_max_percent`` (lines and transformers),
        ``rows``. Raises ``ValueError`` naming the first row that does not converge.
    """
    import copy

    net = copy.deepcopy(net)
    vmin, vmax, loading = np.inf, -np.inf, 0.0
    for t in range(len(load_p)):
        p, q = do_nothing_injections(res.network, load_p[t], gen_p_max[t])
        set_pandapower_point(net, res, p, q)
        try:
            run_pandapower(net)
        except Exception as err:  # pandapower raises its own LoadflowNotConverged
            raise ValueError(f"do-nothing power flow does not converge at profile row {t}: {err}") from err
        vm = net.res_bus.vm_pu.to_numpy()
        vmin, vmax = min(vmin, np.nanmin(vm)), max(vmax, np.nanmax(vm))
        for table in ("res_line", "res_trafo"):
            if len(net[table]):
                loading = max(loading, float(np.nanmax(net[table].loading_percent)))
    return {"vm_min": float(vmin), "vm_max": float(vmax), "loading_max_percent": loading, "rows": len(load_p)}
