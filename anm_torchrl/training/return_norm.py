"""Rewards scaled by the running spread of the discounted return (opt-in, PPO's ``loss.return_norm``).

The reward normalisation of SB3's ``VecNormalize`` and Gymnasium's ``NormalizeReward``: every env keeps its
discounted return ``R_t = γ R_{t-1} + r_t`` (reset after a done step), running statistics of those returns are
updated with every batch, and the rewards the learner sees are divided by their standard deviation (not centred,
so a reward's sign is kept; not clipped, so ANM6-Easy's terminal penalties keep their weight). Where a fixed scale
(``loss.reward_scale``) suits the rewards of the start of training (penalties of thousands), this follows them as
they shrink. Evaluation and logged returns are never scaled.
"""

from __future__ import annotations

import torch


class ReturnNormalizer:
    """Per-env discounted returns, their running mean and variance (Gymnasium's ``RunningMeanStd``, the statistics
    its ``NormalizeReward`` keeps), and the rewards divided by their standard deviation.

    Args:
        gamma: the training objective's discount.
        eps: added to the variance before the square root.
    """

    def __init__(self, gamma: float, eps: float = 1e-8):
        from gymnasium.wrappers.utils import RunningMeanStd

        if not 0 <= float(gamma) <= 1:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        self.gamma, self.eps = float(gamma), float(eps)
        self.ret: torch.Tensor | None = None  # (..., 1): each env's return so far, carried across batches
        self.stats = RunningMeanStd(shape=())

    @property
    def var(self) -> float:
        """The running variance of the returns."""
        return float(self.stats.var)

    def __call__(self, reward: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
        """``reward`` / std of the running returns, after updating them with this batch.

        Args:
            reward: (..., T, 1), time in the second-to-last dimension (a collector's batch).
            done: (..., T, 1) bool, True where an episode ended (its return restarts at the next step).
        """
        if reward.shape != done.shape or reward.ndim < 2:
            raise ValueError(f"reward and done must be (..., T, 1) alike, got {tuple(reward.shape)} and "
                             f"{tuple(done.shape)}")
        shape = reward.shape[:-2] + reward.shape[-1:]
        if self.ret is None or self.ret.shape != shape:
            self.ret = reward.new_zeros(shape, dtype=torch.float64)
        returns = []
        for t in range(reward.shape[-2]):
            self.ret = self.gamma * self.ret + reward[..., t, :].double()
            returns.append(self.ret)
            self.ret = torch.where(done[..., t, :], torch.zeros_like(self.ret), self.ret)
        self.stats.update(torch.stack(returns, -2).reshape(-1).cpu().numpy())
        return (reward / (self.var + self.eps) ** 0.5).to(reward.dtype)

    def state_dict(self) -> dict:
        return {"count": float(self.stats.count), "mean": float(self.stats.mean), "var": self.var,
                "ret": None if self.ret is None else self.ret.clone()}

    def load_state_dict(self, state: dict) -> None:
        self.stats.count, self.stats.mean, self.stats.var = (float(state[k]) for k in ("count", "mean", "var"))
        self.ret = None if state["ret"] is None else state["ret"].clone()
