"""PINN loss components over training (paper Fig. 5), read from the PINN training's TensorBoard run.

Tags ``surrogate/<module>/<term>`` (``generator`` and ``storage``: stationarity, primal, complementarity, loss,
val_loss…; ``power_balance``: residual_p, residual_q, loss…), as written by
``anm_torchrl.surrogates.pinn.train.train_pinn(log_dir=...)``.
"""

from __future__ import annotations

import glob
from pathlib import Path
from typing import Any

from anm_torchrl.experiments.common import RunContext
from anm_torchrl.experiments.io import result


def read_scalars(log_dir: str | Path, prefix: str = "surrogate/") -> dict[str, list[tuple[int, float]]]:
    """Every scalar tag under ``prefix`` in the TensorBoard event files below ``log_dir``: tag -> [(step, value)]."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out: dict[str, list[tuple[int, float]]] = {}
    files = sorted(glob.glob(str(Path(log_dir) / "**" / "events.out.tfevents.*"), recursive=True))
    for f in files:
        acc = EventAccumulator(f, size_guidance={"scalars": 0})
        acc.Reload()
        for tag in acc.Tags().get("scalars", []):
            if tag.startswith(prefix):
                out.setdefault(tag, []).extend((e.step, float(e.value)) for e in acc.Scalars(tag))
    return {k: sorted(v) for k, v in out.items()}


def run(cfg: dict[str, Any], ctx: RunContext) -> dict:
    """Read the first of ``ctx.pinn_logs`` that holds ``surrogate/*`` scalars."""
    tried = []
    for d in ctx.pinn_logs:
        if d is None or not Path(d).exists():
            tried.append(f"{d}: missing")
            continue
        try:
            scalars = read_scalars(d)
        except Exception as err:  # noqa: BLE001 - tensorboard missing or corrupt file
            tried.append(f"{d}: {type(err).__name__}: {err}")
            continue
        if scalars:
            return result("pinn_losses", "ok", {"log_dir": str(d), "scalars": scalars}, config=cfg)
        tried.append(f"{d}: no surrogate/* scalars")
    return result("pinn_losses", "not available", reason="no PINN TensorBoard run: " + "; ".join(tried), config=cfg)
