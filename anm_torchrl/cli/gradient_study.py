"""Command line of the time-to-threshold study (:mod:`anm_torchrl.experiments.gradient_study`): one campaign per
network, every cell a recipe's default command with its seed; finished cells are reused, so a stopped campaign
resumes. Writes ``<out>/<network>.json`` and ``.md``; ``--docs`` re-renders the page's gradients block from every
record in ``<out>``.

    python -m anm_torchrl.cli.gradient_study --network anm6_easy --seeds 0 1 2 --jobs 2 \\
        --runs-dir outputs/gradient_study --out results/gradient_study --docs docs/RESULTS.md
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from anm_torchrl.cli.args import count
from anm_torchrl.experiments import gradient_study

log = logging.getLogger(__name__)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m anm_torchrl.cli.gradient_study",
                                     description=gradient_study.__doc__.splitlines()[0])
    parser.add_argument("--network", default="anm6_easy")
    parser.add_argument("--methods", nargs="+", default=list(gradient_study.METHODS),
                        choices=list(gradient_study.METHODS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--jobs", type=count, default=2, help="runs at a time (one torch thread each)")
    parser.add_argument("--runs-dir", default="outputs/gradient_study", help="the cells' run directories")
    parser.add_argument("--override", nargs="*", default=[], help="recipe keys of every cell (key=value), e.g. a "
                        "smaller budget; the record lists them")
    parser.add_argument("--out", default=None, help="folder of <network>.json / .md (e.g. results/gradient_study)")
    parser.add_argument("--docs", default=None, help="a page whose gradients block is re-rendered from <out>")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    record = gradient_study.campaign(args.network, args.methods, args.seeds, Path(args.runs_dir), jobs=args.jobs,
                                     overrides=tuple(args.override))
    record["command"] = "python -m anm_torchrl.cli.gradient_study " + " ".join(argv if argv is not None
                                                                               else sys.argv[1:])
    for f in record["failed"]:
        log.error("cell %s failed:\n%s", f["run_dir"], f["error"])
    if record["failed"]:  # a record missing cells would report censored times for runs that never ran
        sys.exit(f"gradient_study: {len(record['failed'])} cell(s) failed (above); no record written. Finished "
                 f"cells are reused by the next run of the same command")
    text = gradient_study.markdown(record)
    if args.out:
        from anm_torchrl.experiments.io import write_record

        out = Path(args.out)
        write_record(out, args.network, record, text)
        if args.docs:
            records = [json.loads(p.read_text()) for p in sorted(out.glob("*.json"))]
            gradient_study.update_page(args.docs, records)
    log.info("%s", text)
    return record


if __name__ == "__main__":
    main()
