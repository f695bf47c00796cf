"""How a run stops on a signal (anm_torchrl.training.signals): inside the training loop the first SIGINT or SIGTERM
only asks it to stop (the iteration finishes: an interrupt raised inside TorchRL's SAC loss became tensordict's own
error and the run lost its summary); a second one, or one outside the loop, interrupts at once."""

from __future__ import annotations

import multiprocessing
import os
import signal

import pytest

from anm_torchrl.training.signals import graceful, in_worker, stop_requested, stop_signals


def _deliver(sig) -> None:
    os.kill(os.getpid(), sig)
    for _ in range(1000):  # Python runs the handler between bytecodes of the main thread
        pass


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_in_the_loop_the_first_signal_asks_and_the_second_interrupts(sig):
    with stop_signals():
        with graceful():
            _deliver(sig)  # no KeyboardInterrupt: the loop sees the request after its iteration
            assert stop_requested() == signal.Signals(sig).name
            with pytest.raises(KeyboardInterrupt):
                _deliver(sig)


def test_outside_the_loop_a_signal_interrupts_at_once():
    with stop_signals():
        with pytest.raises(KeyboardInterrupt):
            _deliver(signal.SIGTERM)
        assert stop_requested() == "SIGTERM"
    with stop_signals():  # a new run starts with no request
        assert stop_requested() is None


def test_the_handlers_are_restored_after_the_run():
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with stop_signals():
        assert signal.getsignal(signal.SIGINT) is not before[signal.SIGINT]
    assert {s: signal.getsignal(s) for s in before} == before


def _child_handlers(owner: int, queue) -> None:
    queue.put(in_worker(owner, lambda: [signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)]))


def test_collector_workers_ignore_both_signals_and_the_training_process_does_not():
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    proc = ctx.Process(target=_child_handlers, args=(os.getpid(), queue))
    proc.start()
    assert queue.get(timeout=60) == [signal.SIG_IGN, signal.SIG_IGN]
    proc.join(timeout=60)
    before = signal.getsignal(signal.SIGINT)
    assert in_worker(os.getpid(), lambda: signal.getsignal(signal.SIGINT)) is before is not signal.SIG_IGN
