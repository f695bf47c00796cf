"""The torch backend's Newton Jacobians are built and solved in chunks of bounded memory, with the same numbers.

Unbounded, one Newton step on a 320-bus feeder holds N·638²·8 B = 3.3 MB per env several times over (2.35 GB at
256 envs, > 8 GB at 1,024: issue 25); ``powerflow.JACOBIAN_BUDGET_BYTES`` caps it. Each matrix is factorised on
its own whether batched with others or not, so chunking must not change a bit of the result or of the implicit
gradient.
"""

from __future__ import annotations

import pytest
import torch

import anm_torchrl.grid.powerflow as pf
from anm_torchrl.grid.implicit import implicit_power_flow
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.surrogates.pinn.evaluate import random_transitions


@pytest.fixture(scope="module")
def injections():
    sim = network_simulator("case33bw", backend="torch")
    state, action = random_transitions(sim, 48, seed=11)
    _, trn = sim.step(state, action)
    s = torch.complex(trn.p_dev @ sim.net.incidence, trn.q_dev @ sim.net.incidence)
    s[:, 0] = 0
    return sim.net.y_bus, s


def test_chunk_rows_fit_the_budget():
    m = 2 * 319  # a 320-bus network's Jacobian
    rows = pf.jacobian_rows(1024, m)
    assert 1 <= rows < 1024 and rows * pf._JACOBIAN_COPIES * m * m * 8 <= pf.JACOBIAN_BUDGET_BYTES
    assert pf.jacobian_rows(1024, 10) == 1024  # small networks stay one batch
    assert pf.jacobian_rows(5, 10 ** 6) == 1  # never zero


def test_chunked_newton_is_bit_identical(injections, monkeypatch):
    y_bus, s = injections
    whole = pf.newton_raphson(y_bus, s)
    m = 2 * (s.shape[1] - 1)
    monkeypatch.setattr(pf, "JACOBIAN_BUDGET_BYTES", 5 * pf._JACOBIAN_COPIES * m * m * 8)  # 5 rows per chunk
    assert pf.jacobian_rows(len(s), m) == 5
    chunked = pf.newton_raphson(y_bus, s)
    assert whole.converged.all()
    assert torch.equal(whole.v, chunked.v) and torch.equal(whole.n_iter, chunked.n_iter)


def test_chunked_implicit_gradient_is_bit_identical(injections, monkeypatch):
    y_bus, s = injections

    def grads():
        p, q = s.real.clone().requires_grad_(), s.imag.clone().requires_grad_()
        v = implicit_power_flow(y_bus, torch.complex(p, q)).v
        (v.abs() ** 2).sum().backward()
        return p.grad, q.grad

    gp, gq = grads()
    m = 2 * (s.shape[1] - 1)
    monkeypatch.setattr(pf, "JACOBIAN_BUDGET_BYTES", 7 * pf._JACOBIAN_COPIES * m * m * 8)
    cp, cq = grads()
    assert gp.abs().sum() > 0
    assert torch.equal(gp, cp) and torch.equal(gq, cq)
