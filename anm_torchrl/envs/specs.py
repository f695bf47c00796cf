"""Specs and key names shared by every env of the package (true simulator and surrogates).

The contract (DESIGN.md §3), for a batch of N envs on a network with n_dev devices, n_gen non-slack
generators, n_des storage units, n_bus buses, n_br branches (ANM6-Easy: 7, 2, 1, 6, 5):

=====================  ==================================  =======  ==========================================
key                    shape                               dtype    meaning
=====================  ==================================  =======  ==========================================
``state``              (N, 2·n_dev + n_des + n_gen + 1)    float64  gym-anm state (MW, MVAr, MWh, time index)
``observation``        (N, n_obs)                          float32  gym-anm observation clipped to its bounds
``action``             (N, 2·n_gen + 2·n_des)              float32  P gen, Q gen, P storage, Q storage (MW/MVAr)
``reward``             (N, 1)                              float32  −(ΔE_c + Pen_c); −c1/(1−γ) when terminal
``terminated``         (N, 1)                              bool     power flow did not converge / predicted
``grid.e_loss``        (N, 1)                              float32  ΔE, p.u.·h (baseMVA·h)
``grid.penalty``       (N, 1)                              float32  λΦ before clipping
``grid.curtailment``   (N, 1)                              float32  renewable curtailment, MW
``grid.v_magn``        (N, n_bus)                          float32  bus voltage magnitudes, p.u.
``grid.branch_s``      (N, n_br)                           float32  sign(P_from)·max(|S_from|, |S_to|), MVA
=====================  ==================================  =======  ==========================================

Surrogates that cannot predict a ``grid`` quantity report NaN for it.
"""

from __future__ import annotations

import dataclasses
import operator

import numpy as np
import torch
from torchrl.data import Bounded, Categorical, Composite, Unbounded

from anm_torchrl.grid import fastchecks
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.grid.state import _pairs

GRID_KEYS = ("e_loss", "penalty", "curtailment", "v_magn", "branch_s")


def grid_sizes(sim: GridSimulator) -> dict[str, int]:
    """Trailing size of each ``("grid", k)`` entry."""
    return {"e_loss": 1, "penalty": 1, "curtailment": 1, "v_magn": sim.net.n_bus,
            "branch_s": int(sim.net.branches.rate.shape[0])}


def make_specs(sim: GridSimulator, batch_size: torch.Size, device, obs_map=None) -> dict:
    """The observation, state, action, reward and done specs of an env over ``sim`` with ``batch_size``.

    ``obs_map`` (an :class:`~anm_torchrl.envs.observation.ObservationMap`, default ``"state"``) gives the
    observation bounds; where gym-anm's low exceeds its high (a load with Q/P < 0) the spec holds the sorted pair,
    and every bound is widened to include 0: gym-anm's terminal observation is all zeros even where its own
    bounds exclude 0 (e.g. SOC_MIN > 0), and it is kept exactly.
    """
    from anm_torchrl.envs.observation import ObservationMap

    bs = torch.Size(batch_size)
    obs_map = obs_map if obs_map is not None else ObservationMap(sim, "state", (0.0, float(sim.n_time - 1)))
    o_low = torch.minimum(torch.minimum(obs_map.low, obs_map.high), torch.zeros_like(obs_map.low))
    o_high = torch.maximum(torch.maximum(obs_map.low, obs_map.high), torch.zeros_like(obs_map.low))
    a_low, a_high = sim.action_bounds()
    f32 = torch.float32
    grid = Composite({k: Unbounded((*bs, n), dtype=f32, device=device) for k, n in grid_sizes(sim).items()},
                     shape=bs, device=device)
    obs = Composite(
        observation=Bounded(o_low.to(f32).expand(*bs, -1), o_high.to(f32).expand(*bs, -1), (*bs, o_low.numel()),
                            dtype=f32, device=device),
        state=Unbounded((*bs, sim.state_dim), dtype=torch.float64, device=device),
        grid=grid,
        shape=bs, device=device,
    )
    return {
        "observation_spec": obs,
        "state_spec": Composite(state=Unbounded((*bs, sim.state_dim), dtype=torch.float64, device=device),
                                shape=bs, device=device),
        "action_spec": Bounded(a_low.to(f32).expand(*bs, -1), a_high.to(f32).expand(*bs, -1),
                               (*bs, sim.action_dim), dtype=f32, device=device),
        "reward_spec": Unbounded((*bs, 1), dtype=f32, device=device),
        "done_spec": Composite(done=Categorical(2, (*bs, 1), dtype=torch.bool, device=device),
                               terminated=Categorical(2, (*bs, 1), dtype=torch.bool, device=device),
                               shape=bs, device=device),
    }


@dataclasses.dataclass(frozen=True)
class ActionBox:
    """The action box (A,) MW/MVAr in float64 and the box :func:`check_action` accepts.

    The action spec is float32: a bound such as 0.754 MW (an earlier case33bw's) rounds outward in float32, so the
    spec's own high/low must pass. ``accept_low``/``accept_high`` are the bounds widened to the nearest float32
    value outside them, computed once here rather than on every step.
    """

    low: torch.Tensor
    high: torch.Tensor
    accept_low: torch.Tensor
    accept_high: torch.Tensor
    arrays: tuple | None = None  # (accept_low, accept_high, low, high) as NumPy arrays for the compiled check

    @classmethod
    def of(cls, low: torch.Tensor, high: torch.Tensor) -> "ActionBox":
        acc_low, acc_high = _f32_outward(low, -1), _f32_outward(high, 1)
        arrays = None
        if low.device.type == "cpu":
            arrays = tuple(np.ascontiguousarray(x.numpy(), dtype=np.float64) for x in (acc_low, acc_high, low, high))
        return cls(low, high, acc_low, acc_high, arrays)


def check_action_dtype(dtype: torch.dtype | np.dtype | type) -> None:
    """Refuse an action dtype that is not a real number: bool (0/1 MW by accident), complex, object, strings.

    Floats (float16, bfloat16, float32, float64) and integers are cast exactly to float64 by the callers.

    Raises:
        TypeError: naming the dtype.
    """
    if isinstance(dtype, torch.dtype):
        ok = dtype in (torch.float16, torch.bfloat16, torch.float32, torch.float64, torch.uint8, torch.int8,
                              torch.int16, torch.int32, torch.int64)
    else:
        dt = np.dtype(dtype)
        ok = dt.kind in "iu" or (dt.kind == "f" and dt.itemsize <= 8)
    if not ok:
        raise TypeError(f"action dtype {dtype} is not supported: actions are real numbers in MW/MVAr (float16, "
                        f"float32, float64 or integers, cast to float64); bool, complex, object and string "
                        f"actions are refused")


def check_action(action: torch.Tensor, box: ActionBox, clip: bool) -> torch.Tensor:
    """Validate a batch of actions (N, A); return it as float64 inside ``box`` (clipped to it if ``clip``).

    Any float or integer dtype is cast to float64 first (:func:`check_action_dtype`).

    Raises:
        TypeError: a bool, complex or other non-real dtype.
        ValueError: wrong trailing shape, NaN/inf entries (always), or entries outside the (float32-rounded) box
            unless ``clip`` — the message names the env indices and action entries involved.
    """
    low, high = box.low, box.high
    check_action_dtype(action.dtype)
    if action.ndim != 2 or action.shape[-1] != low.shape[-1]:
        raise ValueError(f"action must have shape (num_envs, {low.shape[-1]}), got {tuple(action.shape)}")
    if action.dtype not in (torch.float32, torch.float64):  # exact: the compiled pass reads these two only
        action = action.to(torch.float64)
    if box.arrays is not None and fastchecks.usable(action):  # one compiled pass; on failure the checks below
        out = fastchecks.clamp_action(action, *box.arrays, clip)  # name what is wrong
        if out is not None:
            return out
    a = action.to(torch.float64)
    bad = ~torch.isfinite(a)
    if bad.any():
        envs, entries = bad.nonzero(as_tuple=True)
        raise ValueError(f"non-finite action at (env, entry) {_pairs(envs, entries)}")
    if not clip:
        out = (a < box.accept_low) | (a > box.accept_high)
        if out.any():
            envs, entries = out.nonzero(as_tuple=True)
            vals = a[envs[:5], entries[:5]].tolist()
            raise ValueError(
                f"action outside the box at (env, entry) {_pairs(envs, entries)}; values {vals}; box low "
                f"{low.tolist()} high {high.tolist()} (MW/MVAr). Pass action_mode='clip' to clip instead.")
    # inside the float32-rounded box: onto the exact float64 box (the polygon projection would do the same)
    return torch.clamp(a, low, high)


def _f32_outward(bound: torch.Tensor, direction: int) -> torch.Tensor:
    """``bound`` (float64) widened to the nearest float32 value on its outer side (``direction`` ±1)."""
    b32 = bound.to(torch.float32)
    inward = (b32.to(torch.float64) - bound) * direction < 0
    b32 = torch.where(inward, torch.nextafter(b32, torch.full_like(b32, direction * float("inf"))), b32)
    return b32.to(torch.float64)


def check_integer(name: str, value, low: int | None = None, optional: bool = False) -> int | None:
    """``value`` as an int if it is one (Python or NumPy integer, not bool), else a ``ValueError`` naming ``name``."""
    if value is None and optional:
        return None
    try:
        if isinstance(value, bool):
            raise TypeError
        out = operator.index(value)
    except TypeError:
        out = None
    if out is None or (low is not None and out < low):
        expected = "an integer" + (f" >= {low}" if low is not None else "") + (" or None" if optional else "")
        raise ValueError(f"{name} must be {expected}, got {value!r}") from None
    return out
