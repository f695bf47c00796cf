"""XGBoost training with early stopping and a progress bar, and prediction on the asked thread count (shared by
the regressor and the classifier)."""

from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator

import numpy as np
import torch
from tqdm.auto import tqdm


@contextmanager
def openmp_threads(n: int) -> Iterator[None]:
    """Let xgboost use ``n`` OpenMP threads inside the block; the caller's torch thread count is restored after.

    ``torch.set_num_threads(k)`` caps the OpenMP runtime that torch and xgboost share, and xgboost then runs on
    ``k`` threads whatever its ``nthread`` says (measured on xgboost 3.2: ``nthread=2`` after
    ``torch.set_num_threads(1)`` used one core). Raising torch's count for the call makes ``nthread`` hold.
    """
    n, before = int(n), torch.get_num_threads()
    if n < 1:
        raise ValueError(f"xgboost thread count must be >= 1, got {n}")
    if n != before:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)


def predict(booster, x: np.ndarray, n_jobs: int) -> np.ndarray:
    """``booster``'s prediction for ``x`` (N, n_features) on ``n_jobs`` threads; features are compared in float32
    by xgboost, so casting here gives the same trees and is faster."""
    with openmp_threads(n_jobs):
        return booster.inplace_predict(np.ascontiguousarray(x, dtype=np.float32), validate_features=False)


def train_booster(params: dict, x: np.ndarray, y: np.ndarray, x_val: np.ndarray | None, y_val: np.ndarray | None,
                  num_boost_round: int, early_stopping_rounds: int | None, weight: np.ndarray | None = None,
                  progress: bool = False, desc: str = "xgboost", min_delta: float = 0.0):
    """Train an ``xgboost.Booster``; with a validation set, stop early and keep only the best rounds.

    Early stopping: after ``early_stopping_rounds`` rounds without a validation improvement larger than
    ``min_delta`` (in the metric's units). ``params["nthread"]`` (required) is the thread count, honoured whatever
    torch's own count is (:func:`openmp_threads`).

    Returns:
        ``(booster, info)`` with ``info = {"best_iteration", "rounds", "best_score", "metric"}``.
    """
    import xgboost as xgb

    if "nthread" not in params:
        raise ValueError("train_booster needs params['nthread'], the thread count to train on")
    with openmp_threads(params["nthread"]):
        return _train(xgb, params, x, y, x_val, y_val, num_boost_round, early_stopping_rounds, weight, progress,
                      desc, min_delta)


def _train(xgb, params, x, y, x_val, y_val, num_boost_round, early_stopping_rounds, weight, progress, desc,
           min_delta):
    dtrain = xgb.DMatrix(x, label=y, weight=weight)
    evals = []
    if x_val is not None and len(x_val):
        evals = [(xgb.DMatrix(x_val, label=y_val), "val")]
    bar = tqdm(total=num_boost_round, desc=desc, unit="round", disable=not progress, leave=False)

    class _Bar(xgb.callback.TrainingCallback):
        def after_iteration(self, model, epoch, evals_log):
            bar.update(1)
            if evals_log.get("val"):
                metric, values = next(iter(evals_log["val"].items()))
                bar.set_postfix({metric: f"{values[-1]:.4g}"}, refresh=False)
            return False

    history: dict = {}
    callbacks: list = [_Bar()]
    if evals and early_stopping_rounds:
        callbacks.append(xgb.callback.EarlyStopping(rounds=int(early_stopping_rounds), min_delta=float(min_delta),
                                                    save_best=False))
    booster = xgb.train(params, dtrain, num_boost_round=num_boost_round, evals=evals, evals_result=history,
                        verbose_eval=False, callbacks=callbacks)
    bar.close()
    rounds = booster.num_boosted_rounds()
    info = {"rounds": rounds, "best_iteration": rounds - 1, "best_score": None, "metric": None}
    if evals and early_stopping_rounds:
        best = int(booster.best_iteration)
        metric = next(iter(history["val"]))
        info.update(best_iteration=best, best_score=float(history["val"][metric][best]), metric=metric)
        booster = booster[: best + 1]
    return booster, info
