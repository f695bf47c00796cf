"""Command line of the imitation study (:mod:`anm_torchrl.experiments.imitation`): behaviour cloning of the AC-MPC
expert with DAgger rounds, scored like the leaderboard. Writes ``<out>/imitation_<network>.json`` and ``.md``.

    python -m anm_torchrl.cli.imitation --network anm6_easy --labels 1024 --rounds 3 --jobs 2 --out results/tuning
"""

from __future__ import annotations

import argparse
import logging
import sys

from anm_torchrl.cli.args import count, index, run_main
from anm_torchrl.experiments import imitation


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m anm_torchrl.cli.imitation",
                                     description=imitation.__doc__.splitlines()[0])
    parser.add_argument("--network", default="anm6_easy")
    parser.add_argument("--labels", type=count, default=1024, help="states labelled by the expert per round")
    parser.add_argument("--rounds", type=index, default=3, help="DAgger rounds after the first cloning")
    parser.add_argument("--visit-starts", type=count, default=16, help="rollouts of a DAgger round")
    parser.add_argument("--visit-steps", type=count, default=288, help="steps of each rollout")
    parser.add_argument("--horizon", type=count, default=imitation.EXPERT_HORIZON, help="the expert's N")
    parser.add_argument("--epochs", type=count, default=300)
    parser.add_argument("--no-time-features", action="store_true")
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--jobs", type=count, default=2, help="processes of expert solves")
    parser.add_argument("--out", default=None, help="folder of imitation_<network>.json / .md")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    from anm_torchrl.networks import check_network_name

    check_network_name(args.network)
    record = imitation.study(args.network, args.labels, args.rounds, args.visit_starts, args.visit_steps,
                             args.horizon, args.epochs, not args.no_time_features, args.seed, args.jobs)
    record["command"] = "python -m anm_torchrl.cli.imitation " + " ".join(argv if argv is not None else sys.argv[1:])
    text = imitation.markdown(record)
    if args.out:
        from anm_torchrl.experiments.io import write_record
        from anm_torchrl.networks.user import network_label  # a network file's stem, not its path

        write_record(args.out, f"imitation_{network_label(args.network)}", record, text)
    print(text)
    return record


if __name__ == "__main__":
    run_main(main, "anm_torchrl.cli.imitation")
