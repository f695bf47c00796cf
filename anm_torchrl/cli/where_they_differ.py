"""``python -m anm_torchrl.cli.where_they_differ``: a trained policy beside the optimum on the test state where they
differ most (:mod:`anm_torchrl.experiments.where_they_differ`)."""

from __future__ import annotations

import argparse
import logging

import torch

from anm_torchrl.cli.args import count, index, run_main
from anm_torchrl.experiments.where_they_differ import GAP_RECORD, run


def main(argv: list[str] | None = None) -> dict:
    """Parse ``argv``, measure, write the record and the figure, print the summary."""
    ap = argparse.ArgumentParser(description="a trained policy beside the perfect-foresight optimum on one test state")
    ap.add_argument("--checkpoint", default="pretrained:anm6_easy", help="a checkpoint or pretrained:<name>")
    ap.add_argument("--out", required=True, help="path stem of the record (.json) and the figure (.png)")
    ap.add_argument("--gap-record", default=str(GAP_RECORD), help="the gap study's record of the optimum")
    ap.add_argument("--state", type=index, default=None, help="a test state index (default: the largest gap)")
    ap.add_argument("--window-days", type=count, default=3, help="days shown in the time-series panels")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    rec = run(args.checkpoint, args.out, args.gap_record, args.state, args.window_days)
    pol, opt, gap = rec["policy"]["discounted"], rec["optimum"]["discounted"], rec["gap_discounted"]
    print(f"state {rec['state_index']}: policy {pol['reward']:.4f}, optimum {opt['reward']:.4f} "
          f"(recorded {rec['optimum']['recorded_discounted_return']:.4f}); the optimum's discounted savings: "
          f"energy loss {-gap['e_loss']:.4f} (curtailment {-gap['curtailment']:.4f}), penalty {-gap['penalty']:.4f}")
    return rec


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO)
    run_main(main, "anm_torchrl.cli.where_they_differ")
