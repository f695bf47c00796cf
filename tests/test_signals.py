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
    # the request ends with its run: a training called afterwards without the context (a library caller, a test)
    # stopped at its first update when it stayed set
    assert stop_requested() is None
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


def test_a_process_whose_parent_has_gone_gets_sigterm(tmp_path):
    """A study's cell outlives a study stopped with ``kill`` (its pool's workers are not in the signal's way):
    :func:`stop_when_orphaned` sends the cell SIGTERM once its parent has gone, so it stops as a run does."""
    import subprocess
    import sys
    import textwrap
    import time

    got = tmp_path / "got"
    child = textwrap.dedent(f"""
        import signal, sys, time
        from anm_torchrl.training.signals import stop_when_orphaned
        def on_term(signum, frame):
            open({str(got)!r}, "w").write(signal.Signals(signum).name)
            sys.exit(0)
        signal.signal(signal.SIGTERM, on_term)
        stop_when_orphaned(poll_s=0.05)
        print("ready", flush=True)
        time.sleep(60)
    """)
    parent = (f"import subprocess, sys, time; subprocess.Popen([sys.executable, '-c', {child!r}]); "
              "time.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", parent], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"  # the child's (inherited stdout): its watch has started
        assert not got.exists()  # its parent is alive: no signal yet
    finally:
        proc.kill()
        proc.wait()
    deadline = time.monotonic() + 30
    while not got.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert got.read_text() == "SIGTERM"
