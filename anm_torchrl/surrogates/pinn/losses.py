"""PINN losses, built only from the shared residual functions of :mod:`anm_torchrl.grid.residuals`.

No solved example enters any loss: the KKT-NNs are trained on the KKT conditions of the device projection and
the power-balance network on the AC power-flow equations, each at Sobol points of its input box.

* KKT (per device, in rating units, see :mod:`.kkt`): stationarity ``(x − t) + Gᵀλ``, primal feasibility
  ``max(0, Gx − h)`` and complementary slackness ``λ ⊙ (Gx − h)``; dual feasibility holds by construction
  (softplus/ReLU head). Each term is the mean of the squared residual entries.
* Power balance (paper eqs. 30–32, standard polar form — the paper's printed Q equation has a sign slip): the
  mean squared real and imaginary mismatch ``V ⊙ conj(Y V) − S_bus`` at the non-slack buses, with the slack at
  1∠0. ``robust="pseudo_huber"`` or ``"cauchy"`` replaces the square per residual entry by a penalty that grows
  slower for large residuals, so the ≈2 % of box points with no power-flow solution (voltage collapse; their
  residual cannot vanish) do not dominate the gradient.
"""

from __future__ import annotations

import torch

from anm_torchrl.grid.residuals import (
    kkt_complementarity,
    kkt_primal_violation,
    kkt_stationarity,
    power_flow_residual,
)


def kkt_losses(x: torch.Tensor, target: torch.Tensor, lam: torch.Tensor, g: torch.Tensor, h: torch.Tensor,
               norm: str = "squared") -> dict[str, torch.Tensor]:
    """KKT residual losses of ``min ½‖x − target‖² s.t. g x ≤ h``, averaged over samples and devices.

    Args:
        x: (..., 2) primal; target: (..., 2); lam: (..., m) duals (≥ 0); g: (..., m, 2) broadcastable; h: (..., m).
        norm: ``"squared"`` (mean squared residual entry) or ``"l2"`` (mean Euclidean norm of each device's
            residual vector, as in the KKT-NN paper; its gradient does not fade as the residual shrinks).

    Returns:
        ``{"stationarity", "primal", "complementarity"}`` scalars.
    """
    res = {"stationarity": kkt_stationarity(x, target, lam, g), "primal": kkt_primal_violation(x, g, h),
           "complementarity": kkt_complementarity(x, lam, g, h)}
    if norm == "squared":
        return {k: v.square().mean() for k, v in res.items()}
    if norm == "l2":
        return {k: torch.sqrt(v.square().sum(-1) + 1e-24).mean() for k, v in res.items()}
    raise ValueError(f"norm must be 'squared' or 'l2', got {norm!r}")


def kkt_errors(x: torch.Tensor, target: torch.Tensor, lam: torch.Tensor, g: torch.Tensor,
               h: torch.Tensor) -> dict[str, torch.Tensor]:
    """Largest absolute KKT residual of each sample (N,) (all entries after the batch dimension), diagnostics."""
    per = {"stationarity": kkt_stationarity(x, target, lam, g), "primal": kkt_primal_violation(x, g, h),
           "complementarity": kkt_complementarity(x, lam, g, h)}
    return {k: v.abs().flatten(1).amax(1) for k, v in per.items()}


def pseudo_huber(r: torch.Tensor, scale: float) -> torch.Tensor:
    """``2c²(√(1 + (r/c)²) − 1)``: ≈ r² for |r| ≪ c, ≈ 2c|r| for |r| ≫ c (c = ``scale``)."""
    return 2 * scale ** 2 * (torch.sqrt(1 + (r / scale) ** 2) - 1)


def cauchy(r: torch.Tensor, scale: float) -> torch.Tensor:
    """``c² log(1 + (r/c)²)``: ≈ r² for |r| ≪ c; grows logarithmically (its gradient fades) for |r| ≫ c."""
    return scale ** 2 * torch.log1p((r / scale) ** 2)


ROBUST = {"squared": lambda r, c: r.square(), "pseudo_huber": pseudo_huber, "cauchy": cauchy}


def power_balance_residuals(v_magn: torch.Tensor, v_ang: torch.Tensor, p_bus: torch.Tensor, q_bus: torch.Tensor,
                            y_bus: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(ΔP, ΔQ) (N, n_bus − 1) p.u. at the non-slack buses, from :func:`grid.residuals.power_flow_residual`."""
    dp, dq = power_flow_residual(v_magn, v_ang, p_bus, q_bus, y_bus)
    return dp[..., 1:], dq[..., 1:]


def power_balance_losses(v_magn: torch.Tensor, v_ang: torch.Tensor, p_bus: torch.Tensor, q_bus: torch.Tensor,
                         y_bus: torch.Tensor, robust: str = "squared", robust_scale: float = 0.01,
                         unit: float | torch.Tensor = 1.0) -> dict[str, torch.Tensor]:
    """Mean penalised AC power-flow residual at the non-slack buses (paper eqs. 31, 32).

    Args:
        v_magn, v_ang: (N, n_bus) predicted voltages (slack entries 1 and 0); p_bus, q_bus: (N, n_bus) p.u.
        y_bus: (n_bus, n_bus) complex admittance.
        robust: ``"squared"`` (the paper's mean squared residual), ``"pseudo_huber"`` or ``"cauchy"``.
        robust_scale: the robust penalty's scale c (in ``unit``).
        unit: the residuals are measured in this unit (p.u.): 1 (p.u. on the network's base), or the size of the
            network's injections (``residual_unit="box"``), so that one loss scale fits feeders of any base and size.

    Returns:
        ``{"residual_p", "residual_q"}`` scalars.
    """
    if robust not in ROBUST:
        raise ValueError(f"robust must be one of {sorted(ROBUST)}, got {robust!r}")
    dp, dq = power_balance_residuals(v_magn, v_ang, p_bus, q_bus, y_bus)
    dp, dq = dp / unit, dq / unit
    rho = ROBUST[robust]
    return {"residual_p": rho(dp, robust_scale).mean(), "residual_q": rho(dq, robust_scale).mean()}
