"""The env accepts its own float32 action spec's bounds on every registered network (a bound such as 0.754 MW,
an earlier case33bw's, rounds outward in float32) and still rejects actions outside it."""

import pytest
import torch

from anm_torchrl.networks import list_networks
from anm_torchrl.training.factory import make_true_env


@pytest.mark.parametrize("network", list_networks())
def test_spec_bounds_are_accepted(network):
    env = make_true_env(2, network=network)
    spec = env.action_spec
    for bound in (spec.space.low, spec.space.high):
        td = env.reset()
        td["action"] = bound.expand(2, -1).clone()
        out = env.step(td)
        assert torch.isfinite(out["next", "reward"]).all()
    td = env.reset()
    td["action"] = (spec.space.high + spec.space.high.abs() * 1e-3 + 1e-3).expand(2, -1).clone()
    with pytest.raises(ValueError, match="outside the box"):
        env.step(td)
