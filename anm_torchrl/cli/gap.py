"""Command line of the gap study (:mod:`anm_torchrl.experiments.gap`): every controller against the
perfect-foresight optimum, on the same test states.

    python -m anm_torchrl.cli.gap --episodes 8 --seed 0 --steps 3000 --rows optimal --out rec.json
    python -m anm_torchrl.cli.gap --episodes 8 --seed 0 --steps 3000 --rows acmpc_64 --only 0,1 \
        --out part.json                                            # a costly row on some of the states
    python -m anm_torchrl.cli.gap --episodes 8 --seed 0 --steps 3000 --merge part.json --out rec.json
    python -m anm_torchrl.cli.gap --combine rec.json --test-returns results/reproduction/test_returns.json \
        --readme README.md docs/OPTIMAL.md --out results/gap/optimal_gap_table.json   # the published table
    python -m anm_torchrl.cli.gap --render results/gap/optimal_gap_table.json --readme README.md docs/OPTIMAL.md

Rows, protocol and the loss column: :mod:`anm_torchrl.experiments.gap`.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import torch

from anm_torchrl.cli.args import count, index, run_main
from anm_torchrl.evaluation import EVAL_MAX_STEPS
from anm_torchrl.experiments.gap import ANM6, DEFAULT_ROWS, markdown, measure, write_record

log = logging.getLogger(__name__)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m anm_torchrl.cli.gap", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--network", default=ANM6, help="registered network (default anm6_easy)")
    ap.add_argument("--episodes", type=count, default=4, help="number of test states (default 4)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the test states (default 0, the test seed)")
    ap.add_argument("--steps", type=count, default=EVAL_MAX_STEPS, help=f"episode length T (default {EVAL_MAX_STEPS})")
    ap.add_argument("--rows", default=",".join(DEFAULT_ROWS), help="comma-separated rows (default: all)")
    ap.add_argument("--only", default="", help="comma-separated state indices the rows run on (default: all)")
    ap.add_argument("--stability", type=index, default=0,
                    help="re-solve the optimum of this many first states from every warm start (default 0)")
    ap.add_argument("--formulations", type=index, default=0,
                    help="time polar vs rectangular voltages on the first state over this many steps (default 0: no)")
    ap.add_argument("--merge", nargs="*", default=[],
                    help="records of the same protocol (e.g. rows measured in parallel runs) whose rows are merged "
                         "into --out")
    ap.add_argument("--drop", default="",
                    help="comma-separated rows removed from --out before --merge (to replace them by re-measured "
                         "ones)")
    ap.add_argument("--combine", default="",
                    help="build the published table from this gap record into --out (no evaluation)")
    ap.add_argument("--test-returns", default="", help="with --combine: the test_returns record (ANM6-Easy's PPO rows)")
    ap.add_argument("--ppo", default="",
                    help="with --combine, another network: its payoff PPO record "
                         "(results/payoff/inputs/ppo_<network>.json)")
    ap.add_argument("--readme", nargs="*", default=[],
                    help="with --combine: pages whose <!-- optimum:gap --> block is rewritten")
    ap.add_argument("--markdown", action="store_true", help="print the record's table as Markdown and exit")
    ap.add_argument("--render", default="",
                    help="rewrite the gap block of the --readme pages from this published table record (no evaluation, "
                         "no record written)")
    ap.add_argument("--out", default="", help="JSON record (rows of an existing record are kept)")
    args = ap.parse_args(argv)
    if args.render:
        if not args.readme:
            ap.error("--render needs --readme <pages>")
        from anm_torchrl.experiments.gap_table import update_pages

        update_pages(args.readme, json.loads(Path(args.render).read_text()))
        return {}
    if not args.out:
        ap.error("--out is required (except with --render)")
    if args.markdown:
        sys.stdout.write(markdown(json.loads(Path(args.out).read_text())) + "\n")
        return {}
    command = "python -m anm_torchrl.cli.gap " + " ".join(argv if argv is not None else sys.argv[1:])
    if args.combine:
        from anm_torchrl.experiments.gap_table import combine, update_pages

        tr = json.loads(Path(args.test_returns).read_text()) if args.test_returns else None
        ppo = json.loads(Path(args.ppo).read_text()) if args.ppo else None
        rec = {**combine(json.loads(Path(args.combine).read_text()), tr, ppo, record=args.out), "command": command}
        update_pages(args.readme, rec)  # first: a page without the block refuses the table before it is written
        write_record(Path(args.out), rec)
        return rec
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    torch.set_num_threads(1)
    try:
        return measure(args.network, args.episodes, args.seed, args.steps, Path(args.out), command,
                       rows=[r for r in args.rows.split(",") if r], only=[int(i) for i in args.only.split(",") if i],
                       drop=[r for r in args.drop.split(",") if r], merge=args.merge, formulations=args.formulations,
                       stability_states=args.stability)
    except ValueError as err:  # bad input named by the library: the command's error
        raise SystemExit(str(err)) from None


if __name__ == "__main__":
    run_main(main, "anm_torchrl.cli.gap")
