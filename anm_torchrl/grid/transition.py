"""``Transition``: everything one batched transition computes, whichever backend computed it."""

from __future__ import annotations

import dataclasses

import torch


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
