"""pandapower net -> gym-anm network dict and profiles (the registered feeders are built with it in
:mod:`anm_torchrl.networks.feeders`, whose command line re-makes a committed case).

What gym-anm can represent, and the defaults used where pandapower has no value (:class:`ImportDefaults`):

* **Topology** through pandapower's own ``pd2ppc`` (``to_ppc``): closed bus-bus switches fuse buses, tap
  positions become ratios, transformers become pi branches with the tap on the high-voltage (from) side —
  gym-anm's TAP/SHIFT (SHIFT taken modulo 360°, gym-anm wants [0, 360]); one whose low-voltage side is the slack
  bus is drawn from it instead (tap 1/τ, z·τ², B/τ²: the same two-port). Phase shifts that close no loop
  are set to 0 (they only rotate the angles behind them; gym-anm's flat-start Newton–Raphson fails behind a
  150° shift); so bus angles are pandapower's minus the shifts upstream. Lines and transformers behind an
  open switch, and every out-of-service element, are dropped; isolated buses are dropped.
* **Unsupported physics is refused or removed, and the removal is applied to the pandapower net the checks
  run on** (:func:`prepare`): gym-anm branches have no shunt conductance and B >= 0, so transformer
  magnetising currents (``i0_percent``, ``pfe_kw``) and line conductance ``g_us_per_km`` are set to 0; bus
  shunts, wards, asymmetric impedances or ones with shunt terms, DC lines, voltage-dependent loads,
  voltage-controlled generators (``gen``: model them as ``sgen``) and reactive-only loads (p_mw 0, q_mvar not) raise
  one ``ValueError`` naming them all; a symmetric series ``impedance`` is a branch without rating.
* **Three-winding transformers** are pandapower's three two-winding branches through the star point (pd2ppc's
  auxiliary bus, at the hv voltage): a gym-anm bus without devices, VMIN 0 and VMAX :data:`STAR_POINT_VMAX` (no
  voltage limit at a fictional node, so no penalty there); windings rated sn_hv/mv/lv_mva.
* **Parallel branches** (gym-anm forbids them) are merged into one pi branch (admittances and charging add,
  ratings add; a plain line drawn the other way is the same branch); parallel branches with different taps raise.
* **Slack**: the in-service ``ext_grid`` bus becomes bus 0 (gym-anm's power flow fixes V = 1∠0 at bus 0; other
  buses keep pandapower's order). Its set-point ``vm_pu∠va`` is folded exactly into the branches at bus 0
  (TAP / vm_pu, SHIFT − va; lines at bus 0 are oriented away from it), and the slack bus's BASE_KV is
  ``vn_kv · vm_pu`` so kV observations stay true. Slack VMIN = VMAX = 1 (no penalty on a fixed voltage).
* **Buses**: VMIN/VMAX from ``min_vm_pu``/``max_vm_pu``, else ``ImportDefaults.vmin/vmax`` (0.9/1.1, EN 50160).
* **Loads** (DEV_TYPE −1): Q/P = q_mvar / p_mw of the nominal load (0 when p_mw = 0), PMAX 0, PMIN = −(peak of
  its profile and nominal P).
* **Static generators**: renewable (DEV_TYPE 2) when ``type`` names PV, wind, hydro or aggregated LV RES,
  else classical (1, e.g. CHP, fuel cell, biomass). Rating S = max(p_mw·scaling, sn_mva). Renewables get an
  inverter polygon (QMAX = −QMIN = 0.6 S, corners P+ = 0.8 S, Q+ = Q− = 0: a linearised S circle through
  (0.8, ±0.6) and (1, 0)); classical ones Q within ±0.62·PMAX (power factor 0.85), no corners. An element's own
  ``max_q_mvar`` / ``min_q_mvar`` (sgen, storage), where given, replace these Q limits (the corners' Q then 0, or
  the limit nearest 0 when 0 is outside them).
* **Storage** (3): PMAX = −min_p_mw, PMIN = −max_p_mw (pandapower counts charging positive), the same
  inverter polygon on both sides (its corners P± = ±0.8 S cut to [PMIN, PMAX]; a unit that can only charge or only
  discharge, as SimBench's home batteries with max_p_mw 0, is imported as given and logged, or with
  ``ImportDefaults.storage_two_way`` given the mirrored range PMIN = −PMAX), SOC_MAX = max_e_mwh
  or 4 h × PMAX, SOC_MIN = min_e_mwh or 0, EFF 0.95.
* **Branch RATE**: lines max_i_ka·df·parallel·√3·vn_kv, transformers sn_mva·df·parallel (MVA); ratings above
  10⁴ MVA (pandapower's "unlimited" 99999 kA) become NaN = no limit.
* The slack device's P/Q bounds are ext_grid's min/max if given, else ±2× the installed load and generation.
"""

from __future__ import annotations

import copy
import logging
import re
from dataclasses import asdict, dataclass, field

import numpy as np

from anm_torchrl._extras import require

pd = require("pandas")  # pandapower's dependency: the [feeders] extra

logger = logging.getLogger(__name__)

RENEWABLE_TYPE = re.compile(r"(^|[^a-z])(pv|wp|res)([^a-z]|$)|wind|hydro|solar", re.IGNORECASE)
UNSUPPORTED = ("shunt", "ward", "xward", "dcline", "svc", "tcsc", "ssc", "vsc",
               "asymmetric_load", "asymmetric_sgen", "motor")
NAN = float("nan")
#: VMAX (p.u.) of a three-winding transformer's star point, with VMIN 0: a fictional node has no voltage limit
STAR_POINT_VMAX = 10.0


@dataclass(frozen=True)
class ImportDefaults:
    """Values used where pandapower has none (units: p.u. of voltage, fractions of rating S, hours)."""

    vmin: float = 0.9
    vmax: float = 1.1
    inverter_q: float = 0.6  # QMAX = -QMIN = 0.6 S
    inverter_corner_p: float = 0.8  # P+ = 0.8 S (and P- = -0.8 S for storage); Q+ = Q- = 0 at |P| = S
    classical_q: float = 0.62  # |Q| <= 0.62 PMAX: power factor 0.85
    storage_hours: float = 4.0  # SOC_MAX = 4 h x PMAX when max_e_mwh is not given
    storage_eff: float = 0.95  # one-way (dis)charging efficiency (~0.90 round trip)
    #: a storage unit that works one way only (SimBench's home batteries: max_p_mw 0) gets the mirrored P range
    #: (PMIN = -PMAX) instead of its own: opt-in (``import_network --two-way-storage``), the source says so
    storage_two_way: bool = False
    slack_margin: float = 2.0  # slack |P|, |Q| <= 2 x (installed load + generation) when ext_grid has no limits
    unlimited_mva: float = 1e4  # ratings above this are "no limit" (NaN)


@dataclass
class ImportResult:
    """A converted net: the gym-anm tables, the element of every device, and the bus map."""

    network: dict
    load_idx: list  # pandapower load index of each load device, device-ID order
    gen_elements: list  # ("sgen" | "gen", index, renewable: bool) of each non-slack generator, ID order
    storage_idx: list
    bus_map: dict  # pandapower bus index -> gym-anm bus id (fused buses share an id)
    mirrored: list = field(default_factory=list)  # storage indices given the mirrored P range (storage_two_way)


def prepare(net):
    """A copy of ``net`` reduced to what gym-anm can represent (see module docstring).

    Raises:
        ValueError: naming every element gym-anm cannot represent at once (pandapower indices), with what to do.
    """
    net = copy.deepcopy(net)
    problems = []
    for table in UNSUPPORTED:
        if table in net and len(net[table]):
            on = net[table].in_service.astype(bool)
            if on.any():
                problems.append(f"{table} {list(net[table].index[on])} (gym-anm has no model for it)")
            net[table] = net[table].iloc[:0]  # the rest is out of service: nothing to represent
    if "impedance" in net and len(net.impedance):  # a plain series impedance is a gym-anm branch
        imp = net.impedance
        shunt = [c for c in ("gf_pu", "bf_pu", "gt_pu", "bt_pu") if c in imp]
        odd = imp.index[imp.in_service.astype(bool) & ((imp.rft_pu != imp.rtf_pu) | (imp.xft_pu != imp.xtf_pu)
                                                       | (imp[shunt].fillna(0).abs() > 0).any(axis=1))]
        if len(odd):
            problems.append(f"impedance {list(odd)} (asymmetric or with shunt terms; a symmetric series impedance "
                            "converts)")
        net.impedance = imp[imp.in_service.astype(bool)]
    const = [c for c in net.load.columns if c.startswith("const_")]
    bad = net.load.index[(net.load[const].fillna(0).abs() > 0).any(axis=1) & net.load.in_service]
    if len(bad):
        problems.append(f"loads {list(bad)} are voltage dependent ({const}); gym-anm loads are constant power")
    reactive = net.load.index[net.load.in_service.astype(bool) & (net.load.p_mw == 0) & (net.load.q_mvar != 0)]
    if len(reactive):
        problems.append(f"loads {list(reactive)} have p_mw 0 and q_mvar not; a gym-anm load's Q follows its P (a "
                        "constant Q/P), so a reactive-only load has no model")
    gens = net.gen.index[net.gen.in_service] if "gen" in net and len(net.gen) else []
    if len(gens):
        problems.append(f"gens {list(gens)} control their bus voltage (PV buses); gym-anm's generators are P/Q "
                        "set-points: model them as sgens (pandapower.toolbox.replace_gen_by_sgen)")
    neg = net.sgen.index[net.sgen.in_service & (net.sgen.p_mw * net.sgen.scaling < 0)] if len(net.sgen) else []
    if len(neg):
        problems.append(f"sgens {list(neg)} have p_mw < 0; gym-anm generators only inject: model them as loads")
    n_eg = int(net.ext_grid.in_service.sum()) if "ext_grid" in net else 0
    if n_eg != 1:
        problems.append(f"{n_eg} in-service ext_grids; gym-anm has exactly one slack bus: "
                        + ("add one (pandapower.create_ext_grid)" if n_eg == 0 else
                           "split the net into one per ext_grid (e.g. pandapower.networks.mv_oberrhein("
                           "separation_by_sub=True)) and import each"))
    at_slack = _slack_bus_devices(net) if n_eg == 1 else {}
    if any(at_slack.values()):
        problems.append(_at_slack_problem(at_slack))
    if n_eg == 1 and not problems:  # (after the rest: the tables emptied above can be what connects a part)
        problems += _unsupplied(net)
    if problems:
        raise ValueError("the pandapower net has what gym-anm cannot represent: " + "; ".join(problems)
                         + " (set in_service=False on an element to leave it out, accepting the change in the power "
                         "flow)")
    if len(net.sgen):  # a unit rated 0 MVA can never inject (its potential is clipped to 0): no action to learn
        inert = [i for i in net.sgen.index[net.sgen.in_service.astype(bool)] if _sgen_rating(net.sgen.loc[i]) <= 0]
        if inert:
            net.sgen.loc[inert, "in_service"] = False
            logger.warning("left out: sgens %s have no rating (p_mw x scaling and sn_mva 0): they can never inject",
                           inert[:10] + (["..."] if len(inert) > 10 else []))
    sw = net.switch[~net.switch.closed.astype(bool)]
    net.line.loc[sw.element[sw.et == "l"].unique(), "in_service"] = False
    net.trafo.loc[sw.element[sw.et == "t"].unique(), "in_service"] = False
    # an open switch at one winding of a trafo3w opens that winding alone: pd2ppc does it (its row's BR_STATUS 0)
    net.switch = net.switch[net.switch.closed.astype(bool) | net.switch.et.isin(("b", "t3"))]
    on_t, on_l = net.trafo.in_service.astype(bool), net.line.in_service.astype(bool)
    pfe = float(net.trafo.pfe_kw[on_t].sum()) if len(net.trafo) else 0.0
    if len(net.trafo3w):
        pfe += float(net.trafo3w.pfe_kw[net.trafo3w.in_service.astype(bool)].sum())
    gl = bool((net.line.get("g_us_per_km", pd.Series(0.0, index=net.line.index))[on_l] > 0).any())
    if pfe > 0 or gl:  # the reward's losses are the series losses alone: say how much is left out
        parts = ([f"transformer no-load losses, {pfe:.3g} kW in all (pfe_kw, with their magnetising currents)"]
                 if pfe > 0 else []) + (["line shunt conductance (g_us_per_km)"] if gl else [])
        logger.warning("left out (gym-anm's branches have no shunt conductance): %s; the env's energy losses are the "
                       "series losses only", " and ".join(parts))
    for table in ("trafo", "trafo3w"):
        net[table]["i0_percent"] = 0.0
        net[table]["pfe_kw"] = 0.0
    net.line["g_us_per_km"] = 0.0
    return net


def _at_slack_problem(at_slack: dict[str, list[int]]) -> str:
    """Why devices on the ext_grid's bus (``{table: indices}``) are refused, and what to do."""
    named = "; ".join(f"{t} {idx}" for t, idx in at_slack.items() if idx)
    # gym-anm's slack P is the whole bus-0 injection: theirs would count nowhere
    return (f"pandapower elements on the ext_grid's bus or a bus fused with it by a closed bus-bus switch ({named}): "
            "gym-anm sets the slack device's P and Q to that bus's whole injection, so the slack's power leaves "
            "theirs out while the energy loss still counts it (a load there gives a negative loss); connect them to "
            "a bus joined to the ext_grid's by a line or transformer")


def _slack_bus_devices(net) -> dict[str, list[int]]:
    """In-service loads, sgens and storage units (pandapower indices per table) on the in-service ext_grid's bus or
    a bus joined to it by closed bus-bus switches (what pandapower fuses into one bus)."""
    fused = {int(net.ext_grid.bus[net.ext_grid.in_service.astype(bool)].iloc[0])}
    sw = net.switch
    if len(sw):  # pandapower fuses a closed bus-bus switch without impedance between in-service buses
        z = sw.z_ohm.fillna(0.0) if "z_ohm" in sw else pd.Series(0.0, index=sw.index)
        on = set(net.bus.index[net.bus.in_service.astype(bool)])
        sw = sw[(sw.et == "b") & sw.closed.astype(bool) & (z <= 0) & sw.bus.isin(on) & sw.element.isin(on)]
    pairs = [(int(a), int(b)) for a, b in zip(sw.bus, sw.element)] if len(sw) else []
    grew = True
    while grew:  # the closure of the switches' pairs around the ext_grid's bus
        grew = False
        for a, b in pairs:
            if (a in fused) != (b in fused):
                fused |= {a, b}
                grew = True
    return {t: [int(i) for i in net[t].index[net[t].in_service.astype(bool) & net[t].bus.isin(fused)]]
            for t in ("load", "sgen", "storage") if t in net and len(net[t])}


def _star_points(net, stars, bus_lookup, new_id) -> dict[int, int]:
    """gym-anm bus id -> pandapower index of the in-service trafo3w whose star point it is; ``stars``: pd2ppc's
    auxiliary bus of each trafo3w row (``_pd2ppc_lookups["aux"]["trafo3w"]``; empty without trafo3w)."""
    t3 = net.trafo3w
    if not len(t3):
        return {}
    return {int(new_id[bus_lookup[a]]): int(i) for a, i, on in zip(stars, t3.index, t3.in_service.astype(bool))
            if on and new_id[bus_lookup[a]] >= 0}


def _unsupplied(net) -> list[str]:
    """What sits in a part of ``net`` the ext_grid does not supply (an island, an out-of-service bus): its in-service
    branches and devices, by pandapower index (empty: none; a bare bus is dropped silently, it carries nothing)."""
    from pandapower import topology

    buses = {int(b) for b in topology.unsupplied_buses(net)}  # (its graph leaves out-of-service buses out)
    buses |= {int(b) for b in net.bus.index[~net.bus.in_service.astype(bool)]}
    if not buses:
        return []
    found = []
    sw = net.switch[~net.switch.closed.astype(bool)]
    opened = {(et, int(e), int(b)) for et, e, b in zip(sw.et, sw.element, sw.bus)}  # a branch's end left open
    for table, cols in (("line", ("from_bus", "to_bus")), ("trafo", ("hv_bus", "lv_bus")),
                        ("trafo3w", ("hv_bus", "mv_bus", "lv_bus")),
                        ("impedance", ("from_bus", "to_bus")), ("load", ("bus",)), ("sgen", ("bus",)),
                        ("storage", ("bus",))):
        df = net[table]
        et = {"line": "l", "trafo": "t", "trafo3w": "t3"}.get(table)  # the tables a switch can open an end of
        ends = [df[c].isin(buses) for c in cols]
        if et is not None and opened:
            ends = [end & ~pd.Series([(et, int(i), int(b)) in opened for i, b in zip(df.index, df[c])],
                                     index=df.index, dtype=bool) for end, c in zip(ends, cols)]
        hit = df.index[df.in_service.astype(bool) & np.logical_or.reduce(ends)]
        if len(hit):
            found.append(f"{table}s {[int(i) for i in hit[:10]]}{' ...' if len(hit) > 10 else ''}")
    if not found:
        return []
    return [f"buses {sorted(buses)[:10]}{' ...' if len(buses) > 10 else ''} are not supplied from the ext_grid (an "
            f"island or an out-of-service bus) and carry in-service {', '.join(found)}: connect them or take "
            "those out of service"]


def _ratings(net, ppc, lookup, defaults: ImportDefaults) -> np.ndarray:
    """MVA rating of every row of ``ppc["branch"]`` (``to_ppc`` keeps the in-service rows of its lookup)."""
    total = max(e for _, e in lookup.values())
    rate, status = np.full(total, np.inf), np.zeros(total, dtype=bool)
    for table, (s, e) in lookup.items():
        if e == s:  # an empty table (its out-of-service rows left out by prepare)
            continue
        if table not in ("line", "trafo", "trafo3w", "impedance"):
            raise ValueError(f"pandapower branch element {table!r} is not supported")
        df = net[table]
        if table == "trafo3w":  # three two-winding branches each: every hv winding, then mv, then lv (pd2ppc)
            status[s:e] = np.tile(df.in_service.to_numpy(dtype=bool), 3)
            rate[s:e] = np.concatenate([df[f"sn_{w}_mva"].to_numpy() for w in ("hv", "mv", "lv")])
            continue
        status[s:e] = df.in_service.to_numpy(dtype=bool)
        if table == "impedance":  # no thermal rating (its sn_mva is the base of its p.u. values)
            continue
        if table == "line":
            vn = net.bus.vn_kv.loc[df.from_bus].to_numpy()
            rate[s:e] = df.max_i_ka.to_numpy() * df.df.to_numpy() * df.parallel.to_numpy() * np.sqrt(3) * vn
        else:
            rate[s:e] = df.sn_mva.to_numpy() * df.df.to_numpy() * df.parallel.to_numpy()
    rate = rate[status]
    if rate.size != ppc["branch"].shape[0]:
        raise ValueError(f"pandapower's ppc has {ppc['branch'].shape[0]} branches, expected {rate.size} in service")
    return np.where(rate > defaults.unlimited_mva, NAN, rate)


def _merge_parallel(rows: list[np.ndarray], where) -> np.ndarray:
    """One pi branch equal to parallel pi branches of the same (from, to, tap, shift); ``where(f, t)`` names a
    branch's ends for messages (pandapower's buses)."""
    first = rows[0]
    for k, r in enumerate(rows[1:], 1):
        if r[0] == first[1] and r[1] == first[0] and r[6] == 1.0 and r[7] == 0.0:
            rows[k] = r = r.copy()  # a plain line (no tap, no shift) is the same branch drawn either way
            r[[0, 1]] = first[[0, 1]]
        if not np.allclose(r[[0, 1, 6, 7]], first[[0, 1, 6, 7]]):
            raise ValueError(f"parallel branches {where(int(first[0]), int(first[1]))} differ in orientation, tap "
                             f"or shift; gym-anm has no parallel branches and merges only equal ones: give them the "
                             "same tap position and shift, or take one out of service")
    y = sum(1.0 / (r[2] + 1j * r[3]) for r in rows)
    z = 1.0 / y
    out = first.copy()
    out[2], out[3] = z.real, z.imag
    out[4] = sum(r[4] for r in rows)
    out[5] = sum(r[5] for r in rows)  # NaN (no limit) if any is unlimited
    return out


def _reversed_tap_branch(row: np.ndarray) -> np.ndarray:
    """A branch ``[f, t, R, X, B, RATE, τ, θ°]`` (ideal transformer τ∠θ on the f side) as the equal two-port drawn from
    t: tap 1/τ ∠ −θ, series impedance z·τ², line charging B/τ² (the bus admittance entries match exactly: Y_ff =
    (y + jB/2)/τ², Y_tt = y + jB/2, Y_ft = −y/(τ∠−θ), Y_tf = −y/(τ∠θ) on both drawings)."""
    f, t, r, x, b, rate, tau, shift = row
    return np.array([t, f, r * tau ** 2, x * tau ** 2, b / tau ** 2, rate, 1.0 / tau, -shift])


def _branches(ppc, keep_bus, new_id, rate, vm, va_deg, where) -> np.ndarray:
    """gym-anm's branch table from ppc's branches; ``where(f, t)`` names a branch's ends (gym-anm bus ids) for
    messages."""
    require("pandapower")
    from pandapower.pypower.idx_brch import BR_B, BR_R, BR_STATUS, BR_X, F_BUS, SHIFT, T_BUS, TAP

    br = ppc["branch"]
    if np.iscomplexobj(br):
        if np.abs(br.imag).max() > 0:
            raise ValueError("pandapower's branch table has complex entries (shunt conductance); not supported")
        br = br.real
    groups: dict[tuple[int, int], list[np.ndarray]] = {}
    for k in range(br.shape[0]):
        f, t = int(br[k, F_BUS]), int(br[k, T_BUS])
        if br[k, BR_STATUS] == 0 or not (keep_bus[f] and keep_bus[t]):
            continue
        f, t = new_id[f], new_id[t]
        if f == t:
            raise ValueError(f"branch {k} of pandapower's ppc connects fused bus {f} to itself")
        tap = br[k, TAP] if br[k, TAP] != 0 else 1.0
        row = np.array([f, t, br[k, BR_R], br[k, BR_X], br[k, BR_B], rate[k], tap, br[k, SHIFT]])
        if row[2] < 0 or row[3] < 0 or row[4] < 0:  # (a three-winding transformer's star equivalent can be)
            raise ValueError(f"the branch {where(f, t)} has R = {row[2]:.6g}, X = {row[3]:.6g} and B = {row[4]:.6g} "
                             "p.u.; gym-anm needs all three >= 0 (a series capacitor, or an equivalent with negative "
                             "resistance or reactance, has no model): take it out of service or replace it")
        if t == 0 and tap == 1.0 and row[7] == 0.0:
            row[[0, 1]] = [t, f]  # a plain line into the slack bus: orient it away so the fold below applies
        elif t == 0:  # tapped towards the slack bus: the same two-port drawn from bus 0, its tap on the slack's side
            row = _reversed_tap_branch(row)
        if row[0] == 0:
            row[6] /= vm
            row[7] -= va_deg
        row[7] = row[7] % 360.0
        groups.setdefault((min(f, t), max(f, t)), []).append(row)
    return np.array([_merge_parallel(g, where) if len(g) > 1 else g[0] for g in groups.values()],
                    dtype=np.float64)


def _drop_loop_free_shifts(branch: np.ndarray, n_bus: int) -> np.ndarray:
    """SHIFT = 0 everywhere when no loop has a net phase shift (e.g. radial feeders, parallel Dyn5 units).

    A shift that closes no loop only rotates the angles of the buses behind it: |V|, P, Q and the reward are
    unchanged. Removing it matters because gym-anm's Newton-Raphson starts flat (all angles 0) and does not
    converge behind SimBench's 150 deg HV/MV transformers. Shifts on a loop are physical and are kept.
    """
    theta = np.full(n_bus, np.nan)
    theta[0] = 0.0
    adj: dict[int, list[tuple[int, float]]] = {}
    for f, t, *_, shift in branch:
        adj.setdefault(int(f), []).append((int(t), -shift))
        adj.setdefault(int(t), []).append((int(f), shift))
    stack = [0]
    while stack:
        b = stack.pop()
        for nb, d in adj.get(b, []):
            if np.isnan(theta[nb]):
                theta[nb] = theta[b] + d
                stack.append(nb)
    mismatch = (theta[branch[:, 0].astype(int)] - theta[branch[:, 1].astype(int)] - branch[:, 7]) % 360.0
    if np.all(np.minimum(mismatch, 360.0 - mismatch) < 1e-9):
        branch = branch.copy()
        branch[:, 7] = 0.0
    else:
        logger.info("phase shifts close a loop; kept as gym-anm SHIFT")
    return branch


def _sgen_rating(row) -> float:
    s = row.p_mw * row.scaling
    sn = row.get("sn_mva", NAN)
    return float(max(s, sn)) if np.isfinite(sn) else float(s)


def _q_range(table: str, i, row, qmax: float, qmin: float) -> tuple[float, float]:
    """The element's own ``max_q_mvar`` / ``min_q_mvar`` where pandapower has them (finite), else ``qmax`` /
    ``qmin``; an empty range is refused by name."""
    hi, lo = row.get("max_q_mvar", NAN), row.get("min_q_mvar", NAN)
    hi, lo = float(hi) if np.isfinite(hi) else qmax, float(lo) if np.isfinite(lo) else qmin
    if lo > hi:
        raise ValueError(f"pandapower {table} {i}: min_q_mvar {lo} > max_q_mvar {hi}")
    return hi, lo


def _inverter(table: str, i, row, s: float, d: ImportDefaults) -> list[float]:
    """QMAX, QMIN, P+, P-, Q+, Q- of an inverter of rating s (MVA): its own Q limits where it has them, else
    +-0.6 S; P- is set by the caller for storage."""
    qmax, qmin = _q_range(table, i, row, d.inverter_q * s, -d.inverter_q * s)
    q_corner = min(max(0.0, qmin), qmax)  # the polygon's corners at |P| = 0.8 S reach Q = 0, or the nearest limit
    return [qmax, qmin, d.inverter_corner_p * s, NAN, q_corner, q_corner]


def convert(net, load_peak: np.ndarray, defaults: ImportDefaults = ImportDefaults()) -> ImportResult:
    """Convert a :func:`prepare`-d pandapower net into gym-anm tables.

    Args:
        net: pandapower net returned by :func:`prepare`.
        load_peak: (n_load_in_service,) MW, the largest P of each in-service load over its profile
            (sets the load's PMIN = -max(peak, nominal P)).
        defaults: values used where pandapower has none.
    """
    require("pandapower")
    from pandapower.converter.pypower.to_ppc import to_ppc
    from pandapower.pypower.idx_bus import BASE_KV, BUS_TYPE, NONE, REF, VA, VM

    ppc = to_ppc(net, calculate_voltage_angles=True, trafo_model="pi", init="flat", check_connectivity=True)
    lookup = net._pd2ppc_lookups
    bus_lookup = lookup["bus"]
    keep = ppc["bus"][:, BUS_TYPE] != NONE
    # the net's buses and the trafo3w star points; not pd2ppc's bus at a winding's open switch (nothing is
    # attached there and the winding, without magnetising branch, carries no current to it)
    stars = lookup.get("aux", {}).get("trafo3w", [])
    known = {int(bus_lookup[b]) for b in net.bus.index} | {int(bus_lookup[a]) for a in stars}
    keep &= np.isin(np.arange(len(keep)), sorted(known))
    slack = np.flatnonzero(ppc["bus"][:, BUS_TYPE] == REF)
    if slack.size != 1:
        raise ValueError(f"the net must have exactly one in-service ext_grid (slack), found {slack.size}")
    slack = int(slack[0])
    order = [slack] + [int(r) for r in np.flatnonzero(keep) if r != slack]
    new_id = np.full(ppc["bus"].shape[0], -1)
    new_id[order] = np.arange(len(order))
    vm, va = float(ppc["bus"][slack, VM]), float(ppc["bus"][slack, VA])

    # an isolated bus is left out of ppc["bus"] but keeps a lookup index past its end (pandapower 3)
    bus_map = {int(b): int(new_id[bus_lookup[b]]) for b in net.bus.index[net.bus.in_service]
               if bus_lookup[b] < len(new_id) and new_id[bus_lookup[b]] >= 0}
    vmax = np.full(len(order), np.inf)
    vmin = np.full(len(order), -np.inf)
    hi_col = net.bus.get("max_vm_pu", pd.Series(NAN, index=net.bus.index))
    lo_col = net.bus.get("min_vm_pu", pd.Series(NAN, index=net.bus.index))
    for b, g in bus_map.items():  # fused buses: the tightest limits of their members
        hi, lo = hi_col.at[b], lo_col.at[b]
        vmax[g] = min(vmax[g], hi if np.isfinite(hi) else defaults.vmax)
        vmin[g] = max(vmin[g], lo if np.isfinite(lo) else defaults.vmin)
    bus = np.column_stack([np.arange(len(order)), np.ones(len(order)), ppc["bus"][order, BASE_KV], vmax, vmin])
    bus[0, 1], bus[0, 2], bus[0, 3], bus[0, 4] = 0, bus[0, 2] * vm, 1.0, 1.0

    members: dict[int, list[int]] = {}  # gym-anm bus -> its pandapower buses (several where fused)
    for b, g in bus_map.items():
        members.setdefault(g, []).append(b)
    star = _star_points(net, stars, bus_lookup, new_id)
    for g, i in star.items():  # a fictional node: no voltage limit (finite, as gym-anm needs), no penalty there
        bus[g, 3], bus[g, 4] = STAR_POINT_VMAX, 0.0

    def name(g: int) -> str:
        if g in star:
            return f"(the star point of trafo3w {star[g]})"
        m = members.get(g, [])
        return str(m[0]) if len(m) == 1 else str(m)

    def where(f: int, t: int) -> str:
        return f"between pandapower buses {name(f)} and {name(t)}"

    branch = _branches(ppc, keep, new_id, _ratings(net, ppc, lookup["branch"], defaults), vm, va, where)
    branch = _drop_loop_free_shifts(branch, len(order))

    def on_grid(table):
        df = net[table]
        return df[df.in_service & df.bus.map(lambda b: b in bus_map)]

    at_slack = {t: [int(i) for i in on_grid(t).index if bus_map[net[t].bus[i]] == 0]
                for t in ("load", "sgen", "storage")}
    if any(at_slack.values()):  # prepare() names them first; here after pandapower's own fusion of buses
        raise ValueError(_at_slack_problem(at_slack))
    devices, load_idx, gen_elements, storage_idx = [], [], [], []
    loads = on_grid("load")
    if len(load_peak) != len(loads):
        raise ValueError(f"load_peak has {len(load_peak)} entries, expected {len(loads)} (in-service loads)")
    for (i, row), peak in zip(loads.iterrows(), load_peak):
        p = row.p_mw * row.scaling
        if p < 0 or peak < 0:
            raise ValueError(f"pandapower load {i}: p_mw {p} / profile peak {peak} < 0; gym-anm loads only consume")
        if row.p_mw == 0 and row.q_mvar != 0:
            raise ValueError(f"pandapower load {i}: p_mw 0 with q_mvar {row.q_mvar}; a gym-anm load's Q follows its P "
                             "(a constant Q/P), so a reactive-only load has no model")
        qp = row.q_mvar / row.p_mw if row.p_mw != 0 else 0.0
        devices.append([-1, bus_map[row.bus], -1, qp, 0.0, -max(peak, p), *[NAN] * 9])
        load_idx.append(int(i))
    for table in ("sgen", "gen"):
        for i, row in on_grid(table).iterrows():
            s = _sgen_rating(row) if table == "sgen" else float(np.nanmax([row.p_mw, row.get("sn_mva", NAN)]))
            renewable = table == "sgen" and bool(RENEWABLE_TYPE.search(str(row.get("type", ""))))
            if renewable:
                inv = _inverter(table, i, row, s, defaults)
                devices.append([-1, bus_map[row.bus], 2, NAN, s, 0.0, *inv, NAN, NAN, NAN])
            else:
                qmax, qmin = _q_range(table, i, row, defaults.classical_q * s, -defaults.classical_q * s)
                devices.append([-1, bus_map[row.bus], 1, NAN, s, 0.0, qmax, qmin, *[NAN] * 7])
            gen_elements.append((table, int(i), renewable))
    one_way = {"charge": [], "discharge": []}  # pandapower storage indices of units that work one way only
    two_way = []  # of those, the ones given the mirrored range (defaults.storage_two_way)
    for i, row in on_grid("storage").iterrows():
        pmax = -row.min_p_mw if np.isfinite(row.get("min_p_mw", NAN)) else abs(row.p_mw)
        pmin = -row.max_p_mw if np.isfinite(row.get("max_p_mw", NAN)) else -abs(row.p_mw)
        s = max(pmax, -pmin)
        if pmax <= 0 or pmin >= 0:
            one_way["charge" if pmax <= 0 else "discharge"].append(int(i))
            if defaults.storage_two_way and s > 0:  # (a unit without any P range has nothing to mirror)
                two_way.append(int(i))
                pmax, pmin = s, -s
        inv = _inverter("storage", i, row, s, defaults)
        # the polygon's corners inside the P range: gym-anm wants PMIN <= P- <= P+ <= PMAX, and a one-way unit
        # (SimBench's home batteries: max_p_mw 0) or a lopsided one has one side shorter than 0.8 S
        inv[2], inv[3] = min(inv[2], pmax), max(-defaults.inverter_corner_p * s, pmin)
        emax = row.max_e_mwh if np.isfinite(row.get("max_e_mwh", NAN)) else defaults.storage_hours * pmax
        emin = row.min_e_mwh if np.isfinite(row.get("min_e_mwh", NAN)) else 0.0
        devices.append([-1, bus_map[row.bus], 3, NAN, pmax, pmin, *inv, emax, emin, defaults.storage_eff])
        storage_idx.append(int(i))
    for way, idx in one_way.items():
        if idx:
            how = ("made two-way (--two-way-storage): P range mirrored" if set(idx) <= set(two_way) else
                   "imported as given (--two-way-storage mirrors a non-empty P range)")
            logger.warning("%d pandapower storage units can only %s (min_p_mw or max_p_mw 0), %s: indices %s",
                           len(idx), way, how, idx)

    if not devices:
        raise ValueError("the pandapower net has no load, generator or storage unit besides its ext_grid")
    dev = np.array(devices, dtype=np.float64)
    installed = -dev[dev[:, 2] == -1, 5].sum() + dev[dev[:, 2] > 0, 4].sum()
    eg = net.ext_grid[net.ext_grid.in_service].iloc[0]
    lim = defaults.slack_margin * installed

    def bound(col, default):
        v = eg.get(col, NAN)
        return float(v) if np.isfinite(v) else default

    slack_row = [-1, 0, 0, NAN, bound("max_p_mw", lim), bound("min_p_mw", -lim), bound("max_q_mvar", lim),
                 bound("min_q_mvar", -lim), *[NAN] * 7]
    dev = np.vstack([slack_row, dev])
    dev[:, 0] = np.arange(dev.shape[0])
    network = {"baseMVA": float(net.sn_mva), "bus": bus, "device": dev, "branch": branch}
    return ImportResult(network, load_idx, gen_elements, storage_idx, bus_map, two_way)


def profiles(res: ImportResult, load_mw, sgen_mw) -> tuple[np.ndarray, np.ndarray]:
    """gym-anm profiles from pandapower element profiles.

    Args:
        res: the conversion.
        load_mw: DataFrame (T, loads) MW consumption (>= 0), columns = pandapower load indices.
        sgen_mw: DataFrame (T, sgens) MW potential output, columns = pandapower sgen indices.

    Returns:
        ``load_p`` (T, n_load) MW injections (<= 0) and ``gen_p_max`` (T, n_gen) MW potentials; classical
        generators (dispatchable) have their PMAX at every step.
    """
    load_p = -load_mw[res.load_idx].to_numpy(dtype=np.float64)
    dev = res.network["device"]
    pmax = dev[np.isin(dev[:, 2], (1, 2)), 4]
    cols = []
    for (table, i, renewable), p in zip(res.gen_elements, pmax):
        cols.append(sgen_mw[i].to_numpy(dtype=np.float64) if renewable else np.full(len(load_p), p))
    return load_p, np.column_stack(cols) if cols else np.zeros((len(load_p), 0))


def from_pandapower(net, load_mw, sgen_mw, defaults: ImportDefaults = ImportDefaults()):
    """A pandapower net and its element profiles as gym-anm tables and profiles (:func:`prepare`, :func:`convert`,
    :func:`profiles`).

    Args:
        net: the pandapower net (not modified).
        load_mw: DataFrame (T, loads) MW consumption (>= 0) with a column for every in-service load (its
            pandapower index); its maxima set the loads' PMIN.
        sgen_mw: DataFrame (T, sgens) MW potential with a column for every in-service renewable sgen.

    Returns:
        ``(prepared net, ImportResult, load_p (T, n_load) MW, gen_p_max (T, n_gen) MW)``.

    Raises:
        ValueError: what :func:`prepare` / :func:`convert` refuse, or a profile without a column an element needs
            (naming the elements).
    """
    prepared = prepare(net)
    in_service = prepared.load.index[prepared.load.in_service]
    missing = [int(i) for i in in_service if i not in load_mw.columns]
    if missing:
        raise ValueError(f"the load profile has no column for pandapower loads {missing}")
    res = convert(prepared, load_mw[in_service].max(axis=0).to_numpy(dtype=np.float64), defaults)
    missing = [i for table, i, renewable in res.gen_elements if renewable and i not in sgen_mw.columns]
    if missing:
        raise ValueError(f"the renewable profile has no column for pandapower sgens {missing}")
    load_p, gen_p_max = profiles(res, load_mw, sgen_mw)
    return prepared, res, load_p, gen_p_max


def defaults_record(defaults: ImportDefaults) -> dict:
    """The defaults as a JSON-serialisable dict (stored in a case's meta)."""
    return asdict(defaults)

