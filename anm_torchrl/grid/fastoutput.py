"""Compiled one-pass assembly of a step's outputs on the CPU (numba): the state vector and the env's outputs.

After the transition, :meth:`GridSimulator.build_state` and ``ANMEnv._output`` cost ~25 small torch ops (scale
to MW, concatenate, zero terminal rows, clip the observation, cast to float32): ~15 % of a batch-1 step and
several passes over the batch at 16,384 envs. The loops here write the same values (the same IEEE operations,
bit for bit; tested in ``tests/test_fastchecks.py``) in one pass. The torch code stays the reference and the
path for other devices.
"""

from __future__ import annotations

import numpy as np
import torch

from anm_torchrl.grid.jit import njit as _njit


@_njit()
def _state_rows(p_dev, q_dev, soc, p_pot, aux, converged, b, out):
    """``out`` (N, 2 n_dev + n_des + n_gen + 1) = [p_dev, q_dev, soc, p_pot]·b and aux; zeros where not converged."""
    n_dev, n_des, n_gen = p_dev.shape[1], soc.shape[1], p_pot.shape[1]
    for e in range(out.shape[0]):
        if not converged[e]:
            for j in range(out.shape[1]):
                out[e, j] = 0.0
            continue
        for r in range(n_dev):
            out[e, r] = p_dev[e, r] * b
            out[e, n_dev + r] = q_dev[e, r] * b
        for k in range(n_des):
            out[e, 2 * n_dev + k] = soc[e, k] * b
        for k in range(n_gen):
            out[e, 2 * n_dev + n_des + k] = p_pot[e, k] * b
        out[e, out.shape[1] - 1] = aux[e]


def build_state(tr, aux: torch.Tensor, b: float) -> torch.Tensor:
    """:meth:`~anm_torchrl.grid.simulator.GridSimulator.build_state` for CPU float64 transitions, in one pass."""
    n = tr.p_dev.shape[0]
    out = np.empty((n, 2 * tr.p_dev.shape[1] + tr.soc.shape[1] + tr.p_pot.shape[1] + 1))
    a = np.ascontiguousarray(aux.reshape(-1).numpy(), dtype=np.float64)
    _state_rows(tr.p_dev.numpy(), tr.q_dev.numpy(), tr.soc.numpy(), tr.p_pot.numpy(), a, tr.converged.numpy(),
                float(b), out)
    return torch.from_numpy(out)


@_njit()
def _env_rows(state, converged, v, s_max, e_loss, pen, curt, reward, b, low, high, obs, v_magn, branch_s, e32, p32,
              c32, r32, terminated):
    """The float32 outputs of ``ANMEnv._output`` / ``_step``; ``obs`` (N, 0) when the observation is not the
    state (then computed by the observation map)."""
    clip = obs.shape[1] > 0
    for e in range(state.shape[0]):
        ok = converged[e]
        if clip:
            for j in range(state.shape[1]):  # np.clip order (high wins if low > high), zeros on terminal rows
                obs[e, j] = np.float32(min(max(state[e, j], low[j]), high[j])) if ok else np.float32(0.0)
        for i in range(v.shape[1]):
            v_magn[e, i] = np.float32(abs(v[e, i]))
        for k in range(s_max.shape[1]):
            branch_s[e, k] = np.float32(s_max[e, k] * b)
        e32[e, 0], p32[e, 0], c32[e, 0] = np.float32(e_loss[e]), np.float32(pen[e]), np.float32(curt[e] * b)
        r32[e, 0] = np.float32(reward[e])
        terminated[e, 0] = not ok


def env_outputs(state: torch.Tensor, tr, b: float, low: np.ndarray | None, high: np.ndarray | None
                ) -> dict[str, torch.Tensor]:
    """Observation (when ``low``/``high`` are given: the state clipped to them), grid quantities, reward and
    ``terminated`` of an env step from a CPU state (N, state_dim) and its transition (float32 / bool, (N, ·))."""
    n = state.shape[0]
    f32 = np.float32
    clip = low is not None
    out = {"observation": np.empty((n, state.shape[1] if clip else 0), dtype=f32),
           "v_magn": np.empty((n, tr.v.shape[1]), dtype=f32), "branch_s": np.empty((n, tr.s_apparent_max.shape[1]),
                                                                                   dtype=f32),
           "e_loss": np.empty((n, 1), dtype=f32), "penalty": np.empty((n, 1), dtype=f32),
           "curtailment": np.empty((n, 1), dtype=f32), "reward": np.empty((n, 1), dtype=f32),
           "terminated": np.empty((n, 1), dtype=np.bool_)}
    empty = np.empty(0)
    _env_rows(np.ascontiguousarray(state.numpy()), tr.converged.numpy(), tr.v.numpy(), tr.s_apparent_max.numpy(),
              tr.e_loss.numpy(), tr.penalty.numpy(), tr.curtailment.numpy(), tr.reward.numpy(), float(b),
              low if clip else empty, high if clip else empty, *out.values())
    return {k: torch.from_numpy(v) for k, v in out.items() if k != "observation" or clip}
