"""Command line of the SB3 benchmark (:mod:`anm_torchrl.benchmarks.sb3`): logs one table, and writes its JSON
record where ``--out`` says (nothing is written without it: a run at other sizes never replaces the committed
``results/benchmarks/bench_sb3.json``).

    python -m anm_torchrl.cli.bench_sb3 [--num-envs 64] [--n-steps 16] [--rollouts 16] [--gym-rollouts 1]
                                        [--threads 1] [--out results/benchmarks/bench_sb3.json]
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from anm_torchrl.benchmarks import sb3
from anm_torchrl.cli.args import check_out, count, index, run_main
from anm_torchrl.strict_json import json_text

log = logging.getLogger(__name__)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m anm_torchrl.cli.bench_sb3",
                                     description=sb3.__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=count, default=64)
    parser.add_argument("--n-steps", type=count, default=16, help="PPO rollout length per env")
    parser.add_argument("--rollouts", type=count, default=16, help="timed rollouts on our env")
    parser.add_argument("--gym-rollouts", type=count, default=1, help="timed rollouts on gym-anm (slow)")
    parser.add_argument("--threads", type=count, default=1)
    parser.add_argument("--seed", type=index, default=0)
    parser.add_argument("--out", default=None, help="write the JSON record here (default: print the table only)")
    args = parser.parse_args(argv)
    if args.num_envs * args.n_steps < 2:  # SB3's PPO asserts it (a traceback after the env was built)
        raise ValueError("--num-envs x --n-steps must be at least 2 (SB3's PPO needs a rollout of 2 frames or more)")
    check_out(args.out)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    command = " ".join([parser.prog, *(sys.argv[1:] if argv is None else argv)])
    record = sb3.run(args.num_envs, args.n_steps, args.rollouts, args.gym_rollouts, args.threads, args.seed,
                     command=command)
    log.info("%s", sb3.table(record))
    if args.out is not None:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json_text(record, indent=2) + "\n")
        log.info("written to %s", out)


if __name__ == "__main__":
    run_main(main, "anm_torchrl.cli.bench_sb3")
