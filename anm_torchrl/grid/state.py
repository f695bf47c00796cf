"""``GridState``: gym-anm's state vector with names, and the one state validation of the package.

gym-anm's state is ``[dev_p (n_dev, MW), dev_q (n_dev, MVAr), des_soc (n_des, MWh), gen_p_max (n_gen, MW),
aux (K = 1)]``. :func:`from_vector` / :func:`to_vector` convert between that vector (N, state_dim) and a
``TensorDict`` with those five entries (the names of gym-anm's ``STATE_VARIABLES``), so that envs, datasets
and surrogates use names instead of re-derived slices. :func:`check_state` is the validation shared by
``set_state`` and ``step`` (before any backend runs, so both backends see the same inputs).
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

STATE_KEYS = ("dev_p", "dev_q", "des_soc", "gen_p_max", "aux")


def state_sizes(n_dev: int, n_des: int, n_gen: int, n_aux: int = 1) -> dict[str, int]:
    """Width of each :data:`STATE_KEYS` block."""
    return {"dev_p": n_dev, "dev_q": n_dev, "des_soc": n_des, "gen_p_max": n_gen, "aux": n_aux}


def state_slices(sizes: dict[str, int]) -> dict[str, slice]:
    """Slice of each block in the state vector, in gym-anm's order."""
    out, start = {}, 0
    for k in STATE_KEYS:
        out[k] = slice(start, start + sizes[k])
        start += sizes[k]
    return out


def from_vector(state: torch.Tensor, sizes: dict[str, int]) -> TensorDict:
    """``GridState`` TensorDict (batch (N,)) from a state vector (N, state_dim) MW/MVAr/MWh/aux."""
    sl = state_slices(sizes)
    width = sl["aux"].stop
    if state.ndim != 2 or state.shape[1] != width:
        raise ValueError(f"state must have shape (N, {width}), got {tuple(state.shape)}")
    return TensorDict({k: state[:, s] for k, s in sl.items()}, batch_size=state.shape[:1])


def to_vector(grid_state: TensorDict) -> torch.Tensor:
    """State vector (N, state_dim) in gym-anm's order from a ``GridState`` TensorDict."""
    return torch.cat([grid_state[k] for k in STATE_KEYS], -1)


def check_state(state: torch.Tensor, sizes: dict[str, int], soc_min: torch.Tensor, soc_max: torch.Tensor,
                n_time: int | None) -> None:
    """Reject states no gym-anm transition can start from, naming the env index and the entry.

    Checks: shape (N, state_dim); every entry finite; SoC within [SOC_MIN, SOC_MAX] (MWh); with the
    time-index rule (``n_time`` given) the auxiliary variable an integer in [0, n_time - 1].

    Args:
        state: (N, state_dim) float64.
        sizes: :func:`state_sizes` of the network.
        soc_min, soc_max: (n_des,) MWh.
        n_time: number of time indices T of the profiles, or ``None`` when a user ``next_vars`` reads aux.

    Raises:
        ValueError: naming the (env, entry) pairs at fault and their values.
    """
    sl = state_slices(sizes)
    width = sl["aux"].stop
    if state.ndim != 2 or state.shape[1] != width:
        raise ValueError(f"state must have shape (num_envs, {width}), got {tuple(state.shape)}")
    bad = ~torch.isfinite(state)
    if bad.any():
        envs, entries = bad.nonzero(as_tuple=True)
        raise ValueError(f"non-finite state at (env, entry) {_pairs(envs, entries)}")
    soc = state[:, sl["des_soc"]]
    bad = (soc < soc_min) | (soc > soc_max)
    if bad.any():
        envs, cols = bad.nonzero(as_tuple=True)
        raise ValueError(f"SoC (MWh) must lie in [SOC_MIN, SOC_MAX] = [{soc_min.tolist()}, {soc_max.tolist()}]; "
                         f"(env, entry) {_pairs(envs, cols + sl['des_soc'].start)} have "
                         f"{soc[envs[:5], cols[:5]].tolist()}")
    if n_time is not None:
        aux = state[:, sl["aux"].start]
        bad = (aux != aux.round()) | (aux < 0) | (aux > n_time - 1)
        if bad.any():
            envs = bad.nonzero().squeeze(1)
            raise ValueError(f"time index (state entry {sl['aux'].start}) must be an integer in [0, {n_time - 1}]; "
                             f"envs {envs.tolist()[:5]} have {aux[envs[:5]].tolist()}")


def _pairs(envs: torch.Tensor, entries: torch.Tensor, limit: int = 5) -> str:
    pairs = list(zip(envs.tolist(), entries.tolist()))
    more = f" and {len(pairs) - limit} more" if len(pairs) > limit else ""
    return ", ".join(map(str, pairs[:limit])) + more
