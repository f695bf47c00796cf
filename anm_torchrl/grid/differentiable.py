"""gym-anm's transition with gradients: next state, reward and penalty w.r.t. the set-points and the state.

The torch backend's transition (:mod:`anm_torchrl.grid.backends.torch`, the same forward numbers) with the power
flow differentiated by the implicit function theorem (:mod:`anm_torchrl.grid.implicit`). The projections onto the
capability polygons and the storage sets differentiate through their active constraints (as torch ops do: the
gradient of the clamp/min that is binding); the SoC update and its clipping likewise. Non-converged rows carry no
gradient (zero) and the terminal reward.
"""

from __future__ import annotations

import functools

import torch

from anm_torchrl.grid.backends import torch as torch_backend
from anm_torchrl.grid.implicit import implicit_power_flow
from anm_torchrl.grid.powerflow import MAX_ITER, TOL
from anm_torchrl.grid.transition import Transition


def transition(sim, soc: torch.Tensor, p_load: torch.Tensor, p_pot: torch.Tensor, setpoints: torch.Tensor,
               tol: float = TOL, max_iter: int = MAX_ITER, solver=None) -> Transition:
    """Differentiable :meth:`~anm_torchrl.grid.simulator.GridSimulator.apply` (p.u.): ``soc`` (N, n_des) p.u.·h,
    raw ``p_load`` (N, n_load), raw ``p_pot`` (N, n_gen), ``setpoints`` (N, action_dim), all float64.

    Every output of the :class:`Transition` is differentiable (``converged``/``n_iter`` excepted); the Newton
    tolerance ``tol`` (p.u.) sets the forward (the default is the simulator's); ``solver`` runs its Newton–Raphson
    (:func:`~anm_torchrl.grid.implicit.implicit_power_flow`'s: None = torch ops)."""
    pf = functools.partial(implicit_power_flow, tol=tol, max_iter=max_iter, solver=solver)
    return torch_backend.transition(sim, soc, p_load, p_pot, setpoints, power_flow=pf)


def step(sim, state: torch.Tensor, action: torch.Tensor, tol: float = TOL, max_iter: int = MAX_ITER, solver=None
         ) -> tuple[torch.Tensor, Transition]:
    """Differentiable :meth:`~anm_torchrl.grid.simulator.GridSimulator.step`: ``state`` (N, state_dim)
    MW/MVAr/MWh/aux, ``action`` (N, action_dim) MW/MVAr → next state (N, state_dim) (zeros, without gradient,
    on terminal rows) and the :class:`Transition`. The gradient w.r.t. ``state`` flows through its SoC only (the
    exogenous variables of the next step come from :meth:`~anm_torchrl.grid.simulator.GridSimulator.next_vars`)."""
    b = sim.net.base_mva
    p_load, p_pot, aux = sim.next_vars(state.detach())
    soc = state[:, sim.state_slices()["des_soc"]] / b
    tr = transition(sim, soc, p_load / b, p_pot / b, action / b, tol, max_iter, solver)
    return torch_backend.TorchBackend().build_state(tr, aux, b), tr
