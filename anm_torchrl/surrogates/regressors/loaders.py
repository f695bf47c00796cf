"""Registry loaders of the data-driven surrogates (``surrogate=lr|dt|rf|xgb|dnn``).

Contract (:mod:`anm_torchrl.surrogates.registry`): ``load_<kind>(sim=..., device=..., dataset=..., path=...,
n_jobs=...)`` returns a :class:`RegressorSurrogate` running on ``sim`` — its foresight features (next-step loads
and potentials) and its terminal classifier read ``sim``'s profiles. ``sim`` must have the network the model
was trained on; a stored dataset other than ``dataset`` raises (an argument the loader cannot honour).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from anm_torchrl.data.generic import for_network
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.paths import surrogate_dir
from anm_torchrl.surrogates.regressors.defaults import DATASETS, KINDS, META_FILE, train_command
from anm_torchrl.surrogates.regressors.io import load_surrogate_folder
from anm_torchrl.surrogates.regressors.module import RegressorSurrogate
from anm_torchrl.surrogates.terminal import ModelFileError


def load_regressor_surrogate(kind: str, sim: GridSimulator | None = None, device=None, dataset: str = "generative",
                             path: str | os.PathLike | None = None, n_jobs: int = 1) -> RegressorSurrogate:
    """Load trained surrogate ``kind`` for ``dataset`` from ``path`` (default ``surrogate_dir(kind, dataset)``, suffixed
    with the network key on networks other than ANM6-Easy).

    Args:
        kind: ``lr``, ``dt``, ``rf``, ``xgb`` or ``dnn``.
        sim: the simulator it runs on (the env's); default ANM6-Easy on ``device``.
        device: torch device (None: ``sim``'s, or the CPU).
        dataset: the dataset it was trained on (``generative``, ``agent``).
        path: the surrogate folder.
        n_jobs: xgboost prediction threads.

    Raises:
        FileNotFoundError: nothing trained there; the message gives the command that trains it.
        ModelFileError / ArtifactError (``ValueError``): a corrupted folder, a model of another kind, dataset,
            state layout or network.
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    if dataset not in DATASETS:
        raise ValueError(f"dataset must be one of {DATASETS}, got {dataset!r}")
    if sim is None:
        sim = network_simulator(ANM6_EASY, device=device if device is not None else "cpu")
    elif device is not None and torch.device(device) != sim.net.dev.device:
        raise ValueError(f"device={device!r} differs from the simulator's device {sim.net.dev.device}; pass one")
    default = path is None
    p = for_network(surrogate_dir(kind, dataset), sim) if default else Path(path)
    if not (p / META_FILE).is_file():
        raise FileNotFoundError(f"no trained {kind!r} surrogate for the {dataset!r} dataset at {p}; train it with: "
                                f"{train_command(kind, dataset, sim, None if default else p)}")
    sur = load_surrogate_folder(p, kind=kind, device=sim.net.dev.device, sim=sim, n_jobs=n_jobs)
    stored = sur.meta.get("dataset")
    if stored != dataset:
        raise ModelFileError(f"{p} holds a surrogate trained on the {stored!r} dataset, dataset={dataset!r} was asked "
                             f"for; pass dataset={stored!r} or train one: {train_command(kind, dataset, sim)}")
    return sur
