"""Where a trained PINN lives and when a training may replace it.

The default cache of a network is ``surrogate_dir("pinn") / <network key> / pinn.safetensors``
(:func:`anm_torchrl.grid.identity.network_key`: a changed network never loads a stale model). Rules:

* a preset without an acceptance bar (``smoke``) never trains into the default cache unless
  ``overwrite_cache=True`` (checked before training);
* a training that fails its preset's acceptance bar (:func:`.presets.check_acceptance`) is not written to the
  default cache unless ``overwrite_cache=True``; it goes to ``reject_path`` when given, then
  :class:`CacheRejectedError` says where;
* an explicit ``path`` is written as asked (the caller chose it).
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path
from typing import Any

from anm_torchrl.grid.identity import network_key
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.paths import surrogate_dir
from anm_torchrl.surrogates.pinn.io import resolve_path, save_pinn
from anm_torchrl.surrogates.pinn.loop import train_pinn
from anm_torchrl.surrogates.pinn.presets import PINNTrainConfig, check_default_target

log = logging.getLogger(__name__)


class CacheRejectedError(RuntimeError):
    """A trained PINN failed its acceptance bar and was not written to the default cache."""


def default_path(sim: GridSimulator) -> Path:
    """The default cache file of a PINN for ``sim``'s network."""
    return surrogate_dir("pinn") / network_key(sim) / "pinn.safetensors"


def is_default(file: Path, sim: GridSimulator) -> bool:
    """Whether ``file`` is the default cache of ``sim``'s network (paths compared resolved)."""
    return Path(file).expanduser().resolve() == default_path(sim).resolve()


def check_may_train_into(file: Path, cfg: PINNTrainConfig, sim: GridSimulator, overwrite_cache: bool) -> None:
    """Raise ``ValueError`` before any work if ``cfg`` can never be accepted into the default cache ``file``."""
    if is_default(file, sim):
        check_default_target(cfg, str(file), overwrite_cache)


def train_and_save(cfg: PINNTrainConfig, sim: GridSimulator, path: str | Path | None = None,
                   overwrite_cache: bool = False, reject_path: str | Path | None = None,
                   log_dir: str | Path | None = None, progress: bool = False,
                   jobs: int | None = None) -> tuple[Path, dict[str, Any]]:
    """Train ``cfg`` on ``sim`` (on its device) and save it to ``path`` (default: the cache) under the rules above;
    ``jobs``: processes of the training (:func:`.loop.train_pinn`).

    Returns:
        ``(file, report)``.

    Raises:
        ValueError: a preset without acceptance bar aimed at the default cache (before training).
        CacheRejectedError: the model failed its bar and the target was the default cache.
    """
    file = resolve_path(path) if path is not None else default_path(sim)
    check_may_train_into(file, cfg, sim, overwrite_cache)
    stages = file.parent / f".{file.stem}.stages"  # finished stages: a killed training resumes from them
    modules, report = train_pinn(cfg, sim, log_dir=log_dir, progress=progress, stage_dir=stages, jobs=jobs)
    shutil.rmtree(stages, ignore_errors=True)  # the training is complete: its outcome is decided below
    if is_default(file, sim) and not report["accepted"] and not overwrite_cache:
        where = ""
        if reject_path is not None:
            where = f"; it was saved to {save_pinn(reject_path, modules, cfg, report, sim)}"
        failed = "; ".join(report["acceptance_failures"])
        raise CacheRejectedError(f"the trained PINN failed its acceptance bar ({failed}) and was not written to the "
                                 f"default cache {file}{where}; pass overwrite_cache=true to store it there anyway")
    if not report["accepted"]:
        log.warning("PINN saved to %s although it failed its acceptance bar: %s", file, report["acceptance_failures"])
    return save_pinn(file, modules, cfg, report, sim), report
