"""A user's pandapower net, or any SimBench grid, as a network file every recipe takes (``network=<file>.npz``),
checked against pandapower before it is written. Needs the ``feeders`` extra (pandapower, simbench); the command
line is ``python -m anm_torchrl.cli.import_network``.

The conversion is :mod:`anm_torchrl.networks.pandapower_import`'s (what gym-anm cannot model is refused by name);
the reward constants are the registered feeders' (ANM6-Easy's: 15-minute steps, gamma 0.995, lambda 100, costs
clipped at 1 and 100).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from anm_torchrl._extras import require
from anm_torchrl.networks import pandapower_import as ppi
from anm_torchrl.networks import pf_check
from anm_torchrl.networks.feeders import ENV, STEPS_PER_DAY
from anm_torchrl.networks.user import SUFFIX, save_network

pd = require("pandas")

#: largest | |V| pandapower - |V| gym-anm | (p.u.) accepted at the checked rows: both solve the same equations to
#: far below it (the registered feeders agree to 1e-9); above it the conversion is wrong, and nothing is written
VM_TOL = 1e-6


def check_network_out(out: str | os.PathLike, overwrite: bool) -> Path:
    """The output path, refused before any work when it is not ``.npz`` or names an existing file (unless
    ``overwrite``) or a folder."""
    path = Path(out)
    if path.suffix != SUFFIX:  # save_network's own rule, checked before the work
        raise ValueError(f"a network file ends with {SUFFIX}, got {path}")
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists (overwrite it with --force)")
    return path


def read_pandapower(net_path: str | os.PathLike, loads_csv=None, sgens_csv=None, rows: int = STEPS_PER_DAY):
    """A pandapower net saved as JSON (``pandapower.to_json``) and its profiles.

    Args:
        net_path: the net's JSON file.
        loads_csv, sgens_csv: CSV files of one 15-minute step per row and one column per element, headed by its
            pandapower index: MW consumed by every in-service load, MW potential of every in-service renewable
            sgen. None: the element's nominal ``p_mw * scaling`` at every step (``rows`` steps, or as many as the
            other profile has).

    Returns:
        ``(net, load MW (T, loads), sgen MW (T, sgens), source text)``.
    """
    pp = require("pandapower")
    net_path = Path(net_path)
    if not net_path.is_file():
        raise FileNotFoundError(f"no pandapower net at {net_path}")
    try:
        net = pp.from_json(str(net_path))
    except Exception as err:  # pandapower raises what its JSON reader meets
        raise ValueError(f"{net_path} is not a pandapower net in JSON ({type(err).__name__}: {err})") from None
    given = {what: _read_csv(path, what) for path, what in ((loads_csv, "load"), (sgens_csv, "renewable")) if path}
    for table, what in (("load", "load"), ("sgen", "renewable")):  # a column of no element: another net's file?
        extra = sorted(set(given[what].columns) - set(net[table].index)) if what in given else []
        if extra:
            known = list(net[table].index)
            raise ValueError(f"the {what} profile has columns {extra[:5]} that are no {table} of {net_path.name} "
                             f"(its {table} indices: {known[:10]}{' ...' if len(known) > 10 else ''})")
    rows = len(next(iter(given.values()))) if given else rows  # a nominal profile as long as a given one
    profiles = [given[what] if what in given else
                pd.DataFrame({i: np.full(rows, float(r.p_mw * r.scaling)) for i, r in net[table].iterrows()},
                             index=range(rows))  # rows even where the net has no such element (no sgen: 0 columns)
                for table, what in (("load", "load"), ("sgen", "renewable"))]
    if profiles[0].shape[0] != profiles[1].shape[0]:
        raise ValueError(f"the load profile has {profiles[0].shape[0]} rows, the renewable profile "
                         f"{profiles[1].shape[0]}: one row per 15-minute step in both")
    given = ", ".join(f"{what} profile {path}" if path else f"nominal {what} values at {rows} steps"
                      for path, what in ((loads_csv, "load"), (sgens_csv, "renewable")))
    return net, profiles[0], profiles[1], f"pandapower net {net_path.name}; {given}"


def _read_csv(path, what: str):
    try:
        df = pd.read_csv(path)
    except (OSError, ValueError) as err:
        raise ValueError(f"the {what} profile {path} is not a readable CSV ({type(err).__name__}: {err})") from None
    try:
        df.columns = [int(c) for c in df.columns]
        values = df.to_numpy(dtype=np.float64)
    except ValueError:
        raise ValueError(f"the {what} profile {path} must hold numbers (MW) under integer headers (pandapower "
                         f"indices), got columns {list(df.columns)[:5]}") from None
    if len(df) == 0 or not np.isfinite(values).all():
        raise ValueError(f"the {what} profile {path} must hold at least one row of finite MW values")
    return df


def import_network(net, load_mw, sgen_mw, out: str | os.PathLike, *, source: str, check_rows: int = 4,
                   overwrite: bool = False, defaults: ppi.ImportDefaults = ppi.ImportDefaults()) -> dict:
    """Convert (with ``defaults``, :class:`.pandapower_import.ImportDefaults`), check and save a pandapower net as
    a network file.

    The do-nothing point (loads as profiled, renewables at their potential) must converge in pandapower on every
    profile row, and gym-anm's power flow must land on pandapower's voltages at ``check_rows`` rows spread over the
    profile (within :data:`VM_TOL`); nothing is written otherwise.

    Returns:
        A summary: ``path``, ``buses``, ``devices`` (count by kind), ``rows``, do-nothing ``vm_min``/``vm_max``
        (p.u.) and ``loading_max_percent`` (pandapower's), ``vm_max_diff`` (p.u., gym-anm against pandapower).
    """
    path = check_network_out(out, overwrite)
    prepared, res, load_p, gen_p_max = ppi.from_pandapower(net, load_mw, sgen_mw, defaults)
    if res.mirrored:  # the file says what differs from the net as given
        source += f"; storage units {res.mirrored} made two-way (P range mirrored, --two-way-storage)"
    sweep = pf_check.do_nothing_sweep(prepared, res, load_p, gen_p_max)
    network, diff = res.network, 0.0
    for t in np.unique(np.linspace(0, len(load_p) - 1, max(1, check_rows)).astype(int)):
        p, q = pf_check.do_nothing_injections(network, load_p[t], gen_p_max[t])
        pf_check.set_pandapower_point(prepared, res, p, q)
        pf_check.run_pandapower(prepared)
        vm, ok = pf_check.gym_anm_vm(network, p, q)
        row_diff = float(np.abs(pf_check.compare_vm(prepared, res, vm)).max()) if ok else float("inf")
        if row_diff > VM_TOL:
            raise ValueError(f"gym-anm's power flow of the converted net differs from pandapower's at profile row "
                             f"{t} by {row_diff:.2e} p.u. (converged: {ok}); not written")
        diff = max(diff, row_diff)
    save_network(path, network, load_p, gen_p_max, source=source, **ENV)
    kinds = {"load": -1, "classical generator": 1, "renewable": 2, "storage unit": 3}
    dev = network["device"][:, 2]
    return {"path": str(path), "buses": int(network["bus"].shape[0]), "rows": int(len(load_p)),
            "devices": {k: int((dev == v).sum()) for k, v in kinds.items()}, **{k: sweep[k] for k in
            ("vm_min", "vm_max", "loading_max_percent")}, "vm_max_diff": diff}

