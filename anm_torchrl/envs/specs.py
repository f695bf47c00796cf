"""Specs and key names shared by every env of the package (true simulator and surrogates).

The contract (DESIGN.md §3), for a batch of N envs:

=================  ==========  =======  ==============================================================
key                shape       dtype    meaning
=================  ==========  =======  ==============================================================
``state``          (N, 18)     float64  gym-anm state (MW, MVAr, MWh, time index)
``observation``    (N, 18)     float32  clip(state) to the observation bounds
``action``         (N, 6)      float32  P PV, P wind, Q PV, Q wind, P DES, Q DES (MW / MVAr)
``reward``         (N, 1)      float32  −(ΔE_c + Pen_c); −100/(1−γ) on a terminal step
``terminated``     (N, 1)      bool     power flow did not converge (true sim) / predicted (surrogates)
``grid.e_loss``    (N, 1)      float32  ΔE, p.u.·h (100 MWh)
``grid.penalty``   (N, 1)      float32  λΦ before clipping
``grid.curtailment`` (N, 1)    float32  renewable curtailment, MW
``grid.v_magn``    (N, 6)      float32  bus voltage magnitudes, p.u.
``grid.branch_s``  (N, 5)      float32  sign(P_from)·max(|S_from|, |S_to|), MVA
=================  ==========  =======  ==============================================================

Surrogates that cannot predict a ``grid`` quantity report NaN for it.
"""

from __future__ import annotations

import torch
from torchrl.data import Bounded, Categorical, Composite, Unbounded

from anm_torchrl.grid.simulator import GridSimulator

GRID_KEYS = ("e_loss", "penalty", "curtailment", "v_magn", "branch_s")


def grid_sizes(sim: GridSimulator) -> dict[str, int]:
    """Trailing size of each ``("grid", k)`` entry."""
    return {"e_loss": 1, "penalty": 1, "curtailment": 1, "v_magn": sim.net.n_bus,
            "branch_s": int(sim.net.branches.rate.shape[0])}


def make_specs(sim: GridSimulator, batch_size: torch.Size, device) -> dict:
    """The observation, state, action, reward and done specs of an env over ``sim`` with ``batch_size``."""
    bs = torch.Size(batch_size)
    s_low, s_high = sim.state_bounds()
    a_low, a_high = sim.action_bounds()
    f32 = torch.float32
    grid = Composite({k: Unbounded((*bs, n), dtype=f32, device=device) for k, n in grid_sizes(sim).items()},
                     shape=bs, device=device)
    obs = Composite(
        observation=Bounded(s_low.to(f32).expand(*bs, -1), s_high.to(f32).expand(*bs, -1), (*bs, sim.state_dim),
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


def observation_from_state(state: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """gym-anm observation: the state clipped to its bounds, as float32."""
    return torch.clamp(state, low, high).to(torch.float32)


def check_action(action: torch.Tensor, low: torch.Tensor, high: torch.Tensor, clip: bool) -> torch.Tensor:
    """Validate a batch of actions (N, A); return it as float64, clipped to the box if ``clip``.

    Raises:
        ValueError: wrong trailing shape, NaN/inf entries (always), or entries outside [low, high] unless
            ``clip`` — the message names the env indices and action entries involved.
    """
    if action.ndim != 2 or action.shape[-1] != low.shape[-1]:
        raise ValueError(f"action must have shape (num_envs, {low.shape[-1]}), got {tuple(action.shape)}")
    a = action.to(torch.float64)
    bad = ~torch.isfinite(a)
    if bad.any():
        envs, entries = bad.nonzero(as_tuple=True)
        raise ValueError(f"non-finite action at (env, entry) {_pairs(envs, entries)}")
    if clip:
        return torch.clamp(a, low, high)
    out = (a < low) | (a > high)
    if out.any():
        envs, entries = out.nonzero(as_tuple=True)
        vals = a[envs[:5], entries[:5]].tolist()
        raise ValueError(
            f"action outside the box at (env, entry) {_pairs(envs, entries)}; values {vals}; box low "
            f"{low.tolist()} high {high.tolist()} (MW/MVAr). Pass action_mode='clip' to clip instead.")
    return a


def _pairs(envs: torch.Tensor, entries: torch.Tensor, limit: int = 5) -> str:
    pairs = list(zip(envs.tolist(), entries.tolist()))
    more = f" and {len(pairs) - limit} more" if len(pairs) > limit else ""
    return ", ".join(map(str, pairs[:limit])) + more
