"""``python -m anm_torchrl.cli.data_driven_battery``: the data-driven surrogates on the PINN battery's random networks
(:mod:`anm_torchrl.experiments.data_driven_battery`)."""

from __future__ import annotations

import argparse
import logging

import torch

from anm_torchrl.cli.args import count, run_main
from anm_torchrl.experiments.data_driven_battery import PINN_RECORD, run
from anm_torchrl.surrogates.regressors.defaults import KINDS


def main(argv: list[str] | None = None) -> dict:
    """Parse ``argv``, measure, write the record and its table, print the table."""
    ap = argparse.ArgumentParser(description="data-driven surrogates built on first use on random networks")
    ap.add_argument("--seeds", type=int, nargs="+", help="battery seeds (-1: issue 23's network); required unless "
                    "--refresh-pinn")
    ap.add_argument("--refresh-pinn", action="store_true", help="only re-read the PINN's figures of the record "
                    "<out>.json from --pinn-record (after the PINN battery was re-measured) and rewrite it")
    ap.add_argument("--kinds", nargs="+", default=["lr", "dt", "xgb", "dnn"], choices=KINDS)
    ap.add_argument("--n-random", type=count, default=4000)
    ap.add_argument("--n-jobs", type=count, default=2, help="threads of xgboost / forests")
    ap.add_argument("--pinn-record", default=str(PINN_RECORD))
    ap.add_argument("--out", required=True, help="path stem of the record (.json) and table (.md)")
    args = ap.parse_args(argv)
    from anm_torchrl.experiments.data_driven_battery import markdown, refresh_pinn

    if args.refresh_pinn:
        rec = refresh_pinn(args.out, args.pinn_record)
        print(markdown(rec))
        return rec
    if not args.seeds:
        ap.error("--seeds is required (unless --refresh-pinn)")
    torch.set_num_threads(1)
    rec = run(args.seeds, args.kinds, args.out, args.n_random, args.n_jobs, args.pinn_record)

    print(markdown(rec))
    return rec


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO)
    run_main(main, "anm_torchrl.cli.data_driven_battery")
