"""Where a number was measured: the machine (CPU, cores, memory, torch threads) and the versions of the packages and
of the checkout. The lowest floor: records of every layer (benchmarks, experiments, recipes) call it."""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path
from typing import Any


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity on Linux, else every logical core)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def machine_info() -> dict[str, Any]:
    """CPU model, logical cores, torch threads, OS and Python of this machine."""
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gb = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem_gb = round(int(line.split()[1]) / 2**20, 1)
    except OSError:
        pass
    return {"cpu": cpu, "logical_cores": os.cpu_count(), "usable_cores": usable_cpus(), "memory_gb": mem_gb,
            "torch_threads": _torch_threads(), "platform": platform.platform(),
            "python": platform.python_version(), "hostname_hash": hash(platform.node()) % 10_000}


def versions() -> dict[str, str | None]:
    """Versions of the packages the results depend on, and the git commit of the checkout (None if unknown)."""
    from importlib import metadata

    out: dict[str, str | None] = {}
    for pkg in ("anm_torchrl", "torch", "torchrl", "tensordict", "numpy", "gym-anm", "scikit-learn", "xgboost-cpu",
                "xgboost", "hydra-core", "matplotlib", "osqp", "numba", "casadi"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = None
    try:
        root = Path(__file__).resolve().parents[1]  # the checkout: anm_torchrl/provenance.py -> repo root
        out["git_commit"] = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True,
                                           timeout=10).stdout.strip() or None
        dirty = subprocess.run(["git", "status", "--porcelain"], cwd=root, capture_output=True, text=True, timeout=10)
        out["git_dirty"] = str(bool(dirty.stdout.strip()))
    except (OSError, subprocess.SubprocessError):
        out["git_commit"] = None
    return out


def _torch_threads() -> int | None:
    import sys

    torch = sys.modules.get("torch")  # not imported here for it: a record of a torch-free run says None
    return torch.get_num_threads() if torch is not None else None
