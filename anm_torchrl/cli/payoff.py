"""Command line of the payoff study's record (:mod:`anm_torchrl.experiments.payoff`): merge parts measured apart
into it, then print its tables.

    python -m anm_torchrl.cli.payoff results/payoff/payoff.json                      # print the tables
    python -m anm_torchrl.cli.payoff results/payoff/payoff.json --merge-ppo SRC --note "<how SRC was made>"
    python -m anm_torchrl.cli.payoff results/payoff/payoff.json --merge-cost SRC --networks case33bw --note "<how>"
    python -m anm_torchrl.cli.payoff results/payoff/payoff.json --reread-accuracy
"""

from __future__ import annotations

import argparse
import sys

from anm_torchrl.cli.args import run_main
from anm_torchrl.experiments.io import read_json
from anm_torchrl.experiments.payoff import merge_cost, merge_ppo, reread_accuracy
from anm_torchrl.experiments.payoff_report import markdown


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m anm_torchrl.cli.payoff",
                                     description="print the payoff study's tables from its record")
    parser.add_argument("record", nargs="?", default="results/payoff/payoff.json")
    parser.add_argument("--merge-ppo", metavar="SRC", help="first replace the record's ppo part by SRC's (merge_ppo)")
    parser.add_argument("--merge-cost", metavar="SRC", help="first replace the record's cost rows of --networks by "
                        "SRC's (merge_cost)")
    parser.add_argument("--networks", nargs="*", default=[], help="with --merge-cost: the networks to replace")
    parser.add_argument("--note", help="with --merge-ppo / --merge-cost: how SRC was made (replaces the record's "
                        "note about that part)")
    parser.add_argument("--reread-accuracy", action="store_true", help="first replace the record's pinn_accuracy "
                        "part by the generic PINN's record (accuracy_part)")
    args = parser.parse_args(argv)
    if args.merge_cost and not args.networks:
        parser.error("--merge-cost needs --networks <names> (the networks whose rows it replaces)")
    if args.reread_accuracy:
        reread_accuracy(args.record)
    if args.merge_ppo:
        merge_ppo(args.merge_ppo, args.record, args.note)
    if args.merge_cost:
        merge_cost(args.merge_cost, args.record, args.networks, args.note)
    sys.stdout.write(markdown(read_json(args.record)) + "\n")


if __name__ == "__main__":
    run_main(main, "anm_torchrl.cli.payoff")
