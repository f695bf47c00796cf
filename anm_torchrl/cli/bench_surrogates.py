"""Command line of the surrogate-speed benchmark (:mod:`anm_torchrl.benchmarks.surrogates`): prints one table.

    python -m anm_torchrl.cli.bench_surrogates [--batch-sizes 1,4096] [--surrogates lr,dt,rf,xgb,dnn]
                                               [--datasets generative,agent] [--min-time 2.0] [--rounds 3]
                                               [--threads 1] [--device cpu]
"""

from __future__ import annotations

import argparse
import time

import torch

from anm_torchrl.benchmarks.surrogates import DATASETS, KINDS, markdown_table, measure
from anm_torchrl.cli.args import count, int_list, positive_float, run_main


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(prog="python -m anm_torchrl.cli.bench_surrogates",
                                     description="data-driven surrogate envs vs ANM6Env, transitions/s")
    parser.add_argument("--batch-sizes", type=int_list(1), default=[1, 4096], help="comma-separated batch sizes")
    parser.add_argument("--surrogates", default=",".join(KINDS), help="comma-separated surrogate names")
    parser.add_argument("--datasets", default=",".join(DATASETS), help="comma-separated training datasets")
    parser.add_argument("--min-time", type=positive_float, default=2.0, help="seconds of steady state per measurement")
    parser.add_argument("--min-steps", type=count, default=3, help="at least this many batched steps")
    parser.add_argument("--rounds", type=count, default=3, help="interleaved rounds (median reported)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=count, default=1, help="torch.set_num_threads")
    args = parser.parse_args(argv)
    from anm_torchrl.training.recipe_errors import check_device

    check_device(args.device, "--device")  # was an AssertionError / RuntimeError traceback at the first model
    batches = args.batch_sizes
    kinds, datasets = [k for k in args.surrogates.split(",") if k], [d for d in args.datasets.split(",") if d]
    for option, given, known in (("--surrogates", kinds, KINDS), ("--datasets", datasets, DATASETS)):
        if set(given) - set(known):
            parser.error(f"argument {option}: {sorted(set(given) - set(known))} not among {list(known)}")
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    results, missing = measure(batches, kinds, datasets, args.min_time, args.min_steps, args.rounds, args.device)
    table = markdown_table(results, batches)
    print(table)
    for note in missing:
        print(f"- {note}")
    print(f"\n<!-- torch {torch.__version__}, {torch.get_num_threads()} thread(s), device {args.device}, median of "
          f"{args.rounds} interleaved rounds of >= {args.min_time} s, {time.perf_counter() - start:.0f} s in all; "
          f"env step = rand_action + step_and_maybe_reset -->")
    return table


if __name__ == "__main__":
    run_main(main, "anm_torchrl.cli.bench_surrogates")
