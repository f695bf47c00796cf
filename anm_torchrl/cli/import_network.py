"""``python -m anm_torchrl.cli.import_network``: any SimBench grid, or a user's pandapower net, as a network file every
recipe takes (:mod:`anm_torchrl.networks.user_import`)::

    python -m anm_torchrl.cli.import_network --simbench 1-LV-rural1--0-sw --out rural1.npz
    python -m anm_torchrl.cli.import_network --pandapower my_net.json --loads loads.csv --sgens pv.csv --out my.npz
    python recipes/ppo.py network=rural1.npz
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from anm_torchrl.cli.args import count, index, run_main


def main(argv: list[str] | None = None) -> dict:
    """Parse ``argv``, convert, check against pandapower, write the file, print its summary."""
    ap = argparse.ArgumentParser(description="a SimBench grid or a pandapower net as an anm_torchrl network file")
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--simbench", metavar="CODE", help="a SimBench code, e.g. 1-LV-rural1--0-sw, 1-MV-comm--0-sw")
    src.add_argument("--pandapower", metavar="NET.json", help="a pandapower net saved with pandapower.to_json")
    ap.add_argument("--out", required=True, help="the network file to write (.npz)")
    ap.add_argument("--force", action="store_true", help="replace an existing --out file")
    ap.add_argument("--start-day", type=index, default=None, help="--simbench: first day of 2016's profiles "
                    "(default 150, 2016-05-30, as the registered SimBench feeder)")
    ap.add_argument("--days", type=count, default=None, help="--simbench: days of profiles (default 7)")
    ap.add_argument("--loads", metavar="CSV", help="--pandapower: MW consumed per 15-minute step (rows) by every "
                    "in-service load (columns headed by its pandapower index); default: nominal p_mw at every step")
    ap.add_argument("--sgens", metavar="CSV", help="--pandapower: MW potential per step of every in-service "
                    "renewable sgen; default: nominal p_mw at every step")
    ap.add_argument("--rows", type=count, default=96, help="--pandapower without CSVs: steps of the constant "
                    "profiles (default 96, one day)")
    ap.add_argument("--summary", metavar="JSON", help="also write the summary (and the command line, wall time and "
                    "machine) to this JSON file")
    ap.add_argument("--two-way-storage", action="store_true", help="storage units that can only charge or only "
                    "discharge (SimBench's home batteries: max_p_mw 0) get the mirrored P range instead "
                    "(PMIN = -PMAX); the file's source says so")
    ap.add_argument("--check-rows", type=count, default=4, help="profile rows where gym-anm's power flow is "
                    "compared with pandapower's (every row must converge in pandapower)")
    args = ap.parse_args(argv)
    if args.simbench is None and (args.start_day is not None or args.days is not None):
        ap.error("--start-day and --days are --simbench options")
    if args.pandapower is None and (args.loads or args.sgens):
        ap.error("--loads and --sgens are --pandapower options")

    from anm_torchrl.networks import feeders, user_import

    user_import.check_network_out(args.out, args.force)  # before seconds of loading
    t0 = time.perf_counter()
    if args.simbench:
        start, days = (feeders.START_DAY if args.start_day is None else args.start_day,
                       feeders.N_DAYS if args.days is None else args.days)
        net, load_mw, sgen_mw = feeders.simbench_grid(args.simbench, start, days)
        source = (f"SimBench {args.simbench} with its own 15-minute profiles of 2016, {days} days from day {start} "
                  "(python -m anm_torchrl.cli.import_network)")
    else:
        net, load_mw, sgen_mw, source = user_import.read_pandapower(args.pandapower, args.loads, args.sgens,
                                                                    args.rows)
    from anm_torchrl.networks.pandapower_import import ImportDefaults

    out = user_import.import_network(net, load_mw, sgen_mw, args.out, source=source, check_rows=args.check_rows,
                                     overwrite=args.force,
                                     defaults=ImportDefaults(storage_two_way=args.two_way_storage))
    if args.summary:
        from anm_torchrl.artifacts import atomic_write
        from anm_torchrl.provenance import machine_info
        from anm_torchrl.strict_json import json_text

        command = "python -m anm_torchrl.cli.import_network " + " ".join(sys.argv[1:] if argv is None else argv)
        record = {**out, "source": source, "wall_s": time.perf_counter() - t0, "command": command,
                  "machine": machine_info()}
        Path(args.summary).parent.mkdir(parents=True, exist_ok=True)
        atomic_write(Path(args.summary), json_text(record, indent=2).encode())
    dev = ", ".join(f"{n} {k}{'s' if n != 1 else ''}" for k, n in out["devices"].items())
    print(f"wrote {out['path']}: {out['buses']} buses; {dev}; {out['rows']} profile rows; do-nothing |V| "
          f"{out['vm_min']:.4f}-{out['vm_max']:.4f} p.u., loading up to {out['loading_max_percent']:.1f} % "
          f"(pandapower); gym-anm's power flow within {out['vm_max_diff']:.1e} p.u. of pandapower's")
    from anm_torchrl.networks.resolve import check_controllable  # the training recipes' own check: one home

    try:
        check_controllable(out["path"])
    except ValueError as err:  # every training recipe refuses it: say so here, not at the first training
        print(f"no policy can be trained on it ({err}); evaluate it with python recipes/evaluate.py "
              f"policy=do_nothing network={out['path']}")
    else:
        print(f"train on it: python recipes/ppo.py network={out['path']}")
    return out


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    run_main(main, "anm_torchrl.cli.import_network")
