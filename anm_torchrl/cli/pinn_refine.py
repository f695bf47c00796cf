"""Apply the PINN's refinement rule (today's, :mod:`anm_torchrl.surrogates.pinn.refine`) to a saved model.

``python -m anm_torchrl.cli.pinn_refine --network <name> --path <file>`` chooses the model's Newton steps by the
rule from physics alone and rewrites the file with its k and record (same weights): the fix a model trained before
the rule is refused with.
"""

from __future__ import annotations

import argparse
import logging
from typing import Any

import torch

from anm_torchrl.cli.args import run_main
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.surrogates.pinn.io import apply_refine_rule

log = logging.getLogger(__name__)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Parse ``argv``, apply the rule, log and return its record."""
    ap = argparse.ArgumentParser(description="choose a saved PINN's Newton steps by the rule (today's: v3) and "
                                             "rewrite the file")
    ap.add_argument("--network", required=True, help="the registered network the model was trained on")
    ap.add_argument("--path", required=True, help="the model file (or its folder)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    rec = apply_refine_rule(args.path, network_simulator(args.network))
    log.info("%s: k = %d (%s)", args.path, rec["k"], rec)
    return rec


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO)
    run_main(main, "anm_torchrl.cli.pinn_refine")
