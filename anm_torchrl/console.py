"""Console output that reads well in a file: TorchRL's log lines without ANSI colours when not on a terminal.

TorchRL gives its ``"torchrl"`` logger a console handler whose formatter wraps every line in ANSI colour codes
(``torchrl/_utils.py``), and that logger does not propagate, so Hydra's log file never sees it; but a run whose
output is redirected (``python recipes/ppo.py > ppo.log 2>&1``, a batch job's log) got the raw escape codes.
"""

from __future__ import annotations

import logging

PLAIN_FORMAT = "%(asctime)s [%(name)s][%(levelname)s] %(message)s"


def plain_torchrl_console() -> None:
    """Give TorchRL's console handlers a plain formatter where their stream is not a terminal (idempotent).

    Call after ``torchrl`` is imported (its import replaces the handlers of the ``"torchrl"`` logger).
    """
    for handler in logging.getLogger("torchrl").handlers:
        stream = getattr(handler, "stream", None)
        if isinstance(handler, logging.StreamHandler) and not (hasattr(stream, "isatty") and stream.isatty()):
            handler.setFormatter(logging.Formatter(PLAIN_FORMAT))
