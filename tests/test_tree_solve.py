"""The torch backend's block-tree Newton step (``grid.tree_solve``) against the dense Jacobian and LU.

Round-off tolerances: the tree eliminates without pivoting across buses, the dense LU pivots, so the two agree to
a few ulps of the solution's scale (1e-10 relative here, measured ~1e-14 on |V|), not bit for bit.
"""

from __future__ import annotations

import pytest
import torch

import anm_torchrl.grid.powerflow as pf
import anm_torchrl.grid.tree_solve as ts
from anm_torchrl.grid.implicit import implicit_power_flow
from anm_torchrl.grid.residuals import power_injection
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.networks.random import generate
from anm_torchrl.surrogates.pinn.evaluate import random_transitions


def _case(name_or_seed):
    if isinstance(name_or_seed, str):
        sim = network_simulator(name_or_seed, backend="torch")
    else:
        case = generate(name_or_seed, n_bus=30, meshed=False)
        sim = network_simulator(case.network, case.load_p, case.gen_p_max, backend="torch")
    state, action = random_transitions(sim, 40, seed=3)
    _, trn = sim.step(state, action)
    s = torch.complex(trn.p_dev @ sim.net.incidence, trn.q_dev @ sim.net.incidence)
    s[:, 0] = 0
    return sim.net.y_bus, s


@pytest.fixture(params=["case33bw", 4], ids=["case33bw", "random30"])
def case(request):
    return _case(request.param)


@pytest.fixture
def forced_tree(monkeypatch):
    monkeypatch.setattr(ts, "TREE_WORK", 0.0)
    monkeypatch.setattr(ts, "BANDED_MIN_BUS", 0)


def _dense_at(y_bus, s, seed=0):
    """Voltages near the solution (a few flat-start Newton steps, perturbed) and the dense Jacobian there."""
    x, *_ = pf.newton_iterates(y_bus, s, max_iter=2)
    x = x + 1e-3 * torch.randn(x.shape, generator=torch.Generator().manual_seed(seed), dtype=x.dtype)
    v = pf._voltages(x, s.shape[1])
    s_inj = power_injection(v, y_bus)
    return v, s_inj, pf._jacobian(v, s_inj, y_bus[1:, 1:].conj())


def test_blocks_are_the_dense_jacobians(case):
    y_bus, s = case
    forest = ts.bus_forest(y_bus)
    assert forest is not None
    v, s_inj, jac = _dense_at(y_bus, s)
    d, low, up = ts.jacobian_blocks(v, s_inj, y_bus, forest)
    k = d.shape[1]
    rows = torch.stack([torch.arange(k), torch.arange(k) + k])  # [P; Q] rows / [θ; |V|] columns of bus i
    for i in range(k):
        torch.testing.assert_close(d[:, i], jac[:, rows[:, i]][:, :, rows[:, i]], rtol=0, atol=1e-12)
        p = int(forest.parent[i])
        if p >= 0:
            torch.testing.assert_close(low[:, i], jac[:, rows[:, p]][:, :, rows[:, i]], rtol=0, atol=1e-12)
            torch.testing.assert_close(up[:, i], jac[:, rows[:, i]][:, :, rows[:, p]], rtol=0, atol=1e-12)


@pytest.mark.parametrize("transpose", [False, True])
def test_tree_step_equals_the_dense_solve(case, transpose):
    y_bus, s = case
    v, s_inj, jac = _dense_at(y_bus, s, seed=1)
    rhs = torch.randn(len(s), jac.shape[-1], dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    want = torch.linalg.solve(jac.transpose(-1, -2) if transpose else jac, rhs.unsqueeze(-1)).squeeze(-1)
    got, info = ts.tree_newton_step(v, s_inj, y_bus, rhs, ts.bus_forest(y_bus), transpose=transpose)
    assert (info == 0).all()
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10 * want.abs().max().item())


def test_newton_on_the_tree_equals_dense(case, forced_tree):
    y_bus, s = case
    assert ts.use_tree(y_bus, len(s)) is not None
    tree = pf.newton_raphson(y_bus, s)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ts, "TREE_WORK", float("inf"))
        dense = pf.newton_raphson(y_bus, s)
    assert torch.equal(tree.converged, dense.converged) and tree.converged.all()
    assert torch.equal(tree.n_iter, dense.n_iter)
    assert (tree.v - dense.v).abs().max() < 1e-12


def test_implicit_gradient_on_the_tree_equals_dense(case, forced_tree):
    y_bus, s = case

    def grads():
        p, q = s.real.clone().requires_grad_(), s.imag.clone().requires_grad_()
        v = implicit_power_flow(y_bus, torch.complex(p, q)).v
        (v.abs() ** 2 + v.angle()).sum().backward()
        return torch.cat([p.grad, q.grad], 1)

    tree = grads()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ts, "TREE_WORK", float("inf"))
        dense = grads()
    assert dense.abs().max() > 0
    torch.testing.assert_close(tree, dense, rtol=1e-9, atol=1e-9 * dense.abs().max().item())


def test_singular_block_is_reported():
    y_bus, s = _case("case33bw")
    v, s_inj, _ = _dense_at(y_bus, s)
    forest = ts.bus_forest(y_bus)
    d, low, up = ts.jacobian_blocks(v, s_inj, y_bus, forest)
    leaf = next(i for i in range(d.shape[1]) if not (forest.parent == i).any())  # no child updates its block
    d[0, leaf] = 0.0  # env 0: a zero diagonal block
    x = ts.block_tree_solve(d, low, up, torch.ones(len(s), d.shape[1], 2, dtype=d.dtype), forest)
    assert not torch.isfinite(x[0]).all() and torch.isfinite(x[1:]).all()


def test_which_batches_go_to_the_tree():
    anm6 = network_simulator("anm6_easy", backend="torch").net.y_bus
    assert ts.use_tree(anm6, 10 ** 6) is None  # below BANDED_MIN_BUS: always dense (bit-identical ANM6-Easy)
    c33 = network_simulator("case33bw", backend="torch").net.y_bus
    assert ts.use_tree(c33, 1) is None and ts.use_tree(c33, 1024) is not None
    cigre = network_simulator("cigre_mv", backend="torch").net.y_bus
    assert ts.bus_forest(cigre) is not None  # radial with its switches open
    meshed = generate(5, n_bus=30, meshed=True)
    sim = network_simulator(meshed.network, meshed.load_p, meshed.gen_p_max, backend="torch")
    assert ts.bus_forest(sim.net.y_bus) is None
