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
    """Polar Jacobian (N, 2n-2, 2n-2) of the mismatch w.r.t. [θ, |V|] on the non-slack buses.

    ∂S/∂θ = j diag(V) conj(diag(I) − Y diag(V)),  ∂S/∂|V| = diag(V/|V|) conj(diag(I)) + diag(V) conj(Y diag(V/|V|)).
    """
    y = y_bus[1:, 1:]
    vs = v[:, 1:]
    i = (v @ y_bus.T)[:, 1:]
    vn = vs / vs.abs()
    ds_dth = -1j * vs.unsqueeze(-1) * (y * vs.unsqueeze(1)).conj()  # off-diagonal part
    ds_dvm = vs.unsqueeze(-1) * (y * vn.unsqueeze(1)).conj()
    ds_dth = ds_dth + torch.diag_embed(1j * vs * i.conj())
    ds_dvm = ds_dvm + torch.diag_embed(vn * i.conj())
    jac = torch.empty(v.shape[0], 2 * (v.shape[1] - 1), 2 * (v.shape[1] - 1), dtype=v.real.dtype, device=v.device)
    k = v.shape[1] - 1
    jac[:, :k, :k], jac[:, :k, k:] = ds_dth.real, ds_dvm.real
    jac[:, k:, :k], jac[:, k:, k:] = ds_dth.imag, ds_dvm.imag
    return jac


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
    # The active rows are carried compactly and only written back when they stop, so the rare env that runs
    # all max_iter iterations costs a few small ops per iteration. NaN > tol is False: NaN stops an env.
    idx = (diff > tol).nonzero().squeeze(1)
    xa, sa = x[idx], s_bus[idx]
    va = _voltages(xa, n)
    fa = _mismatch(va, y_bus, sa)
    for it in range(1, max_iter + 1):
        if idx.numel() == 0:
            break
        dx, info = torch.linalg.solve_ex(_jacobian(va, y_bus), fa.unsqueeze(-1))
        dx = torch.where((info != 0).unsqueeze(1), float("nan"), dx.squeeze(-1))  # singular J -> NaN, as spsolve
        xa = xa - dx
        va = _voltages(xa, n)
        fa = _mismatch(va, y_bus, sa)
        da = fa.abs().amax(1)
        going = (da > tol) & (it < max_iter)
        if not bool(going.all()):
            stop = ~going
            x[idx[stop]], diff[idx[stop]], n_iter[idx[stop]] = xa[stop], da[stop], it
            idx, xa, va, fa, sa = idx[going], xa[going], va[going], fa[going], sa[going]
    converged = ~torch.isnan(diff) & (diff <= tol)
    return PowerFlowResult(v=_voltages(x, n), converged=converged, n_iter=n_iter, mismatch_inf=diff)
