"""Command line of the study of networks nobody tuned (:mod:`anm_torchrl.experiments.unseen`): random networks saved
as a user's files, their optimum and do-nothing, and every algorithm's documented command on them at its defaults.
Finished baselines and cells are reused, so a stopped study resumes. Writes ``<out>/unseen_networks.json`` and
``.md``; ``--readme`` re-renders the page's block.

    python -m anm_torchrl.cli.unseen_networks --networks 9101:18:radial 9202:24:meshed 9303:40:radial \\
        --algorithms ppo shac --seeds 0 --jobs 2 --runs-dir outputs/unseen --out results/unseen --readme README.md
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from anm_torchrl.cli.args import add_study_arguments, finish_study, read_kept, run_main
from anm_torchrl.experiments import unseen

log = logging.getLogger(__name__)
STEM = "unseen_networks"


def spec(text: str) -> str:
    try:
        unseen.parse_spec(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m anm_torchrl.cli.unseen_networks",
                                     description=unseen.__doc__.splitlines()[0])
    parser.add_argument("--networks", nargs="+", type=spec, required=True,
                        help="random networks SEED:BUSES:radial|meshed (anm_torchrl.networks.random.generate), or "
                             "network files (.npz)")
    parser.add_argument("--algorithms", nargs="+", default=["ppo", "shac"], choices=list(unseen.RECIPE))
    add_study_arguments(parser, seeds=[0], runs_dir="outputs/unseen",  # also the network files and baselines
                        out="folder of unseen_networks.json / .md (e.g. results/unseen)")
    parser.add_argument("--readme", default=None, help="a page whose unseen-networks block is re-rendered")
    parser.add_argument("--keep", default=None, help="an earlier record of this study: its baselines, and the cells "
                        "of the algorithms not in --algorithms, are kept (one column re-made, no optimum solved)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    keep = read_kept(args.keep)
    record = unseen.study(args.networks, args.algorithms, args.seeds, Path(args.runs_dir), jobs=args.jobs,
                          overrides=tuple(args.override), keep=keep, keep_source=args.keep or "")
    finish_study("unseen_networks", argv, record)
    text = unseen.markdown(record)
    if args.out:
        from anm_torchrl.experiments.io import write_record

        path = write_record(Path(args.out), STEM, record, text)
        if args.readme:
            unseen.update_page(args.readme, record, str(path))
    log.info("%s", text)
    return record


if __name__ == "__main__":
    run_main(main, "anm_torchrl.cli.unseen_networks")
