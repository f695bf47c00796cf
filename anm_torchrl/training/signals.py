"""How a training run stops on a signal: Ctrl-C (SIGINT) and SIGTERM (``kill``, a scheduler's preemption or time
limit) alike.

Under :func:`stop_signals` (what ``run_recipe`` runs ``train`` in), a signal that comes while the training loop runs
(:func:`graceful`) only asks it to stop: the loop finishes its iteration, sees :func:`stop_requested` and ends as
interrupted (``last.pt``, ``summary.json``). A ``KeyboardInterrupt`` raised at an arbitrary bytecode could land inside
a library's context manager: in TorchRL's SAC loss (``params.to_module``) the exit then failed with tensordict's own
``RuntimeError``, which replaced the interrupt, so the run died without its summary and could have left a network
holding another's parameters. A second signal, or one outside the loop (building the models, the test states),
interrupts at once, as before.

Helper processes (the background validation, collector workers) ignore both signals (:func:`ignore_stop_signals`):
a Ctrl-C in a terminal reaches the whole process group, and the training process closes its helpers when it stops.
A study's cell, trained in a worker process of the study, sends itself SIGTERM when the study has gone
(:func:`stop_when_orphaned`): a study stopped with ``kill`` would otherwise leave its cells training for nobody.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
_state: dict[str, Any] = {"signal": None, "graceful": False}


def stop_requested() -> str | None:
    """The name of the signal that asked the run to stop (``"SIGINT"``, ``"SIGTERM"``), or None."""
    return _state["signal"]


@contextlib.contextmanager
def stop_signals() -> Iterator[None]:
    """Within: SIGINT and SIGTERM set :func:`stop_requested`; inside :func:`graceful` the first one does only that,
    elsewhere (or a second one) it also raises ``KeyboardInterrupt``. Outside the main thread (where Python runs
    signal handlers) both keep their handlers."""
    _state.update(signal=None, graceful=False)
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_signal(signum, frame):
        first = _state["signal"] is None
        _state["signal"] = signal.Signals(signum).name
        if first and _state["graceful"]:
            # os.write, not print or logging: a handler can run inside either's own write
            os.write(2, b"\nstopping after this iteration (the same signal again stops at once)\n")
            return
        raise KeyboardInterrupt

    previous = {s: signal.signal(s, on_signal) for s in _STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        # the request belongs to this run: a later train() called without this context must not see it
        _state.update(signal=None, graceful=False)


@contextlib.contextmanager
def graceful() -> Iterator[None]:
    """Within (the training loop): a first signal under :func:`stop_signals` waits for :func:`stop_requested`."""
    _state["graceful"] = True
    try:
        yield
    finally:
        _state["graceful"] = False


def ignore_stop_signals() -> None:
    """Ignore SIGINT and SIGTERM in this (helper) process: its training process stops it."""
    for s in _STOP_SIGNALS:
        signal.signal(s, signal.SIG_IGN)


@contextlib.contextmanager
def stop_signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM held back (blocked) in this thread while the block runs, delivered after it: a helper
    process forked inside the block starts with them blocked too, so none reaches it before it calls
    :func:`ignore_stop_signals` and :func:`release_stop_signals`."""
    signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)


def release_stop_signals() -> None:
    """Unblock SIGINT and SIGTERM in a helper forked under :func:`stop_signals_held` (after ignoring them)."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)


def stop_when_orphaned(poll_s: float = 1.0) -> threading.Thread:
    """Send this process SIGTERM once its parent process has gone (checked every ``poll_s`` seconds in a daemon
    thread, which is returned); under :func:`stop_signals` it then stops as a run does on SIGTERM."""
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        os.kill(os.getpid(), signal.SIGTERM)

    thread = threading.Thread(target=watch, name="stop-when-orphaned", daemon=True)
    thread.start()
    return thread


def in_worker(owner: int, factory: Callable[..., Any], *args, **kwargs) -> Any:
    """``factory(*args, **kwargs)``, after :func:`ignore_stop_signals` when called in a process other than ``owner``
    (the training process's pid: a collector worker building its env); in the training process itself, just the
    call."""
    if os.getpid() != owner:
        ignore_stop_signals()
    return factory(*args, **kwargs)
