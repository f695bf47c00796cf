"""The ANM6-Easy transition as batched float64 torch maths, numbered as in gym-anm (spec §3.5), and its reset.

State vectors are in gym-anm's order and units (MW, MVAr, MWh, time index; spec §3.1); actions in MW/MVAr
(spec §3.2). Internally everything is p.u. on ``base_mva``. No TorchRL here: :mod:`anm_torchrl.envs` wraps it.
"""

from __future__ import annotations

import dataclasses

import torch

from anm_torchrl.grid import anm6_easy as data
from anm_torchrl.grid import devices as dv
from anm_torchrl.grid.network import LOAD, RENEWABLE, SLACK, STORAGE, Network, anm6_easy_network, branch_flows
from anm_torchrl.grid.powerflow import newton_raphson
from anm_torchrl.grid.residuals import power_injection
from anm_torchrl.grid.reward import clipped_reward, curtailment, energy_loss, penalty, terminal_reward


@dataclasses.dataclass
class Transition:
    """Everything one batched transition computes (p.u. unless noted); N = batch size.

    Attributes:
        p_dev, q_dev: (N, n_dev) applied injections, slack from the power flow (+inf if NaN).
        soc: (N, n_des) p.u.·h after the update.  p_pot: (N, n_gen) clipped potentials.
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
    """Batched transition model of a gym-anm environment (float64), e.g. :func:`anm6_easy_simulator`.

    Args:
        net: the network.
        load_series: (n_load, T) load P (MW) per time index, loads in ascending device id.
        p_max_series: (n_gen, T) raw renewable potentials (MW); clipped to [PMIN, PMAX] when used.
        gamma, lamb, costs_clipping: reward constants.
        backend: ``"torch"`` (batched tensor ops, any device), ``"numba"`` (one compiled loop over the batch,
            float64 CPU only, several times faster; :mod:`anm_torchrl.grid.kernel`) or ``"auto"`` (numba when
            it is installed and the network is on the CPU). Both give the same transitions to round-off.
    """

    def __init__(self, net: Network, load_series: torch.Tensor, p_max_series: torch.Tensor, gamma: float,
                 lamb: float, costs_clipping: tuple[float, float], backend: str = "auto"):
        self.net = net
        kind = net.dev_type.tolist()
        self.slack_ids = [i for i, k in enumerate(kind) if k == SLACK]
        self.load_ids = [i for i, k in enumerate(kind) if k == LOAD]
        self.gen_ids = [i for i, k in enumerate(kind) if k == RENEWABLE]
        self.des_ids = [i for i, k in enumerate(kind) if k == STORAGE]
        if len(self.slack_ids) != 1 or net.dev_bus[self.slack_ids[0]] != 0:
            raise ValueError("exactly one slack device, at bus 0, is required")
        self.gamma, self.lamb, self.costs_clipping = gamma, lamb, costs_clipping
        self.load_series = load_series.to(net.dev) / net.base_mva
        self.p_max_series = p_max_series.to(net.dev) / net.base_mva
        self.n_time = self.load_series.shape[1]
        self.gen_g, self.gen_h0 = dv.generator_polygon(net, self.gen_ids)
        polys = [dv.storage_polygon(net, d) for d in self.des_ids]
        self.des_g = torch.stack([p[0] for p in polys]) if polys else None
        self.des_h0 = torch.stack([p[1] for p in polys]) if polys else None
        self._gen_poly = [dv.Polygon(g) for g in self.gen_g]
        self._des_poly = [dv.Polygon(g) for g in self.des_g] if polys else []
        gid, did, lid = (torch.tensor(ix, dtype=torch.long, device=net.dev.device)
                         for ix in (self.gen_ids, self.des_ids, self.load_ids))
        self._gid, self._did, self._lid = gid, did, lid
        self.counted = (net.dev_type != STORAGE).to(net.dev.dtype)  # ΔE counts gens, slack and loads
        self.terminal_reward = terminal_reward(gamma, costs_clipping)
        self.backend = self._pick_backend(backend)
        self._kernel = None

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

    def state_slices(self) -> dict[str, slice]:
        """gym-anm ``STATE_VARIABLES`` blocks of the state vector."""
        n, d, g = self.net.n_dev, self.n_des, self.n_gen
        return {"dev_p": slice(0, n), "dev_q": slice(n, 2 * n), "des_soc": slice(2 * n, 2 * n + d),
                "gen_p_max": slice(2 * n + d, 2 * n + d + g), "aux": slice(2 * n + d + g, 2 * n + d + g + 1)}

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
        dev = self.net.dev[self._lid]
        p = torch.clamp(self.load_series[:, t_index].T, dev[:, dv.PMIN], dev[:, dv.PMAX])
        return p, p * dev[:, 3]

    def p_pot_at(self, t_index: torch.Tensor) -> torch.Tensor:
        """Clipped renewable potentials (N, n_gen) p.u. at time indices ``t_index`` (N,)."""
        dev = self.net.dev[self._gid]
        return torch.clamp(self.p_max_series[:, t_index].T, dev[:, dv.PMIN], dev[:, dv.PMAX])

    def project_generators(self, target: torch.Tensor, p_pot: torch.Tensor) -> torch.Tensor:
        """Feasible (P, Q) (N, n_gen, 2) p.u. for set-points ``target`` (N, n_gen, 2) and ``p_pot`` (N, n_gen)."""
        h = self.generator_h(p_pot)
        return torch.stack([poly.project(target[:, k], h[:, k]) for k, poly in enumerate(self._gen_poly)], 1)

    def generator_h(self, p_pot: torch.Tensor) -> torch.Tensor:
        """Generator right-hand sides (N, n_gen, 7) for ``p_pot`` (N, n_gen) p.u."""
        return dv.generator_h(self.gen_h0, p_pot)

    def storage_h(self, soc: torch.Tensor) -> torch.Tensor:
        """Storage right-hand sides (N, n_des, 10) for ``soc`` (N, n_des) p.u.·h."""
        return torch.stack([dv.storage_h(self.net, d, self.des_h0[k], soc[:, k])
                            for k, d in enumerate(self.des_ids)], 1)

    def project_storage(self, target: torch.Tensor, soc: torch.Tensor) -> torch.Tensor:
        """Feasible (P, Q) (N, n_des, 2) p.u. for set-points (N, n_des, 2) and SoC (N, n_des) p.u.·h."""
        h = self.storage_h(soc)
        return torch.stack([poly.project(target[:, k], h[:, k]) for k, poly in enumerate(self._des_poly)], 1)

    def soc_update(self, soc: torch.Tensor, p_des: torch.Tensor) -> torch.Tensor:
        """SoC after applying ``p_des`` (N, n_des) p.u. for Δt; one-way efficiency both ways, then clipped."""
        d = self.net.dev[self._did]
        eff, dt = d[:, dv.EFF], self.net.delta_t
        nxt = torch.where(p_des <= 0, soc - dt * eff * p_des, soc - dt * p_des / eff)
        return torch.clamp(nxt, d[:, dv.SOC_MIN], d[:, dv.SOC_MAX])

    def transition(self, soc: torch.Tensor, t_index: torch.Tensor, setpoints: torch.Tensor) -> Transition:
        """One batched transition of the simulator (spec §3.5 steps 4–7).

        Args:
            soc: (N, n_des) state of charge before the step, p.u.·h.
            t_index: (N,) long, time index whose loads and potentials apply.
            setpoints: (N, action_dim) p.u., action order (P gen, Q gen, P DES, Q DES).
        """
        if self.backend == "numba":
            if self._kernel is None:
                from anm_torchrl.grid.kernel import CompiledTransition

                self._kernel = CompiledTransition(self)
            return Transition(**self._kernel(soc, t_index, setpoints))
        net, ng, nd = self.net, self.n_gen, self.n_des
        n_env = setpoints.shape[0]
        p_dev = setpoints.new_zeros(n_env, net.n_dev)
        q_dev = setpoints.new_zeros(n_env, net.n_dev)
        # 1. loads follow the time series.
        p_dev[:, self._lid], q_dev[:, self._lid] = self.loads_at(t_index)
        # 2. renewable generators: potential, then projection onto the capability polygon.
        p_pot = self.p_pot_at(t_index)
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
        curt = curtailment(p_pot, p_dev[:, self._gid])
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
        sl, b = self.state_slices(), self.net.base_mva
        out = state.clone()
        p_load, q_load = self.loads_at(t_index)
        out[:, sl["dev_p"].start + self._lid] = p_load * b
        out[:, sl["dev_q"].start + self._lid] = q_load * b
        out[:, sl["gen_p_max"]] = self.p_pot_at(t_index) * b
        out[:, sl["aux"]] = t_index.unsqueeze(1).to(out)
        return out

    def build_state(self, tr: Transition, aux: torch.Tensor) -> torch.Tensor:
        """State (N, state_dim) in MW/MVAr/MWh after ``tr``; zeros where the power flow did not converge."""
        b = self.net.base_mva
        state = torch.cat([tr.p_dev * b, tr.q_dev * b, tr.soc * b, tr.p_pot * b, aux.unsqueeze(1).to(tr.p_dev)], 1)
        return torch.where(tr.converged.unsqueeze(1), state, torch.zeros_like(state))

    def step(self, state: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, Transition]:
        """gym-anm ``step`` for a batch: ``state`` (N, state_dim) MW…, ``action`` (N, action_dim) MW/MVAr.

        Returns the next state (zeros on terminal rows) and the :class:`Transition` (reward, convergence…).
        Only the SoC and the time index of ``state`` matter: loads and potentials come from the series.
        """
        sl = self.state_slices()
        aux_next = (state[:, sl["aux"]].squeeze(1).round().long() + 1) % self.n_time
        tr = self.transition(state[:, sl["des_soc"]] / self.net.base_mva, aux_next, action / self.net.base_mva)
        return self.build_state(tr, aux_next), tr

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
    """The ANM6-Easy simulator of gym-anm 2.0.1 on ``device`` (``backend``: see :class:`GridSimulator`)."""
    series = torch.as_tensor(data.TIME_SERIES_MW, device=device)
    return GridSimulator(anm6_easy_network(device), load_series=series[:3], p_max_series=series[3:],
                         gamma=data.GAMMA, lamb=data.LAMB, costs_clipping=data.COSTS_CLIPPING, backend=backend)
