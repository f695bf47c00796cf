"""Command line of the time-to-threshold study (:mod:`anm_torchrl.experiments.gradient_study`): one campaign per
network, every cell a recipe's default command with its seed; finished cells are reused, so a stopped campaign
resumes; ``--keep`` keeps an earlier record's rows of the methods not re-made. Writes ``<out>/<network>.json`` and
``.md``; ``--docs`` re-renders the page's gradients block from every record in ``<out>``.

    python -m anm_torchrl.cli.gradient_study --network anm6_easy --seeds 0 1 2 --jobs 2 \\
        --runs-dir outputs/gradient_study --out results/gradient_study --docs docs/RESULTS.md
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from anm_torchrl.networks import check_network_name
from anm_torchrl.cli.args import add_study_arguments, finish_study, read_kept, run_main
from anm_torchrl.experiments import gradient_study

log = logging.getLogger(__name__)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m anm_torchrl.cli.gradient_study",
                                     description=gradient_study.__doc__.splitlines()[0])
    parser.add_argument("--network", default="anm6_easy")
    parser.add_argument("--methods", nargs="+", default=list(gradient_study.METHODS),
                        choices=list(gradient_study.METHODS))
    add_study_arguments(parser, seeds=[0, 1, 2], runs_dir="outputs/gradient_study",
                        out="folder of <network>.json / .md (e.g. results/gradient_study)")
    parser.add_argument("--docs", default=None, help="a page whose gradients block is re-rendered from <out>")
    parser.add_argument("--keep", default=None, help="an earlier record of this campaign: the rows of the methods "
                        "not in --methods are kept (one method's cells re-made)")
    args = parser.parse_args(argv)
    check_network_name(args.network)  # before its gap record is looked for under that name
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    record = gradient_study.campaign(args.network, args.methods, args.seeds, Path(args.runs_dir), jobs=args.jobs,
                                     overrides=tuple(args.override), keep=read_kept(args.keep),
                                     keep_source=args.keep or "")
    finish_study("gradient_study", argv, record)
    text = gradient_study.markdown(record)
    if args.out:
        from anm_torchrl.experiments.io import write_record
        from anm_torchrl.networks.user import network_label  # a network file's stem, not its path

        out = Path(args.out)
        write_record(out, network_label(args.network), record, text)
        if args.docs:
            records = [json.loads(p.read_text()) for p in sorted(out.glob("*.json"))]
            gradient_study.update_page(args.docs, records)
    log.info("%s", text)
    return record


if __name__ == "__main__":
    run_main(main, "anm_torchrl.cli.gradient_study")
