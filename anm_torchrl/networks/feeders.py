"""The registered pandapower / SimBench feeders: how each is built, profiled, checked and saved.

Re-make a committed case (needs the ``feeders`` extra: pandapower, simbench; the runtime package never imports
this module)::

    python -m anm_torchrl.networks.feeders --name case33bw   # or cigre_mv, simbench_mv_semiurb, all

Profiles are SimBench's 15-minute profiles (year 2016), one slice of ``N_DAYS`` days from ``START_DAY``; the
feeders that ship none (``case33bw``, ``cigre_mv``) take SimBench's standard profiles by customer class, each
scaled so that its annual maximum is the feeder's nominal value (the nominal loads of these cases are peak loads).

* ``case33bw`` — pandapower's Baran & Wu 33-bus feeder (M. E. Baran, F. F. Wu, "Network reconfiguration in
  distribution systems for loss reduction and load balancing", IEEE Trans. Power Delivery 4(2), 1989; 12.66 kV,
  3.715 MW / 2.3 MVAr peak, tie lines open) with the PV placement of MAPDN (J. Wang, W. Xu, Y. Gu, W. Song,
  T. C. Green, "Multi-Agent Reinforcement Learning for Active Voltage Control on Power Distribution Networks",
  NeurIPS 2021; code github.com/Future-Power-Networks/MAPDN, whose 33-bus net is made by
  github.com/xuwkk/gen_pandapower_pv ``bus33bw.py`` @43d373fc, ``PV_bus_index = [12,17,21,24,28,32]``): **six PV
  units at buses 13, 18, 22, 25, 29 and 33** (1-based; pandapower indices 12, 17, 21, 24, 28, 32), one at the end
  of each lateral and of the main feeder, and MAPDN's voltage band, 0.95–1.05 p.u. at every non-slack bus (the
  pandapower case has 0.9–1.1). Placement and band from the study; the rest are this project's choices:
  - sizes: 1.0 MW each (6.0 MW nominal; MAPDN's PV series are not in the stored sources, so their scale could
    not be copied). Chosen so that the case has MAPDN's problem, over-voltage from PV: with SimBench's ``PV3``
    profile the six units give up to 3.29 MW in the profile week against 0.50–2.30 MW of load, so do-nothing
    exceeds 1.05 p.u. at midday (max 1.057) and falls below 0.95 p.u. at the evening peak (min 0.948), and the
    controller has curtailment, reactive power and storage to use both ways (0.5 MW each gave no over-voltage);
  - no wind (MAPDN has none);
  - two storage units of 0.5 MW / 2 MWh at the ends of the two longest laterals (buses 18 and 33, indices 17 and
    32, beside two of the PV units), because gym-anm's task is about shifting energy and MAPDN has no storage;
  - every load follows SimBench ``lv_semiurb5`` (peak-scaled); no line ratings (no branch penalty), as the case.
  An earlier placement (three DG units at buses 14/24/30 of 0.754/1.100/1.071 MW) was dropped on 2026-12-03:
  no readable study could be found for it.
* ``cigre_mv`` — pandapower's ``create_cigre_network_mv(with_der="all")`` (CIGRE TB 575, 2014, European MV
  benchmark: 14 buses at 20 kV; 8 PV, 1 wind park, 2 fuel cells, 1 CHP diesel, 1 residential fuel cell pair,
  2 batteries); its default switch states (S1–S3 open, radial). Residential loads take SimBench
  ``lv_semiurb5``, commercial/industrial ``G2-A``; PV ``PV3``, wind ``WP4``; fuel cells and CHP are classical
  (dispatchable) generators.
* ``simbench_mv_semiurb`` — SimBench ``1-MV-semiurb--0-sw`` (Meinecke et al., "SimBench — A Benchmark Dataset of
  Electric Power Systems to Compare Innovative Solutions Based on Power Flow Analysis", Energies 13(12) 3290,
  2020): 117 buses at 110/20 kV, 115 loads, 121 static generators, with its own load and generation profiles.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from anm_torchrl._extras import require
from anm_torchrl.networks import pandapower_import as ppi
from anm_torchrl.networks.case_file import save_case

pd = require("pandas")  # pandapower's dependency: the [feeders] extra

logger = logging.getLogger(__name__)

START_DAY = 150  # 2016-05-30, a week with both PV output and evening load peaks
N_DAYS = 7
STEPS_PER_DAY = 96
ENV = {"delta_t": 0.25, "gamma": 0.995, "lamb": 100.0, "costs_clipping": [1.0, 100.0]}  # ANM6-Easy's
SIMBENCH_CODE = "1-MV-semiurb--0-sw"

CASE33_PV_BUSES = (12, 17, 21, 24, 28, 32)  # MAPDN's (pandapower indices)
CASE33_DG = [(bus, 1.0, "PV", "PV3") for bus in CASE33_PV_BUSES]  # (bus index, MW, type, SimBench profile)
CASE33_V_BAND = (0.95, 1.05)  # MAPDN's (p.u., non-slack buses)
CASE33_STORAGE = [(17, 0.5, 2.0), (32, 0.5, 2.0)]  # (bus index, MW, MWh)


def _rows(start_day: int = START_DAY, days: int = N_DAYS) -> slice:
    start = start_day * STEPS_PER_DAY
    return slice(start, start + days * STEPS_PER_DAY)


def _simbench_net(code: str = SIMBENCH_CODE):
    sb = require("simbench")

    try:
        return sb.get_simbench_net(code)
    except Exception as err:  # simbench raises bare Exceptions / assertion errors for an unknown code: named here
        raise ValueError(f"SimBench could not load grid {code!r} ({type(err).__name__}: {err}); codes look like "
                         "1-LV-rural1--0-sw (simbench.collect_all_simbench_codes())") from None


def _library() -> tuple[pd.DataFrame, pd.DataFrame]:
    """SimBench's load and renewable profile tables (35,136 rows of 2016), as factors of nominal values."""
    prof = _simbench_net().profiles
    return prof["load"], prof["renewables"]


def _peak_scaled(series: pd.Series) -> np.ndarray:
    """A profile slice divided by the annual maximum of the profile (1 = the annual peak)."""
    return (series.to_numpy(dtype=np.float64) / series.max())[_rows()]


def _by_class(table: pd.DataFrame, profile_of: dict, library: pd.DataFrame, peak: bool) -> pd.DataFrame:
    cols = {}
    for i, row in table.iterrows():
        series = library[profile_of[i]]
        factor = _peak_scaled(series) if peak else series.to_numpy(dtype=np.float64)[_rows()]
        cols[i] = row.p_mw * row.scaling * factor
    return pd.DataFrame(cols)


def _case33bw_net():
    pp = require("pandapower")
    pn = require("pandapower.networks")

    net = pn.case33bw()
    net.bus.loc[net.bus.index != net.ext_grid.bus.iloc[0], ["min_vm_pu", "max_vm_pu"]] = CASE33_V_BAND
    for bus, p, kind, _ in CASE33_DG:
        pp.create_sgen(net, bus, p_mw=p, q_mvar=0.0, sn_mva=p, type=kind, name=f"{kind} bus {bus + 1}")
    for bus, p, e in CASE33_STORAGE:
        pp.create_storage(net, bus, p_mw=0.0, max_e_mwh=e, min_e_mwh=0.0, max_p_mw=p, min_p_mw=-p,
                          name=f"storage bus {bus + 1}")
    return net


def _case33bw_profiles(net):
    loads, ren = _library()
    load_mw = _by_class(net.load, {i: "lv_semiurb5_pload" for i in net.load.index}, loads, peak=True)
    sgen_mw = _by_class(net.sgen, {i: prof for i, (_, _, _, prof) in zip(net.sgen.index, CASE33_DG)}, ren,
                        peak=False)
    return load_mw, sgen_mw


def _cigre_net():
    pn = require("pandapower.networks")

    return pn.create_cigre_network_mv(with_der="all")


def _cigre_profiles(net):
    loads, ren = _library()
    load_prof = {i: "lv_semiurb5_pload" if n.startswith("Load R") else "G2-A_pload" for i, n in net.load.name.items()}
    load_mw = _by_class(net.load, load_prof, loads, peak=True)
    ren_idx = [i for i, t in net.sgen.type.items() if ppi.RENEWABLE_TYPE.search(str(t))]
    sgen_prof = {i: "PV3" if net.sgen.type[i] == "PV" else "WP4" for i in ren_idx}
    return load_mw, _by_class(net.sgen.loc[ren_idx], sgen_prof, ren, peak=False)


def _simbench_profiles(net, start_day: int = START_DAY, days: int = N_DAYS):
    sb = require("simbench")

    absolute = sb.get_absolute_values(net, profiles_instead_of_study_cases=True)
    rows = _rows(start_day, days)
    load_mw = absolute[("load", "p_mw")].iloc[rows].reset_index(drop=True)
    sgen_mw = absolute[("sgen", "p_mw")].iloc[rows].reset_index(drop=True)
    return load_mw, sgen_mw


def simbench_grid(code: str, start_day: int = START_DAY, days: int = N_DAYS):
    """Any SimBench grid with ``days`` days of its own 15-minute profiles (year 2016) from day ``start_day``.

    Returns:
        ``(pandapower net, load MW (T, loads), sgen MW (T, sgens))``, T = 96 ``days``.

    Raises:
        ValueError: an unknown code, or a slice outside the year.
    """
    if not (0 <= start_day and days >= 1 and start_day + days <= 366):
        raise ValueError(f"SimBench's profiles cover the 366 days of 2016: days {start_day} to {start_day + days} "
                         "are not inside it")
    net = _simbench_net(code)
    load_mw, sgen_mw = _simbench_profiles(net, start_day, days)
    return net, load_mw, sgen_mw


def _source(name: str) -> str:
    """The feeder's paragraph of this module's docstring."""
    return __doc__.split(f"* ``{name}``")[1].split("\n* ``")[0].strip()


# name -> (pandapower net builder, element profiles (load MW, sgen MW) of that net)
BUILDERS = {"case33bw": (_case33bw_net, _case33bw_profiles), "cigre_mv": (_cigre_net, _cigre_profiles),
            "simbench_mv_semiurb": (_simbench_net, _simbench_profiles)}


def raw_net(name: str):
    """The pandapower net of feeder ``name`` as built (before :func:`pandapower_import.prepare`)."""
    if name not in BUILDERS:
        raise ValueError(f"unknown feeder {name!r}; known: {list(BUILDERS)}")
    return BUILDERS[name][0]()


def build(name: str, defaults: ppi.ImportDefaults = ppi.ImportDefaults()):
    """Prepared pandapower net, conversion and gym-anm profiles of feeder ``name``.

    Returns:
        ``(prepared net, ImportResult, load_p (T, n_load) MW, gen_p_max (T, n_gen) MW, source text)``.
    """
    raw = raw_net(name)
    load_mw, sgen_mw = BUILDERS[name][1](raw)
    net, res, load_p, gen_p_max = ppi.from_pandapower(raw, load_mw, sgen_mw, defaults)
    return net, res, load_p, gen_p_max, _source(name)


def build_and_save(name: str) -> Path:
    """Build ``name``, check its do-nothing power flow on every profile row with pandapower, save the case."""
    from anm_torchrl.networks.pf_check import do_nothing_sweep

    defaults = ppi.ImportDefaults()
    net, res, load_p, gen_p_max, source = build(name, defaults)
    sweep = do_nothing_sweep(net, res, load_p, gen_p_max)
    logger.info("%s: %d buses, %d devices, %d branches; do-nothing |V| in [%.4f, %.4f] p.u., max loading %.1f %%",
                name, res.network["bus"].shape[0], res.network["device"].shape[0], res.network["branch"].shape[0],
                sweep["vm_min"], sweep["vm_max"], sweep["loading_max_percent"])
    meta = {"name": name, "source": source, "env": ENV, "defaults": ppi.defaults_record(defaults),
            "profile_slice": {"start_day_2016": START_DAY, "days": N_DAYS, "rows": N_DAYS * STEPS_PER_DAY},
            "elements": {"load": res.load_idx, "gen": res.gen_elements, "storage": res.storage_idx},
            "bus_map": {str(k): v for k, v in res.bus_map.items()}, "do_nothing_pandapower": sweep}
    return save_case(name, res.network, load_p, gen_p_max, meta)


def main(argv: list[str] | None = None) -> None:
    """Command line: re-import one registered feeder (or ``all``) and rewrite its case file."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--name", required=True, choices=[*BUILDERS, "all"])
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for name in BUILDERS if args.name == "all" else [args.name]:
        path = build_and_save(name)
        logger.info("wrote %s", path)


if __name__ == "__main__":
    main()
