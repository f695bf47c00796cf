"""argparse types shared by the command lines: a count or a duration out of range is refused by the parser, naming
the option (``error: argument --rows: must be an integer >= 1, got 0``), before any work starts; and the options
and the failure rule of the studies of training cells."""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path
from typing import Any, Callable


def integer(minimum: int) -> Callable[[str], int]:
    """An argparse ``type``: an integer ``>= minimum``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer >= {minimum}, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be an integer >= {minimum}, got {value}")
        return value
    return parse


def positive_float(text: str) -> float:
    """An argparse ``type``: a finite float > 0 (seconds, a tolerance)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number > 0, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


#: what a command reports as one line instead of a traceback: a user's input the library refuses by name (a
#: ``ValueError``: ``ArtifactError``, ``DatasetError`` and JSON errors included) or a path that is missing, taken
#: or not writable
USER_ERRORS = (ValueError, FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError, PermissionError)


def run_main(main: Callable[[], Any], module: str) -> None:
    """Run a command's ``main()`` as ``python -m <module>`` does, with :data:`USER_ERRORS` as one line
    ``python -m <module>: <message>`` (exit status 1)."""
    try:
        main()
    except USER_ERRORS as err:
        raise SystemExit(f"python -m {module}: {err}") from None


#: a count of at least one (rows, runs, episodes, steps, threads, jobs)
count = integer(1)
#: an index or a count that may be zero
index = integer(0)


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
