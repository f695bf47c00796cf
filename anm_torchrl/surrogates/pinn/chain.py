"""The PINN surrogate of any network as a chain of ``TensorDictModule``s (paper §4.2); :mod:`.load` loads it.

``state`` (N, state_dim), ``action`` (N, action_dim) (gym-anm order and units, float64; ANM6-Easy: 18 and 6)
flow through:

=====================  =========================================  ===============================================
module                 reads                                      writes (all p.u. unless noted, float64)
=====================  =========================================  ===============================================
``exogenous``          ``state``, ``action``                      ``("pinn", k)`` for k = ``gen_target`` (N, n_gen, 2),
                                                                  ``p_pot`` (N, n_gen) at t+1, ``des_target``
                                                                  (N, n_des, 2), ``soc`` (N, n_des) p.u.·h,
                                                                  ``p_load``/``q_load`` (N, n_load) at t+1,
                                                                  ``t_next`` (N,) aux of the next state
``generator`` KKT-NN   ``gen_target``, ``p_pot``                  ``gen_pq`` (N, n_gen, 2) [, ``gen_lambda`` (…, 7)]
``storage`` KKT-NN     ``des_target``, ``soc``                    ``des_pq`` (N, n_des, 2) [, ``des_lambda`` (…, 10)]
``aggregation``        ``gen_pq``, ``des_pq``, ``p_load``,        ``p_dev``/``q_dev`` (N, n_dev) (slack 0),
                       ``q_load``                                 ``p_bus``/``q_bus`` (N, n_bus)
``power_balance`` PINN ``p_bus``, ``q_bus``                       ``v_magn`` (N, n_bus), ``v_ang`` (N, n_bus) rad
``slack``              ``v_magn``, ``v_ang``, ``p_dev``,          ``p_dev_all``/``q_dev_all`` (slack from the bus-0
                       ``q_dev``, ``p_bus``, ``q_bus``            equations), ``branch_s`` (N, n_branch) signed,
                                                                  ``pf_residual`` (N,) max |ΔP|, |ΔQ| at buses 1…
``terminal``           ``pf_residual``, ``v_magn`` (physics) or   ``terminated`` (N, 1) bool
                       ``state``, ``action`` (classifier)
``next_state``         ``state`` and the above                    ``next_state`` (N, state_dim), ``reward``,
                                                                  ``("grid", k)``: ``e_loss``, ``penalty``,
                                                                  ``curtailment`` (MW), ``v_magn``, ``branch_s`` (MVA)
=====================  =========================================  ===============================================

The slack injection, branch flows, SoC update, ΔE, λΦ, curtailment and the clipped reward are the same
``anm_torchrl.grid`` functions the simulator calls (``power_injection``, ``branch_flows``, ``soc_update``,
``energy_loss``, ``penalty``, ``curtailment``, ``clipped_reward``); only the projections and the power flow are
learned. Every piece is a ``TensorDictModule`` usable alone, e.g.
``chain.select_subsequence(in_keys=[("pinn", "p_bus"), ("pinn", "q_bus")], out_keys=[("pinn", "v_magn")])``.
The multipliers λ (bracketed) are written only by a chain built with ``duals=True``: they are a training device
(the KKT losses), and their networks would double the projections' inference cost. :func:`run_chain` runs the
same modules on plain tensors, without the ``TensorDict`` bookkeeping (~20 % of a step at batch 64), for
callers that differentiate through many steps (SHAC).

Terminal states (``terminal="physics"``, the default, needs no simulator sample): a transition is terminal when
the power-flow residual of the predicted voltages at the predicted injections exceeds ``residual_threshold``
(p.u.) — the network cannot satisfy the equations where no power-flow solution exists (voltage collapse) —
or a predicted |V| leaves ``[v_low, v_high]``. Measured against the simulator's non-convergence on 2 × 20,000
uniform random transitions (``grid.reset.random_state`` + uniform actions, 0.48–0.52 % terminal) with the
``default`` model (``evaluate.terminal_sweep``):

=========  ===========  ===========
threshold  precision    recall
=========  ===========  ===========
0.003      0.76         1.00
**0.005**  0.97–0.98    0.96–1.00
0.01       0.99         0.75
0.02       1.00         0.48–0.50
=========  ===========  ===========

The threshold suits a model as accurate as the ``default`` preset (residual p99 ≈ 2e-3 p.u. on reachable
injections); a less trained model needs a larger one. ``terminal="classifier"`` uses the gradient-boosting
``TerminalClassifier`` of :mod:`anm_torchrl.surrogates.terminal` instead (one trained on 60,000 simulator
transitions scored precision 0.81 / recall 0.77 on the same set).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn

from anm_torchrl.grid.network import branch_flows
from anm_torchrl.grid.residuals import bus_voltage, power_injection
from anm_torchrl.grid.reward import clipped_reward, curtailment, energy_loss, penalty
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.grid.identity import transition_key
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.surrogates.pinn.kkt import GeneratorKKT, PrimalProjection, StorageKKT
from anm_torchrl.surrogates.pinn.losses import power_balance_residuals
from anm_torchrl.surrogates.pinn.power_balance import PowerBalanceNet
from anm_torchrl.surrogates.pinn.presets import MODULES

log = logging.getLogger(__name__)

P = "pinn"
DEFAULT_RESIDUAL_THRESHOLD = 0.005  # p.u. (0.5 MW/MVAr); precision/recall in the module docstring
DEFAULT_V_RANGE = (0.4, 1.4)  # p.u.; predicted |V| outside is treated as collapse
TERMINALS = ("physics", "classifier")


class ExogenousInputs(nn.Module):
    """Split ``state`` and ``action`` into the modules' inputs (p.u.), with the loads and potentials of the next
    step (perfect foresight, as the simulator: :meth:`GridSimulator.next_vars`, so a ``next_vars`` hook is
    followed; ``t_next`` is the next state's auxiliary variable)."""

    def __init__(self, sim: GridSimulator):
        super().__init__()
        self.sim = sim

    def forward(self, state: torch.Tensor, action: torch.Tensor):
        sim, b = self.sim, self.sim.net.base_mva
        sl = sim.state_slices()
        state, action = state.to(torch.float64), action.to(torch.float64) / b
        p_load_mw, p_pot_mw, aux = sim.next_vars(state)
        p_load, q_load = sim.load_pq(p_load_mw / b)
        gen_target, des_target = sim.split_action(action)
        return (gen_target, sim.clip_p_pot(p_pot_mw / b), des_target, state[:, sl["des_soc"]] / b, p_load, q_load,
                aux.squeeze(1))


class BusAggregation(nn.Module):
    """Device injections (N, n_dev) p.u. (slack 0) and their sums per bus (N, n_bus) (paper §4.2, step 2)."""

    def __init__(self, sim: GridSimulator):
        super().__init__()
        self.sim = sim

    def forward(self, gen_pq, des_pq, p_load, q_load):
        sim = self.sim
        n = gen_pq.shape[0]
        p_dev = gen_pq.new_zeros(n, sim.net.n_dev)
        q_dev = gen_pq.new_zeros(n, sim.net.n_dev)
        p_dev[:, sim.load_ids], q_dev[:, sim.load_ids] = p_load, q_load
        p_dev[:, sim.gen_ids], q_dev[:, sim.gen_ids] = gen_pq[..., 0], gen_pq[..., 1]
        p_dev[:, sim.des_ids], q_dev[:, sim.des_ids] = des_pq[..., 0], des_pq[..., 1]
        return p_dev, q_dev, p_dev @ sim.net.incidence, q_dev @ sim.net.incidence


class SlackAndFlows(nn.Module):
    """Slack injection from the bus-0 power-flow equation (paper eqs. 33–34, standard polar form), branch
    flows, and the largest power-flow residual at the other buses, from the predicted voltages."""

    def __init__(self, sim: GridSimulator):
        super().__init__()
        self.sim = sim

    def forward(self, v_magn, v_ang, p_dev, q_dev, p_bus, q_bus):
        net = self.sim.net
        v = bus_voltage(v_magn, v_ang)
        s_slack = power_injection(v, net.y_bus)[:, 0]
        p_all, q_all = p_dev.clone(), q_dev.clone()
        slack = self.sim.slack_ids[0]
        p_all[:, slack], q_all[:, slack] = s_slack.real, s_slack.imag
        s_max = branch_flows(v, net.branches)["s_apparent_max"]
        dp, dq = power_balance_residuals(v_magn, v_ang, p_bus, q_bus, net.y_bus)
        residual = torch.cat([dp, dq], -1).abs().amax(-1)
        return p_all, q_all, s_max, residual


class PhysicsTerminal(nn.Module):
    """``terminated`` (N, 1) = power-flow residual > ``residual_threshold`` (p.u.) or some |V| outside
    ``[v_low, v_high]`` (p.u.) or a non-finite residual.

    Raises:
        ValueError: ``residual_threshold`` not a finite number > 0, or ``v_range`` not finite with
            0 <= v_low < v_high.
    """

    def __init__(self, residual_threshold: float = DEFAULT_RESIDUAL_THRESHOLD,
                 v_range: tuple[float, float] = DEFAULT_V_RANGE):
        super().__init__()
        thr = float(residual_threshold)
        if not (math.isfinite(thr) and thr > 0):
            raise ValueError(f"residual_threshold must be a finite number > 0 (p.u.), got {residual_threshold!r}")
        lo, hi = (float(v) for v in v_range)
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo < hi):
            raise ValueError(f"v_range must be two finite numbers 0 <= v_low < v_high (p.u.), got {v_range!r}")
        self.residual_threshold, self.v_low, self.v_high = thr, lo, hi

    def forward(self, residual, v_magn):
        bad = ~(residual <= self.residual_threshold)  # NaN counts as terminal
        bad |= ((v_magn < self.v_low) | (v_magn > self.v_high)).any(-1)
        return bad.unsqueeze(-1)


class ClassifierTerminal(nn.Module):
    """``terminated`` (N, 1) from a trained ``TerminalClassifier`` (``predict_terminated(state, action)``)."""

    def __init__(self, classifier: Any):
        super().__init__()
        self.classifier = classifier

    def forward(self, state, action):
        out = self.classifier.predict_terminated(state, action)
        return torch.as_tensor(out, dtype=torch.bool, device=state.device).reshape(-1, 1)


class NextStateReward(nn.Module):
    """Next state (N, state_dim) and reward (N, 1) from the predicted grid, with the simulator's own functions; the
    ``("grid", k)`` diagnostics in the env's units. Terminal rows get the terminal reward and a zero state."""

    def __init__(self, sim: GridSimulator):
        super().__init__()
        self.sim = sim

    def forward(self, p_dev, q_dev, des_pq, soc, p_pot, t_next, v_magn, branch_s, terminated):
        sim, net = self.sim, self.sim.net
        b = net.base_mva
        soc_next = sim.soc_update(soc, des_pq[..., 0])
        curt = curtailment(p_pot, p_dev[:, sim.gen_ids], sim.renewable)  # classical generators are not curtailed
        e_loss = energy_loss(p_dev, sim.counted, curt, net.delta_t)
        pen = penalty(v_magn, branch_s, net, sim.lamb)
        reward = clipped_reward(e_loss, pen, sim.costs_clipping)
        term = terminated.reshape(-1)
        reward = torch.where(term, torch.full_like(reward, sim.terminal_reward), reward)
        state = torch.cat([p_dev * b, q_dev * b, soc_next * b, p_pot * b, t_next.reshape(-1, 1).to(p_dev)], 1)
        state = torch.where(term.unsqueeze(1), torch.zeros_like(state), state)
        return (state, reward.unsqueeze(-1), e_loss.unsqueeze(-1), pen.unsqueeze(-1), (curt * b).unsqueeze(-1),
                v_magn, branch_s * b)


def build_chain(sim: GridSimulator, generator: GeneratorKKT, storage: StorageKKT, power_balance: PowerBalanceNet,
                terminal: str = "physics", classifier: Any = None,
                residual_threshold: float = DEFAULT_RESIDUAL_THRESHOLD,
                v_range: tuple[float, float] = DEFAULT_V_RANGE, duals: bool = False) -> TensorDictSequential:
    """Assemble the PINN surrogate chain (see the module docstring) from trained modules.

    Args:
        sim: the simulator whose grid functions, series and constants the chain uses.
        generator, storage, power_balance: the networks.
        terminal: ``"physics"`` (:class:`PhysicsTerminal`) or ``"classifier"`` (needs ``classifier``).
        classifier: an object with ``predict_terminated(state, action) -> (N,) bool``.
        residual_threshold, v_range: of the physics check.
        duals: also write the KKT-NNs' multipliers ``gen_lambda`` / ``des_lambda`` (the other outputs are the same).
    """
    if terminal not in TERMINALS:
        raise ValueError(f"terminal must be one of {TERMINALS}, got {terminal!r}")
    k = lambda *names: [(P, n) for n in names]  # noqa: E731

    def projection(module: nn.Module, name: str, theta: str) -> TensorDictModule:
        ins = k(f"{name}_target", theta)
        if duals:
            return TensorDictModule(module, in_keys=ins, out_keys=k(f"{name}_pq", f"{name}_lambda"))
        return TensorDictModule(PrimalProjection(module), in_keys=ins, out_keys=k(f"{name}_pq"))

    mods = [
        TensorDictModule(ExogenousInputs(sim), in_keys=["state", "action"],
                         out_keys=k("gen_target", "p_pot", "des_target", "soc", "p_load", "q_load", "t_next")),
        projection(generator, "gen", "p_pot"),
        projection(storage, "des", "soc"),
        TensorDictModule(BusAggregation(sim), in_keys=k("gen_pq", "des_pq", "p_load", "q_load"),
                         out_keys=k("p_dev", "q_dev", "p_bus", "q_bus")),
        TensorDictModule(power_balance, in_keys=k("p_bus", "q_bus"), out_keys=k("v_magn", "v_ang")),
        TensorDictModule(SlackAndFlows(sim), in_keys=k("v_magn", "v_ang", "p_dev", "q_dev", "p_bus", "q_bus"),
                         out_keys=k("p_dev_all", "q_dev_all", "branch_s", "pf_residual")),
    ]
    if terminal == "physics":
        mods.append(TensorDictModule(PhysicsTerminal(residual_threshold, v_range),
                                     in_keys=k("pf_residual", "v_magn"), out_keys=["terminated"]))
    else:
        if classifier is None:
            raise ValueError("terminal='classifier' needs a classifier (load_pinn: classifier_path=...)")
        mods.append(TensorDictModule(ClassifierTerminal(classifier), in_keys=["state", "action"],
                                     out_keys=["terminated"]))
    mods.append(TensorDictModule(
        NextStateReward(sim),
        in_keys=[*k("p_dev_all", "q_dev_all", "des_pq", "soc", "p_pot", "t_next", "v_magn", "branch_s"), "terminated"],
        out_keys=["next_state", "reward", ("grid", "e_loss"), ("grid", "penalty"), ("grid", "curtailment"),
                  ("grid", "v_magn"), ("grid", "branch_s")]))
    chain = TensorDictSequential(*mods)
    chain.transition_key = transition_key(sim)  # SurrogateEnv refuses to run it on another network or other profiles
    return chain.eval()


def run_chain(chain: TensorDictSequential, inputs: dict) -> dict:
    """Run ``chain``'s modules in order on plain tensors: ``inputs`` maps its in-keys (e.g. ``"state"``,
    ``"action"``) to tensors; returns every key the modules write (``("pinn", k)``, ``"next_state"``, ...) — the
    values ``chain(TensorDict(inputs))`` holds, computed by the same modules, without building a ``TensorDict``.

    Raises:
        KeyError: an input a module reads is neither given nor written by an earlier module.
        ValueError: a module returned another number of outputs than its out-keys.
    """
    values = dict(inputs)
    for mod in chain.module:
        out = mod.module(*(values[key] for key in mod.in_keys))
        out = out if isinstance(out, tuple) else (out,)
        if len(out) != len(mod.out_keys):
            raise ValueError(f"{type(mod.module).__name__} returned {len(out)} outputs for out_keys {mod.out_keys}")
        values.update(zip(mod.out_keys, out))
    return values
