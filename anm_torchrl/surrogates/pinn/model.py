"""The three PINN networks of a training configuration (generator and storage KKT-NNs, power balance)."""

from __future__ import annotations

from torch import nn

from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.surrogates.pinn.kkt import GeneratorKKT, StorageKKT
from anm_torchrl.surrogates.pinn.power_balance import PowerBalanceNet
from anm_torchrl.surrogates.pinn.presets import REFINE_AUTO, PINNTrainConfig


def check_pinn_network(sim: GridSimulator) -> None:
    """Refuse a network the PINN cannot be trained for: an action entry whose range is a single value (a storage
    unit without reactive power, QMIN = QMAX; a generator with PMIN = PMAX), on which its KKT modules' training
    diverges. The true simulator and SHAC through the exact model take such a network.

    Raises:
        ValueError: naming the entries and what to use instead."""
    from anm_torchrl.networks.resolve import single_value_actions

    flat = single_value_actions(sim)
    if flat:
        raise ValueError(f"the PINN surrogate does not train on a network where the action range of "
                         f"{', '.join(flat)} is a single value (its KKT modules diverge there); train on the true "
                         "simulator (surrogate=none) or through the exact model (shac.py model.dynamics=exact)")


def build_modules(cfg: PINNTrainConfig, sim: GridSimulator, refine_steps: int | None = None) -> dict[str, nn.Module]:
    """Untrained ``generator`` (:class:`GeneratorKKT`), ``storage`` (:class:`StorageKKT`) and
    ``power_balance`` (:class:`PowerBalanceNet`) networks for ``cfg``, float32, on the simulator's device.

    ``refine_steps``: the power balance's refinement steps (None: the config's; its ``auto`` builds 0 until
    :func:`.refine.choose_refine_steps` sets them after training)."""
    check_pinn_network(sim)
    g, s, p = cfg.generator, cfg.storage, cfg.power_balance
    if refine_steps is None:
        refine_steps = 0 if p.refine_steps == REFINE_AUTO else p.refine_steps
    mods = {
        "generator": GeneratorKKT(sim, g.hidden, g.depth, g.activation, g.dual_activation,
                                  hard_constraints=g.hard_constraints, gated=g.gated, separate_dual=g.separate_dual,
                                  dual_gate=g.dual_gate),
        "storage": StorageKKT(sim, s.hidden, s.depth, s.activation, s.dual_activation,
                              hard_constraints=s.hard_constraints, gated=s.gated, separate_dual=s.separate_dual,
                              dual_gate=s.dual_gate),
        "power_balance": PowerBalanceNet(sim, p.hidden, p.depth, p.activation, p.v_scale, p.ang_scale,
                                         refine_steps=refine_steps),
    }
    return {k: m.to(sim.net.dev.device) for k, m in mods.items()}
