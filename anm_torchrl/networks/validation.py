"""Validation of gym-anm network dicts and exogenous profiles, with gym-anm's defaults applied.

:func:`validate_network` rejects at least everything gym-anm 2.0.1 rejects (``simulator/check_network.py``,
the ``Bus``, ``TransmissionLine`` and device classes), plus what gym-anm accepts but cannot simulate (a NaN
capability line that makes its cvxpy projection fail, a slack bus that is not bus 0, bus ids that are not
0..n_bus-1: gym-anm's power flow silently treats bus 0 as the slack and sizes its Y-bus by the largest id;
buses not connected to the slack bus, whose power flow cannot converge; a device other than the slack one on bus
0, which gym-anm drops from the energy balance by setting the slack device's P to the whole bus injection). Empty
tables are (0, ncols) arrays;
an empty bus or device table is refused as empty, and a one-bus network deliberately (the power flow needs a
non-slack bus).
Every error is a ``ValueError`` naming the table, the row (bus / device / branch id) and the column.

The normalized dict has float64 tables sorted as gym-anm orders them (buses and devices by id, branches as
given), every ``None``/NaN replaced by gym-anm's default (``devices.py`` ``_check_type_specific_specs``):

* loads: PMAX 0, PMIN −inf (Q/P is required);
* generators (slack and non-slack): PMAX +inf, PMIN −inf (slack) or 0, QMAX +inf, QMIN −inf, P+ = PMAX,
  Q+ = QMAX, Q− = QMIN; P− is ignored by gym-anm (kept NaN);
* storage: PMAX +inf, PMIN −inf, QMAX +inf, QMIN −inf, P+ = PMAX, P− = PMIN, Q+ = QMAX, Q− = QMIN,
  SOC_MIN 0, EFF 1 (SOC_MAX is required);
* branches: R, X, B 0, RATE +inf, TAP 1, SHIFT 0.

Columns that a device type does not use (Q/P of non-loads, SoC columns of non-storage) are NaN.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping

import numpy as np

from anm_torchrl.grid.devices import _slopes

BUS_COLS = ("BUS_ID", "BUS_TYPE", "BASE_KV", "VMAX", "VMIN")
DEV_COLS = ("DEV_ID", "BUS_ID", "DEV_TYPE", "Q/P", "PMAX", "PMIN", "QMAX", "QMIN", "P+", "P-", "Q+", "Q-",
            "SOC_MAX", "SOC_MIN", "EFF")
BRANCH_COLS = ("F_BUS", "T_BUS", "BR_R", "BR_X", "BR_B", "RATE", "TAP", "SHIFT")
#: smallest branch impedance accepted, p.u.: at 1e-6 the numba and torch backends agree to 4e-8 MW on ANM6-Easy with
#: one branch shrunk to it; at 1e-12 they disagree on 3 of 256 terminations (issue 25). The registered feeders'
#: smallest is 1.0e-4 (SimBench).
Z_MIN = 1e-6
DEV_TYPES = {-1: "load", 0: "slack", 1: "classical generator", 2: "renewable generator", 3: "storage unit"}
C = {name: j for j, name in enumerate(DEV_COLS)}


def _table(net: Mapping, key: str, cols: tuple[str, ...]) -> np.ndarray:
    """``net[key]`` as a float64 (n, len(cols)) array with ``None`` -> NaN."""
    if key not in net:
        raise ValueError(f"network dict has no {key!r} table (expected keys 'baseMVA', 'bus', 'device', 'branch')")
    rows = net[key]
    try:
        arr = np.array([[np.nan if v is None else float(v) for v in row] for row in rows], dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"network table {key!r} must hold numbers or None: {err}") from None
    if arr.ndim == 1 and arr.size == 0:  # no rows: a valid empty table (e.g. the branches of a one-bus network)
        arr = arr.reshape(0, len(cols))
    if arr.ndim != 2 or arr.shape[1] != len(cols):
        got = arr.shape[1] if arr.ndim == 2 else "ragged rows"
        raise ValueError(f"network table {key!r} must have {len(cols)} columns {list(cols)}, got {got}")
    if arr.shape[0] == 0 and key != "branch":
        raise ValueError(f"network table {key!r} is empty")
    return arr


def _fail(table: str, row: str, col: str, msg: str) -> ValueError:
    return ValueError(f"network table {table!r}, {row}, column {col}: {msg}")


def _check_buses(bus: np.ndarray) -> np.ndarray:
    for j, name in enumerate(("BUS_ID", "BUS_TYPE", "BASE_KV", "VMAX", "VMIN")):
        bad = np.flatnonzero(~np.isfinite(bus[:, j]))
        if bad.size:
            raise _fail("bus", f"row {bad[0]}", name, f"must be a finite number, got {bus[bad[0], j]}")
    ids = bus[:, 0]
    if np.unique(ids).size != ids.size:
        raise _fail("bus", "rows", "BUS_ID", f"bus ids must be unique, got {ids.tolist()}")
    bus = bus[np.argsort(ids, kind="stable")]
    for b in bus:
        name = f"bus {int(b[0])}"
        if b[1] not in (0, 1):
            raise _fail("bus", name, "BUS_TYPE", f"must be 0 (slack) or 1 (PQ), got {b[1]}")
        if b[2] <= 0:
            raise _fail("bus", name, "BASE_KV", f"must be > 0, got {b[2]}")
        if b[3] < 0:
            raise _fail("bus", name, "VMAX", f"must be >= 0, got {b[3]}")
        if b[4] < 0:
            raise _fail("bus", name, "VMIN", f"must be >= 0, got {b[4]}")
        if b[1] == 1 and b[3] < b[4]:
            raise _fail("bus", name, "VMAX", f"VMAX {b[3]} < VMIN {b[4]}")
    if not np.array_equal(bus[:, 0], np.arange(bus.shape[0])):
        raise _fail("bus", "rows", "BUS_ID", f"bus ids must be 0..{bus.shape[0] - 1} (gym-anm sizes its Y-bus "
                    f"by the largest id), got {bus[:, 0].tolist()}")
    slack = np.flatnonzero(bus[:, 1] == 0)
    if slack.size != 1:
        raise _fail("bus", "rows", "BUS_TYPE", f"exactly one slack bus (BUS_TYPE 0) is required, got "
                    f"{slack.size} (buses {slack.tolist()})")
    if slack[0] != 0:
        raise _fail("bus", f"bus {slack[0]}", "BUS_TYPE", "the slack bus must be bus 0 (gym-anm's power flow "
                    "fixes V = 1∠0 at bus 0 whatever BUS_TYPE says)")
    return bus


def _default(row: np.ndarray, col: str, value: float) -> None:
    if math.isnan(row[C[col]]):
        row[C[col]] = value


def _check_device(row: np.ndarray, n_bus: int) -> None:
    """Apply gym-anm's defaults to one device row in place and raise on what gym-anm rejects."""
    name = f"device {int(row[0])}"
    kind = int(row[C["DEV_TYPE"]])

    def need(cond: bool, col: str, msg: str) -> None:
        if not cond:
            raise _fail("device", name, col, msg)

    if kind == -1:
        need(not math.isnan(row[C["Q/P"]]), "Q/P", "a load needs a Q/P ratio")
        _default(row, "PMAX", 0.0)
        _default(row, "PMIN", -np.inf)
        need(row[C["PMAX"]] <= 0, "PMAX", f"a load's PMAX must be <= 0, got {row[C['PMAX']]}")
        row[C["P+"]: C["EFF"] + 1] = np.nan
    elif kind in (0, 1, 2):
        slack = kind == 0
        _default(row, "PMAX", np.inf)
        _default(row, "PMIN", -np.inf if slack else 0.0)
        need(slack or row[C["PMAX"]] >= 0, "PMAX", f"must be >= 0 for a generator, got {row[C['PMAX']]}")
        need(slack or row[C["PMIN"]] >= 0, "PMIN", f"must be >= 0 for a generator, got {row[C['PMIN']]}")
        row[[C["Q/P"], C["P-"], C["SOC_MAX"], C["SOC_MIN"], C["EFF"]]] = np.nan
    elif kind == 3:
        need(not math.isnan(row[C["SOC_MAX"]]), "SOC_MAX", "a storage unit needs SOC_MAX")
        _default(row, "PMAX", np.inf)
        _default(row, "PMIN", -np.inf)
        _default(row, "SOC_MIN", 0.0)
        _default(row, "EFF", 1.0)
        need(row[C["PMAX"]] >= 0, "PMAX", f"must be >= 0 for a storage unit, got {row[C['PMAX']]}")
        need(row[C["PMIN"]] <= 0, "PMIN", f"must be <= 0 for a storage unit, got {row[C['PMIN']]}")
        need(row[C["SOC_MIN"]] >= 0, "SOC_MIN", f"must be >= 0, got {row[C['SOC_MIN']]}")
        need(row[C["SOC_MAX"]] >= row[C["SOC_MIN"]], "SOC_MAX",
             f"SOC_MAX {row[C['SOC_MAX']]} < SOC_MIN {row[C['SOC_MIN']]}")
        need(math.isfinite(row[C["SOC_MAX"]]), "SOC_MAX", f"must be finite, got {row[C['SOC_MAX']]}")
        # EFF = 0 divides by zero in the SoC rows of the projection (gym-anm accepts it, then fails in cvxpy).
        need(0 < row[C["EFF"]] <= 1, "EFF", f"must lie in (0, 1], got {row[C['EFF']]}")
        row[C["Q/P"]] = np.nan
    else:
        raise _fail("device", name, "DEV_TYPE", f"must be one of {sorted(DEV_TYPES)}, got {row[C['DEV_TYPE']]}")
    need(row[C["PMAX"]] >= row[C["PMIN"]], "PMAX", f"PMAX {row[C['PMAX']]} < PMIN {row[C['PMIN']]}")
    if kind == -1:
        return
    _default(row, "QMAX", np.inf)
    _default(row, "QMIN", -np.inf)
    need(row[C["QMAX"]] >= row[C["QMIN"]], "QMAX", f"QMAX {row[C['QMAX']]} < QMIN {row[C['QMIN']]}")
    _default(row, "P+", row[C["PMAX"]])
    need(row[C["PMIN"]] <= row[C["P+"]] <= row[C["PMAX"]], "P+", f"P+ {row[C['P+']]} outside [PMIN, PMAX]")
    _default(row, "Q+", row[C["QMAX"]])
    _default(row, "Q-", row[C["QMIN"]])
    need(row[C["Q+"]] <= row[C["QMAX"]], "Q+", f"Q+ {row[C['Q+']]} > QMAX {row[C['QMAX']]}")
    need(row[C["Q-"]] >= row[C["QMIN"]], "Q-", f"Q- {row[C['Q-']]} < QMIN {row[C['QMIN']]}")
    need(row[C["Q+"]] >= row[C["Q-"]], "Q+", f"Q+ {row[C['Q+']]} < Q- {row[C['Q-']]}")
    if kind == 3:
        _default(row, "P-", row[C["PMIN"]])
        need(row[C["PMIN"]] <= row[C["P-"]] <= row[C["PMAX"]], "P-", f"P- {row[C['P-']]} outside [PMIN, PMAX]")
        need(row[C["P+"]] >= row[C["P-"]], "P+", f"P+ {row[C['P+']]} < P- {row[C['P-']]}")
    if kind != 0:
        # gym-anm builds the capability lines (tau, rho) in float64 and hands them to cvxpy, which rejects NaN
        # data (e.g. PMAX = P+ = +inf gives rho = inf - 0 * inf); rows with +inf right-hand sides are inactive.
        with np.errstate(invalid="ignore", divide="ignore"):
            lines = _slopes(row.tolist())
        used = lines if kind == 3 else lines[:4]
        need(all(not math.isnan(v) for v in used) and all(math.isfinite(t) for t in used[::2]), "P+",
             f"the capability lines (tau, rho) = {used} are not finite: give finite PMAX, QMAX, QMIN or corners")


def _check_devices(dev: np.ndarray, n_bus: int) -> np.ndarray:
    for j in range(3):
        bad = np.flatnonzero(~np.isfinite(dev[:, j]))
        if bad.size:
            raise _fail("device", f"row {bad[0]}", DEV_COLS[j], f"must be a finite number, got {dev[bad[0], j]}")
    for j in (0, 2):  # a fractional id or type would be truncated by int() here and compared exactly elsewhere
        bad = np.flatnonzero(dev[:, j] != np.round(dev[:, j]))
        if bad.size:
            raise _fail("device", f"row {bad[0]}", DEV_COLS[j], f"must be an integer, got {dev[bad[0], j]}")
    ids = dev[:, 0]
    if np.unique(ids).size != ids.size:
        raise _fail("device", "rows", "DEV_ID", f"device ids must be unique, got {ids.tolist()}")
    dev = dev[np.argsort(ids, kind="stable")].copy()
    for row in dev:
        if not (0 <= row[1] < n_bus and row[1] == int(row[1])):
            raise _fail("device", f"device {int(row[0])}", "BUS_ID", f"bus {row[1]} does not exist "
                        f"(buses 0..{n_bus - 1})")
        for j in range(3, len(DEV_COLS)):
            if np.isinf(row[j]) and j not in (C["PMIN"], C["PMAX"], C["QMIN"], C["QMAX"]):
                raise _fail("device", f"device {int(row[0])}", DEV_COLS[j], f"must be finite or None, got {row[j]}")
        _check_device(row, n_bus)
    slack = np.flatnonzero(dev[:, 2] == 0)
    if slack.size != 1:
        raise _fail("device", "rows", "DEV_TYPE", f"exactly one slack device (DEV_TYPE 0) is required, got "
                    f"{slack.size} (devices {dev[slack, 0].astype(int).tolist()})")
    if dev[slack[0], 1] != 0:
        raise _fail("device", f"device {int(dev[slack[0], 0])}", "BUS_ID",
                    f"the slack device must sit on the slack bus 0, got bus {int(dev[slack[0], 1])}")
    return dev


def _check_branches(br: np.ndarray, n_bus: int) -> np.ndarray:
    br = br.copy()
    seen: set[tuple[int, int]] = set()
    for k, row in enumerate(br):
        for j in (0, 1):
            if not (np.isfinite(row[j]) and row[j] == int(row[j]) and 0 <= row[j] < n_bus):
                raise _fail("branch", f"branch row {k}", BRANCH_COLS[j], f"bus {row[j]} does not exist "
                            f"(buses 0..{n_bus - 1})")
        f, t = int(row[0]), int(row[1])
        name = f"branch ({f}, {t})"
        if f == t:
            raise _fail("branch", name, "T_BUS", "a branch must link two different buses")
        if (f, t) in seen or (t, f) in seen:
            raise _fail("branch", name, "F_BUS", "parallel branches are not supported by gym-anm")
        seen.update({(f, t)})
        for j, default in ((2, 0.0), (3, 0.0), (4, 0.0), (5, np.inf), (6, 1.0), (7, 0.0)):
            if math.isnan(row[j]):
                row[j] = default
            elif np.isinf(row[j]):
                raise _fail("branch", name, BRANCH_COLS[j], f"must be finite or None, got {row[j]}")
        for j in (2, 3, 4, 5):
            if row[j] < 0:
                raise _fail("branch", name, BRANCH_COLS[j], f"must be >= 0, got {row[j]}")
        if row[2] == 0 and row[3] == 0:
            raise _fail("branch", name, "BR_X", "r = x = 0 gives an infinite admittance (use a small x)")
        if math.hypot(row[2], row[3]) < Z_MIN:
            raise _fail("branch", name, "BR_X", f"|r + jx| = {math.hypot(row[2], row[3]):.3g} p.u. is below {Z_MIN:g} "
                        f"p.u.: the power flow is ill-conditioned there (the two backends disagree on convergence); "
                        f"merge the two buses, or give the branch |z| >= {Z_MIN:g} p.u.")
        if row[6] <= 0:
            raise _fail("branch", name, "TAP", f"must be > 0, got {row[6]}")
        if not 0 <= row[7] <= 360:
            raise _fail("branch", name, "SHIFT", f"must lie in [0, 360] degrees, got {row[7]}")
    return br


def _check_connected(br: np.ndarray, n_bus: int) -> None:
    """Every bus is reached from the slack bus 0 through the branches (an island has no voltage reference: its
    power flow never converges, and every reset would be re-drawn until it gives up)."""
    adjacent: list[list[int]] = [[] for _ in range(n_bus)]
    for f, t in br[:, :2].astype(int).tolist():
        adjacent[f].append(t)
        adjacent[t].append(f)
    seen, todo = {0}, [0]
    while todo:
        for b in adjacent[todo.pop()]:
            if b not in seen:
                seen.add(b)
                todo.append(b)
    islands = sorted(set(range(n_bus)) - seen)
    if islands:
        raise _fail("branch", "rows", "F_BUS/T_BUS", f"the network is disconnected: bus(es) {islands} are not "
                    f"connected to the slack bus 0 by any path of branches (an island has no voltage reference; "
                    f"its power flow cannot converge)")


def validate_network(network: Mapping) -> dict:
    """Check a gym-anm network dict and return it normalized (see the module docstring).

    Args:
        network: ``{"baseMVA": float, "bus": (n_bus, 5), "device": (n_dev, 15), "branch": (n_br, 8)}``
            (arrays or nested lists; ``None`` or NaN where gym-anm allows a missing value).

    Returns:
        ``{"baseMVA": float, "bus", "device", "branch"}`` as float64 arrays (buses and devices sorted by id).

    Raises:
        ValueError: naming the table, the row (bus / device / branch id) and the column at fault.
    """
    if not isinstance(network, Mapping):
        raise ValueError(f"network must be a dict with 'baseMVA', 'bus', 'device', 'branch', got {type(network)}")
    if "baseMVA" not in network:
        raise ValueError("network dict has no 'baseMVA' entry")
    try:
        base = float(network["baseMVA"])
    except (TypeError, ValueError):
        raise ValueError(f"network 'baseMVA' must be a number, got {network['baseMVA']!r}") from None
    if not (math.isfinite(base) and base > 0):
        raise ValueError(f"network 'baseMVA' must be finite and > 0, got {base}")
    bus = _check_buses(_table(network, "bus", BUS_COLS))
    dev = _check_devices(_table(network, "device", DEV_COLS), bus.shape[0])
    br = _check_branches(_table(network, "branch", BRANCH_COLS), bus.shape[0])
    if bus.shape[0] < 2:
        raise ValueError("network table 'bus' has a single bus: a one-bus network (no branches) is not supported, "
                         "because the power flow (both backends) solves for the non-slack buses and needs at least "
                         "one; add a bus joined to the slack bus 0 by a branch")
    others = dev[(dev[:, 1] == 0) & (dev[:, 2] != 0), 0].astype(int).tolist()
    if others:  # gym-anm sets the slack device's P, Q to the whole bus-0 injection: theirs would vanish from it
        raise _fail("device", f"devices {others}", "BUS_ID", "only the slack device may sit on the slack bus 0: "
                    "gym-anm sets the slack device's P and Q to the whole bus-0 injection, so the slack's power "
                    "leaves another device there out while the energy loss still counts it (a load there gives a "
                    "negative loss); connect it to a bus joined to bus 0 by a branch")
    _check_connected(br, bus.shape[0])
    return {"baseMVA": base, "bus": bus, "device": dev, "branch": br}


def device_ids(network: Mapping, kinds: tuple[int, ...]) -> list[int]:
    """Device ids (ascending) of a normalized network whose DEV_TYPE is in ``kinds``."""
    dev = network["device"]
    return [int(d) for d in dev[np.isin(dev[:, 2], kinds), 0]]


def validate_profile(values, name: str, n_cols: int, what: str) -> np.ndarray:
    """Check an exogenous profile: float64 (T, n_cols), T >= 1, every entry finite.

    Args:
        values: array-like (T, n_cols) MW.
        name: the argument's name, for the message (``"load_p"``, ``"gen_p_max"``).
        n_cols: expected number of columns.
        what: what the columns are, for the message (``"loads 1, 3, 5 in device-id order"``).
    """
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be a numeric (T, {n_cols}) array: {err}") from None
    if arr.ndim == 1 and n_cols == 0:
        arr = arr.reshape(-1, 0)
    if arr.ndim != 2 or arr.shape[1] != n_cols or arr.shape[0] < 1:
        raise ValueError(f"{name} must have shape (T >= 1, {n_cols}) ({what}), got {arr.shape}")
    bad = np.argwhere(~np.isfinite(arr))
    if bad.size:
        t, c = bad[0]
        raise ValueError(f"{name} must be finite; row {t}, column {c} ({what}) is {arr[t, c]} "
                         f"({len(bad)} non-finite entries)")
    return arr


def validate_profiles(network: Mapping, load_p, gen_p_max) -> tuple[np.ndarray, np.ndarray]:
    """Check a normalized network's two exogenous profiles together (:func:`validate_profile` each).

    Args:
        network: a normalized gym-anm network (:func:`validate_network`).
        load_p: (T, n_load) MW, loads in device-id order.
        gen_p_max: (T, n_gen) MW, non-slack generators in device-id order; the same T as ``load_p``.

    Returns:
        (load_p, gen_p_max) as float64 arrays.
    """
    loads, gens = device_ids(network, (-1,)), device_ids(network, (1, 2))
    load_p = validate_profile(load_p, "load_p", len(loads), f"loads {loads} in device-id order")
    gen_p_max = validate_profile(gen_p_max, "gen_p_max", len(gens), f"non-slack generators {gens} in device-id order")
    if load_p.shape[0] != gen_p_max.shape[0]:
        raise ValueError(f"load_p and gen_p_max must have the same T rows, got {load_p.shape[0]} and "
                         f"{gen_p_max.shape[0]}")
    return load_p, gen_p_max


def check_reward_args(delta_t, gamma, lamb, costs_clipping) -> tuple[float, float]:
    """gym-anm's ``check_env_args`` for the reward constants; returns the clipping with ``None`` entries as +inf.

    Raises:
        ValueError: a constant gym-anm would reject (naming it and the value received).
    """
    def real(x) -> bool:  # numpy scalars too; a bool is not a constant; +inf would make the rewards NaN
        return isinstance(x, numbers.Real) and not isinstance(x, (bool, np.bool_)) and math.isfinite(x)

    if not (real(delta_t) and delta_t > 0):
        raise ValueError(f"delta_t must be a finite number > 0 (h), got {delta_t!r}")
    # gamma = 1 makes the terminal reward -c1 / (1 - gamma) a division by zero
    if not (real(gamma) and 0 <= gamma < 1):
        raise ValueError(f"gamma must lie in [0, 1), got {gamma!r}")
    if not (real(lamb) and lamb >= 0):
        raise ValueError(f"lamb must be a finite number >= 0, got {lamb!r}")
    if costs_clipping is None:
        return math.inf, math.inf
    if isinstance(costs_clipping, (str, bytes)) or np.ndim(costs_clipping) != 1 or len(costs_clipping) != 2:
        raise ValueError(f"costs_clipping must be (c_energy, c_penalty), got {costs_clipping!r}")
    c = tuple(math.inf if v is None else float(v) for v in costs_clipping)
    if not all(v > 0 for v in c):
        raise ValueError(f"costs_clipping entries must be > 0 (or None), got {costs_clipping!r}")
    return c
