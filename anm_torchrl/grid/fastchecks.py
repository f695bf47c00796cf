"""One-pass compiled checks of a step's inputs (state, action) for the CPU hot path (numba).

:func:`anm_torchrl.grid.state.check_state` and :func:`anm_torchrl.envs.specs.check_action` validate with ~15
torch ops each and name the env and entry at fault; at batch 1 that is ~15 % of an ``ANMEnv`` step, at batch
16,384 several passes over the batch. The loops here only answer "is everything valid?" in one pass (and, for
actions, write the float64 copy clamped to the box). When they answer no, the callers run the torch checks,
which raise with the details. Both accept exactly the same inputs (tested in ``tests/test_fastchecks.py``).

``usable(x)`` says whether a tensor can take this path (numba installed, a CPU tensor without grad).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from anm_torchrl.grid.jit import available
from anm_torchrl.grid.jit import njit as _njit


def usable(x: torch.Tensor) -> bool:
    """True when ``x`` can be read by the compiled checks (numba installed, CPU, no autograd graph)."""
    return available() and x.device.type == "cpu" and not x.requires_grad


@_njit()
def _state_ok(state, soc_start, soc_min, soc_max, aux_col, n_time):
    """Every entry finite, SoC (columns ``soc_start`` + k) within [soc_min, soc_max] and, with ``n_time`` > 0,
    column ``aux_col`` an integer in [0, n_time - 1]."""
    for e in range(state.shape[0]):
        for j in range(state.shape[1]):
            x = state[e, j]
            if not (x - x == 0.0):  # NaN or ±inf
                return False
        for k in range(soc_min.shape[0]):
            x = state[e, soc_start + k]
            if not (soc_min[k] <= x <= soc_max[k]):
                return False
        if n_time > 0:
            a = state[e, aux_col]
            if not (0.0 <= a <= n_time - 1 and a == math.floor(a)):
                return False
    return True


def state_ok(state: torch.Tensor, soc_start: int, soc_min: np.ndarray, soc_max: np.ndarray, aux_col: int,
             n_time: int | None) -> bool:
    """Whether :func:`anm_torchrl.grid.state.check_state` would accept ``state`` (N, state_dim) float64, checked
    in one compiled pass (``soc_min``/``soc_max`` (n_des,) MWh; ``n_time`` ``None``: no time-index rule)."""
    return bool(_state_ok(state.detach().numpy(), soc_start, soc_min, soc_max, aux_col,
                          0 if n_time is None else int(n_time)))


@_njit()
def _clamp_action(action, accept_low, accept_high, low, high, clip, out):
    """``out`` = float64(action) clamped to [low, high]; False on a non-finite entry or, unless ``clip``, an
    entry outside [accept_low, accept_high]."""
    for e in range(action.shape[0]):
        for j in range(action.shape[1]):
            a = np.float64(action[e, j])
            if not (a - a == 0.0):
                return False
            if not clip and (a < accept_low[j] or a > accept_high[j]):
                return False
            out[e, j] = min(max(a, low[j]), high[j])
    return True


def clamp_action(action: torch.Tensor, accept_low: np.ndarray, accept_high: np.ndarray, low: np.ndarray,
                 high: np.ndarray, clip: bool) -> torch.Tensor | None:
    """The float64 action (N, A) clamped to [low, high], or ``None`` where
    :func:`anm_torchrl.envs.specs.check_action` would raise (non-finite entries; outside the accepted box
    unless ``clip``)."""
    out = np.empty(tuple(action.shape), dtype=np.float64)
    ok = _clamp_action(action.detach().numpy(), accept_low, accept_high, low, high, bool(clip), out)
    return torch.from_numpy(out) if ok else None
