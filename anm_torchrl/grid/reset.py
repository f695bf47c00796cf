"""The reset samplers of a :class:`~anm_torchrl.grid.simulator.GridSimulator`, as functions of the simulator.

Each returns states (n, state_dim) in MW/MVAr/MWh/aux and their :class:`~anm_torchrl.grid.transition.Transition`;
rows whose power flow fails are re-drawn (:func:`resample`, gym-anm's 100 attempts).

- :func:`random_state`: uniform over the reachable state space (``ANMEnv``'s default ``init="uniform"``).
- :func:`gym_anm_reset`: ANM6-Easy's ``init_state`` distribution (:func:`sample_initial`, :func:`initial_state`).
- :func:`reset_with`: a user's ``init(n, generator)``, each state passed through :func:`reset_from_states`
  (gym-anm's ``Simulator.reset(init_state)``).
"""

from __future__ import annotations

import dataclasses

from typing import TYPE_CHECKING

import torch

from anm_torchrl.grid import devices as dv
from anm_torchrl.grid.transition import Transition

if TYPE_CHECKING:
    from anm_torchrl.grid.simulator import GridSimulator


def sample_initial(sim: GridSimulator, n: int, generator: torch.Generator | None = None,
                   intended: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Draw ANM6-Easy initial conditions (spec §5.2).

    gym-anm's distribution (``intended=False``) keeps its unit bugs: generator Q uniform in
    ±QMAX/base_mva MVAr (±0.3 / ±0.5) and SoC uniform in [SOC_MIN, SOC_MAX)/base_mva MWh ([0, 1)).
    ``intended=True`` draws Q in [QMIN, QMAX] MVAr and SoC in [SOC_MIN, SOC_MAX) MWh instead.

    Returns ``t0`` (n,) long, generator Q (n, n_gen) MVAr and SoC (n, n_des) MWh.
    """
    dev, b = sim.net.dev, sim.net.base_mva
    kw = dict(generator=generator, dtype=dev.dtype, device=dev.device)
    t0 = torch.randint(0, sim.n_time, (n,), generator=generator, device=dev.device)
    g, d = dev[sim.gen_idx], dev[sim.des_idx]
    unit = b if intended else 1.0  # gym-anm uses the p.u. bounds as MVAr / MWh
    q = g[:, dv.QMIN] * unit + torch.rand(n, sim.n_gen, **kw) * (g[:, dv.QMAX] - g[:, dv.QMIN]) * unit
    soc = d[:, dv.SOC_MIN] * unit + torch.rand(n, sim.n_des, **kw) * (d[:, dv.SOC_MAX] - d[:, dv.SOC_MIN]) * unit
    return t0, q, soc


def initial_state(sim: GridSimulator, t0: torch.Tensor, q_gen: torch.Tensor, soc: torch.Tensor
                  ) -> tuple[torch.Tensor, Transition]:
    """gym-anm ``Simulator.reset``: the state reached from initial conditions (spec §5.3).

    Generators are set to their raw potential P and ``q_gen`` (MVAr), storage to (0, 0) with SoC at
    SOC_MIN, one transition at time ``t0`` is solved, then the SoC is overwritten with ``soc`` (MWh).

    Returns the state (n, state_dim) and the :class:`Transition` of that initial power flow.
    """
    b = sim.net.base_mva
    setpoints = torch.cat([sim.p_max_series[:, t0].T, q_gen / b, soc.new_zeros(soc.shape[0], 2 * sim.n_des)], 1)
    soc_min = sim.net.dev[sim.des_idx, dv.SOC_MIN].expand_as(soc)
    tr = sim.transition(soc_min, t0, setpoints)
    tr.soc = soc / b
    return sim.build_state(tr, t0), tr


def reset_from_states(sim: GridSimulator, state: torch.Tensor) -> Transition:
    """gym-anm's ``Simulator.reset(init_state)`` for a batch of states (N, state_dim) MW….

    Loads take the state's P (clipped), generators project the state's (P, Q) under the state's potentials,
    storage projects its (P, Q) with the SoC at SOC_MIN (P <= 0) or SOC_MAX (P > 0), the power flow is
    solved; then the SoC is the state's. Returns that :class:`Transition` (``build_state`` with the state's
    aux gives gym-anm's reconstructed initial state).
    """
    sl, b = sim.state_slices(), sim.net.base_mva
    p, q = state[:, sl["dev_p"]] / b, state[:, sl["dev_q"]] / b
    d = sim.net.dev[sim.des_idx]
    p_des = p[:, sim.des_idx]
    soc0 = torch.where(p_des <= 0, d[:, dv.SOC_MIN], d[:, dv.SOC_MAX])
    setpoints = torch.cat([p[:, sim.gen_idx], q[:, sim.gen_idx], p_des, q[:, sim.des_idx]], 1)
    tr = sim.apply(soc0, p[:, sim.load_idx], state[:, sl["gen_p_max"]] / b, setpoints)
    tr.soc = state[:, sl["des_soc"]] / b
    return tr


def reset_with(sim: GridSimulator, init, n: int, generator: torch.Generator | None = None, max_attempts: int = 100
               ) -> tuple[torch.Tensor, Transition]:
    """``n`` initial states from a user sampler ``init(n, generator) -> (n, state_dim)`` MW…, each passed
    through :func:`reset_from_states`; rows whose power flow fails are re-drawn (gym-anm: 100 attempts).

    Raises:
        ValueError: the sampler returned a batch of the wrong shape, or a state the state validator
            (:meth:`GridSimulator.check_state`: finite entries, SoC within its bounds, time index) refuses;
            the message names the ``init`` sampler.
    """

    def draw(k: int) -> tuple[torch.Tensor, Transition]:
        s = torch.as_tensor(init(k, generator), dtype=sim.net.dev.dtype, device=sim.net.dev.device)
        if tuple(s.shape) != (k, sim.state_dim):
            raise ValueError(f"init must return a ({k}, {sim.state_dim}) state batch, got {tuple(s.shape)}")
        try:
            sim.check_state(s)
        except ValueError as err:
            raise ValueError(f"the init= reset sampler {getattr(init, '__name__', init)!r} returned an invalid "
                             f"state: {err}") from None
        tr = reset_from_states(sim, s)
        return sim.build_state(tr, s[:, sim.state_slices()["aux"]]), tr

    return resample(draw, n, max_attempts)


def gym_anm_reset(sim: GridSimulator, n: int, generator: torch.Generator | None = None, intended: bool = False,
                  max_attempts: int = 100) -> tuple[torch.Tensor, Transition]:
    """Sample ``n`` gym-anm initial states (n, state_dim) and their initial transitions.

    Rows whose initial power flow fails are re-drawn, at most ``max_attempts`` times (as gym-anm).
    """
    return resample(lambda k: initial_state(sim, *sample_initial(sim, k, generator, intended)), n, max_attempts)


def random_state(sim: GridSimulator, n: int, generator: torch.Generator | None = None,
                 max_attempts: int = 100) -> tuple[torch.Tensor, Transition]:
    """States spread over the whole reachable state space, (n, state_dim), with their transitions.

    The free variables are drawn uniformly — time index in [0, T), SoC in [SOC_MIN, SOC_MAX), set-points
    over the action box — and everything else follows from one transition at that time index (projection,
    SoC update, power flow). Non-converging draws are re-drawn.
    """
    def draw(k: int) -> tuple[torch.Tensor, Transition]:
        t, soc, setpoints = free_variables(sim, k, generator)
        tr = sim.transition(soc, t, setpoints)
        return sim.build_state(tr, t), tr

    return resample(draw, n, max_attempts)


def free_variables(sim: GridSimulator, n: int, generator: torch.Generator | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The free variables of :func:`random_state`'s draw: time index (n,) uniform in [0, T), SoC (n, n_des) p.u.·h
    uniform in [SOC_MIN, SOC_MAX), set-points (n, action_dim) p.u. uniform over the action box (which must be
    finite: ``ValueError`` otherwise)."""
    dev, b = sim.net.dev, sim.net.base_mva
    a_low, a_high = sim.action_bounds()
    if not (torch.isfinite(a_low).all() and torch.isfinite(a_high).all()):
        raise ValueError(f"random_state draws set-points over the action box, which must be finite; got low "
                         f"{a_low.tolist()}, high {a_high.tolist()} (give PMAX/QMAX/QMIN or use a reset hook)")
    d = dev[sim.des_idx]
    kw = dict(generator=generator, dtype=dev.dtype, device=dev.device)
    t = torch.randint(0, sim.n_time, (n,), generator=generator, device=dev.device)
    soc = d[:, dv.SOC_MIN] + torch.rand(n, sim.n_des, **kw) * (d[:, dv.SOC_MAX] - d[:, dv.SOC_MIN])
    a = a_low + torch.rand(n, sim.action_dim, **kw) * (a_high - a_low)
    return t, soc, a / b


def resample(draw, n: int, max_attempts: int) -> tuple[torch.Tensor, Transition]:
    """``draw(n) -> (state, Transition)``, with the rows whose power flow did not converge re-drawn, at most
    ``max_attempts`` draws in all. Raises ``RuntimeError`` when some rows still fail."""
    state, tr = draw(n)
    for _ in range(max_attempts - 1):
        todo = (~tr.converged).nonzero().squeeze(1)
        if todo.numel() == 0:
            return state, tr
        s_new, tr_new = draw(todo.numel())
        state = state.index_copy(0, todo, s_new)
        tr = Transition(**{f.name: getattr(tr, f.name).index_copy(0, todo, getattr(tr_new, f.name))
                           for f in dataclasses.fields(Transition)})
    if not tr.converged.all():
        raise RuntimeError(f"{int((~tr.converged).sum())} sampled states did not converge after "
                           f"{max_attempts} attempts")
    return state, tr
