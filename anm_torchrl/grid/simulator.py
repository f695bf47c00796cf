"""gym-anm's transition on any network as batched float64 maths, numbered as in gym-anm (spec §3.5), and resets.

State vectors are in gym-anm's order and units (MW, MVAr, MWh, auxiliary variable; spec §3.1); actions in
MW/MVAr (spec §3.2). Internally everything is p.u. on ``base_mva``. Two backends compute the same transition:
batched torch ops here (any device, differentiable) and a compiled numba loop (:mod:`anm_torchrl.grid.kernel`)
fed with one :class:`~anm_torchrl.grid.constants.TransitionConstants`. No TorchRL here: :mod:`anm_torchrl.envs`
wraps it.
"""

from __future__ import annotations

import dataclasses

from collections.abc import Callable

import numpy as np
import torch

from anm_torchrl.grid import devices as dv
from anm_torchrl.grid import fastchecks, fastoutput
from anm_torchrl.grid.constants import TransitionConstants, build_constants, content_key
from anm_torchrl.grid.network import CLASSICAL_GEN, LOAD, RENEWABLE, SLACK, STORAGE, Network, branch_flows
from anm_torchrl.grid.powerflow import newton_raphson
from anm_torchrl.grid.residuals import power_injection
from anm_torchrl.grid.reward import clipped_reward, curtailment, energy_loss, penalty, terminal_reward
from anm_torchrl.grid.state import check_state, state_sizes, state_slices


def _stack(parts: list[torch.Tensor], empty: torch.Tensor) -> torch.Tensor:
    """``torch.stack(parts, 1)``, or ``empty`` (the (N, 0, ...) result) for a network without such devices."""
    return torch.stack(parts, 1) if parts else empty


@dataclasses.dataclass
class Transition:
    """Everything one batched transition computes (p.u. unless noted); N = batch size.

    Attributes:
        p_dev, q_dev: (N, n_dev) applied injections, slack from the power flow (+inf if NaN).
        soc: (N, n_des) p.u.·h after the update.  p_pot: (N, n_gen) clipped potentials of the non-slack
            generators (classical and renewable).
        v: (N, n_bus) complex voltages.  s_apparent_max: (N, n_branch) signed flows.
        converged: (N,) bool.  n_iter: (N,) long.
        e_loss: (N,) p.u.·h.  penalty: (N,) λΦ.  curtailment: (N,) p.u.  reward: (N,) with terminal reward.
    """

    p_dev: torch.Tensor
    q_dev: torch.Tensor
    soc: torch.Tensor
    p_pot: torch.Tensor
    v: torch.Tensor
    s_apparent_max: torch.Tensor
    converged: torch.Tensor
    n_iter: torch.Tensor
    e_loss: torch.Tensor
    penalty: torch.Tensor
    curtailment: torch.Tensor
    reward: torch.Tensor


class GridSimulator:
    """Batched transition model of a gym-anm environment (float64) on any valid network.

    Exogenous variables follow gym-anm's ``next_vars``: by default (the ANM6-Easy convention) the auxiliary
    variable is a time index t and a step reads column (t + 1) mod T of the series; ``next_vars_hook`` replaces
    that rule (see :meth:`next_vars`).

    Args:
        net: the network (bus 0 the slack; build it from validated tables).
        load_series: (n_load, T) load P (MW) per time index, loads in ascending device id.
        p_max_series: (n_gen, T) raw potentials (MW) of the non-slack generators (classical and renewable, in
            device-id order); clipped to [PMIN, PMAX] when used.
        gamma, lamb, costs_clipping: reward constants.
        linear_solver: the numba kernel's Newton step: ``"dense"`` LU, ``"band"`` (RCM-ordered banded LU, for
            large feeders) or ``"auto"`` (:func:`anm_torchrl.grid.constants.jacobian_ordering`).
        backend: ``"torch"`` (batched tensor ops, any device), ``"numba"`` (one compiled loop over the batch,
            float64 CPU only, several times faster; :mod:`anm_torchrl.grid.kernel`) or ``"auto"`` (numba when
            it is installed and the network is on the CPU). Both give the same transitions to round-off.
    """

    def __init__(self, net: Network, load_series: torch.Tensor, p_max_series: torch.Tensor, gamma: float,
                 lamb: float, costs_clipping: tuple[float, float], backend: str = "auto",
                 next_vars_hook: Callable | None = None, linear_solver: str = "auto"):
        self.net = net
        self.linear_solver = linear_solver
        kind = net.dev_type.tolist()
        self.slack_ids = [i for i, k in enumerate(kind) if k == SLACK]
        self.load_ids = [i for i, k in enumerate(kind) if k == LOAD]
        self.gen_ids = [i for i, k in enumerate(kind) if k in (CLASSICAL_GEN, RENEWABLE)]
        self.des_ids = [i for i, k in enumerate(kind) if k == STORAGE]
        if len(self.slack_ids) != 1 or net.dev_bus[self.slack_ids[0]] != 0:
            raise ValueError("exactly one slack device, at bus 0, is required")
        if tuple(load_series.shape[:1]) != (len(self.load_ids),) or tuple(p_max_series.shape[:1]) != (self.n_gen,):
            raise ValueError(f"load_series must be ({len(self.load_ids)}, T) and p_max_series ({self.n_gen}, T), "
                             f"got {tuple(load_series.shape)} and {tuple(p_max_series.shape)}")
        # 1.0 for renewable generators: only their curtailment counts in ΔE (gym-anm's RenewableGen)
        self.renewable = torch.tensor([float(kind[i] == RENEWABLE) for i in self.gen_ids], dtype=net.dev.dtype,
                                      device=net.dev.device)
        self.next_vars_hook = next_vars_hook
        self.gamma, self.lamb, self.costs_clipping = gamma, lamb, costs_clipping
        self.load_series = load_series.to(net.dev) / net.base_mva
        self.p_max_series = p_max_series.to(net.dev) / net.base_mva
        self.n_time = self.load_series.shape[1]
        if self.n_time < 1 or self.p_max_series.shape[1] != self.n_time:
            raise ValueError(f"series need the same T >= 1 columns, got {self.n_time} and {self.p_max_series.shape[1]}")
        self.gen_g, self.gen_h0 = dv.generator_polygon(net, self.gen_ids)
        polys = [dv.storage_polygon(net, d) for d in self.des_ids]
        kw = dict(dtype=net.dev.dtype, device=net.dev.device)
        self.des_g = torch.stack([p[0] for p in polys]) if polys else torch.zeros(0, dv.DES_ROWS, 2, **kw)
        self.des_h0 = torch.stack([p[1] for p in polys]) if polys else torch.zeros(0, dv.DES_ROWS, **kw)
        self._gen_poly = [dv.Polygon(g) for g in self.gen_g]
        self._des_poly = [dv.Polygon(g) for g in self.des_g] if polys else []
        gid, did, lid = (torch.tensor(ix, dtype=torch.long, device=net.dev.device)
                         for ix in (self.gen_ids, self.des_ids, self.load_ids))
        self._gid, self._did, self._lid = gid, did, lid
        self.counted = (net.dev_type != STORAGE).to(net.dev.dtype)  # ΔE counts gens, slack and loads
        self.terminal_reward = terminal_reward(gamma, costs_clipping)
        self.backend = self._pick_backend(backend)
        self._rows_src, self._rows_key, self._rows = None, None, None  # see _series_rows
        # check_state's compiled one-pass path (CPU): SoC columns and bounds (MWh), aux column
        d, sl = net.dev[self._did], self.state_slices()
        self._soc_cols = sl["des_soc"]
        self._fast_state = None if net.dev.device.type != "cpu" else (
            sl["des_soc"].start, *(np.ascontiguousarray((x * net.base_mva).numpy()) for x in
                                   (d[:, dv.SOC_MIN], d[:, dv.SOC_MAX])), sl["aux"].start)
        self._kernel = None
        self._constants: TransitionConstants | None = None

    @property
    def constants(self) -> TransitionConstants:
        """The network tables as one :class:`TransitionConstants` (built on first use)."""
        if self._constants is None:
            self._constants = build_constants(self, self.linear_solver)
        return self._constants

    def _pick_backend(self, backend: str) -> str:
        from anm_torchrl.grid import kernel

        if backend not in ("auto", "torch", "numba"):
            raise ValueError(f"backend must be 'auto', 'torch' or 'numba', got {backend!r}")
        cpu64 = self.net.dev.device.type == "cpu" and self.net.dev.dtype == torch.float64
        if backend == "numba" and not (kernel.available() and cpu64):
            raise ValueError("backend='numba' needs numba installed and a float64 network on the CPU "
                             f"(numba {'found' if kernel.available() else 'missing'}, "
                             f"network on {self.net.dev.device})")
        if backend == "auto":
            return "numba" if kernel.available() and cpu64 else "torch"
        return backend

    # ----------------------------------------------------------------------------------------------- layout
    @classmethod
    def from_tables(cls, network: dict, load_p, gen_p_max, delta_t: float, gamma: float, lamb: float,
                    costs_clipping: tuple[float, float], device=None, backend: str = "auto",
                    next_vars_hook: Callable | None = None, linear_solver: str = "auto") -> "GridSimulator":
        """A simulator from a validated network dict (:func:`anm_torchrl.networks.validation.validate_network`)
        and profiles ``load_p`` (T, n_load), ``gen_p_max`` (T, n_gen) MW in device-id order."""
        from anm_torchrl.grid.network import make_network

        net = make_network(network["bus"], network["branch"], network["device"], float(network["baseMVA"]),
                           float(delta_t), device=device)
        as_t = lambda x: torch.as_tensor(x, dtype=torch.float64, device=device).T  # noqa: E731  (T, n) -> (n, T)
        return cls(net, as_t(load_p), as_t(gen_p_max), gamma=gamma, lamb=lamb, costs_clipping=costs_clipping,
                   backend=backend, next_vars_hook=next_vars_hook, linear_solver=linear_solver)

    @property
    def n_load(self) -> int:
        return len(self.load_ids)

    @property
    def n_gen(self) -> int:
        return len(self.gen_ids)

    @property
    def n_des(self) -> int:
        return len(self.des_ids)

    @property
    def state_dim(self) -> int:
        return 2 * self.net.n_dev + self.n_des + self.n_gen + 1

    @property
    def action_dim(self) -> int:
        return 2 * self.n_gen + 2 * self.n_des

    @property
    def state_sizes(self) -> dict[str, int]:
        """Width of each ``GridState`` block (:mod:`anm_torchrl.grid.state`)."""
        return state_sizes(self.net.n_dev, self.n_des, self.n_gen)

    def state_slices(self) -> dict[str, slice]:
        """gym-anm ``STATE_VARIABLES`` blocks of the state vector."""
        return state_slices(self.state_sizes)

    def check_state(self, state: torch.Tensor) -> None:
        """Raise ``ValueError`` (env index, entry) on a state no transition can start from
        (:func:`anm_torchrl.grid.state.check_state`; the time-index check applies without a ``next_vars_hook``)."""
        n_time = None if self.next_vars_hook is not None else self.n_time
        if self._fast_state is not None and state.ndim == 2 and state.shape[1] == self.state_dim \
                and state.dtype == torch.float64 and fastchecks.usable(state):
            if fastchecks.state_ok(state, *self._fast_state, n_time):
                return  # valid; otherwise the torch check below names what is wrong
        d, b = self.net.dev[self._did], self.net.base_mva
        check_state(state, self.state_sizes, d[:, dv.SOC_MIN] * b, d[:, dv.SOC_MAX] * b, n_time)

    def content_key(self) -> str:
        """sha256 of everything that defines this simulator's transitions: network tables, profiles, Δt, γ, λ,
        costs clipping. Models built for one network compare it to refuse another."""
        net, br = self.net, self.net.branches
        return content_key(net.dev, net.y_bus, net.v_min, net.v_max, br.f_bus, br.t_bus, br.y_series, br.y_shunt,
                           br.tap, br.rate, self.load_series, self.p_max_series,
                           [net.base_mva, net.delta_t, self.gamma, self.lamb, *self.costs_clipping])

    def state_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Observation bounds (state_dim,) in MW/MVAr/MWh (spec §3.1)."""
        dev, b = self.net.dev, self.net.base_mva
        qmax, qmin = dev[:, dv.QMAX].clone(), dev[:, dv.QMIN].clone()
        qp = dev[:, 3]
        is_load = self.net.dev_type == LOAD
        qmax[is_load], qmin[is_load] = (qp * dev[:, dv.PMAX])[is_load], (qp * dev[:, dv.PMIN])[is_load]
        des = dev[self._did]
        low = torch.cat([dev[:, dv.PMIN], qmin, des[:, dv.SOC_MIN], dev[self._gid, dv.PMIN], dev.new_zeros(1)])
        high = torch.cat([dev[:, dv.PMAX], qmax, des[:, dv.SOC_MAX], dev[self._gid, dv.QMAX],
                          dev.new_full((1,), self.n_time - 1)])
        scale = torch.cat([torch.full((2 * self.net.n_dev + self.n_des + self.n_gen,), b, dtype=dev.dtype,
                                      device=dev.device), dev.new_ones(1)])
        return low * scale, high * scale

    def action_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Action box (action_dim,) in MW/MVAr (spec §3.2)."""
        dev, b = self.net.dev, self.net.base_mva
        g, d = dev[self._gid], dev[self._did]
        low = torch.cat([g[:, dv.PMIN], g[:, dv.QMIN], d[:, dv.PMIN], d[:, dv.QMIN]])
        high = torch.cat([g[:, dv.PMAX], g[:, dv.QMAX], d[:, dv.PMAX], d[:, dv.QMAX]])
        return low * b, high * b

    # ------------------------------------------------------------------------------------------- physics
    def loads_at(self, t_index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Load (P, Q) (N, n_load) p.u. at time indices ``t_index`` (N,): P clipped to [PMIN, PMAX]."""
        return self.load_pq(self.load_series[:, t_index].T)

    def load_pq(self, p_load: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Load (P, Q) (N, n_load) p.u. from raw load P (N, n_load) p.u.: clipped to [PMIN, PMAX], Q = (Q/P)·P."""
        dev = self.net.dev[self._lid]
        p = torch.clamp(p_load, dev[:, dv.PMIN], dev[:, dv.PMAX])
        return p, p * dev[:, 3]

    def p_pot_at(self, t_index: torch.Tensor) -> torch.Tensor:
        """Clipped generator potentials (N, n_gen) p.u. at time indices ``t_index`` (N,)."""
        return self.clip_p_pot(self.p_max_series[:, t_index].T)

    def clip_p_pot(self, p_pot: torch.Tensor) -> torch.Tensor:
        """Potentials (N, n_gen) p.u. clipped to each generator's [PMIN, PMAX] (gym-anm's ``p_pot`` setter)."""
        dev = self.net.dev[self._gid]
        return torch.clamp(p_pot, dev[:, dv.PMIN], dev[:, dv.PMAX])

    def next_vars(self, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """gym-anm's ``next_vars`` for a batch: the exogenous variables of the step leaving ``state``.

        Default (ANM6-Easy convention): t' = (t + 1) mod T from the state's time index, load P and raw
        potentials from column t' of the series. With ``next_vars_hook`` set, returns ``hook(state)``.

        Args:
            state: (N, state_dim) MW/MVAr/MWh/aux.

        Returns:
            load P (N, n_load) MW, raw generator potentials (N, n_gen) MW, aux (N, 1) of the next state.
        """
        if self.next_vars_hook is not None:
            p_load, p_pot, aux = self.next_vars_hook(state)
            n = state.shape[0]
            for name, x, k in (("load P", p_load, self.n_load), ("potentials", p_pot, self.n_gen), ("aux", aux, 1)):
                if tuple(x.shape) != (n, k):
                    raise ValueError(f"next_vars_hook must return {name} of shape ({n}, {k}), got {tuple(x.shape)}")
            return p_load.to(state), p_pot.to(state), aux.to(state)
        t = self._next_index(state)
        b = self.net.base_mva
        return self.load_series[:, t].T * b, self.p_max_series[:, t].T * b, t.unsqueeze(1).to(state)

    def project_generators(self, target: torch.Tensor, p_pot: torch.Tensor) -> torch.Tensor:
        """Feasible (P, Q) (N, n_gen, 2) p.u. for set-points ``target`` (N, n_gen, 2) and ``p_pot`` (N, n_gen)."""
        h = self.generator_h(p_pot)
        return _stack([poly.project(target[:, k], h[:, k]) for k, poly in enumerate(self._gen_poly)], target)

    def generator_h(self, p_pot: torch.Tensor) -> torch.Tensor:
        """Generator right-hand sides (N, n_gen, 7) for ``p_pot`` (N, n_gen) p.u."""
        return dv.generator_h(self.gen_h0, p_pot)

    def storage_h(self, soc: torch.Tensor) -> torch.Tensor:
        """Storage right-hand sides (N, n_des, 10) for ``soc`` (N, n_des) p.u.·h."""
        return _stack([dv.storage_h(self.net, d, self.des_h0[k], soc[:, k]) for k, d in enumerate(self.des_ids)],
                      soc.new_zeros(soc.shape[0], 0, dv.DES_ROWS))

    def project_storage(self, target: torch.Tensor, soc: torch.Tensor) -> torch.Tensor:
        """Feasible (P, Q) (N, n_des, 2) p.u. for set-points (N, n_des, 2) and SoC (N, n_des) p.u.·h."""
        h = self.storage_h(soc)
        return _stack([poly.project(target[:, k], h[:, k]) for k, poly in enumerate(self._des_poly)], target)

    def soc_update(self, soc: torch.Tensor, p_des: torch.Tensor) -> torch.Tensor:
        """SoC after applying ``p_des`` (N, n_des) p.u. for Δt; one-way efficiency both ways, then clipped."""
        d = self.net.dev[self._did]
        eff, dt = d[:, dv.EFF], self.net.delta_t
        nxt = torch.where(p_des <= 0, soc - dt * eff * p_des, soc - dt * p_des / eff)
        return torch.clamp(nxt, d[:, dv.SOC_MIN], d[:, dv.SOC_MAX])

    def transition(self, soc: torch.Tensor, t_index: torch.Tensor, setpoints: torch.Tensor) -> Transition:
        """One batched transition at time indices ``t_index`` (N,) of the series (see :meth:`apply`)."""
        return self.apply(soc, self.load_series[:, t_index].T, self.p_max_series[:, t_index].T, setpoints)

    def apply(self, soc: torch.Tensor, p_load: torch.Tensor, p_pot: torch.Tensor, setpoints: torch.Tensor
              ) -> Transition:
        """One batched transition of the simulator (spec §3.5 steps 4–7), on this simulator's backend.

        Args:
            soc: (N, n_des) state of charge before the step, p.u.·h.
            p_load: (N, n_load) raw load P p.u. (clipped to [PMIN, PMAX] here).
            p_pot: (N, n_gen) raw generator potentials p.u. (clipped to [PMIN, PMAX] here).
            setpoints: (N, action_dim) p.u., action order (P gen, Q gen, P DES, Q DES).
        """
        if self.backend == "numba":
            if self._kernel is None:
                from anm_torchrl.grid.kernel import CompiledTransition

                self._kernel = CompiledTransition(self.constants)
            return Transition(**self._kernel(soc, p_load, p_pot, setpoints))
        net, ng, nd = self.net, self.n_gen, self.n_des
        n_env = setpoints.shape[0]
        p_dev = setpoints.new_zeros(n_env, net.n_dev)
        q_dev = setpoints.new_zeros(n_env, net.n_dev)
        # 1. loads follow their exogenous P.
        p_dev[:, self._lid], q_dev[:, self._lid] = self.load_pq(p_load)
        # 2. non-slack generators: potential, then projection onto the capability polygon.
        p_pot = self.clip_p_pot(p_pot)
        gen = self.project_generators(torch.stack([setpoints[:, :ng], setpoints[:, ng:2 * ng]], -1), p_pot)
        p_dev[:, self._gid], q_dev[:, self._gid] = gen[..., 0], gen[..., 1]
        # 3. storage: SoC-dependent projection, then SoC update.
        des_target = torch.stack([setpoints[:, 2 * ng:2 * ng + nd], setpoints[:, 2 * ng + nd:]], -1)
        des = self.project_storage(des_target, soc)
        p_dev[:, self._did], q_dev[:, self._did] = des[..., 0], des[..., 1]
        soc_next = self.soc_update(soc, des[..., 0])
        return self._solve(p_dev, q_dev, p_pot, soc_next)

    def _solve(self, p_dev: torch.Tensor, q_dev: torch.Tensor, p_pot: torch.Tensor, soc: torch.Tensor) -> Transition:
        """Power flow, slack injection, branch flows and reward for device injections (N, n_dev) p.u."""
        net = self.net
        # 4. bus injections and AC power flow (the slack injection is 0 at this point).
        p_dev[:, self.slack_ids[0]] = 0.0
        q_dev[:, self.slack_ids[0]] = 0.0
        s_bus = torch.complex(p_dev @ net.incidence, q_dev @ net.incidence)
        pf = newton_raphson(net.y_bus, s_bus)
        # 5. slack injection and branch flows from the (possibly non-converged) voltages.
        s_slack = power_injection(pf.v, net.y_bus)[:, 0]
        inf = torch.full_like(s_slack.real, float("inf"))
        p_dev[:, self.slack_ids[0]] = torch.where(torch.isnan(s_slack.real), inf, s_slack.real)
        q_dev[:, self.slack_ids[0]] = torch.where(torch.isnan(s_slack.imag), inf, s_slack.imag)
        s_max = branch_flows(pf.v, net.branches)["s_apparent_max"]
        # 6. reward terms; a non-converged power flow is terminal.
        curt = curtailment(p_pot, p_dev[:, self._gid], self.renewable)
        e_loss = energy_loss(p_dev, self.counted, curt, net.delta_t)
        pen = penalty(pf.v.abs(), s_max, net, self.lamb)
        reward = clipped_reward(e_loss, pen, self.costs_clipping)
        reward = torch.where(pf.converged, reward, torch.full_like(reward, self.terminal_reward))
        return Transition(p_dev=p_dev, q_dev=q_dev, soc=soc, p_pot=p_pot, v=pf.v, s_apparent_max=s_max,
                          converged=pf.converged, n_iter=pf.n_iter, e_loss=e_loss, penalty=pen,
                          curtailment=curt, reward=reward)

    def operating_point(self, state: torch.Tensor) -> Transition:
        """Re-solve the power flow of the injections written in ``state`` (N, state_dim) MW… .

        Gives the grid quantities (voltages, flows, ΔE, λΦ) of a state that was set rather than reached by a
        transition; for a reached state they equal the transition's (up to the NR tolerance).
        """
        sl, b = self.state_slices(), self.net.base_mva
        return self._solve(state[:, sl["dev_p"]] / b, state[:, sl["dev_q"]] / b, state[:, sl["gen_p_max"]] / b,
                           state[:, sl["des_soc"]] / b)

    def with_exogenous(self, state: torch.Tensor, t_index: torch.Tensor) -> torch.Tensor:
        """A copy of ``state`` (N, state_dim) whose exogenous entries — load P and Q, renewable potentials and
        the time index — are those of the series at ``t_index`` (N,) (perfect foresight)."""
        b = self.net.base_mva
        return self.with_next_vars(state, self.load_series[:, t_index].T * b, self.p_max_series[:, t_index].T * b,
                                   t_index.unsqueeze(1).to(state))

    def with_next_vars(self, state: torch.Tensor, p_load: torch.Tensor, p_pot: torch.Tensor, aux: torch.Tensor
                       ) -> torch.Tensor:
        """A copy of ``state`` whose exogenous entries are those of :meth:`next_vars`' output (MW, aux)."""
        sl, b = self.state_slices(), self.net.base_mva
        out = state.clone()
        p, q = self.load_pq(p_load / b)
        out[:, sl["dev_p"].start + self._lid] = p * b
        out[:, sl["dev_q"].start + self._lid] = q * b
        out[:, sl["gen_p_max"]] = self.clip_p_pot(p_pot / b) * b
        out[:, sl["aux"]] = aux.to(out)
        return out

    def build_state(self, tr: Transition, aux: torch.Tensor) -> torch.Tensor:
        """State (N, state_dim) in MW/MVAr/MWh after ``tr`` and ``aux`` (N,) or (N, 1); zeros where the power flow
        did not converge."""
        b = self.net.base_mva
        if self.backend == "numba":  # one compiled pass, the same values bit for bit
            return fastoutput.build_state(tr, aux, b)
        state = torch.cat([tr.p_dev * b, tr.q_dev * b, tr.soc * b, tr.p_pot * b, aux.reshape(-1, 1).to(tr.p_dev)], 1)
        return torch.where(tr.converged.unsqueeze(1), state, torch.zeros_like(state))

    def step(self, state: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, Transition]:
        """gym-anm ``step`` for a batch: ``state`` (N, state_dim) MW…, ``action`` (N, action_dim) MW/MVAr.

        Returns the next state (zeros on terminal rows) and the :class:`Transition` (reward, convergence…).
        Only the SoC and the auxiliary variable of ``state`` matter: loads, potentials and the next auxiliary
        variable come from :meth:`next_vars`.
        """
        b = self.net.base_mva
        if self.next_vars_hook is None:
            t = self._next_index(state)
            load_pu, pot_pu = self._series_rows()
            p_load, p_pot, aux = load_pu[t], pot_pu[t], t.unsqueeze(1).to(state)
        else:
            p_load, p_pot, aux = self.next_vars(state)
            p_load, p_pot = p_load / b, p_pot / b
        tr = self.apply(state[:, self._soc_cols] / b, p_load, p_pot, action / b)
        return self.build_state(tr, aux), tr

    def _next_index(self, state: torch.Tensor) -> torch.Tensor:
        """Time index (N,) long of the step leaving ``state``: (t + 1) mod T (the default ``next_vars`` rule)."""
        return (state[:, -1].round().long() + 1) % self.n_time

    def _series_rows(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The series as (T, n_load) and (T, n_gen) p.u. rows, holding exactly what :meth:`next_vars` (MW) then
        ``/ base_mva`` give (bit for bit), so that :meth:`step` gathers contiguous rows instead. Recomputed when
        a series is replaced or modified in place (experiments rescale them)."""
        src = (self.load_series, self.p_max_series)
        key = tuple(x._version for x in src)
        if self._rows_src is None or any(a is not c for a, c in zip(src, self._rows_src)) or self._rows_key != key:
            b = self.net.base_mva
            self._rows = tuple((x * b / b).T.contiguous() for x in src)
            self._rows_src, self._rows_key = src, key  # holding the tensors: their ids cannot be reused
        return self._rows

    # --------------------------------------------------------------------------------------------- reset
    def sample_initial(self, n: int, generator: torch.Generator | None = None,
                       intended: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Draw ANM6-Easy initial conditions (spec §5.2).

        gym-anm's distribution (``intended=False``) keeps its unit bugs: generator Q uniform in
        ±QMAX/base_mva MVAr (±0.3 / ±0.5) and SoC uniform in [SOC_MIN, SOC_MAX)/base_mva MWh ([0, 1)).
        ``intended=True`` draws Q in [QMIN, QMAX] MVAr and SoC in [SOC_MIN, SOC_MAX) MWh instead.

        Returns ``t0`` (n,) long, generator Q (n, n_gen) MVAr and SoC (n, n_des) MWh.
        """
        dev, b = self.net.dev, self.net.base_mva
        kw = dict(generator=generator, dtype=dev.dtype, device=dev.device)
        t0 = torch.randint(0, self.n_time, (n,), generator=generator, device=dev.device)
        g, d = dev[self._gid], dev[self._did]
        unit = b if intended else 1.0  # gym-anm uses the p.u. bounds as MVAr / MWh
        q = g[:, dv.QMIN] * unit + torch.rand(n, self.n_gen, **kw) * (g[:, dv.QMAX] - g[:, dv.QMIN]) * unit
        soc = d[:, dv.SOC_MIN] * unit + torch.rand(n, self.n_des, **kw) * (d[:, dv.SOC_MAX] - d[:, dv.SOC_MIN]) * unit
        return t0, q, soc

    def initial_state(self, t0: torch.Tensor, q_gen: torch.Tensor, soc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """gym-anm ``Simulator.reset``: the state reached from initial conditions (spec §5.3).

        Generators are set to their raw potential P and ``q_gen`` (MVAr), storage to (0, 0) with SoC at
        SOC_MIN, one transition at time ``t0`` is solved, then the SoC is overwritten with ``soc`` (MWh).

        Returns the state (n, state_dim) and the :class:`Transition` of that initial power flow.
        """
        b = self.net.base_mva
        setpoints = torch.cat([self.p_max_series[:, t0].T, q_gen / b, soc.new_zeros(soc.shape[0], 2 * self.n_des)], 1)
        soc_min = self.net.dev[self._did, dv.SOC_MIN].expand_as(soc)
        tr = self.transition(soc_min, t0, setpoints)
        tr.soc = soc / b
        return self.build_state(tr, t0), tr

    def reset_from_states(self, state: torch.Tensor) -> Transition:
        """gym-anm's ``Simulator.reset(init_state)`` for a batch of states (N, state_dim) MW….

        Loads take the state's P (clipped), generators project the state's (P, Q) under the state's potentials,
        storage projects its (P, Q) with the SoC at SOC_MIN (P <= 0) or SOC_MAX (P > 0), the power flow is
        solved; then the SoC is the state's. Returns that :class:`Transition` (``build_state`` with the state's
        aux gives gym-anm's reconstructed initial state).
        """
        sl, b = self.state_slices(), self.net.base_mva
        p, q = state[:, sl["dev_p"]] / b, state[:, sl["dev_q"]] / b
        d = self.net.dev[self._did]
        p_des = p[:, self._did]
        soc0 = torch.where(p_des <= 0, d[:, dv.SOC_MIN], d[:, dv.SOC_MAX])
        setpoints = torch.cat([p[:, self._gid], q[:, self._gid], p_des, q[:, self._did]], 1)
        tr = self.apply(soc0, p[:, self._lid], state[:, sl["gen_p_max"]] / b, setpoints)
        tr.soc = state[:, sl["des_soc"]] / b
        return tr

    def reset_with(self, init, n: int, generator: torch.Generator | None = None, max_attempts: int = 100
                   ) -> tuple[torch.Tensor, Transition]:
        """``n`` initial states from a user sampler ``init(n, generator) -> (n, state_dim)`` MW…, each passed
        through :meth:`reset_from_states`; rows whose power flow fails are re-drawn (gym-anm: 100 attempts)."""

        def draw(k: int) -> tuple[torch.Tensor, Transition]:
            s = torch.as_tensor(init(k, generator), dtype=self.net.dev.dtype, device=self.net.dev.device)
            if tuple(s.shape) != (k, self.state_dim):
                raise ValueError(f"init must return a ({k}, {self.state_dim}) state batch, got {tuple(s.shape)}")
            tr = self.reset_from_states(s)
            return self.build_state(tr, s[:, self.state_slices()["aux"]]), tr

        return self._resample(draw, n, max_attempts)

    def reset(self, n: int, generator: torch.Generator | None = None, intended: bool = False,
              max_attempts: int = 100) -> tuple[torch.Tensor, Transition]:
        """Sample ``n`` gym-anm initial states (n, state_dim) and their initial transitions.

        Rows whose initial power flow fails are re-drawn, at most ``max_attempts`` times (as gym-anm).
        """
        return self._resample(lambda k: self.initial_state(*self.sample_initial(k, generator, intended)), n,
                              max_attempts)

    def random_state(self, n: int, generator: torch.Generator | None = None,
                     max_attempts: int = 100) -> tuple[torch.Tensor, Transition]:
        """States spread over the whole reachable state space, (n, state_dim), with their transitions.

        The free variables are drawn uniformly — time index in [0, T), SoC in [SOC_MIN, SOC_MAX), set-points
        over the action box — and everything else follows from one transition at that time index (projection,
        SoC update, power flow). Non-converging draws are re-drawn.
        """
        dev, b = self.net.dev, self.net.base_mva
        a_low, a_high = self.action_bounds()
        if not (torch.isfinite(a_low).all() and torch.isfinite(a_high).all()):
            raise ValueError(f"random_state draws set-points over the action box, which must be finite; got low "
                             f"{a_low.tolist()}, high {a_high.tolist()} (give PMAX/QMAX/QMIN or use a reset hook)")
        d = dev[self._did]
        kw = dict(generator=generator, dtype=dev.dtype, device=dev.device)

        def draw(k: int) -> tuple[torch.Tensor, Transition]:
            t = torch.randint(0, self.n_time, (k,), generator=generator, device=dev.device)
            soc = d[:, dv.SOC_MIN] + torch.rand(k, self.n_des, **kw) * (d[:, dv.SOC_MAX] - d[:, dv.SOC_MIN])
            a = a_low + torch.rand(k, self.action_dim, **kw) * (a_high - a_low)
            tr = self.transition(soc, t, a / b)
            return self.build_state(tr, t), tr

        return self._resample(draw, n, max_attempts)

    @staticmethod
    def _resample(draw, n: int, max_attempts: int) -> tuple[torch.Tensor, Transition]:
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


def anm6_easy_simulator(device=None, backend: str = "auto") -> GridSimulator:
    """The ANM6-Easy simulator of gym-anm 2.0.1 on ``device`` (``backend``: see :class:`GridSimulator`).

    Kept here for its many importers; the data lives in :mod:`anm_torchrl.networks.anm6_easy`.
    """
    from anm_torchrl.networks import anm6_easy

    return anm6_easy.simulator(device=device, backend=backend)
