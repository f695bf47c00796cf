"""The compiled CPU hot path equals the torch reference: the one-pass step checks (``grid/fastchecks.py``) accept
exactly what the torch checks accept and return the same clamped action, the output assembly
(``grid/fastoutput.py``) writes the same bits, and the small-network (dense) Newton path equals the generic one
bit for bit."""

import numpy as np
import pytest
import torch

from anm_torchrl.envs.specs import ActionBox, check_action
from anm_torchrl.grid import devices as dv
from anm_torchrl.grid import fastchecks
from anm_torchrl.grid.backends.numba import CompiledTransition, _flat_start_lu, available
from anm_torchrl.grid.state import check_state
from anm_torchrl.networks import anm6_easy
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.grid import reset as grid_reset

pytestmark = pytest.mark.skipif(not available(), reason="numba not installed")


def _torch_accepts(fn) -> bool:
    try:
        fn()
    except ValueError:
        return False
    return True


@pytest.fixture(scope="module")
def sim():
    return network_simulator(ANM6_EASY, backend="numba")


def _states(sim, n=64):
    """Valid states, then one corruption per row kind (each must be rejected by both checks)."""
    gen = torch.Generator().manual_seed(0)
    state, _ = grid_reset.gym_anm_reset(sim, n, gen)
    sl, soc_max = sim.state_slices(), float(sim.net.dev[sim.des_idx[0], dv.SOC_MAX] * sim.net.base_mva)
    bad = []
    for col, value in ((3, float("nan")), (0, float("inf")), (sl["des_soc"].start, -1e-9),
                       (sl["des_soc"].start, soc_max + 1e-9), (sl["aux"].start, 2.5), (sl["aux"].start, -1.0),
                       (sl["aux"].start, float(sim.n_time))):
        s = state.clone()
        s[n // 2, col] = value
        bad.append(s)
    edges = state.clone()
    edges[0, sl["des_soc"].start], edges[1, sl["des_soc"].start] = 0.0, soc_max  # bounds are inclusive
    edges[2, sl["aux"].start], edges[3, sl["aux"].start] = 0.0, sim.n_time - 1
    return [state, edges], bad


def test_state_check_agrees_with_torch(sim):
    good, bad = _states(sim)
    d, b = sim.net.dev[sim.des_idx], sim.net.base_mva
    lo, hi = d[:, dv.SOC_MIN] * b, d[:, dv.SOC_MAX] * b  # MWh
    sl = sim.state_slices()
    for s, expected in [(s, True) for s in good] + [(s, False) for s in bad]:
        torch_ok = _torch_accepts(lambda: check_state(s, sim.state_sizes, lo, hi, sim.n_time))
        fast_ok = fastchecks.state_ok(s, sl["des_soc"].start, lo.numpy(), hi.numpy(), sl["aux"].start, sim.n_time)
        assert torch_ok == fast_ok == expected
    # no time-index rule (a user next_vars reads aux): a fractional aux passes both
    s = good[0].clone()
    s[0, sl["aux"].start] = 2.5
    assert fastchecks.state_ok(s, sl["des_soc"].start, lo.numpy(), hi.numpy(), sl["aux"].start, None)
    assert _torch_accepts(lambda: check_state(s, sim.state_sizes, lo, hi, None))


@pytest.mark.parametrize("clip", [False, True])
def test_action_check_agrees_with_torch(sim, clip):
    low, high = sim.action_bounds()
    box = ActionBox.of(low, high)
    gen = torch.Generator().manual_seed(1)
    inside = (low + torch.rand(256, low.numel(), generator=gen, dtype=torch.float64) * (high - low)).float()
    spec_edges = torch.stack([low.float(), high.float()])  # float32-rounded bounds: accepted, clamped to the box
    outside = inside.clone()
    outside[7, 2] = float(high[2]) * 1.01 + 1.0
    nonfinite = inside.clone()
    nonfinite[3, 0] = float("nan")
    for a in (inside, spec_edges, outside, nonfinite):
        fast = fastchecks.clamp_action(a, *box.arrays, clip)
        a64 = a.to(torch.float64)
        ref = torch.clamp(a64, low, high)  # what the torch path returns when it accepts
        in_box = bool(((a64 >= box.accept_low) & (a64 <= box.accept_high)).all())
        torch_ok = bool(torch.isfinite(a64).all()) and (clip or in_box)
        assert (fast is not None) == bool(torch_ok)
        if fast is not None:
            assert torch.equal(fast, ref)
            assert torch.equal(check_action(a, box, clip), ref)  # the env entry point takes the fast path
        else:
            with pytest.raises(ValueError):
                check_action(a, box, clip)


def test_dense_newton_path_is_bit_identical(sim):
    """ANM6-Easy runs the dense Newton path; forcing the generic (CSR, band LU) path on the same dense layout
    must give the same bits in every output."""
    c = sim.constants
    assert c.dense
    generic = c._replace(dense=False)
    generic = generic._replace(**dict(zip(("lu0", "piv0", "ok0"),
                                          _flat_start_lu(c.y, c.ycsr, False, c.ix, c.kl, c.ku, c.parent))))
    gen = torch.Generator().manual_seed(2)
    n = 512
    state, _ = grid_reset.gym_anm_reset(sim, n, gen)
    low, high = sim.action_bounds()
    a = (low + torch.rand(n, low.numel(), generator=gen, dtype=torch.float64) * (high - low)) / sim.net.base_mva
    soc = state[:, sim.state_slices()["des_soc"]] / sim.net.base_mva
    t = torch.randint(0, sim.n_time, (n,), generator=gen)
    args = (soc, sim.load_series[:, t].T.contiguous(), sim.p_max_series[:, t].T.contiguous(), a)
    out_dense, out_generic = CompiledTransition(c)(*args), CompiledTransition(generic)(*args)
    assert (~out_dense["converged"]).any() or out_dense["n_iter"].max() > 1  # the loop ran past its first step
    for k, v in out_dense.items():
        assert np.array_equal(v.numpy(), out_generic[k].numpy(), equal_nan=True), k


def test_compiled_outputs_equal_the_torch_ops(sim):
    """``fastoutput`` writes what GridSimulator.build_state's and ANMEnv._output's torch ops give, bit for bit
    (terminal rows included: the batch below has non-converged rows)."""
    from anm_torchrl.grid import fastoutput

    gen = torch.Generator().manual_seed(3)
    n = 2048
    state, _ = grid_reset.gym_anm_reset(sim, n, gen)
    low, high = sim.action_bounds()
    a = low + torch.rand(n, low.numel(), generator=gen, dtype=torch.float64) * (high - low) * 1.5  # some collapse
    t = torch.randint(0, sim.n_time, (n,), generator=gen)
    b = sim.net.base_mva
    tr = sim.apply(state[:, sim.state_slices()["des_soc"]] / b, sim.load_series[:, t].T, sim.p_max_series[:, t].T,
                   a / b)
    assert (~tr.converged).any() and tr.converged.any()
    ref = torch.cat([tr.p_dev * b, tr.q_dev * b, tr.soc * b, tr.p_pot * b, t.reshape(-1, 1).to(tr.p_dev)], 1)
    ref = torch.where(tr.converged.unsqueeze(1), ref, torch.zeros_like(ref))
    built = fastoutput.build_state(tr, t, b)
    assert torch.equal(built, ref)
    o_low, o_high = sim.state_bounds()
    out = fastoutput.env_outputs(built, tr, b, o_low.numpy(), o_high.numpy())
    obs = torch.minimum(torch.maximum(built, o_low), o_high)
    obs = torch.where(tr.converged.unsqueeze(1), obs, torch.zeros_like(obs)).to(torch.float32)
    expected = {"observation": obs, "v_magn": tr.v.abs().float(), "branch_s": (tr.s_apparent_max * b).float(),
                "e_loss": tr.e_loss.float().unsqueeze(1), "penalty": tr.penalty.float().unsqueeze(1),
                "curtailment": (tr.curtailment * b).float().unsqueeze(1), "reward": tr.reward.float().unsqueeze(1),
                "terminated": (~tr.converged).unsqueeze(1)}
    for k, v in expected.items():
        assert torch.equal(out[k], v), k


def test_step_follows_replaced_and_rescaled_series():
    """GridSimulator.step gathers the exogenous rows from a cached copy of the series: replacing a series (as
    experiments do) or scaling it in place must show in the next step, exactly as next_vars gives it."""
    sim = network_simulator(ANM6_EASY, backend="numba")
    state, _ = grid_reset.gym_anm_reset(sim, 8, torch.Generator().manual_seed(4))
    a = torch.zeros(8, sim.action_dim, dtype=torch.float64)
    lid = sim.state_slices()["dev_p"].start + sim.load_idx
    for change in (lambda: None, lambda: setattr(sim, "load_series", sim.load_series * 1.1),
                   lambda: sim.load_series.mul_(0.9)):
        change()
        nxt, tr = sim.step(state, a)
        p_load = sim.next_vars(state)[0]
        dev = sim.net.dev[sim.load_idx]
        expected = torch.clamp(p_load / sim.net.base_mva, dev[:, dv.PMIN], dev[:, dv.PMAX])
        ok = tr.converged
        assert torch.equal(nxt[ok][:, lid], (expected * sim.net.base_mva)[ok])
