"""The physics as named residual functions — the single definition shared by the simulator, its tests and the
PINN losses.

* AC power flow (polar form): the complex mismatch ``V ⊙ conj(Y V) - S_bus`` per bus.
* KKT conditions of the device projection ``min 1/2 ||x - target||^2 s.t. G x <= h``.
"""

from __future__ import annotations

import torch


def bus_voltage(v_magn: torch.Tensor, v_ang: torch.Tensor) -> torch.Tensor:
    """Complex voltages (..., n_bus) from magnitudes (p.u.) and angles (rad)."""
    return torch.polar(v_magn, v_ang)


def power_injection(v: torch.Tensor, y_bus: torch.Tensor) -> torch.Tensor:
    """Complex power injected at each bus, ``S = V ⊙ conj(Y V)`` (..., n_bus) p.u., for ``v`` (..., n_bus)."""
    return v * (v @ y_bus.T).conj()


def power_flow_mismatch(v: torch.Tensor, y_bus: torch.Tensor, s_bus: torch.Tensor) -> torch.Tensor:
    """Complex AC power-flow residual ``V ⊙ conj(Y V) - S_bus`` (..., n_bus) p.u.

    Zero at a power-flow solution for the non-slack buses; at the slack bus it equals the slack injection
    minus ``s_bus[..., 0]``.
    """
    return power_injection(v, y_bus) - s_bus


def power_flow_residual(v_magn: torch.Tensor, v_ang: torch.Tensor, p_bus: torch.Tensor, q_bus: torch.Tensor,
                        y_bus: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Real (ΔP, ΔQ) residuals (..., n_bus) p.u. of the AC power-flow equations in polar form."""
    v = bus_voltage(v_magn, v_ang)
    m = power_flow_mismatch(v, y_bus.to(v.dtype), torch.complex(p_bus, q_bus))
    return m.real, m.imag


def kkt_stationarity(x: torch.Tensor, target: torch.Tensor, lam: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """∇_x L = (x - target) + Gᵀ λ, shape (..., 2)."""
    return (x - target) + torch.einsum("...mk,...m->...k", g.expand(*lam.shape, 2), lam)


def kkt_primal_violation(x: torch.Tensor, g: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """max(0, G x - h), shape (..., m): zero iff ``x`` is feasible."""
    return torch.relu(constraint_slack(x, g, h))


def kkt_complementarity(x: torch.Tensor, lam: torch.Tensor, g: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """λ ⊙ (G x - h), shape (..., m); rows with h = +inf (inactive by construction) give 0."""
    s = constraint_slack(x, g, h)
    return torch.where(torch.isinf(s), torch.zeros_like(s), lam * s)


def kkt_dual_violation(lam: torch.Tensor) -> torch.Tensor:
    """max(0, -λ), shape (..., m)."""
    return torch.relu(-lam)


def constraint_slack(x: torch.Tensor, g: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """G x - h, shape (..., m) (≤ 0 when feasible)."""
    return (g * x.unsqueeze(-2)).sum(-1) - h
