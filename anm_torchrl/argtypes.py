"""argparse types and the error rule shared by the command lines (``python -m anm_torchrl.cli.*``, the benchmark
modules' own ``main``): a count, a duration or a list out of range is refused by the parser, naming the option
(``error: argument --rows: must be an integer >= 1, got 0``), before any work starts; a user's error is one line.
Standard library only: any floor of the package may use it."""

from __future__ import annotations

import argparse
import math
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


def int_list(minimum: int) -> Callable[[str], list[int]]:
    """An argparse ``type``: comma-separated integers, each ``>= minimum`` (``--batch-sizes 1,256,4096``)."""
    one = integer(minimum)

    def parse(text: str) -> list[int]:
        items = [one(t.strip()) for t in text.split(",") if t.strip()]
        if not items:
            raise argparse.ArgumentTypeError(f"must name at least one integer >= {minimum}, got {text!r}")
        return items
    return parse


def name_list(choices: tuple[str, ...]) -> Callable[[str], list[str]]:
    """An argparse ``type``: comma-separated names among ``choices`` (``--backends numba,torch``)."""
    def parse(text: str) -> list[str]:
        items = [t.strip() for t in text.split(",") if t.strip()]
        bad = [t for t in items if t not in choices]
        if bad or not items:
            raise argparse.ArgumentTypeError(f"must be comma-separated names among {', '.join(choices)}, got {text!r}")
        return items
    return parse


#: what a command reports as one line instead of a traceback: a user's input the library refuses by name (a
#: ``ValueError``: ``ArtifactError``, ``DatasetError`` and JSON errors included) or a path that is missing, taken
#: or not writable
USER_ERRORS = (ValueError, OSError)


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
