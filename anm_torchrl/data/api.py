"""The dataset entry points behind :mod:`anm_torchrl.data`: default folders, generation, saving, loading."""


from __future__ import annotations

import os
from pathlib import Path

from tensordict import TensorDict

from anm_torchrl.artifacts import exclusive_lock
from anm_torchrl.data.agent import WaypointAgent, generate_agent
from anm_torchrl.data.generic import for_dataset, for_network
from anm_torchrl.networks.resolve import is_anm6
from anm_torchrl.data.generative import generate_generative
from anm_torchrl.data.registry import available_datasets, dataset_generator, register_dataset
from anm_torchrl.data.storage import (KINDS, SPLITS, DatasetError, checksum, load_dataset, make_command, read_meta,
                                      save_dataset, split)
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.paths import dataset_dir

__all__ = ["KINDS", "SPLITS", "DatasetError", "WaypointAgent", "available_datasets", "checksum", "default_dataset_dir",
           "ensure_dataset", "for_dataset", "for_network",
           "generate", "generate_agent", "generate_generative", "load_dataset", "make_dataset", "read_meta",
           "register_dataset", "save_dataset", "split"]


def default_dataset_dir(kind: str, size: int, seed: int, sim: GridSimulator) -> Path:
    """Default folder of a dataset of ``sim``: :func:`anm_torchrl.paths.dataset_dir` (ANM6-Easy), suffixed with the
    network key on any other network and with the simulator fingerprint on profiles other than the network's shipped
    ones (:func:`anm_torchrl.data.generic.for_dataset`)."""
    return for_dataset(dataset_dir(kind, size, seed), sim)


def generate(kind: str, size: int, seed: int = 0, *, sim: GridSimulator, progress: bool = False,
             **options) -> tuple[TensorDict, dict]:
    """Generate (in memory) a dataset of a registered ``kind`` (:func:`available_datasets`); ``options`` go to
    its generator."""
    return dataset_generator(kind)(size, seed, sim=sim, progress=progress, **options)


def make_dataset(kind: str, size: int, seed: int = 0, path: str | os.PathLike | None = None,
                 overwrite: bool = False, *, sim: GridSimulator, progress: bool = False,
                 **options) -> Path:
    """Generate a dataset and write it to ``path`` (default :func:`anm_torchrl.paths.dataset_dir`).

    The path's exclusive lock is held from the existence check to the final rename, so two runs on one path
    cannot both write: the second raises ``LockedError`` (a ``FileExistsError``) at once.
    """
    path = Path(path) if path is not None else default_dataset_dir(kind, size, seed, sim)
    dataset_generator(kind)  # unknown kind: fail before taking the lock
    with exclusive_lock(path):
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} exists; pass overwrite=true to replace it")
        td, meta = generate(kind, size, seed, sim=sim, progress=progress, **options)
        return save_dataset(td, path, meta, overwrite=overwrite, lock=False)


def ensure_dataset(kind: str, size: int, seed: int = 0, path: str | os.PathLike | None = None,
                   generate_missing: bool = True, *, sim: GridSimulator, progress: bool = False,
                   verify: bool = True, **options) -> tuple[TensorDict, dict]:
    """Load the dataset at ``path`` (default location), generating it first if it is missing.

    ``options`` (``fractions`` included; the generator's defaults for those not given) must be those the dataset
    was made with (:func:`load_dataset`'s ``options``).

    Raises:
        DatasetError: it is missing and ``generate_missing`` is False (the message gives the command), or it
            exists but is corrupted or mismatched, other generator options included (it is never silently
            regenerated).
    """
    path = Path(path) if path is not None else default_dataset_dir(kind, size, seed, sim)
    if not path.exists():
        if not generate_missing:
            network = "" if is_anm6(sim) else " network=<its name>"
            raise DatasetError(f"no {kind} dataset at {path}; generate it with: {make_command(kind, size, seed)}"
                               f"{network} out={path}")
        make_dataset(kind, size, seed, path=path, sim=sim, progress=progress, **options)
    return load_dataset(path, kind=kind, size=size, seed=seed, sim=sim, verify=verify, options=options)
