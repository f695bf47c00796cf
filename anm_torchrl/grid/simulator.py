"""gym-anm's transition on any network as batched float64 maths, numbered as in gym-anm (spec §3.5), and resets.

State vectors are in gym-anm's order and units (MW, MVAr, MWh, auxiliary variable; spec §3.1); actions in
MW/MVAr (spec §3.2). Internally everything is p.u. on ``base_mva``. The transition itself is computed by the
backend resolved once at construction (:mod:`anm_torchrl.grid.backends`: batched torch ops, or a compiled numba
loop fed with one :class:`~anm_torchrl.grid.constants.TransitionConstants`); the reset samplers are functions of
:mod:`anm_torchrl.grid.reset`. No TorchRL here: :mod:`anm_torchrl.envs` wraps it.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np
import torch

from anm_torchrl.grid import devices as dv
from anm_torchrl.grid import fastchecks
from anm_torchrl.grid.backends import get_backend
from anm_torchrl.grid.backends import torch as torch_backend
from anm_torchrl.grid.constants import TransitionConstants, build_constants
from anm_torchrl.grid.network import CLASSICAL_GEN, LOAD, RENEWABLE, SLACK, STORAGE, Network
from anm_torchrl.grid.reward import terminal_reward
from anm_torchrl.grid.state import _pairs, check_state, state_sizes, state_slices
from anm_torchrl.grid.transition import Transition

log = logging.getLogger(__name__)
#: MW by which a profile value must pass a device's limit to be reported as clipped (the parity tolerance: the
#: MW -> p.u. -> MW round trip of a value at its limit is not exact)
CLIP_TOL = 1e-6
_REPORTED: set[tuple[int, str]] = set()  # clipping reports logged in this process: one per level and case

__all__ = ["GridSimulator", "Transition"]


def _stack(parts: list[torch.Tensor], empty: torch.Tensor) -> torch.Tensor:
    """``torch.stack(parts, 1)``, or ``empty`` (the (N, 0, ...) result) for a network without such devices."""
    return torch.stack(parts, 1) if parts else empty


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
            float64 CPU only, several times faster) or ``"auto"`` (numba when it is installed and the network is
            on the CPU), resolved once by :func:`anm_torchrl.grid.backends.get_backend`. Both give the same
            transitions to round-off.

    Attributes (public, read by the envs, datasets and surrogates):
        load_ids, gen_ids, des_ids, slack_ids: device rows (Python lists) of the loads, non-slack generators
            (classical and renewable), storage units and the slack.
        load_idx, gen_idx, des_idx: the same rows as (n,) long tensors on the network's device.
        gen_polygons, des_polygons: the :class:`~anm_torchrl.grid.devices.Polygon` of each generator / storage
            unit.
        physics: the resolved backend (:mod:`anm_torchrl.grid.backends`); ``backend``: its name.
    """

    def __init__(self, net: Network, load_series: torch.Tensor, p_max_series: torch.Tensor, gamma: float,
                 lamb: float, costs_clipping: tuple[float, float], backend: str = "auto",
                 next_vars_hook: Callable | None = None, linear_solver: str = "auto",
                 profile_clip_level: int = logging.WARNING, profile_source: str = "the profiles"):
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
        self.gen_polygons = [dv.Polygon(g) for g in self.gen_g]
        self.des_polygons = [dv.Polygon(g) for g in self.des_g] if polys else []
        self.gen_idx, self.des_idx, self.load_idx = (torch.tensor(ix, dtype=torch.long, device=net.dev.device)
                                                     for ix in (self.gen_ids, self.des_ids, self.load_ids))
        self._clipping_reported = False
        self.report_clipping(self.load_series.T * net.base_mva, self.p_max_series.T * net.base_mva, profile_source,
                             profile_clip_level)
        self.counted = (net.dev_type != STORAGE).to(net.dev.dtype)  # ΔE counts gens, slack and loads
        self.terminal_reward = terminal_reward(gamma, costs_clipping)
        self.physics = get_backend(backend, net)
        self.backend = self.physics.name
        self._rows_src, self._rows_key, self._rows = None, None, None  # see _series_rows
        # check_state's compiled one-pass path (CPU): SoC columns and bounds (MWh), aux column
        d, sl = net.dev[self.des_idx], self.state_slices()
        self._soc_cols = sl["des_soc"]
        self._fast_state = None if net.dev.device.type != "cpu" else (
            sl["des_soc"].start, *(np.ascontiguousarray((x * net.base_mva).numpy()) for x in
                                   (d[:, dv.SOC_MIN], d[:, dv.SOC_MAX])), sl["aux"].start)
        self._transition = None  # bound on first use: the numba backend builds its constants then
        self._constants: TransitionConstants | None = None

    @property
    def constants(self) -> TransitionConstants:
        """The network tables as one :class:`TransitionConstants` (built on first use)."""
        if self._constants is None:
            self._constants = build_constants(self, self.linear_solver)
        return self._constants

    # ----------------------------------------------------------------------------------------------- layout
    @classmethod
    def from_tables(cls, network: dict, load_p, gen_p_max, delta_t: float, gamma: float, lamb: float,
                    costs_clipping: tuple[float, float], device=None, backend: str = "auto",
                    next_vars_hook: Callable | None = None, linear_solver: str = "auto",
                    profile_clip_level: int = logging.WARNING,
                    profile_source: str = "the profiles") -> "GridSimulator":
        """A simulator from a validated network dict (:func:`anm_torchrl.networks.validation.validate_network`)
        and profiles ``load_p`` (T, n_load), ``gen_p_max`` (T, n_gen) MW in device-id order; what the profiles
        hold outside the devices' limits is logged at ``profile_clip_level``, naming them ``profile_source``."""
        from anm_torchrl.grid.network import make_network

        net = make_network(network["bus"], network["branch"], network["device"], float(network["baseMVA"]),
                           float(delta_t), device=device)
        as_t = lambda x: torch.as_tensor(x, dtype=torch.float64, device=device).T  # noqa: E731  (T, n) -> (n, T)
        return cls(net, as_t(load_p), as_t(gen_p_max), gamma=gamma, lamb=lamb, costs_clipping=costs_clipping,
                   backend=backend, next_vars_hook=next_vars_hook, linear_solver=linear_solver,
                   profile_clip_level=profile_clip_level, profile_source=profile_source)

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

    def split_action(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """gym-anm's action layout ``[P_gen, Q_gen, P_des, Q_des]`` (..., action_dim) as the generators' and the
        storage units' (P, Q) targets: (..., n_gen, 2) and (..., n_des, 2), in the action's units."""
        ng, nd = self.n_gen, self.n_des
        return (torch.stack([action[..., :ng], action[..., ng:2 * ng]], -1),
                torch.stack([action[..., 2 * ng:2 * ng + nd], action[..., 2 * ng + nd:]], -1))

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
        d, b = self.net.dev[self.des_idx], self.net.base_mva
        check_state(state, self.state_sizes, d[:, dv.SOC_MIN] * b, d[:, dv.SOC_MAX] * b, n_time)

    def state_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Observation bounds (state_dim,) in MW/MVAr/MWh (spec §3.1)."""
        dev, b = self.net.dev, self.net.base_mva
        qmax, qmin = dev[:, dv.QMAX].clone(), dev[:, dv.QMIN].clone()
        qp = dev[:, 3]
        is_load = self.net.dev_type == LOAD
        qmax[is_load], qmin[is_load] = (qp * dev[:, dv.PMAX])[is_load], (qp * dev[:, dv.PMIN])[is_load]
        des = dev[self.des_idx]
        low = torch.cat([dev[:, dv.PMIN], qmin, des[:, dv.SOC_MIN], dev[self.gen_idx, dv.PMIN], dev.new_zeros(1)])
        high = torch.cat([dev[:, dv.PMAX], qmax, des[:, dv.SOC_MAX], dev[self.gen_idx, dv.QMAX],
                          dev.new_full((1,), self.n_time - 1)])
        scale = torch.cat([torch.full((2 * self.net.n_dev + self.n_des + self.n_gen,), b, dtype=dev.dtype,
                                      device=dev.device), dev.new_ones(1)])
        return low * scale, high * scale

    def action_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Action box (action_dim,) in MW/MVAr (spec §3.2)."""
        dev, b = self.net.dev, self.net.base_mva
        g, d = dev[self.gen_idx], dev[self.des_idx]
        low = torch.cat([g[:, dv.PMIN], g[:, dv.QMIN], d[:, dv.PMIN], d[:, dv.QMIN]])
        high = torch.cat([g[:, dv.PMAX], g[:, dv.QMAX], d[:, dv.PMAX], d[:, dv.QMAX]])
        return low * b, high * b

    # ------------------------------------------------------------------------------------------- physics
    def loads_at(self, t_index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Load (P, Q) (N, n_load) p.u. at time indices ``t_index`` (N,): P clipped to [PMIN, PMAX]."""
        return self.load_pq(self.load_series[:, t_index].T)

    def load_pq(self, p_load: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Load (P, Q) (N, n_load) p.u. from raw load P (N, n_load) p.u.: clipped to [PMIN, PMAX], Q = (Q/P)·P."""
        dev = self.net.dev[self.load_idx]
        p = torch.clamp(p_load, dev[:, dv.PMIN], dev[:, dv.PMAX])
        return p, p * dev[:, 3]

    def p_pot_at(self, t_index: torch.Tensor) -> torch.Tensor:
        """Clipped generator potentials (N, n_gen) p.u. at time indices ``t_index`` (N,)."""
        return self.clip_p_pot(self.p_max_series[:, t_index].T)

    def clip_p_pot(self, p_pot: torch.Tensor) -> torch.Tensor:
        """Potentials (N, n_gen) p.u. clipped to each generator's [PMIN, PMAX] (gym-anm's ``p_pot`` setter)."""
        dev = self.net.dev[self.gen_idx]
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
                bad = ~torch.isfinite(x)
                if bad.any():
                    envs, entries = bad.nonzero(as_tuple=True)
                    raise ValueError(f"the next_vars hook {getattr(self.next_vars_hook, '__name__', '')!r} returned "
                                     f"non-finite {name} at (env, entry) {_pairs(envs, entries)}: every exogenous "
                                     f"variable must be finite (a NaN would make the step terminal silently)")
            if not self._clipping_reported:
                hook = getattr(self.next_vars_hook, "__name__", "")
                self.report_clipping(p_load, p_pot, f"the next_vars hook {hook!r}")
            return p_load.to(state), p_pot.to(state), aux.to(state)
        t = self._next_index(state)
        b = self.net.base_mva
        return self.load_series[:, t].T * b, self.p_max_series[:, t].T * b, t.unsqueeze(1).to(state)

    def clipped_entries(self, p_load: torch.Tensor, p_pot: torch.Tensor) -> list[str]:
        """What the transition will clip of load P (..., n_load) and potentials (..., n_gen) MW, as gym-anm does:
        one line per device and direction (device id, how many entries, the extreme value), empty if nothing.
        One host sync when nothing is clipped (a ``next_vars`` hook's outputs are checked every step)."""
        b = self.net.base_mva
        checks = []  # (kind, x (rows, n), ids, devices, PMAX side, PMIN side)
        for name, x, ids, idx in (("load P", p_load, self.load_ids, self.load_idx),
                                  ("potential", p_pot, self.gen_ids, self.gen_idx)):
            if ids:
                dev = self.net.dev[idx]
                x = x.reshape(-1, len(ids)).to(dev)
                above, below = x > dev[:, dv.PMAX] * b + CLIP_TOL, x < dev[:, dv.PMIN] * b - CLIP_TOL
                checks.append((name, x, ids, dev, above, below))
        if not checks or not bool(torch.stack([(hi | lo).any() for *_, hi, lo in checks]).any()):
            return []
        out = []
        for name, x, ids, dev, above, below in checks:
            for bound, col, side in (("PMAX", dv.PMAX, above), ("PMIN", dv.PMIN, below)):
                for j in side.any(0).nonzero().flatten().tolist():
                    ext = (x[:, j].max() if bound == "PMAX" else x[:, j].min()).item()
                    out.append(f"{name} of device {ids[j]} {'above' if bound == 'PMAX' else 'below'} {bound} "
                               f"({dev[j, col].item() * b:g} MW) at {int(side[:, j].sum())} entries (extreme "
                               f"{ext:g} MW)")
        return out

    def report_clipping(self, p_load: torch.Tensor, p_pot: torch.Tensor, source: str,
                        level: int = logging.WARNING) -> None:
        """Log at ``level``, once per simulator and per distinct message in a process, what of ``source``'s load P /
        potentials (MW) will be clipped to the devices' [PMIN, PMAX] (gym-anm clips them silently; this package
        keeps its behaviour but says so)."""
        lines = self.clipped_entries(p_load, p_pot)
        if lines:
            self._clipping_reported = True
            more = f"; and {len(lines) - 4} more" if len(lines) > 4 else ""
            message = (f"{source} hold values outside the devices' limits, clipped as gym-anm does: "
                       f"{'; '.join(lines[:4])}{more}")
            if (level, message) not in _REPORTED:  # every env of a run builds its own simulator: one line per case
                _REPORTED.add((level, message))
                log.log(level, "%s", message)

    def project_generators(self, target: torch.Tensor, p_pot: torch.Tensor) -> torch.Tensor:
        """Feasible (P, Q) (N, n_gen, 2) p.u. for set-points ``target`` (N, n_gen, 2) and ``p_pot`` (N, n_gen)."""
        h = self.generator_h(p_pot)
        return _stack([poly.project(target[:, k], h[:, k]) for k, poly in enumerate(self.gen_polygons)], target)

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
        return _stack([poly.project(target[:, k], h[:, k]) for k, poly in enumerate(self.des_polygons)], target)

    def soc_update(self, soc: torch.Tensor, p_des: torch.Tensor) -> torch.Tensor:
        """SoC after applying ``p_des`` (N, n_des) p.u. for Δt; one-way efficiency both ways, then clipped."""
        d = self.net.dev[self.des_idx]
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
        if self._transition is None:
            self._transition = self.physics.bind(self)
        return self._transition(soc, p_load, p_pot, setpoints)

    def __getstate__(self) -> dict:
        """Picklable (e.g. for a training process): the bound transition is a cache, bound again on first use."""
        return {**self.__dict__, "_transition": None}

    def operating_point(self, state: torch.Tensor) -> Transition:
        """Re-solve the power flow of the injections written in ``state`` (N, state_dim) MW… .

        Gives the grid quantities (voltages, flows, ΔE, λΦ) of a state that was set rather than reached by a
        transition; for a reached state they equal the transition's (up to the NR tolerance).
        """
        sl, b = self.state_slices(), self.net.base_mva
        # always the torch solve: it reads any state's injections, while a backend's transition starts from set-points
        return torch_backend.solve(self, state[:, sl["dev_p"]] / b, state[:, sl["dev_q"]] / b,
                                   state[:, sl["gen_p_max"]] / b, state[:, sl["des_soc"]] / b)

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
        out[:, sl["dev_p"].start + self.load_idx] = p * b
        out[:, sl["dev_q"].start + self.load_idx] = q * b
        out[:, sl["gen_p_max"]] = self.clip_p_pot(p_pot / b) * b
        out[:, sl["aux"]] = aux.to(out)
        return out

    def build_state(self, tr: Transition, aux: torch.Tensor) -> torch.Tensor:
        """State (N, state_dim) in MW/MVAr/MWh after ``tr`` and ``aux`` (N,) or (N, 1); zeros where the power flow
        did not converge."""
        return self.physics.build_state(tr, aux, self.net.base_mva)

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

