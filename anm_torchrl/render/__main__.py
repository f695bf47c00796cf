"""Render one ANM6-Easy episode of a baseline policy: ``python -m anm_torchrl.render --policy mpc_perfect``.

Writes ``episode_<policy>.png`` and ``.gif`` into ``--out`` (the committed example figure
``docs/figures/episode_mpc_perfect.png`` is ``--policy mpc_perfect --seed 0 --steps 672 --out docs/figures
--no-gif``).
The initial state is the first of gym-anm's reset distribution drawn by ``ANM6Env(1, seed=--seed)``.
"""

from __future__ import annotations

import argparse
import logging

import torch

from anm_torchrl.envs import ANM6Env
from anm_torchrl.render.episode import render_episode


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text}")
    return value


def main(argv: list[str] | None = None) -> None:
    from anm_torchrl.baselines import available_baselines, make_baseline

    parser = argparse.ArgumentParser(prog="python -m anm_torchrl.render", description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default="mpc_perfect", choices=available_baselines(), help="a baseline")
    parser.add_argument("--seed", type=int, default=0, help="seed of the initial state")
    parser.add_argument("--steps", type=_positive, default=96, help="episode length (96 = one day, 672 = one week)")
    parser.add_argument("--out", default="outputs/render", help="output directory")
    parser.add_argument("--gif", action=argparse.BooleanOptionalAction, default=True, help="write the GIF too")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    torch.set_num_threads(1)
    env = ANM6Env(1, seed=args.seed)
    state = env.reset()["state"][0]
    # the optimum plans the episode drawn, not its default T = 3,000 steps (as evaluate.py)
    kwargs = {"horizon": args.steps} if args.policy == "optimal" else {}
    try:
        policy = make_baseline(args.policy, env.sim, **kwargs)
        render_episode(policy, env, state, args.steps, args.out, stem=f"episode_{args.policy}",
                       title=f"ANM6-Easy, {args.policy} policy, seed {args.seed}", gif=args.gif)
    except (ValueError, OSError) as err:  # e.g. --out names a file
        parser.exit(2, f"{parser.prog}: error: {err}\n")


if __name__ == "__main__":
    main()
