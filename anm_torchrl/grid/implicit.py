"""The AC power flow as a differentiable function of the bus injections, by the implicit function theorem.

At a converged solution ``F(x, s) = 0`` (``F`` = [Re, Im] of the non-slack mismatch, ``x`` = [θ_1.., |V|_1..])
with ``∂F/∂s = -I``, so ``dx/ds = J⁻¹`` for the polar Jacobian ``J = ∂F/∂x`` at the solution. The forward runs
:func:`~anm_torchrl.grid.powerflow.newton_iterates` under ``no_grad`` (the same numbers as
:func:`~anm_torchrl.grid.powerflow.newton_raphson`; or a given solver of the same algorithm, such as the
compiled :class:`~anm_torchrl.grid.backends.numba.CompiledPowerFlow`) and keeps only the solution; the backward
rebuilds ``J`` there and solves with ``Jᵀ`` in batched chunks of bounded memory
(:func:`~anm_torchrl.grid.powerflow.solve_newton_step`), or through the solver's own ``adjoint`` where it has one
(the compiled solver's) — the Newton iterations are never backpropagated. Rows that did not converge get a zero
gradient.
"""

from __future__ import annotations

import torch

from anm_torchrl.grid.powerflow import (MAX_ITER, TOL, PowerFlowResult, _voltages, newton_iterates,
                                       solve_newton_step)
from anm_torchrl.grid.residuals import power_injection
from anm_torchrl.grid.tree_solve import tree_newton_step, use_tree


class ImplicitPowerFlow(torch.autograd.Function):
    """``x, converged, n_iter, mismatch_inf = ImplicitPowerFlow.apply(p_bus, q_bus, y_bus, tol, max_iter, solver)``.

    p_bus, q_bus: (N, n_bus) real injections p.u. (entry 0, the slack's, is ignored and gets a zero gradient);
    x: (N, 2n-2) [θ rad, |V| p.u.] of the non-slack buses; the rest as :func:`newton_iterates` (not differentiable).
    ``solver``: the forward's Newton–Raphson, :func:`newton_iterates` (None) or one with its call, e.g.
    :class:`~anm_torchrl.grid.backends.numba.CompiledPowerFlow`.
    """

    @staticmethod
    def forward(ctx, p_bus, q_bus, y_bus, tol, max_iter, solver=None):
        with torch.no_grad():
            s_bus = torch.complex(p_bus, q_bus)
            x, converged, n_iter, diff = (solver or newton_iterates)(y_bus, s_bus, tol, max_iter)
        # the solution, not its Jacobian: (N, 2n-2) instead of (N, 2n-2, 2n-2) held until backward, which
        # rebuilds J in bounded chunks (a SHAC horizon holds one of these per step)
        ctx.save_for_backward(x, converged, y_bus)
        ctx.solver = solver
        ctx.mark_non_differentiable(converged, n_iter, diff)
        return x, converged, n_iter, diff

    @staticmethod
    def backward(ctx, grad_x, *_):
        x, converged, y_bus = ctx.saved_tensors
        k = x.shape[-1] // 2
        # dL/ds = J⁻ᵀ dL/dx (F = S_inj(x) - s, so ∂x/∂s = J⁻¹); non-converged or singular rows: 0
        ok = converged & torch.isfinite(grad_x).all(-1)
        rhs = torch.where(ok[:, None], grad_x, 0.0)
        if hasattr(ctx.solver, "adjoint"):  # a compiled solver solves with Jᵀ too (CompiledPowerFlow.adjoint)
            lam, info = ctx.solver.adjoint(x, rhs)
        else:
            v = _voltages(x, k + 1)
            s_inj = power_injection(v, y_bus)
            forest = use_tree(y_bus, len(x))
            if forest is not None:  # radial and large: Jᵀ on the bus tree, O(n) per row
                lam, info = tree_newton_step(v, s_inj, y_bus, rhs, forest, transpose=True)
            else:
                lam, info = solve_newton_step(v, s_inj, y_bus[1:, 1:].conj(), rhs, transpose=True)
        lam = torch.where((ok & (info == 0))[:, None], lam, 0.0)
        zero = lam.new_zeros(lam.shape[0], 1)
        grad_p = torch.cat([zero, lam[:, :k]], 1)
        grad_q = torch.cat([zero, lam[:, k:]], 1)
        return grad_p, grad_q, None, None, None, None


def implicit_power_flow(y_bus: torch.Tensor, s_bus: torch.Tensor, tol: float = TOL, max_iter: int = MAX_ITER,
                        solver=None) -> PowerFlowResult:
    """:func:`~anm_torchrl.grid.powerflow.newton_raphson` (same forward numbers; ``solver`` as
    :class:`ImplicitPowerFlow`'s) whose voltages ``v`` (N, n_bus) complex are differentiable w.r.t. ``s_bus``
    (N, n_bus) complex p.u. (through its real and imaginary parts)."""
    x, converged, n_iter, diff = ImplicitPowerFlow.apply(s_bus.real, s_bus.imag, y_bus, tol, max_iter, solver)
    return PowerFlowResult(v=_voltages(x, s_bus.shape[1]), converged=converged, n_iter=n_iter, mismatch_inf=diff)
