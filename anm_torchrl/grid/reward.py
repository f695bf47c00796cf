"""Reward terms of gym-anm (spec §4.3): energy loss ΔE, penalty λΦ, clipping, terminal reward. All p.u."""

from __future__ import annotations

import torch

from anm_torchrl.grid.network import Network


def curtailment(p_pot: torch.Tensor, p_gen: torch.Tensor, renewable: torch.Tensor | None = None) -> torch.Tensor:
    """Σ_g max(0, P_pot,g - P_g) over renewable generators, (N,) p.u.

    Args:
        p_pot, p_gen: (N, n_gen) p.u., every non-slack generator.
        renewable: (n_gen,) 1/0 (or bool): which generators are renewable (classical ones are not curtailed,
            gym-anm); ``None``: all of them.
    """
    gap = torch.relu(p_pot - p_gen)
    return (gap if renewable is None else gap * renewable.to(gap.dtype)).sum(-1)


def energy_loss(p_dev: torch.Tensor, counted: torch.Tensor, curtailed: torch.Tensor, delta_t: float) -> torch.Tensor:
    """ΔE = Δt·(Σ_{d counted} P_d + curtailment), (N,) p.u.·h.

    Args:
        p_dev: (N, n_dev) device injections p.u.
        counted: (n_dev,) bool, the generators (slack included) and loads; storage is excluded (gym-anm).
        curtailed: (N,) p.u., from :func:`curtailment`.
        delta_t: h.
    """
    return delta_t * ((p_dev * counted).sum(-1) + curtailed)


def penalty(v_magn: torch.Tensor, s_apparent_max: torch.Tensor, net: Network, lamb: float) -> torch.Tensor:
    """λΦ = λ·Δt·(Σ_i voltage violations + Σ_branches max(0, |S| - rate)), (N,) p.u.

    Args:
        v_magn: (N, n_bus) |V| p.u.
        s_apparent_max: (N, n_branch) signed max apparent flow p.u.
    """
    v_viol = torch.relu(v_magn - net.v_max) + torch.relu(net.v_min - v_magn)
    s_viol = torch.relu(s_apparent_max.abs() - net.branches.rate)
    return lamb * net.delta_t * (v_viol.sum(-1) + s_viol.sum(-1))


def clipped_reward(e_loss: torch.Tensor, pen: torch.Tensor, clipping: tuple[float, float]) -> torch.Tensor:
    """r = -(sign(ΔE)·min(|ΔE|, c0) + min(max(λΦ, 0), c1))."""
    e_c = torch.sign(e_loss) * torch.clamp(e_loss.abs(), max=clipping[0])
    return -(e_c + torch.clamp(pen, min=0.0, max=clipping[1]))


def terminal_reward(gamma: float, clipping: tuple[float, float]) -> float:
    """Reward of a terminal (non-converged) step, -c1 / (1 - γ) = -19999.99999999998 for ANM6-Easy."""
    return -clipping[1] / (1 - gamma)
