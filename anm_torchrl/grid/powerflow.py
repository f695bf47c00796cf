"""Batched Newton–Raphson AC power flow with gym-anm's exact stopping rule (spec §4.1).

Flat start on every call; unknowns ``[θ_1..θ_{n-1}, |V_1|..|V_{n-1}|]`` with the slack (bus 0) fixed at 1∠0;
stop an env at its first iterate with ``||F||_inf <= tol`` (it is then frozen), after ``max_iter`` iterations,
or when ``||F||_inf`` is NaN. Converged ⇔ not NaN and ``||F||_inf <= tol``. Only the still-active rows are
iterated, so the rare non-converging env costs its own 100 iterations and nothing else.
"""

from __future__ import annotations

import dataclasses

import torch

from anm_torchrl.grid.residuals import power_flow_mismatch

TOL = 1e-5
MAX_ITER = 100


@dataclasses.dataclass
class PowerFlowResult:
    """Solution of a batch of power flows.

    Attributes:
        v: (N, n_bus) complex bus voltages (p.u.), the last iterate even when not converged.
        converged: (N,) bool.
        n_iter: (N,) long, Newton iterations done.
        mismatch_inf: (N,) float, ||F||_inf at the returned iterate (p.u.).
    """

    v: torch.Tensor
    converged: torch.Tensor
    n_iter: torch.Tensor
    mismatch_inf: torch.Tensor


def _voltages(x: torch.Tensor, n: int) -> torch.Tensor:
    ang = torch.cat([torch.zeros_like(x[:, :1]), x[:, : n - 1]], 1)
    mag = torch.cat([torch.ones_like(x[:, :1]), x[:, n - 1 :]], 1)
    return torch.polar(mag, ang)


def _mismatch(v: torch.Tensor, y_bus: torch.Tensor, s_bus: torch.Tensor) -> torch.Tensor:
    m = power_flow_mismatch(v, y_bus, s_bus)[:, 1:]
    return torch.cat([m.real, m.imag], 1)


def _jacobian(v: torch.Tensor, y_bus: torch.Tensor) -> torch.Tensor:
    """Polar Jacobian (N, 2n-2, 2n-2) of the mismatch w.r.t. [θ, |V|] on the non-slack buses."""
    i = torch.einsum("ij,nj->ni", y_bus, v)
    yv = y_bus * v.unsqueeze(1)  # Y diag(V): (N, n, n)
    vn = v / v.abs()
    diag_i = torch.diag_embed(i)
    ds_dth = 1j * v.unsqueeze(-1) * (diag_i - yv).conj()
    ds_dvm = torch.diag_embed(vn * i.conj()) + v.unsqueeze(-1) * (y_bus * vn.unsqueeze(1)).conj()
    ds_dth, ds_dvm = ds_dth[:, 1:, 1:], ds_dvm[:, 1:, 1:]
    top = torch.cat([ds_dth.real, ds_dvm.real], 2)
    bot = torch.cat([ds_dth.imag, ds_dvm.imag], 2)
    return torch.cat([top, bot], 1)


def newton_raphson(y_bus: torch.Tensor, s_bus: torch.Tensor, tol: float = TOL,
                   max_iter: int = MAX_ITER) -> PowerFlowResult:
    """Solve the AC power flow for a batch of bus injections.

    Args:
        y_bus: (n_bus, n_bus) complex128 admittance matrix (bus 0 = slack).
        s_bus: (N, n_bus) complex128 injections P + jQ (p.u.); entry 0 is ignored.
        tol: stopping tolerance on ||F||_inf (p.u.).
        max_iter: iteration cap.
    """
    n_env, n = s_bus.shape
    real = torch.float64 if s_bus.dtype == torch.complex128 else torch.float32
    x = torch.cat([torch.zeros(n_env, n - 1, dtype=real, device=s_bus.device),
                   torch.ones(n_env, n - 1, dtype=real, device=s_bus.device)], 1)
    diff = _mismatch(_voltages(x, n), y_bus, s_bus).abs().amax(1)
    n_iter = torch.zeros(n_env, dtype=torch.long, device=s_bus.device)
    for it in range(max_iter):
        # NaN > tol is False: a NaN iterate stops its env, as in gym-anm.
        active = (diff > tol).nonzero().squeeze(1)
        if active.numel() == 0:
            break
        xa, sa = x[active], s_bus[active]
        va = _voltages(xa, n)
        f = _mismatch(va, y_bus, sa)
        jac = _jacobian(va, y_bus)
        dx, info = torch.linalg.solve_ex(jac, f.unsqueeze(-1))
        dx = dx.squeeze(-1)
        dx = torch.where((info != 0).unsqueeze(1), torch.full_like(dx, float("nan")), dx)  # singular J
        xa = xa - dx
        x[active] = xa
        diff[active] = _mismatch(_voltages(xa, n), y_bus, sa).abs().amax(1)
        n_iter[active] = it + 1
    converged = ~torch.isnan(diff) & (diff <= tol)
    return PowerFlowResult(v=_voltages(x, n), converged=converged, n_iter=n_iter, mismatch_inf=diff)
