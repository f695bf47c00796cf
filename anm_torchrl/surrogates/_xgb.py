"""XGBoost training with early stopping and a progress bar (shared by the regressor and the classifier)."""

from __future__ import annotations

import numpy as np
from tqdm.auto import tqdm


def train_booster(params: dict, x: np.ndarray, y: np.ndarray, x_val: np.ndarray | None, y_val: np.ndarray | None,
                  num_boost_round: int, early_stopping_rounds: int | None, weight: np.ndarray | None = None,
                  progress: bool = False, desc: str = "xgboost", min_delta: float = 0.0):
    """Train an ``xgboost.Booster``; with a validation set, stop early and keep only the best rounds.

    Early stopping: after ``early_stopping_rounds`` rounds without a validation improvement larger than
    ``min_delta`` (in the metric's units).

    Returns:
        ``(booster, info)`` with ``info = {"best_iteration", "rounds", "best_score", "metric"}``.
    """
    import xgboost as xgb

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
