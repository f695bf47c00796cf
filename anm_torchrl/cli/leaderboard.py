"""Command line of the leaderboard (:mod:`anm_torchrl.experiments.leaderboard`): trained runs next to the optimum,
MPC and do-nothing on the network's gap-table states; writes ``<out>.json`` and ``<out>.md``.

    python -m anm_torchrl.cli.leaderboard --network anm6_easy --runs outputs/ppo/<run> outputs/sac/<run> ...
                                          [--keep results/leaderboard/anm6_easy.json]
                                          [--out results/leaderboard/anm6_easy] [--readme README.md]
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from anm_torchrl.networks import check_network_name
from anm_torchrl.cli.args import count, read_kept, run_main
from anm_torchrl.experiments import leaderboard
from anm_torchrl.strict_json import json_text

log = logging.getLogger(__name__)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m anm_torchrl.cli.leaderboard",
                                     description=leaderboard.__doc__.splitlines()[0])
    parser.add_argument("--network", default="anm6_easy")
    parser.add_argument("--runs", nargs="*", default=[], help="training run directories (summary.json, best.pt)")
    parser.add_argument("--keep", default=None, help="an earlier record of this network: its runs of the "
                        "(algorithm, training env) groups not given in --runs are kept, named by kept_from")
    parser.add_argument("--threads", type=count, default=1)
    parser.add_argument("--out", default=None, help="write <out>.json and <out>.md")
    parser.add_argument("--readme", nargs="*", default=[], help="pages whose leaderboard block is re-rendered")
    args = parser.parse_args(argv)
    check_network_name(args.network)  # before its gap record is looked for under that name
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    import torch

    torch.set_num_threads(args.threads)
    record = leaderboard.build(args.network, args.runs, keep=read_kept(args.keep), keep_source=args.keep or "")
    record["command"] = "python -m anm_torchrl.cli.leaderboard " + " ".join(argv if argv is not None else sys.argv[1:])
    text = leaderboard.markdown(record)
    if args.out:
        from anm_torchrl.artifacts import atomic_write

        out = Path(args.out)
        atomic_write(out.with_suffix(".json"), json_text(record, indent=2).encode())
        atomic_write(out.with_suffix(".md"), text.encode())
    if args.readme:
        leaderboard.update_pages(args.readme, record)
    log.info("%s", text)


if __name__ == "__main__":
    run_main(main, "anm_torchrl.cli.leaderboard")
