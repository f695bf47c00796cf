"""The DNN surrogate's network and training loop (torch MLP on standardised inputs and targets).

Hyper-parameters (:data:`DEFAULT_PARAMS`, from ``surrogates/conf/models/default.yaml``; override with
``models.dnn.<key>=...`` in ``recipes/train_surrogate.py``):

* 3 hidden layers of 256 units, SiLU — smooth, and enough for ~10 piecewise-smooth outputs from ~30 inputs;
  the paper's PINN modules use 3×512 LeakyReLU, which costs 4× the compute for no gain on this data;
* AdamW, learning rate 2e-3, weight decay 1e-5, mini-batches of 256, halved after 5 epochs without
  validation improvement; stops after 15 epochs without improvement or 150 epochs, keeping the best weights
  (validation MSE in standardised units). The validation error still creeps down at 150 epochs, but R² is
  already ≈0.9998;
* the budget is counted in epochs, never in seconds, so a model does not depend on the machine's load (a
  3-minute wall-clock budget bought ~150 epochs on an idle core, ≈1.8 CPU-s per epoch on 80,000 rows, and 8
  on a loaded one, with 5× the test error). ``max_minutes`` (default 60) is only a safety cap: reaching it
  raises :class:`TrainingBudgetError` instead of returning a model trained for fewer epochs than asked
  (``None``: no cap);
* float32 weights (inputs standardised in float64, then cast).

Training curves go to TensorBoard (``surrogate/train_mse``, ``surrogate/val_mse``, ``surrogate/lr``) when a
``log_dir`` is given.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from typing import Any

import torch
from torch import nn
from tqdm.auto import tqdm

from anm_torchrl.envs.specs import check_integer
from anm_torchrl.surrogates.conf import load_defaults

log = logging.getLogger(__name__)

#: Read from ``anm_torchrl/surrogates/conf/models/default.yaml`` (``dnn``), the one home of these defaults.
DEFAULT_PARAMS: dict[str, Any] = load_defaults("models/default")["dnn"]



class TrainingBudgetError(RuntimeError):
    """The wall-clock safety cap ``max_minutes`` ended training before its epoch budget did."""


ACTIVATIONS = {"silu": nn.SiLU, "relu": nn.ReLU, "leaky_relu": lambda: nn.LeakyReLU(0.01), "tanh": nn.Tanh}


class MLP(nn.Module):
    """``depth`` hidden layers of ``hidden`` units with ``activation``, then a linear output layer."""

    def __init__(self, in_dim: int, out_dim: int, hidden: int = 256, depth: int = 3, activation: str = "silu"):
        super().__init__()
        if activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
        layers: list[nn.Module] = []
        d = in_dim
        for _ in range(depth):
            layers += [nn.Linear(d, hidden), ACTIVATIONS[activation]()]
            d = hidden
        layers.append(nn.Linear(d, out_dim))
        self.net = nn.Sequential(*layers)
        self.arch = {"in_dim": in_dim, "out_dim": out_dim, "hidden": hidden, "depth": depth, "activation": activation}

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


def train_mlp(x: torch.Tensor, y: torch.Tensor, x_val: torch.Tensor, y_val: torch.Tensor,
              params: dict[str, Any] | None = None, seed: int = 0, progress: bool = False,
              log_dir: str | None = None) -> tuple[MLP, dict[str, Any]]:
    """Fit an :class:`MLP` to standardised ``x`` (N, F) → ``y`` (N, T); returns the best model and a summary.

    The model with the lowest validation MSE on (``x_val``, ``y_val``) over at most ``max_epochs`` epochs is kept
    (early stop after ``patience`` epochs without a new best); the summary holds ``epochs``, ``best_epoch``,
    ``best_val_mse``, ``stop`` (``"max_epochs"`` or ``"early_stopping"``) and ``train_seconds``.

    Raises:
        TrainingBudgetError: the wall-clock safety cap ``max_minutes`` was reached first.
    """
    p = {**DEFAULT_PARAMS, **(params or {})}
    for key in ("max_epochs", "patience", "batch_size", "hidden", "depth"):  # 0 epochs saved an untrained model
        check_integer(f"dnn option {key}", p[key], low=1)
    gen = torch.Generator().manual_seed(int(seed))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        model = MLP(x.shape[1], y.shape[1], int(p["hidden"]), int(p["depth"]), str(p["activation"]))
    x, y = x.to(torch.float32), y.to(torch.float32)
    x_val, y_val = x_val.to(torch.float32), y_val.to(torch.float32)
    opt = torch.optim.AdamW(model.parameters(), lr=float(p["lr"]), weight_decay=float(p["weight_decay"]))
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=int(p["lr_patience"]))
    writer = None
    if log_dir is not None:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(log_dir=str(log_dir))
    bs, n = int(p["batch_size"]), x.shape[0]
    best, best_state, best_epoch, bad = math.inf, copy.deepcopy(model.state_dict()), -1, 0
    start = time.perf_counter()
    bar = tqdm(range(int(p["max_epochs"])), desc="dnn", unit="epoch", disable=not progress, leave=False)
    stop_reason = "max_epochs"
    epoch = -1
    for epoch in bar:
        model.train()
        perm = torch.randperm(n, generator=gen)
        total = 0.0
        for i in range(0, n, bs):
            idx = perm[i:i + bs]
            loss = nn.functional.mse_loss(model(x[idx]), y[idx])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += loss.item() * idx.numel()
        train_mse = total / n
        model.eval()
        with torch.no_grad():
            val_mse = (sum(nn.functional.mse_loss(model(x_val[i:i + 8192]), y_val[i:i + 8192], reduction="sum").item()
                           for i in range(0, x_val.shape[0], 8192)) / max(y_val.numel(), 1))
        sched.step(val_mse)
        lr = opt.param_groups[0]["lr"]
        if writer is not None:
            writer.add_scalar("surrogate/train_mse", train_mse, epoch)
            writer.add_scalar("surrogate/val_mse", val_mse, epoch)
            writer.add_scalar("surrogate/lr", lr, epoch)
        bar.set_postfix(train=f"{train_mse:.3g}", val=f"{val_mse:.3g}", refresh=False)
        if val_mse < best:
            best, best_state, best_epoch, bad = val_mse, copy.deepcopy(model.state_dict()), epoch, 0
        else:
            bad += 1
        if bad >= int(p["patience"]):
            stop_reason = "early_stopping"
            break
        cap = p["max_minutes"]
        if cap is not None and epoch + 1 < int(p["max_epochs"]) and time.perf_counter() - start > 60 * float(cap):
            raise TrainingBudgetError(
                f"dnn: the safety cap max_minutes={cap} was reached after {epoch + 1} of "
                f"{int(p['max_epochs'])} epochs (best validation MSE {best:.4g} at epoch {best_epoch}); a model "
                f"cut short by wall time would depend on the machine's load. Raise models.dnn.max_minutes, or set "
                f"it to null")
    bar.close()
    if writer is not None:
        writer.close()
    if not math.isfinite(best):  # restoring best_state would hand back the untrained weights as the fit
        raise RuntimeError(f"dnn: the validation MSE was not finite at any of its {epoch + 1} epochs (diverged at lr "
                           f"{float(p['lr']):g}): lower models.dnn.lr")
    model.load_state_dict(best_state)
    model.eval()
    info = {"epochs": epoch + 1, "best_epoch": best_epoch, "best_val_mse": best, "stop": stop_reason,
            "train_seconds": time.perf_counter() - start, "params": p}
    log.info("dnn: %s after %d epochs, best validation MSE %.4g at epoch %d", stop_reason, epoch + 1, best, best_epoch)
    return model, info
