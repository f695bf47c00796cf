"""Command line of the SB3 benchmark (:mod:`anm_torchrl.benchmarks.sb3`): writes its JSON record, logs one table.

    python -m anm_torchrl.cli.bench_sb3 [--num-envs 64] [--n-steps 16] [--rollouts 16] [--gym-rollouts 1]
                                        [--threads 1] [--out results/benchmarks/bench_sb3.json]
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from anm_torchrl.benchmarks import sb3
from anm_torchrl.cli.args import count
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
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="results/benchmarks/bench_sb3.json")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    record = sb3.run(args.num_envs, args.n_steps, args.rollouts, args.gym_rollouts, args.threads, args.seed)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json_text(record, indent=2) + "\n")
    log.info("%s\n\nwritten to %s", sb3.table(record), out)


if __name__ == "__main__":
    main()
