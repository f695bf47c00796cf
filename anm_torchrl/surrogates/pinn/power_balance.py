"""Power-balance PINN (paper §4.2.3): non-slack bus injections (P_i, Q_i) → bus voltages (|V_i|, θ_i).

The slack bus is fixed at 1∠0. The network is trained on the AC power-flow residual at the non-slack buses
(:func:`anm_torchrl.surrogates.pinn.losses.power_balance_losses`), at Sobol points of the box of bus
injections that ANM6-Easy's devices can produce (:func:`bus_injection_box`, spec §1.6). The slack injection
and the branch flows then follow from the predicted voltages (:mod:`.chain`).

Inputs are normalised to [−1, 1] by that box (buses without devices have a zero-width box and feed 0); the
outputs are ``|V| = 1 + v_scale·y[:n−1]`` and ``θ = ang_scale·y[n−1:]`` (rad) of a :class:`ResidualMLP`, whose
linear input→output connection starts the network as a linearised (DC-like) power flow.

``refine_steps`` > 0 follows the network with that many steps on the same power-flow equations, with
``x = [θ, |V|]`` of the non-slack buses and ``F`` the residual of :func:`.losses.power_balance_residuals`
(physics only, no data; the network itself is trained on its raw output, :mod:`.tasks`):

* ``refine_method="newton"`` (rule v2, :mod:`.refine`; every model trained since): damped Newton steps
  ``x ← x − α J(x)⁻¹ F(x)`` with the exact Jacobian at the current estimate
  (:func:`anm_torchrl.grid.powerflow.power_flow_jacobian`, a batched ``torch.linalg.solve_ex``) and, per sample,
  the first α in :data:`BACKTRACK` that lowers ``max|F|``; a sample no α improves (or a singular J) keeps its
  estimate, so the residual never grows. Converges from the network's estimate wherever Newton–Raphson does;
  one (2n−2)² Jacobian, one factorisation and up to 4 residual evaluations per sample and step;
* ``refine_method="chord"`` (rule v1, model files written before v2 only): ``x ← x − J₀⁻¹ F(x)`` with ``J₀`` the
  Jacobian at the flat start (a constant, inverted once). Cheaper, but it diverges where the operating point is
  far from the flat start in Jacobian terms (a 132/33 kV transformer with X = 0.55 p.u. and tap 1.03: the
  residual grows each step); kept so that v1 files run exactly as they were trained and chosen.
"""

from __future__ import annotations

import torch
from torch import nn

from anm_torchrl.grid import devices as dv
from anm_torchrl.grid.powerflow import power_flow_jacobian
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.surrogates.pinn.losses import power_balance_residuals
from anm_torchrl.surrogates.pinn.nets import ResidualMLP, box_normalise


def bus_injection_box(sim: GridSimulator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-bus box of the injections the devices can produce (:func:`anm_torchrl.grid.devices.bus_injection_box`
    of ``sim``'s network): ``p_low, p_high, q_low, q_high``, each (n_bus,) p.u. For ANM6-Easy (MW/MVAr): bus 3
    P [−10, 30], Q [−32, 30]; bus 4 P [−30, 50], Q [−56, 50]; bus 5 P [−80, 50], Q [−56, 50]; buses 0–2: 0."""
    return dv.bus_injection_box(sim.net)


#: refinement steps after the network: ``newton`` (rule v2) and ``chord`` (rule v1, legacy files)
REFINE_METHODS = ("newton", "chord")
#: step lengths a damped Newton step tries, in order (the first that lowers max|F| is taken)
BACKTRACK = (1.0, 0.5, 0.25, 0.125)


class PowerBalanceNet(nn.Module):
    """(P_i, Q_i) at the non-slack buses → (|V_i|, θ_i), slack at 1∠0.

    Args:
        sim: the simulator (network, device bounds for the input box).
        hidden, depth, activation: the :class:`ResidualMLP`.
        v_scale: p.u. of |V| per unit network output; ang_scale: rad of θ per unit output.
        refine_steps: refinement steps after the network (module docstring; 0: none; a preset's ``auto`` is
            chosen after training, :mod:`.refine`).
        refine_method: ``"newton"`` (damped Newton at the estimate, rule v2) or ``"chord"`` (flat-start chord,
            rule v1: files written before v2), :data:`REFINE_METHODS`.

    ``forward(p_bus (N, n_bus) p.u., q_bus (N, n_bus) p.u., refine=True) -> (v_magn (N, n_bus) p.u.,
    v_ang (N, n_bus) rad)``, float64; entry 0 of the inputs (the slack bus) is ignored; ``refine=False`` skips
    the refinement (the raw network, as trained).
    """

    def __init__(self, sim: GridSimulator, hidden: int = 128, depth: int = 3, activation: str = "silu",
                 v_scale: float = 0.1, ang_scale: float = 0.1, refine_steps: int = 0, refine_method: str = "newton"):
        super().__init__()
        p_lo, p_hi, q_lo, q_hi = bus_injection_box(sim)
        self.register_buffer("in_low", torch.cat([p_lo[1:], q_lo[1:]]), persistent=False)
        self.register_buffer("in_high", torch.cat([p_hi[1:], q_hi[1:]]), persistent=False)
        self.register_buffer("y_bus", sim.net.y_bus.clone(), persistent=False)
        self.n_bus = sim.net.n_bus
        self.v_scale, self.ang_scale = float(v_scale), float(ang_scale)
        n = self.n_bus - 1
        self.net = ResidualMLP(2 * n, 2 * n, hidden=hidden, depth=depth, activation=activation, out_scale=0.1)
        self.refine_steps = 0
        self.refine_method = "newton"
        self.set_refine_method(refine_method)
        self.set_refine_steps(refine_steps)

    def set_refine_method(self, method: str) -> None:
        """Refine with ``method`` (:data:`REFINE_METHODS`) from now on.

        Raises:
            ValueError: another method.
        """
        if method not in REFINE_METHODS:
            raise ValueError(f"refine_method must be one of {REFINE_METHODS}, got {method!r}")
        self.refine_method = method
        if method == "chord" and self.refine_steps:
            self.chord_matrix()

    def set_refine_steps(self, k: int) -> None:
        """Run ``k`` refinement steps after the network from now on (0: none); a chord's matrix J₀⁻¹ is built on
        first need (not saved: it follows from the network's admittance matrix).

        Raises:
            ValueError: ``k`` not an integer >= 0.
        """
        if isinstance(k, bool) or not isinstance(k, int) or k < 0:
            raise ValueError(f"refine_steps must be an integer >= 0, got {k!r}")
        if k and self.refine_method == "chord":
            self.chord_matrix()
        self.refine_steps = k

    def chord_matrix(self) -> torch.Tensor:
        """(J₀⁻¹)ᵀ (2n−2, 2n−2), the matrix a chord step multiplies the residual by (built once)."""
        if "chord" not in self._buffers:
            self.register_buffer("chord", self._flat_start_inverse_jacobian().T.contiguous(), persistent=False)
        return self.chord

    def input_box(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Training box (2(n_bus − 1),) p.u. of ``[P_1..P_{n−1}, Q_1..Q_{n−1}]``."""
        return self.in_low, self.in_high

    def injection_scale(self) -> float:
        """The largest |P| or |Q| bound of a non-slack bus injection (p.u.): the size of this network's injections
        (ANM6-Easy: 0.8 p.u.; a 1 MVA-base feeder can have 45 p.u.), the unit of ``residual_unit="box"``."""
        return float(torch.maximum(self.in_low.abs(), self.in_high.abs()).max())

    def residual(self, x: torch.Tensor, p_bus: torch.Tensor, q_bus: torch.Tensor) -> torch.Tensor:
        """``F(x)`` (N, 2n−2) p.u.: [ΔP, ΔQ] at the non-slack buses of ``x = [θ_1.., |V|_1..]`` (N, 2n−2)."""
        n = self.n_bus - 1
        zero = torch.zeros_like(x[..., :1])
        dp, dq = power_balance_residuals(torch.cat([zero + 1, x[..., n:]], -1), torch.cat([zero, x[..., :n]], -1),
                                         p_bus, q_bus, self.y_bus)
        return torch.cat([dp, dq], -1)

    def refine_step(self, x: torch.Tensor, p_bus: torch.Tensor, q_bus: torch.Tensor, r: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One refinement step of :attr:`refine_method` from ``x`` (N, 2n−2) with residual ``r = F(x)`` (N, 2n−2)
        p.u.; returns the new ``(x, F(x))`` (float64, p.u. / rad)."""
        if self.refine_method == "chord":
            x = x - r @ self.chord_matrix()
            return x, self.residual(x, p_bus, q_bus)
        n = self.n_bus - 1
        one, zero = torch.ones_like(x[..., :1]), torch.zeros_like(x[..., :1])
        jac = power_flow_jacobian(torch.cat([one, x[..., n:]], -1), torch.cat([zero, x[..., :n]], -1), self.y_bus)
        dx, info = torch.linalg.solve_ex(jac, r.unsqueeze(-1))
        dx = dx.squeeze(-1)
        ok = (info == 0).unsqueeze(-1) & torch.isfinite(dx).all(-1, keepdim=True)
        dx = torch.where(ok, dx, torch.zeros_like(dx))  # singular J: the sample keeps its estimate
        norm0 = _inf_norm(r)
        best_x, best_r = x, r
        done = torch.zeros_like(norm0, dtype=torch.bool)
        for a in BACKTRACK:
            xa = x - a * dx
            ra = self.residual(xa, p_bus, q_bus)
            take = ~done & (_inf_norm(ra) < norm0)
            best_x = torch.where(take.unsqueeze(-1), xa, best_x)
            best_r = torch.where(take.unsqueeze(-1), ra, best_r)
            done = done | take
            if bool(done.all()):
                break
        return best_x, best_r

    def refine_state(self, x: torch.Tensor, p_bus: torch.Tensor, q_bus: torch.Tensor, k: int | None = None
                     ) -> torch.Tensor:
        """``x`` (N, 2n−2) = [θ, |V|] of the non-slack buses after ``k`` refinement steps (None: ``refine_steps``)."""
        k = self.refine_steps if k is None else k
        if k:
            r = self.residual(x, p_bus, q_bus)
            for _ in range(k):
                x, r = self.refine_step(x, p_bus, q_bus, r)
        return x

    def _flat_start_inverse_jacobian(self) -> torch.Tensor:
        """J₀⁻¹ (2n−2, 2n−2): the inverse Jacobian of ``F`` at the flat start (it does not depend on the
        injections, which enter ``F`` additively)."""
        n = self.n_bus - 1
        x0 = torch.cat([torch.zeros(1, n), torch.ones(1, n)], -1).double()
        zero = torch.zeros(1, self.n_bus, dtype=torch.float64, device=self.y_bus.device)
        jac = torch.autograd.functional.jacobian(lambda x: self.residual(x, zero, zero), x0.to(zero.device))
        return torch.linalg.inv(jac.reshape(2 * n, 2 * n))

    def forward(self, p_bus: torch.Tensor, q_bus: torch.Tensor, refine: bool = True
                ) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([p_bus[..., 1:], q_bus[..., 1:]], -1).to(torch.float64)
        dtype = self.net.skip.weight.dtype
        y = self.net(box_normalise(x, self.in_low, self.in_high).to(dtype)).to(torch.float64)
        n = self.n_bus - 1
        state = torch.cat([self.ang_scale * y[..., n:], 1 + self.v_scale * y[..., :n]], -1)  # [θ, |V|]
        if refine and self.refine_steps:
            state = self.refine_state(state, p_bus.to(torch.float64), q_bus.to(torch.float64))
        one = torch.ones_like(y[..., :1])
        v_magn = torch.cat([one, state[..., n:]], -1)
        v_ang = torch.cat([torch.zeros_like(one), state[..., :n]], -1)
        return v_magn, v_ang


def _inf_norm(r: torch.Tensor) -> torch.Tensor:
    """max |r| over the last axis (N,), non-finite as +inf."""
    n = r.abs().amax(-1)
    return torch.where(torch.isfinite(n), n, torch.full_like(n, float("inf")))
