"""PPO's opt-in reward normalisation (``loss.return_norm``) against Gymnasium's own running statistics."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gymnasium.wrappers.utils import RunningMeanStd

from anm_torchrl.training.return_norm import ReturnNormalizer


def test_rewards_are_divided_by_the_running_std_of_each_env_s_discounted_return():
    """Two batches of 3 envs x 5 steps with episode ends: the per-env returns carried across the batch boundary and
    reset after a done step, their running variance equal to Gymnasium's ``RunningMeanStd`` fed the same returns
    (float64 both: 1e-12), the rewards divided by its square root."""
    gamma, g = 0.9, torch.Generator().manual_seed(0)
    norm, ref = ReturnNormalizer(gamma), RunningMeanStd(shape=())
    ret = np.zeros(3)
    for _ in range(2):
        reward = torch.randn(3, 5, 1, generator=g, dtype=torch.float64) * 10
        done = torch.rand(3, 5, 1, generator=g) < 0.3
        returns = []
        for t in range(5):  # the reference: NormalizeReward's loop, one step of every env at a time
            ret = ret * gamma + reward[:, t, 0].numpy()
            returns.append(ret.copy())
            ret = np.where(done[:, t, 0].numpy(), 0.0, ret)
        ref.update(np.concatenate(returns))
        out = norm(reward, done)
        assert norm.var == pytest.approx(float(ref.var), rel=1e-12)
        assert torch.allclose(out, reward / np.sqrt(ref.var + 1e-8), rtol=1e-12)
    state = norm.state_dict()
    again = ReturnNormalizer(gamma)
    again.load_state_dict(state)
    assert again.var == norm.var and torch.equal(again.ret, norm.ret)  # a resumed run goes on from here


def test_mismatched_shapes_are_refused():
    with pytest.raises(ValueError, match=r"reward and done must be \(\.\.\., T, 1\) alike"):
        ReturnNormalizer(0.99)(torch.zeros(2, 4, 1), torch.zeros(2, 4, dtype=torch.bool))
