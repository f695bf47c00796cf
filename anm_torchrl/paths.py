"""Where trained artifacts (surrogates, datasets) live by default.

``$ANM_TORCHRL_HOME`` if set, else ``~/.cache/anm_torchrl``. Recipes and loaders accept explicit paths too.
"""

from __future__ import annotations

import io

import os
from pathlib import Path
from typing import Any


def artifact_home() -> Path:
    """Root folder of cached artifacts (created on demand by writers, not here): ``$ANM_TORCHRL_HOME``, or
    ``~/.cache/anm_torchrl`` where it is unset or empty (an empty value would cache into the current folder)."""
    return Path(os.environ.get("ANM_TORCHRL_HOME") or Path.home() / ".cache" / "anm_torchrl").expanduser()


def surrogate_dir(name: str, dataset: str | None = None) -> Path:
    """Default folder of a trained surrogate, e.g. ``<home>/surrogates/xgb_agent`` or ``<home>/surrogates/pinn``."""
    return artifact_home() / "surrogates" / (name if dataset is None else f"{name}_{dataset}")


def dataset_dir(kind: str, size: int, seed: int) -> Path:
    """Default folder of a dataset, e.g. ``<home>/datasets/generative_100000_s0``."""
    return artifact_home() / "datasets" / f"{kind}_{size}_s{seed}"


def atomic_torch_save(obj: Any, path: str | os.PathLike) -> Path:
    """``torch.save`` to ``path`` atomically (:func:`anm_torchrl.artifacts.atomic_write`). Returns the path.

    Kept for PPO checkpoints; new artifacts use :func:`anm_torchrl.artifacts.save_tensors` (hash-checked).
    """
    import torch

    from anm_torchrl.artifacts import atomic_write

    # serialised in memory, then written as bytes: torch.save's own file writer reports a full disk as a raw
    # RuntimeError ("enforce fail at inline_container.cc"); a plain write raises ENOSPC, which atomic_write turns
    # into a DiskFullError naming the file and saying the previous one is intact
    buf = io.BytesIO()
    torch.save(obj, buf)
    return atomic_write(path, buf.getvalue())
