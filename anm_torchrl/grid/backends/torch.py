"""The ``torch`` backend: gym-anm's transition as batched torch ops (any device, float64, differentiable).

The reference implementation of the contract of :mod:`anm_torchrl.grid.backends`, numbered as gym-anm's
``Simulator.transition`` (spec §3.5). Its tables are the simulator's own torch tensors (on the simulator's
device), read through the simulator's public attributes and projection methods.
"""

from __future__ import annotations

import torch

from anm_torchrl.grid.network import branch_flows
from anm_torchrl.grid.powerflow import newton_raphson
from anm_torchrl.grid.residuals import power_injection
from anm_torchrl.grid.reward import clipped_reward, curtailment, energy_loss, penalty
from anm_torchrl.grid.transition import Transition


def transition(sim, soc: torch.Tensor, p_load: torch.Tensor, p_pot: torch.Tensor, setpoints: torch.Tensor,
               power_flow=newton_raphson) -> Transition:
    """One batched transition of ``sim`` (a :class:`~anm_torchrl.grid.simulator.GridSimulator`): the arguments of
    :meth:`~anm_torchrl.grid.simulator.GridSimulator.apply` (p.u.). ``power_flow(y_bus, s_bus)`` returns a
    :class:`~anm_torchrl.grid.powerflow.PowerFlowResult` (:mod:`anm_torchrl.grid.implicit` gives a differentiable
    one)."""
    net = sim.net
    n_env = setpoints.shape[0]
    p_dev = setpoints.new_zeros(n_env, net.n_dev)
    q_dev = setpoints.new_zeros(n_env, net.n_dev)
    # 1. loads follow their exogenous P.
    p_dev[:, sim.load_idx], q_dev[:, sim.load_idx] = sim.load_pq(p_load)
    # 2. non-slack generators: potential, then projection onto the capability polygon.
    p_pot = sim.clip_p_pot(p_pot)
    gen_target, des_target = sim.split_action(setpoints)
    gen = sim.project_generators(gen_target, p_pot)
    p_dev[:, sim.gen_idx], q_dev[:, sim.gen_idx] = gen[..., 0], gen[..., 1]
    # 3. storage: SoC-dependent projection, then SoC update.
    des = sim.project_storage(des_target, soc)
    p_dev[:, sim.des_idx], q_dev[:, sim.des_idx] = des[..., 0], des[..., 1]
    soc_next = sim.soc_update(soc, des[..., 0])
    return solve(sim, p_dev, q_dev, p_pot, soc_next, power_flow)


def solve(sim, p_dev: torch.Tensor, q_dev: torch.Tensor, p_pot: torch.Tensor, soc: torch.Tensor,
          power_flow=newton_raphson) -> Transition:
    """Power flow, slack injection, branch flows and reward for device injections (N, n_dev) p.u. (written in
    place: the slack's entries), clipped potentials (N, n_gen) p.u. and SoC (N, n_des) p.u.·h."""
    net, slack = sim.net, sim.slack_ids[0]
    # 4. bus injections and AC power flow (the slack injection is 0 at this point).
    p_dev[:, slack] = 0.0
    q_dev[:, slack] = 0.0
    s_bus = torch.complex(p_dev @ net.incidence, q_dev @ net.incidence)
    pf = power_flow(net.y_bus, s_bus)
    # 5. slack injection and branch flows from the (possibly non-converged) voltages.
    s_slack = power_injection(pf.v, net.y_bus)[:, 0]
    inf = torch.full_like(s_slack.real, float("inf"))
    p_dev[:, slack] = torch.where(torch.isnan(s_slack.real), inf, s_slack.real)
    q_dev[:, slack] = torch.where(torch.isnan(s_slack.imag), inf, s_slack.imag)
    s_max = branch_flows(pf.v, net.branches)["s_apparent_max"]
    # 6. reward terms; a non-converged power flow is terminal.
    curt = curtailment(p_pot, p_dev[:, sim.gen_idx], sim.renewable)
    e_loss = energy_loss(p_dev, sim.counted, curt, net.delta_t)
    pen = penalty(pf.v.abs(), s_max, net, sim.lamb)
    reward = clipped_reward(e_loss, pen, sim.costs_clipping)
    reward = torch.where(pf.converged, reward, torch.full_like(reward, sim.terminal_reward))
    return Transition(p_dev=p_dev, q_dev=q_dev, soc=soc, p_pot=p_pot, v=pf.v, s_apparent_max=s_max,
                      converged=pf.converged, n_iter=pf.n_iter, e_loss=e_loss, penalty=pen,
                      curtailment=curt, reward=reward)


class TorchBackend:
    """The ``torch`` backend (contract: :mod:`anm_torchrl.grid.backends`); runs every network on every device."""

    name = "torch"

    def unusable(self, net) -> str | None:
        return None

    def bind(self, sim):
        return lambda soc, p_load, p_pot, setpoints: transition(sim, soc, p_load, p_pot, setpoints)

    def build_state(self, tr: Transition, aux: torch.Tensor, base_mva: float) -> torch.Tensor:
        b = base_mva
        state = torch.cat([tr.p_dev * b, tr.q_dev * b, tr.soc * b, tr.p_pot * b, aux.reshape(-1, 1).to(tr.p_dev)], 1)
        return torch.where(tr.converged.unsqueeze(1), state, torch.zeros_like(state))

    def output_bounds(self, low: torch.Tensor, high: torch.Tensor) -> None:
        return None  # the env's observation map clips

    def env_outputs(self, state: torch.Tensor, tr: Transition, base_mva: float, bounds) -> dict[str, torch.Tensor]:
        f32, b = torch.float32, base_mva
        out = {"e_loss": tr.e_loss.unsqueeze(-1), "penalty": tr.penalty.unsqueeze(-1),
               "curtailment": (tr.curtailment * b).unsqueeze(-1), "v_magn": tr.v.abs(),
               "branch_s": tr.s_apparent_max * b}
        out = {k: v.to(f32) for k, v in out.items()}
        out["reward"], out["terminated"] = tr.reward.to(f32).unsqueeze(-1), (~tr.converged).unsqueeze(-1)
        return out
