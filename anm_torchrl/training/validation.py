"""The protocol's validation passes, here or in a second process.

A validation pass rolls the deterministic policy out on the fixed validation states of the true simulator
(:func:`anm_torchrl.evaluation.evaluate_policy`). It is deterministic, so it may run beside the training: where a
second CPU is free, :class:`BackgroundValidation` evaluates a copy of the policy's weights in
``python -m anm_torchrl.training.validation SETUP`` (:class:`~anm_torchrl.processes.ModuleProcess`) while the next
iterations train. Its results equal :class:`InlineValidation`'s value for
value; only the moment they are known differs (the protocol waits where a result decides the run: an early stop, the
end). Both take ``submit(weights, tag)`` and give ``(tag, metrics)`` pairs, in submission order, from ``results``.
"""

from __future__ import annotations

import os
import pickle
import select
import struct
import sys
from collections import deque
from collections.abc import Mapping
from typing import Any

import torch

from anm_torchrl.processes import ModuleProcess
from anm_torchrl.provenance import usable_cpus

#: validation pass length (steps) from which ``auto`` runs the passes in a second process: a pass of 1,000 steps
#: (~0.5 s on 16 ANM6-Easy states here, results/benchmarks/evaluation_pass.md) outweighs the process's start (~3 s)
#: after a few passes; shorter ones (tests, smoke runs) stay here
BACKGROUND_MIN_STEPS = 1000
#: scheduling niceness of the second process: its passes are off the training's critical path (a result is read
#: one pass later), so where the CPUs are all busy (SHAC's critic worker beside it on 2 cores) the training and its
#: worker come first. On a machine loaded by other work a pass takes longer, and the training waits for it at the
#: next one
NICENESS = 10


def use_background(mode: str | bool, device, threads: int, max_steps: int) -> bool:
    """Whether validation runs in a second process: ``mode`` true / false, or ``"auto"``: on CPU, where this
    process may use at least ``2 x threads`` CPUs (the second process runs ``threads`` threads too) and a pass is at
    least :data:`BACKGROUND_MIN_STEPS` steps long (``max_steps``), on a POSIX system."""
    if isinstance(mode, bool):
        return mode
    if mode != "auto":
        raise ValueError(f"eval.background must be auto, true or false; got {mode!r}")
    return (torch.device(device).type == "cpu" and usable_cpus() >= 2 * int(threads)
            and int(max_steps) >= BACKGROUND_MIN_STEPS and os.name == "posix")  # select() on pipes: POSIX only


def evaluate(policy, states: torch.Tensor, env, max_steps: int, gamma: float) -> dict[str, float]:
    """Metrics of ``policy`` (deterministic, in eval mode for the pass) on ``states`` (E, D) in ``env`` (batch E)
    over ``max_steps`` steps: :meth:`~anm_torchrl.evaluation.EvalResult.metrics` and ``seconds`` (its wall time)."""
    from anm_torchrl.evaluation import evaluate_policy

    policy.eval()
    result = evaluate_policy(policy, states, max_steps=max_steps, gamma=gamma, env=env)
    policy.train()
    return {**result.metrics(), "seconds": result.wall_time}


class InlineValidation:
    """Validation in this process: each submitted pass runs at once on ``policy`` (whose weights the caller set)."""

    def __init__(self, policy, states: torch.Tensor, env, max_steps: int, gamma: float):
        self.policy, self.states, self.env, self.max_steps, self.gamma = policy, states, env, max_steps, gamma
        self._done: deque = deque()

    @property
    def pending(self) -> int:
        return 0

    @property
    def pending_tags(self) -> list[Any]:
        """The tags of the passes submitted and not yet taken by ``results``: none (each runs at submission)."""
        return []

    def submit(self, weights: Mapping[str, torch.Tensor] | None, tag: Any) -> None:
        """Evaluate now; ``weights`` None: the policy as it is (the caller's live policy)."""
        if weights is not None:
            self.policy.load_state_dict(weights)
        self._done.append((tag, evaluate(self.policy, self.states, self.env, self.max_steps, self.gamma)))

    def results(self, wait: bool = False) -> list[tuple[Any, dict[str, float]]]:
        out = list(self._done)
        self._done.clear()
        return out

    def close(self) -> None:
        pass


def _write(stream, obj) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(struct.pack("<Q", len(data)) + data)
    stream.flush()


def _read_exact(stream, n: int) -> bytes | None:
    chunks, left = [], n
    while left:
        chunk = stream.read(left)
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def _read(stream):
    head = _read_exact(stream, 8)
    if head is None:
        return None
    data = _read_exact(stream, struct.unpack("<Q", head)[0])
    return None if data is None else pickle.loads(data)  # our own process's output


class BackgroundValidation(ModuleProcess):
    """Validation in a second process (see the module docstring; :class:`ModuleProcess`); the same arguments as
    :class:`InlineValidation` (the policy and env are pickled to it once; each pass sends only the weights).

    Raises:
        RuntimeError: from ``results`` or ``submit`` once the second process has failed, with its stderr.
    """

    def __init__(self, policy, states: torch.Tensor, env, max_steps: int, gamma: float):
        # unbuffered pipes: ``select`` sees exactly what is unread
        super().__init__(__name__, {"policy": policy, "states": states, "env": env, "max_steps": int(max_steps),
                                    "gamma": float(gamma), "threads": torch.get_num_threads()},
                         prefix="anm_torchrl_validation_", pipes=True)
        self._tags: deque = deque()
        self._broken = False

    @property
    def pending(self) -> int:
        return len(self._tags)

    @property
    def pending_tags(self) -> list[Any]:
        """The tags of the passes submitted and not yet taken by ``results``, in submission order."""
        return list(self._tags)

    def submit(self, weights: Mapping[str, torch.Tensor], tag: Any) -> None:
        """Queue a pass of these weights (copied now: training may change the caller's tensors at once)."""
        try:
            _write(self.proc.stdin, {k: v.detach().cpu().clone() for k, v in weights.items()})
        except (BrokenPipeError, OSError):
            raise self.failure("the validation process") from None
        self._tags.append(tag)

    def results(self, wait: bool = False) -> list[tuple[Any, dict[str, float]]]:
        """The passes finished so far, in submission order; ``wait``: every queued pass (blocks)."""
        if self._broken:
            raise RuntimeError("the validation process was stopped in the middle of a result")
        out = []
        while self._tags:
            if not wait and not select.select([self.proc.stdout], [], [], 0)[0]:
                break
            try:
                metrics = _read(self.proc.stdout)
            except BaseException:  # a Ctrl-C inside a result: the rest of the stream is out of step
                self._broken = True
                self.proc.kill()
                raise
            if metrics is None:
                raise self.failure("the validation process")
            out.append((self._tags.popleft(), metrics))
        return out

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.close()  # the process ends at the end of its input
        super().close(grace_s=10)


def _serve(setup_path: str) -> None:
    """The second process: read weights from stdin until its end, write each pass's metrics to stdout."""
    from anm_torchrl.training.signals import ignore_stop_signals

    # a Ctrl-C (or a scheduler's SIGTERM to the whole job) stops the training process, which then closes us
    ignore_stop_signals()
    out = os.fdopen(os.dup(1), "wb", buffering=0)
    os.dup2(2, 1)  # anything printed goes to stderr, not into the results
    setup = torch.load(setup_path, weights_only=False)  # written by the training process in its own temp folder
    torch.set_num_threads(int(setup["threads"]))
    os.nice(NICENESS)
    policy, inp = setup["policy"], sys.stdin.buffer
    while (weights := _read(inp)) is not None:
        policy.load_state_dict(weights)
        _write(out, evaluate(policy, setup["states"], setup["env"], setup["max_steps"], setup["gamma"]))


if __name__ == "__main__":
    _serve(sys.argv[1])
