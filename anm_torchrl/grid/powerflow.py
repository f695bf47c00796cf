"""Batched Newton–Raphson AC power flow with gym-anm's exact stopping rule (spec §4.1).

Flat start on every call; unknowns ``[θ_1..θ_{n-1}, |V_1|..|V_{n-1}|]`` with the slack (bus 0) fixed at 1∠0;
each step solves with the dense batched LU, or on radial networks where the batch's dense work is large
(:func:`~.tree_solve.use_tree`) with the O(n) block-tree elimination of :mod:`.tree_solve` (the numba kernel's
``"tree"`` solver);
stop an env at its first iterate with ``||F||_inf <= tol`` (it is then frozen), after ``max_iter`` iterations,
or when ``||F||_inf`` is NaN. Converged ⇔ not NaN and ``||F||_inf <= tol``. Only the still-active rows are
iterated, so the rare non-converging env costs its own 100 iterations and nothing else.
"""

from __future__ import annotations

import dataclasses

import torch

from anm_torchrl.grid.residuals import power_injection
from anm_torchrl.grid.tree_solve import tree_newton_step, use_tree

TOL = 1e-5
MAX_ITER = 100
#: bytes the dense Newton Jacobians of one batched step may take at once. Unbounded, N rows of a 320-bus feeder
#: need N·638²·8 B = 3.3 MB each, several times over (2.35 GB at 256 envs, > 8 GB at 1,024): rows beyond the
#: budget are solved in chunks (:func:`jacobian_rows`), which bounds memory whatever the batch and gives the
#: same numbers (each matrix is factorised on its own either way).
JACOBIAN_BUDGET_BYTES = 256 * 2**20
_JACOBIAN_COPIES = 4  # J, its LU factors and :func:`_jacobian`'s complex intermediates (~2 J's worth)


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


def _mismatch(s_inj: torch.Tensor, s_bus: torch.Tensor) -> torch.Tensor:
    """F = [Re, Im] of the non-slack mismatch (N, 2n-2) from ``power_injection`` (N, n) and ``s_bus``."""
    m = (s_inj - s_bus)[:, 1:]
    return torch.cat([m.real, m.imag], 1)


def _jacobian(v: torch.Tensor, s_inj: torch.Tensor, y_conj: torch.Tensor) -> torch.Tensor:
    """Polar Jacobian (N, 2n-2, 2n-2) of F w.r.t. [θ, |V|] on the non-slack buses.

    From ∂S/∂θ = j diag(V) conj(diag(I) − Y diag(V)) and ∂S/∂|V| = diag(V/|V|) conj(diag(I)) +
    diag(V) conj(Y diag(V/|V|)), written with A_ik = V_i conj(Y_ik V_k) and S_i = V_i conj(I_i):
    ∂S/∂θ = −jA + diag(jS), ∂S/∂|V| = A / |V_k| + diag(S / |V|). ``y_conj`` = conj(Y[1:, 1:]).
    """
    vs, s = v[:, 1:], s_inj[:, 1:]
    k = vs.shape[1]
    vm = vs.abs()
    a = vs.unsqueeze(-1) * (y_conj * vs.conj().unsqueeze(1))
    b = a / vm.unsqueeze(1)
    jac = torch.empty(v.shape[0], 2 * k, 2 * k, dtype=vm.dtype, device=v.device)
    jac[:, :k, :k], jac[:, k:, :k] = a.imag, -a.real
    jac[:, :k, k:], jac[:, k:, k:] = b.real, b.imag
    sr, si = s.real, s.imag
    diag = jac.diagonal(0, 1, 2)
    diag[:, :k] -= si
    diag[:, k:] += si / vm
    jac.diagonal(k, 1, 2).add_(sr / vm)
    jac.diagonal(-k, 1, 2).add_(sr)
    return jac


def jacobian_rows(n_rows: int, m: int, itemsize: int = 8) -> int:
    """Rows of (m, m) Jacobians one chunk may hold within :data:`JACOBIAN_BUDGET_BYTES` (≥ 1, ≤ ``n_rows``)."""
    return max(1, min(n_rows, JACOBIAN_BUDGET_BYTES // (_JACOBIAN_COPIES * m * m * itemsize)))


def solve_newton_step(v: torch.Tensor, s_inj: torch.Tensor, y_conj: torch.Tensor, rhs: torch.Tensor,
                      transpose: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """``J(v)⁻¹ rhs`` (or ``J(v)⁻ᵀ rhs``) (N, m) and ``info`` (N,), nonzero where ``J`` is singular (LAPACK's) or
    not finite, for the polar Jacobian at voltages ``v`` (N, n) with injections ``s_inj`` (N, n), ``y_conj`` =
    conj(Y[1:, 1:]); built and solved in chunks of :func:`jacobian_rows` rows. A non-finite ``J`` is replaced by
    the identity before the solve, so its row's solution is meaningless and only ``info`` says so."""
    n, m = rhs.shape
    rows = jacobian_rows(n, m, rhs.element_size())
    eye = torch.eye(m, dtype=rhs.dtype, device=rhs.device)
    dx, info = torch.empty_like(rhs), torch.empty(n, dtype=torch.int32, device=rhs.device)
    for i in range(0, n, rows):
        sl = slice(i, i + rows)
        jac = _jacobian(v[sl], s_inj[sl], y_conj)
        finite = torch.isfinite(jac).flatten(1).all(-1)
        jac = torch.where(finite[:, None, None], jac, eye)
        sol, code = torch.linalg.solve_ex(jac.transpose(-1, -2) if transpose else jac, rhs[sl].unsqueeze(-1))
        dx[sl], info[sl] = sol.squeeze(-1), torch.where(finite, code, 1)
    return dx, info


def power_flow_jacobian(v_magn: torch.Tensor, v_ang: torch.Tensor, y_bus: torch.Tensor) -> torch.Tensor:
    """Jacobian (N, 2n−2, 2n−2) of the non-slack mismatch ``[ΔP, ΔQ]`` w.r.t. ``[θ_1.., |V|_1..]`` (rad, p.u.).

    Args:
        v_magn, v_ang: (N, n_bus) bus voltages (p.u., rad), bus 0 the slack.
        y_bus: (n_bus, n_bus) complex admittance matrix.

    The same Jacobian Newton–Raphson factorises (:func:`_jacobian`); the injections enter the mismatch additively,
    so it does not depend on them. Built with torch ops (differentiable).
    """
    v = torch.polar(v_magn, v_ang)
    y = y_bus.to(v.dtype)
    return _jacobian(v, power_injection(v, y), y[1:, 1:].conj())


def newton_raphson(y_bus: torch.Tensor, s_bus: torch.Tensor, tol: float = TOL,
                   max_iter: int = MAX_ITER) -> PowerFlowResult:
    """Solve the AC power flow for a batch of bus injections.

    Args:
        y_bus: (n_bus, n_bus) complex128 admittance matrix (bus 0 = slack).
        s_bus: (N, n_bus) complex128 injections P + jQ (p.u.); entry 0 is ignored.
        tol: stopping tolerance on ||F||_inf (p.u.).
        max_iter: iteration cap.
    """
    x, converged, n_iter, diff = newton_iterates(y_bus, s_bus, tol, max_iter)
    return PowerFlowResult(v=_voltages(x, s_bus.shape[1]), converged=converged, n_iter=n_iter, mismatch_inf=diff)


def newton_iterates(y_bus: torch.Tensor, s_bus: torch.Tensor, tol: float = TOL, max_iter: int = MAX_ITER
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`newton_raphson`'s iteration: the unknowns ``x`` (N, 2n-2) = [θ_1.., |V|_1..] (rad, p.u.) it stopped
    at, ``converged`` (N,) bool, ``n_iter`` (N,) long and ``||F||_inf`` (N,) p.u."""
    n_env, n = s_bus.shape
    real = torch.float64 if s_bus.dtype == torch.complex128 else torch.float32
    x = torch.cat([torch.zeros(n_env, n - 1, dtype=real, device=s_bus.device),
                   torch.ones(n_env, n - 1, dtype=real, device=s_bus.device)], 1)
    y_conj = y_bus[1:, 1:].conj()
    diff = _mismatch(power_injection(_voltages(x, n), y_bus), s_bus).abs().amax(1)
    n_iter = torch.zeros(n_env, dtype=torch.long, device=s_bus.device)
    # The active rows are carried compactly and only written back when they stop, so the rare env that runs
    # all max_iter iterations costs a few small ops per iteration. NaN > tol is False: NaN stops an env.
    idx = (diff > tol).nonzero().squeeze(1)
    xa, sa = x[idx], s_bus[idx]
    va = _voltages(xa, n)
    sia = power_injection(va, y_bus)
    fa = _mismatch(sia, sa)
    for it in range(1, max_iter + 1):
        if idx.numel() == 0:
            break
        forest = use_tree(y_bus, len(idx))  # radial and a large batch: O(n) block-tree steps, not the dense LU
        if forest is not None:
            dx, info = tree_newton_step(va, sia, y_bus, fa, forest)
        elif it == 1:  # every env is still at the flat start: one Jacobian, one LU factorisation for all
            lu, piv, info = torch.linalg.lu_factor_ex(_jacobian(va[:1], sia[:1], y_conj))
            # every row as one right-hand side of the one factorisation: broadcasting (1, m, m) against (N, m, 1)
            # would copy the factors N times (3.3 GB at 1,024 envs on 320 buses)
            dx = torch.linalg.lu_solve(lu[0], piv[0], fa.T).T
        else:
            dx, info = solve_newton_step(va, sia, y_conj, fa)
        dx = torch.where((info != 0).unsqueeze(1), float("nan"), dx)  # singular J -> NaN, as spsolve
        xa = xa - dx
        va = _voltages(xa, n)
        sia = power_injection(va, y_bus)
        fa = _mismatch(sia, sa)
        da = fa.abs().amax(1)
        going = (da > tol) & (it < max_iter)
        if not bool(going.all()):
            stop = ~going
            x[idx[stop]], diff[idx[stop]], n_iter[idx[stop]] = xa[stop], da[stop], it
            idx, xa, va, sia, fa, sa = idx[going], xa[going], va[going], sia[going], fa[going], sa[going]
    converged = ~torch.isnan(diff) & (diff <= tol)
    return x, converged, n_iter, diff
