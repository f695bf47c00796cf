"""Command line of the training-loop benchmark (:mod:`anm_torchrl.benchmarks.training`): where an iteration's time
goes (env alone, collection, update, loop) per algorithm and batch size, measured in one run.

    python -m anm_torchrl.cli.bench_training [--network anm6_easy] [--envs 256 1024 4096] [--algorithms ppo sac shac]
                                             [--iterations 3] [--out results/benchmarks/bench_training]
                                             [--override KEY=VALUE ...] [--compare KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import logging

from anm_torchrl.benchmarks import training
from anm_torchrl.cli.args import check_out, count, run_main

log = logging.getLogger(__name__)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m anm_torchrl.cli.bench_training",
                                     description=training.__doc__.splitlines()[0])
    parser.add_argument("--network", default="anm6_easy")
    parser.add_argument("--envs", type=count, nargs="+", default=[256, 1024, 4096])
    parser.add_argument("--algorithms", nargs="+", default=list(training.ALGORITHMS),
                        choices=list(training.ALGORITHMS))
    parser.add_argument("--iterations", type=count, default=3, help="timed iterations per row (after one warm-up)")
    parser.add_argument("--override", nargs="*", default=[], metavar="KEY=VALUE",
                        help="Hydra overrides of every algorithm's config, e.g. loss.mini_batch_size=8192")
    parser.add_argument("--compare", nargs="+", default=[], metavar="KEY=VALUE",
                        help="also measure every row with these overrides, right after it (same load), e.g. "
                             "loss.compile=true")
    parser.add_argument("--out", default=None, help="write <out>.json and <out>.md (default: print only)")
    args = parser.parse_args(argv)
    check_out(args.out)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    record = training.measure(args.network, tuple(args.envs), tuple(args.algorithms), args.iterations,
                              tuple(args.override), tuple(args.compare))
    log.info("%s", training.markdown(record))  # first: a failed write loses no measurement
    if args.out:
        training.write(record, args.out)


if __name__ == "__main__":
    run_main(main, "anm_torchrl.cli.bench_training")
