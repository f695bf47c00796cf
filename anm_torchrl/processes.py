"""A second process running one of the package's own modules — the one way the package starts a process of its own.

``python -m <module> <setup file> [args]``: a fresh interpreter (unlike ``multiprocessing``'s spawn it never
re-runs the caller's script), its setup saved by ``torch.save`` in a temp folder of its own, its stderr kept in a
file there (read for the error message; a pipe nobody reads could fill and stall it). Used by the PINN's stage
process (:mod:`anm_torchrl.surrogates.pinn.loop`) and the background validation
(:mod:`anm_torchrl.training.validation`).
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any


class ModuleProcess:
    """``python -m module SETUP *args`` started at once; ``pipes``: its stdin and stdout are unbuffered pipes
    (``self.proc.stdin`` / ``.stdout``), else closed. ``self.folder`` is its temp folder (removed by ``close``)."""

    def __init__(self, module: str, setup: dict[str, Any], *, prefix: str, args: tuple = (), pipes: bool = False):
        import torch

        self.tmp = tempfile.TemporaryDirectory(prefix=prefix)
        self.folder = Path(self.tmp.name)
        torch.save(setup, self.folder / "setup.pt")
        self._err = open(self.folder / "stderr.txt", "wb")
        pipe = subprocess.PIPE if pipes else subprocess.DEVNULL
        self.proc = subprocess.Popen([sys.executable, "-m", module, str(self.folder / "setup.pt"), *map(str, args)],
                                     stdin=pipe, stdout=pipe, stderr=self._err, bufsize=0)

    def failure(self, what: str) -> RuntimeError:
        """The error of a process that failed (or is failing): ``"<what> failed (exit N): <its last stderr line>"``
        and its stderr's tail; waits up to 10 s for it to end, then kills it."""
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._err.flush()
        err = (self.folder / "stderr.txt").read_bytes().decode(errors="replace").strip()
        last = err.splitlines()[-1] if err else "no error output"
        return RuntimeError(f"{what} failed (exit {self.proc.returncode}): {last}\n{err[-3000:]}")

    def close(self, grace_s: float = 0.0) -> None:
        """End the process (it has ``grace_s`` seconds to end by itself, then it is killed) and remove its folder."""
        if self.proc.poll() is None:
            try:
                self.proc.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._err.close()
        self.tmp.cleanup()
