"""Registry loaders of the data-driven surrogates (``surrogate=lr|dt|rf|xgb|dnn``).

Contract (:mod:`anm_torchrl.surrogates.registry`): ``load_<kind>(sim=..., device=..., dataset=..., path=...,
n_jobs=...)`` returns a :class:`RegressorSurrogate` running on ``sim`` — its foresight features (next-step loads
and potentials) and its terminal classifier read ``sim``'s profiles. ``sim`` must have the network the model
was trained on; a stored dataset other than ``dataset`` raises (an argument the loader cannot honour).
"""

from __future__ import annotations

import logging
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

log = logging.getLogger(__name__)


def load_regressor_surrogate(kind: str, sim: GridSimulator | None = None, device=None, dataset: str = "generative",
                             path: str | os.PathLike | None = None, n_jobs: int = 1,
                             train_if_missing: bool | None = None, size: int | None = None,
                             progress: bool = True) -> RegressorSurrogate:
    """Load trained surrogate ``kind`` for ``dataset`` from ``path`` (default ``surrogate_dir(kind, dataset)``, suffixed
    with the network key on networks other than ANM6-Easy).

    Args:
        kind: ``lr``, ``dt``, ``rf``, ``xgb`` or ``dnn``.
        sim: the simulator it runs on (the env's); default ANM6-Easy on ``device``.
        device: torch device (None: ``sim``'s, or the CPU).
        dataset: the dataset it was trained on (``generative``, ``agent``).
        path: the surrogate folder.
        n_jobs: xgboost prediction threads (and training threads when trained here).
        train_if_missing: train it when nothing is saved there (:func:`.first_use.train_default`: the recipe's
            defaults); default True for the default folder and False for an explicit ``path`` (a mistyped path is
            an error, not minutes of training).
        size: dataset rows of that training (default :data:`anm_torchrl.data.defaults.DEFAULT_SIZE`; the default
            folder takes only the default size, as in the recipe).
        progress: progress bars while training.

    Raises:
        FileNotFoundError: nothing trained there and training not asked for; the message gives the command.
        ValueError: a training of fewer rows than the default asked for the default folder.
        ModelFileError / ArtifactError (``ValueError``): a corrupted folder (also one without its
            ``surrogate.json``: never replaced by a training here), a model of another kind, dataset, state layout
            or network.
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
    train = train_if_missing if train_if_missing is not None else default
    if not (p / META_FILE).is_file() and p.is_dir() and any(p.iterdir()):
        # saves are atomic (the description lands with the model): a folder without it is damaged or not ours
        held = ", ".join(sorted(f.name for f in p.iterdir())[:5])
        then = ("load it again to train it" if train
                else f"train it with: {train_command(kind, dataset, sim, None if default else p)}")
        raise ModelFileError(f"{p} holds {held} but no {META_FILE}: not a saved {kind!r} surrogate (damaged or "
                             f"another program's); nothing was overwritten: move or delete the folder, then {then}")
    if not (p / META_FILE).is_file() and train:
        from anm_torchrl.data.defaults import DEFAULT_SIZE
        from anm_torchrl.surrogates.regressors.first_use import train_default

        rows = DEFAULT_SIZE if size is None else int(size)
        if default and rows != DEFAULT_SIZE:
            raise ValueError(f"size={rows} differs from the default {DEFAULT_SIZE} rows: a model trained on it would "
                             f"take the default folder {p}; pass path=... for it")
        log.warning("no trained %r surrogate for the %r dataset at %s: training it now with the recipe's defaults "
                    "(%d rows, generated first if missing; a few minutes on a 2-core CPU)", kind, dataset, p, rows)
        train_default(kind, dataset, sim, p, n_jobs=n_jobs, progress=progress, size=rows)
    if not (p / META_FILE).is_file():
        raise FileNotFoundError(f"no trained {kind!r} surrogate for the {dataset!r} dataset at {p}; train it with: "
                                f"{train_command(kind, dataset, sim, None if default else p)}")
    sur = load_surrogate_folder(p, kind=kind, device=sim.net.dev.device, sim=sim, n_jobs=n_jobs)
    stored = sur.meta.get("dataset")
    if stored != dataset:
        raise ModelFileError(f"{p} holds a surrogate trained on the {stored!r} dataset, dataset={dataset!r} was asked "
                             f"for; pass dataset={stored!r} or train one: {train_command(kind, dataset, sim)}")
    return sur
