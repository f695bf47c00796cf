"""``python -m anm_torchrl.cli.pinn_gradients``: the PINN chain's d(reward)/d(action) against the exact one
(:mod:`anm_torchrl.experiments.pinn_gradients`)."""

from __future__ import annotations

import argparse
import logging

import torch

from anm_torchrl.cli.args import count, run_main
from anm_torchrl.experiments.pinn_gradients import run


def main(argv: list[str] | None = None) -> dict:
    """Parse ``argv``, measure, write the record and the figure, print one line per network and set."""
    ap = argparse.ArgumentParser(description="PINN vs exact gradients of the reward with respect to the action")
    ap.add_argument("--networks", nargs="+", default=["anm6_easy"])
    ap.add_argument("--rows", type=count, default=512, help="(state, action) rows per action set")
    ap.add_argument("--train", action="store_true", help="train a network's default PINN when it is not cached")
    ap.add_argument("--out", required=True, help="path stem of the record (.json) and the figure (.png)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    rec = run(args.networks, args.rows, args.out, args.train)
    for e in rec["networks"]:
        for name, m in e["sets"].items():
            print(f"{e['network']:>20} {name:>16}: cosine median {m['cosine_median']:.3f} (q10 {m['cosine_q10']:.3f}), "
                  f"relative error median {m['rel_error_median']:.3f}, sign agreement {m['sign_agreement']:.3f}, "
                  f"{m['rows']} rows ({m['terminal_rows']} terminal left out)")
            for c, part in m["parting"]["by_action"].items():
                print(f"{'':>38}parting at action {c}: {part['components']} components "
                      f"({part['on_box_bound']:.0%} on the box's bound), autograd exact "
                      f"{part['autograd_exact_median']:.3g} / PINN {part['autograd_pinn_median']:.3g}, "
                      f"{m['parting']['step']} inside the box exact {part['inside_exact_median']:.3g} / PINN "
                      f"{part['inside_pinn_median']:.3g} (medians)")
    return rec


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO)
    run_main(main, "anm_torchrl.cli.pinn_gradients")
