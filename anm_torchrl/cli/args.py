"""What the command lines share: the argparse types and the one-line error rule (:mod:`anm_torchrl.argtypes`, here
for every ``cli`` module), the output check, and the options and the failure rule of the studies of training cells."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

from anm_torchrl.argtypes import (USER_ERRORS, count, index, int_list, integer, name_list, positive_float,
                                  run_main)

__all__ = ["USER_ERRORS", "count", "index", "int_list", "integer", "name_list", "positive_float", "run_main",
           "check_out", "add_study_arguments", "read_kept", "finish_study"]


def check_out(out: str | None, option: str = "--out") -> None:
    """An output path stem (``<out>.json``, ``<out>.md``) whose folder can be written, checked before a measurement
    (not after it: its table was lost)."""
    if out:
        from anm_torchrl.training.recipe_errors import check_writable

        check_writable(Path(out).parent, option)


def add_study_arguments(parser: argparse.ArgumentParser, seeds: list[int], runs_dir: str, out: str) -> None:
    """The options of a study of training cells (``--seeds``, ``--jobs``, ``--runs-dir``, ``--override``, and
    ``--out``: the folder of its records, described by ``out``)."""
    parser.add_argument("--out", default=None, help=out)
    parser.add_argument("--seeds", nargs="+", type=int, default=seeds)
    parser.add_argument("--jobs", type=count, default=2, help="runs at a time (one torch thread each)")
    parser.add_argument("--runs-dir", default=runs_dir, help="the cells' run directories")
    parser.add_argument("--override", nargs="*", default=[], help="recipe keys of every cell (key=value), e.g. a "
                        "smaller budget; the record lists them")


def read_kept(path: str | None) -> dict[str, Any] | None:
    """The earlier record named by a study's ``--keep`` (None without one).

    Raises:
        ValueError: the file is missing, unreadable or not a JSON object (named with the option).
    """
    if not path:
        return None
    try:
        record = json.loads(Path(path).read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f"--keep {path}: not a readable JSON record ({err})") from None
    if not isinstance(record, dict):
        raise ValueError(f"--keep {path}: not a record (a JSON {type(record).__name__}, not an object)")
    return record


def finish_study(prog: str, argv: list[str] | None, record: dict) -> None:
    """Name the study's command line in its ``record`` (``python -m anm_torchrl.cli.<prog> ...``); then log every
    failed part (``run_dir`` or ``record``, and ``error``) and exit naming how many: a record with holes would read
    as a result. Finished parts are reused by the next run of the same command."""
    record["command"] = f"python -m anm_torchrl.cli.{prog} " + " ".join(argv if argv is not None else sys.argv[1:])
    for f in record["failed"]:
        logging.getLogger(prog).error("%s failed:\n%s", f.get("run_dir") or f.get("record"), f["error"])
    if record["failed"]:
        sys.exit(f"{prog}: {len(record['failed'])} part(s) failed (above); no record written. Finished parts are "
                 f"reused by the next run of the same command")
