"""The actor's distribution where some action entries have a single value (a storage unit without reactive power,
QMIN = QMAX; a generator whose PMIN = PMAX): gym-anm's action box is [v, v] there and its env asserts the action lies
in it, so the policy cannot sample those entries. :class:`PartlyFixedTanhNormal` is TorchRL's ``TanhNormal`` over the
entries the policy chooses, with the others written at their value: every sample lies in the box, and the
log-probability is that of the chosen entries alone (the fixed ones carry none)."""

from __future__ import annotations

import torch
from torch import distributions as D
from torchrl.modules import TanhNormal


class PartlyFixedTanhNormal(D.Distribution):
    """``TanhNormal(loc, scale, low, high)`` over the entries ``free`` (F,) of an action (..., A), the others at
    ``fixed`` (A,) (its entries at ``free`` are not read).

    Args:
        loc, scale: (..., F) pre-tanh mean and standard deviation of the chosen entries.
        low, high: (F,) their box (low < high), MW / MVAr.
        free: (F,) long, the chosen entries' positions in the action, increasing.
        fixed: (A,) the action's single values (MW / MVAr) at the other positions.
        tanh_loc: as ``TanhNormal``'s.
    """

    has_rsample = True
    arg_constraints: dict = {}

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor, low: torch.Tensor, high: torch.Tensor,
                 free: torch.Tensor, fixed: torch.Tensor, tanh_loc: bool = False):
        self.inner = TanhNormal(loc, scale, low=low, high=high, tanh_loc=tanh_loc)
        self.free, self.fixed = free.to(loc.device), fixed.to(loc.device, loc.dtype)
        super().__init__(batch_shape=loc.shape[:-1], event_shape=self.fixed.shape, validate_args=False)

    def full(self, chosen: torch.Tensor) -> torch.Tensor:
        """(..., F) chosen entries -> (..., A) action with the fixed entries at their values (differentiable in
        ``chosen``)."""
        base = self.fixed.expand(*chosen.shape[:-1], self.fixed.shape[-1])
        return base.index_copy(-1, self.free, chosen)

    def sample(self, sample_shape=torch.Size()) -> torch.Tensor:
        return self.full(self.inner.sample(sample_shape))

    def rsample(self, sample_shape=torch.Size()) -> torch.Tensor:
        return self.full(self.inner.rsample(sample_shape))

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        return self.inner.log_prob(value.index_select(-1, self.free))

    # TorchRL's losses (SACLoss) score a draw through these where a distribution has them: TanhNormal scores the
    # pre-tanh value it drew, exact where tanh saturates and log_prob's inverse of the rounded action is not
    def rsample_and_log_prob(self, sample_shape=torch.Size()) -> tuple[torch.Tensor, torch.Tensor]:
        chosen, log_prob = self.inner.rsample_and_log_prob(sample_shape)
        return self.full(chosen), log_prob

    def sample_and_log_prob(self, sample_shape=torch.Size()) -> tuple[torch.Tensor, torch.Tensor]:
        chosen, log_prob = self.inner.sample_and_log_prob(sample_shape)
        return self.full(chosen), log_prob

    @property
    def deterministic_sample(self) -> torch.Tensor:
        return self.full(self.inner.deterministic_sample)

    @property
    def mode(self) -> torch.Tensor:
        return self.full(self.inner.mode)
