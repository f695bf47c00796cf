"""Command line of the evaluation benchmark (:mod:`anm_torchrl.benchmarks.evaluation`): a validation pass on the
default path against the reference path (``env.rollout``'s), timed alternately in one run, metrics compared.

    python -m anm_torchrl.cli.bench_evaluation [--network anm6_easy] [--episodes E] [--steps T] [--repeats 3]
                                               [--out results/benchmarks/evaluation_pass]
"""

from __future__ import annotations

import argparse
import logging

from anm_torchrl.benchmarks import evaluation
from anm_torchrl.cli.args import check_out, count, run_main

log = logging.getLogger(__name__)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m anm_torchrl.cli.bench_evaluation",
                                     description=evaluation.__doc__.splitlines()[0])
    parser.add_argument("--network", default="anm6_easy")
    parser.add_argument("--episodes", type=count, default=None, help="states (default: the validation protocol's)")
    parser.add_argument("--steps", type=count, default=None, help="steps per pass (default: the protocol's)")
    parser.add_argument("--repeats", type=count, default=3, help="passes per path (the best is reported)")
    parser.add_argument("--out", default=None, help="write <out>.json and <out>.md (default: print only)")
    args = parser.parse_args(argv)
    from anm_torchrl.networks import check_network_name

    check_network_name(args.network)  # before the per-network defaults are composed (and logged) for it
    check_out(args.out)  # before the measurement
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    record = evaluation.run(args.network, args.episodes, args.steps, args.repeats, args.out, argv)
    log.info("%s", "\n".join(evaluation.markdown(record)))
    return record


if __name__ == "__main__":
    run_main(main, "anm_torchrl.cli.bench_evaluation")
