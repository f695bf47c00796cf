"""argparse types shared by the command lines: a count or a duration out of range is refused by the parser, naming
the option (``error: argument --rows: must be an integer >= 1, got 0``), before any work starts."""

from __future__ import annotations

import argparse
import math
from typing import Callable


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


#: a count of at least one (rows, runs, episodes, steps, threads, jobs)
count = integer(1)
#: an index or a count that may be zero
index = integer(0)
