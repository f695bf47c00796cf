"""XGBoost training with early stopping and a progress bar, and prediction on the asked thread count (shared by
the regressor and the classifier)."""

from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator

import numpy as np
import torch
from tqdm.auto import tqdm

from anm_torchrl._extras import require


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
    xgb = require("xgboost")

    if "nthread" not in params:
        raise ValueError("train_booster needs params['nthread'], the thread count to train on")
    has_val = x_val is not None and len(x_val) > 0
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
    if has_val and early_stopping_rounds:
        callbacks.append(xgb.callback.EarlyStopping(rounds=int(early_stopping_rounds), min_delta=float(min_delta),
                                                    save_best=False))
    with openmp_threads(params["nthread"]):  # binning the DMatrix is threaded too
        dtrain = xgb.DMatrix(x, label=y, weight=weight)
        evals = [(xgb.DMatrix(x_val, label=y_val), "val")] if has_val else []
        booster = xgb.train(params, dtrain, num_boost_round=num_boost_round, evals=evals, evals_result=history,
                            verbose_eval=False, callbacks=callbacks)
    bar.close()
    rounds = booster.num_boosted_rounds()
    info = {"rounds": rounds, "best_iteration": rounds - 1, "best_score": None, "metric": None}
    if has_val and early_stopping_rounds:
        best = int(booster.best_iteration)
        metric = next(iter(history["val"]))
        info.update(best_iteration=best, best_score=float(history["val"][metric][best]), metric=metric)
        booster = booster[: best + 1]
    return booster, info


def capped_prefix_reason(params: dict, info: dict, defaults: dict) -> str:
    """Why a booster trained with a round cap costs at most what the uncapped one costs: said only when it is so.

    A run that differs from the defaults in ``num_boost_round`` alone grows the same first rounds (same data,
    parameters and seed); if its best validation round is its last, the uncapped run, whose early stopping keeps
    everything up to its best round, keeps at least these rounds, and predicting with a prefix of trees does less work.

    Args:
        params: the trained model's parameters (``surrogate.json`` ``params``).
        info: its ``train_info`` (:func:`train_booster`'s ``rounds`` and ``best_iteration``).
        defaults: the uncapped model's parameters.

    Raises:
        ValueError: another parameter differs, the cap is not below the default, or the run stopped improving
            before its cap (then its cost bounds nothing).
    """
    other = sorted(k for k in set(params) | set(defaults) if k != "num_boost_round" and params.get(k) != defaults.get(k))
    if other:
        raise ValueError(f"a capped booster must differ from the defaults in num_boost_round only; it differs in {other}")
    cap, full = int(params["num_boost_round"]), int(defaults["num_boost_round"])
    if cap >= full:
        raise ValueError(f"num_boost_round={cap} is no cap: the default is {full}")
    if (info.get("rounds"), info.get("best_iteration")) != (cap, cap - 1):
        raise ValueError(f"the booster kept {info.get('best_iteration', -1) + 1} of {info.get('rounds')} rounds: it was "
                         f"not cut by its cap of {cap} while improving, so it bounds nothing")
    return (f"a {cap}-round booster cut by its cap while still improving on validation: the uncapped run (same data, "
            f"parameters and seed) grows the same {cap} rounds first and keeps at least these, so it costs at least this")
