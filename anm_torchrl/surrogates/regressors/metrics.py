"""Accuracy of a data-driven surrogate: R² / MAE per output and the terminal classifier's metrics."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

from anm_torchrl.surrogates.regressors.fit import regression_rows, targets_of
from anm_torchrl.surrogates.regressors.module import RegressorSurrogate


def regression_metrics(pred: torch.Tensor, truth: torch.Tensor, names: list[str]) -> dict[str, Any]:
    """R² and MAE per output and overall (the unweighted mean over outputs).

    ``mae`` is in each output's unit (MW, MVAr, MWh, reward units — all of similar magnitude here); ``nmae``
    divides each MAE by that output's standard deviation on ``truth``.
    """
    pred, truth = pred.to(torch.float64).cpu(), truth.to(torch.float64).cpu()
    err = pred - truth
    sse = (err ** 2).sum(0)
    sst = ((truth - truth.mean(0)) ** 2).sum(0)
    r2 = torch.where(sst > 0, 1 - sse / sst, torch.full_like(sse, float("nan")))
    mae = err.abs().mean(0)
    std = truth.std(0)
    nmae = torch.where(std > 0, mae / std, torch.full_like(mae, float("nan")))
    per = {n: {"r2": float(r2[i]), "mae": float(mae[i])} for i, n in enumerate(names)}
    return {"r2": float(np.nanmean(r2.numpy())), "mae": float(mae.mean()), "nmae": float(np.nanmean(nmae.numpy())),
            "n": int(truth.shape[0]), "per_output": per}


def evaluate_surrogate(surrogate: RegressorSurrogate, td: TensorDictBase, batch: int = 65536) -> dict[str, Any]:
    """Regression metrics on the non-terminal rows of ``td`` and classifier metrics on all its rows."""
    rows = regression_rows(td)
    preds = [surrogate.predict_targets(rows.get("state")[i:i + batch], rows.get("action")[i:i + batch])
             for i in range(0, rows.shape[0], batch)]
    out = regression_metrics(torch.cat(preds) if preds else torch.zeros(0, len(surrogate.target_names)),
                             targets_of(rows, surrogate.sim), surrogate.target_names)
    if surrogate.classifier is not None:
        out["terminal"] = surrogate.classifier.evaluate(td.get("state"), td.get("action"), td.get("terminated"))
    return out
