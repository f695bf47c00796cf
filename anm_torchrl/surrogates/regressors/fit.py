"""Fitting a data-driven surrogate on dataset rows (terminal rows left out of the regression)."""

from __future__ import annotations

import logging
import os
import time

import numpy as np
import torch
from tensordict import TensorDictBase

from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.surrogates.features import Featurizer, target_layout
from anm_torchrl.surrogates.regressors.backends import BACKENDS
from anm_torchrl.surrogates.regressors.defaults import DEFAULT_PARAMS, KINDS
from anm_torchrl.surrogates.regressors.module import RegressorSurrogate

log = logging.getLogger(__name__)


def regression_rows(td: TensorDictBase) -> TensorDictBase:
    """The non-terminal rows of a dataset split (terminal rows have gym-anm's zero next state)."""
    return td[~td.get("terminated").reshape(-1).bool()]


def targets_of(td: TensorDictBase, sim: GridSimulator) -> torch.Tensor:
    """Ground-truth targets (N, T) float64 of dataset rows: next-state physics entries, then the reward."""
    idx, _ = target_layout(sim)
    return torch.cat([td.get("next_state")[:, idx], td.get("reward").reshape(-1, 1)], 1).to(torch.float64)


def fit_regressor(kind: str, train: TensorDictBase, val: TensorDictBase, sim: GridSimulator | None = None,
                  params: dict | None = None, foresight: bool = True, clip: bool = True, n_jobs: int = 1,
                  seed: int = 0, progress: bool = False, log_dir: str | os.PathLike | None = None
                  ) -> RegressorSurrogate:
    """Train surrogate ``kind`` on dataset rows ``train`` (validation rows ``val`` for early stopping).

    Terminal rows are dropped. ``params`` override :data:`DEFAULT_PARAMS` ``[kind]``. The returned surrogate has
    no classifier yet: set ``surrogate.classifier`` (a fitted :class:`TerminalClassifier`).
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    sim = sim if sim is not None else network_simulator(ANM6_EASY)
    featurizer = Featurizer(sim, foresight=foresight)
    tr, va = regression_rows(train), regression_rows(val)
    x = featurizer(tr.get("state"), tr.get("action"))
    y = targets_of(tr, sim)
    x_mean, x_std = x.mean(0), x.std(0)
    y_mean, y_std = y.mean(0), y.std(0)
    x_std = torch.where(x_std > 1e-12, x_std, torch.ones_like(x_std))
    y_std = torch.where(y_std > 1e-12, y_std, torch.ones_like(y_std))
    xs, ys = (x - x_mean) / x_std, (y - y_mean) / y_std
    xv = (featurizer(va.get("state"), va.get("action")) - x_mean) / x_std
    yv = (targets_of(va, sim) - y_mean) / y_std
    p = {**DEFAULT_PARAMS[kind], **(params or {})}
    start = time.perf_counter()
    backend, info = BACKENDS[kind].fit(kind, xs, ys, xv, yv, p, n_jobs, seed, progress, log_dir)
    info = {**info, "train_seconds": time.perf_counter() - start, "n_train": int(xs.shape[0]),
            "n_val": int(xv.shape[0])}
    log.info("%s trained in %.1f s on %d rows", kind, info["train_seconds"], xs.shape[0])
    meta = {"params": {k: v for k, v in p.items()}, "train_info": _jsonable(info), "seed": int(seed)}
    return RegressorSurrogate(kind, backend, sim, featurizer, x_mean, x_std, y_mean, y_std, clip=clip, meta=meta)


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x
