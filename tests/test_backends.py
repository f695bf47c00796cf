"""Per-stage differential tests of the two physics backends (torch, numba) on random generic networks.

One random network per seed (radial or meshed, 4-14 buses, taps / shifts / line charging, every device type
in random numbers: zero or several generators and storage units, SOC_MIN > 0, own EFF, corners present or
absent, ``None`` bounds; seeds 0-11 include networks without generators, storage or loads). Both backends step the same states and actions; each stage is compared on its own so
that a mismatch names it: projection (device P, Q), SoC update, power flow (convergence, iterations, V),
branch flows, reward terms. Tolerance 1e-9 (p.u. / MWh): the same algorithms in a different order of float64
operations; observed gaps are ~1e-13.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.networks.random import small_random_network as random_network

pytest.importorskip("numba")
torch.set_num_threads(1)
TOL = 1e-9
N_ = np.nan


def _loop_without_slack(branch: np.ndarray, n_bus: int) -> bool:
    """Whether the branches between non-slack buses close a loop (union-find)."""
    root = list(range(n_bus))

    def find(i: int) -> int:
        while root[i] != i:
            i = root[i]
        return i

    for f, t in branch[:, :2].astype(int):
        if 0 in (f, t):
            continue
        a, b = find(f), find(t)
        if a == b:
            return True
        root[a] = b
    return False


def _stages(tr, sim):
    g, d = sim.gen_idx, sim.des_idx
    return {
        "projection (generators)": (torch.stack([tr.p_dev[:, g], tr.q_dev[:, g]], -1), None),
        "projection (storage)": (torch.stack([tr.p_dev[:, d], tr.q_dev[:, d]], -1), None),
        "SoC update": (tr.soc, None),
        "power flow (voltages)": (tr.v, "ok"),
        "branch flows": (tr.s_apparent_max, "ok"),
        "reward terms": (torch.stack([tr.e_loss, tr.penalty, tr.curtailment, tr.reward], -1), "ok"),
    }


@pytest.mark.parametrize("solver", ["dense", "band", "tree"])
@pytest.mark.parametrize("seed", range(12))
def test_backends_agree_stage_by_stage(seed, solver):
    """torch vs numba with the dense LU, the RCM-ordered band LU or the tree block LU of the Newton step."""
    rng = np.random.default_rng(seed)
    net, load_p, gen_p_max = random_network(rng)
    sims = [GridSimulator.from_tables(net, load_p, gen_p_max, 0.25, 0.99, 100.0, (1.0, 100.0), backend=b,
                                      linear_solver=solver) for b in ("torch", "numba")]
    if solver == "tree" and _loop_without_slack(net["branch"], len(net["bus"])):  # the tree solver refuses it
        with pytest.raises(ValueError, match="radial network"):
            sims[1].constants
        return
    c = sims[1].constants
    assert (c.kl < 2 * sims[1].net.n_bus - 3) == (solver != "dense") and (c.parent.size > 0) == (solver == "tree")
    lo, hi = sims[0].action_bounds()
    n = 400
    action = lo + torch.as_tensor(rng.random((n, lo.numel()))) * (hi - lo)
    soc_lo = sims[0].net.dev[sims[0].des_idx, 13] * 100
    soc_hi = sims[0].net.dev[sims[0].des_idx, 12] * 100
    state = torch.zeros(n, sims[0].state_dim, dtype=torch.float64)
    sl = sims[0].state_slices()
    state[:, sl["des_soc"]] = soc_lo + torch.as_tensor(rng.random((n, soc_lo.numel()))) * (soc_hi - soc_lo)
    state[:, sl["aux"]] = torch.as_tensor(rng.integers(0, 12, (n, 1)), dtype=torch.float64)
    (n0, t0), (n1, t1) = (s.step(state, action) for s in sims)
    assert torch.equal(t0.converged, t1.converged), "power flow (convergence)"
    assert torch.equal(t0.n_iter, t1.n_iter), "power flow (iterations)"
    ok = t0.converged
    assert ok.float().mean() > 0.5, "most random steps should converge (else this tests little)"
    s0, s1 = _stages(t0, sims[0]), _stages(t1, sims[1])
    for stage, (a, rows) in s0.items():
        b = s1[stage][0]
        if rows == "ok":
            a, b = a[ok], b[ok]
        torch.testing.assert_close(b, a, rtol=0, atol=TOL, msg=lambda m, stage=stage: f"stage {stage}: {m}")
    torch.testing.assert_close(n1, n0, rtol=0, atol=TOL, msg=lambda m: f"next state: {m}")


def test_backend_registry_resolves_once_by_name():
    """``get_backend`` is the one place a backend name is resolved: an unknown name is refused naming the known
    ones, a backend that cannot run a network says why, and ``auto`` picks numba for a float64 CPU network."""
    from anm_torchrl.grid.backends import get_backend, list_backends

    net, load_p, gen_p_max = random_network(np.random.default_rng(0))
    sim = GridSimulator.from_tables(net, load_p, gen_p_max, 0.25, 0.995, 100.0, (1.0, 100.0))
    assert sim.backend == "numba" and sim.physics is get_backend("numba")
    with pytest.raises(ValueError, match=r"unknown backend 'gpu'; known: \['auto', 'torch', 'numba'\]"):
        get_backend("gpu")
    assert list_backends() == ["auto", "torch", "numba"]
    with pytest.raises(ValueError, match="cannot run this network: it needs a float64 network on the CPU"):
        get_backend("numba", _Float32Net(sim.net))


class _Float32Net:
    """A stand-in network whose device table is float32 (the numba backend refuses it)."""

    def __init__(self, net):
        self.dev = net.dev.float()


def test_the_compiled_kernel_is_loaded_once_per_process(monkeypatch):
    """The first transition of a process loads (or compiles) the kernel and says so; later calls go straight to it
    (a module flag, not numba's ``signatures`` property, which re-hashes the argument types on every call)."""
    import anm_torchrl.grid.backends.numba as nb
    from anm_torchrl.networks import simulator as network_simulator
    from anm_torchrl.surrogates.pinn.evaluate import random_transitions

    sim = network_simulator("anm6_easy", backend="numba")
    state, action = random_transitions(sim, 4, seed=0)
    first, _ = sim.step(state, action)
    assert nb._KERNEL_READY
    monkeypatch.setattr(nb, "_first_call", lambda run: pytest.fail("the kernel was loaded a second time"))
    again, _ = sim.step(state, action)
    assert torch.equal(first, again)
