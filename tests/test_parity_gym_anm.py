"""Parity of ``anm_torchrl`` with gym-anm 2.0.1's ANM6-Easy (spec §5, §8.2).

(a) The golden trajectory of spec §5.4 (reset(seed=0), 5 steps, the terminal step).
(b) A differential test on ``tests/fixtures/gym_anm_transitions.npz`` (recorded from gym-anm itself by
    ``tests/fixtures/record_gym_anm.py``), every transition stepped in ONE batch: through ``GridSimulator.step``
    and through ``ANM6Env`` (``reset(..., set_state=True)``, float32 actions).
(c) Live checks against gym-anm (skipped if it is not installed): ~200 mixed steps in lockstep, and the reset
    RNG replay of spec §5.2 (``default_rng(seed)``: integers(0, 96), uniform(-0.3, 0.3), uniform(-0.5, 0.5),
    uniform(0, 1) [MWh], then integers(1, 365) for the rendering date).

Tolerances: states within 1e-6 (MW/MVAr/MWh), rewards within 1e-6 relative, identical terminations.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from anm_torchrl.benchmarks.parity import (ANM6_FIXTURE, FIXTURES, REWARD_RTOL, STATE_TOL, compare, fixture_env,
                                           load_fixture, reference_observation, step_recorded)
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.grid import reset as grid_reset

torch.set_num_threads(1)

FIXTURE = FIXTURES / f"{ANM6_FIXTURE}.npz"
TERMINAL_REWARD = -19999.99999999998

GOLDEN_RESET_OBS = [25.34521365, -5, 4, -10, 11, -25, 0, 10.48302624, -1, -0.13812797, -2, -0.45902648, -5, 0,
                    0.01652764, 4, 11, 81]
# action, reward, ΔE, λΦ, {state index: value}
GOLDEN_STEPS = [
    ([30, 50, 0, 0, 0, 0], -2.0304756758, 0.0008523380, 2.0296233378, {0: 25.34093521, 7: 9.85766598, 17: 82}),
    ([10, 20, -5, 5, -20, 10], -15.5845509242, 0.0526416206, 15.5319093036,
     {0: 46.05664823, 6: -20, 13: 10, 14: 4.51652764}),
    ([0, 0, 30, -50, 50, -50], -90.2679344265, 0.0247955617, 90.2431388648,
     {6: 16.25949949, 13: -50, 14: 0, 7: 119.53225096}),
    ([30, 50, 30, 50, -50, 50], -73.8331634091, 0.1039865100, 73.7291768991,
     {6: -37.80487805, 13: 40.24390244, 14: 8.50609756}),
    ([25, 40, -10, -10, 30, -30], -24.2368619861, -0.0709838179, 24.3078458041,
     {6: 30, 14: 0.17276423, 0: -18.39352716}),
]
GOLDEN_BRANCH_S_STEP1 = [27.19, 25.44, 1.42, 2.24, 25.67]  # |S| MVA after step 1
GOLDEN_V_EXTREMES = {3: ("min", 0.687), 4: ("max", 1.191)}  # after steps 3 and 4
TERMINAL_ACTION = [30, 50, -30, -50, 0, -50]


def replay_reset_draws(seed: int, n_resets: int = 1):
    """gym-anm's reset draws from ``default_rng(seed)`` for ``n_resets`` successive resets (spec §5.1–5.2).

    Returns a list of (t0, [Q PV, Q wind] MVAr, SoC MWh). The rendering-date draw integers(1, 365) that
    ``ANM6.reset`` makes after each initial state is consumed too.
    """
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_resets):
        t0 = int(rng.integers(0, 96))
        q = [rng.uniform(-0.3, 0.3), rng.uniform(-0.5, 0.5)]  # p.u. bounds used as MVAr (unit quirk)
        soc = rng.uniform(0.0, 1.0)  # p.u.·h bounds used as MWh (unit quirk)
        rng.integers(1, 365)
        out.append((t0, q, soc))
    return out


def initial_states(sim, draws) -> tuple[torch.Tensor, torch.Tensor]:
    """``grid.reset.initial_state`` for a list of (t0, q, soc) draws: (state (n, 18), converged (n,))."""
    t0 = torch.tensor([d[0] for d in draws], dtype=torch.long)
    q = torch.tensor([d[1] for d in draws], dtype=torch.float64)
    soc = torch.tensor([[d[2]] for d in draws], dtype=torch.float64)
    state, extra = grid_reset.initial_state(sim, t0, q, soc)
    converged = extra if isinstance(extra, torch.Tensor) else extra.converged
    return state, converged


# ------------------------------------------------------------------------------------------ (a) golden values
# every parity test of the physics runs on both backends: batched torch ops and the compiled numba loop
BACKENDS = pytest.mark.parametrize("backend", ["torch", "numba"])


@BACKENDS
def test_golden_trajectory_grid(backend):
    sim = network_simulator(ANM6_EASY, backend=backend)
    assert sim.backend == backend
    draws = replay_reset_draws(0)
    assert draws[0][0] == 81
    state, ok = initial_states(sim, draws)
    assert ok.all()
    np.testing.assert_allclose(state[0].numpy(), GOLDEN_RESET_OBS, rtol=0, atol=6e-9)
    s0 = state.clone()
    for k, (action, r, e_loss, pen, entries) in enumerate(GOLDEN_STEPS, start=1):
        state, tr = sim.step(state, torch.tensor([action], dtype=torch.float64))
        assert tr.converged.item()
        assert tr.reward.item() == pytest.approx(r, abs=1e-9), k
        assert tr.e_loss.item() == pytest.approx(e_loss, abs=1e-9), k
        assert tr.penalty.item() == pytest.approx(pen, abs=1e-9), k
        for i, v in entries.items():
            assert state[0, i].item() == pytest.approx(v, abs=6e-9), (k, i)
        if k == 1:
            s_abs = (tr.s_apparent_max.abs() * 100).squeeze(0).numpy()
            np.testing.assert_allclose(s_abs, GOLDEN_BRANCH_S_STEP1, atol=6e-3)
        if k in GOLDEN_V_EXTREMES:
            kind, v = GOLDEN_V_EXTREMES[k]
            vm = tr.v.abs()
            assert (vm.min() if kind == "min" else vm.max()).item() == pytest.approx(v, abs=6e-4), k
    # From the reset state, a strongly capacitive-absorbing action makes the power flow diverge.
    nxt, tr = sim.step(s0, torch.tensor([TERMINAL_ACTION], dtype=torch.float64))
    assert not tr.converged.item()
    assert tr.reward.item() == TERMINAL_REWARD
    assert torch.count_nonzero(nxt) == 0


@BACKENDS
def test_golden_trajectory_env(backend):
    """The same golden steps through ``ANM6Env`` (float32 actions and rewards), from ``set_state``."""
    from tensordict import TensorDict

    anm6 = pytest.importorskip("anm_torchrl.envs.anm6")
    sim = network_simulator(ANM6_EASY)
    s0, _ = initial_states(sim, replay_reset_draws(0))
    env = anm6.ANM6Env(num_envs=1, seed=0, backend=backend)
    td = env.reset(TensorDict({"state": s0}, [1]), set_state=True)
    np.testing.assert_allclose(td["observation"][0].numpy(), np.float32(GOLDEN_RESET_OBS), rtol=1e-6, atol=1e-6)
    for k, (action, r, e_loss, pen, entries) in enumerate(GOLDEN_STEPS, start=1):
        td["action"] = torch.tensor([action], dtype=torch.float32)
        td = env.step(td)["next"]
        assert not td["terminated"].item()
        assert td["reward"].item() == pytest.approx(r, rel=1e-6), k
        assert td["grid", "penalty"].item() == pytest.approx(pen, rel=1e-6), k
        for i, v in entries.items():
            assert td["state"][0, i].item() == pytest.approx(v, abs=6e-9), (k, i)
    td = env.reset(TensorDict({"state": s0}, [1]), set_state=True)
    td["action"] = torch.tensor([TERMINAL_ACTION], dtype=torch.float32)
    out = env.step(td)["next"]
    assert out["terminated"].item() and out["done"].item()
    assert out["reward"].item() == pytest.approx(TERMINAL_REWARD, rel=1e-7)
    assert torch.count_nonzero(out["state"]) == 0


# ------------------------------------------------------------------------------------------ (b) differential
@pytest.fixture(scope="module")
def fixture_data():
    if not FIXTURE.exists():
        pytest.skip(f"{FIXTURE} missing: run tests/fixtures/record_gym_anm.py")
    return load_fixture(ANM6_FIXTURE)


def test_fixture_coverage(fixture_data):
    """The recording exercises what it claims: ≥ 2,000 transitions, terminations, both SoC rows binding."""
    d = fixture_data
    n = len(d["reward"])
    assert n >= 2000
    assert d["state"].dtype == np.float64 and d["state"].shape == (n, 18) and d["next_state"].shape == (n, 18)
    assert np.array_equal(np.float32(d["action"]).astype(np.float64), d["action"])  # float32-exact actions
    assert d["terminated"].sum() >= 5
    assert np.all(d["next_state"][d["terminated"]] == 0)
    assert np.all(d["reward"][d["terminated"]] == TERMINAL_REWARD)
    live = ~d["terminated"]
    soc_before, soc_after = d["state"][live, 14], d["next_state"][live, 14]
    assert ((soc_before > 88.75) & (d["action"][live, 4] < 0) & (soc_after == 100.0)).sum() >= 20  # charge row
    assert ((soc_before < 13.89) & (d["action"][live, 4] > 0) & (soc_after == 0.0)).sum() >= 20  # discharge row
    assert set(np.unique(d["stream"]).tolist()) == set(range(len(d["stream_names"])))
    assert (d["state"][:, 17] < 25).any() and (d["state"][:, 17] > 50).any()  # night (P_pot PV = 0) and day


def _compare(name, next_state, reward, terminated, d) -> dict:
    stats = compare(d, next_state, reward, terminated)
    print(f"{name}: {stats}")
    assert stats["terminations_ok"], stats
    assert stats["max_abs_state_diff"] <= STATE_TOL, stats
    assert stats["max_rel_reward_diff"] <= REWARD_RTOL, stats
    return stats


@BACKENDS
def test_differential_grid(fixture_data, backend):
    d = fixture_data
    sim = network_simulator(ANM6_EASY, backend=backend)
    nxt, tr = sim.step(torch.as_tensor(d["state"]), torch.as_tensor(d["action"]))
    _compare(f"GridSimulator.step ({backend})", nxt.numpy(), tr.reward.numpy(), (~tr.converged).numpy(), d)


@BACKENDS
def test_differential_env(fixture_data, backend):
    d = fixture_data
    n = len(d["reward"])
    from tensordict import TensorDict

    env = fixture_env(ANM6_FIXTURE, d, backend)
    td = env.reset(TensorDict({"state": torch.as_tensor(d["state"])}, [n]), set_state=True)
    torch.testing.assert_close(td["state"], torch.as_tensor(d["state"]), rtol=0, atol=0)
    out = step_recorded(env, d)
    assert out["state"].dtype == torch.float64 and out["observation"].dtype == torch.float32
    assert out["reward"].shape == (n, 1) and out["reward"].dtype == torch.float32
    assert out["terminated"].shape == (n, 1) and out["terminated"].dtype == torch.bool
    stats = _compare(f"ANM6Env.step ({backend})", out["state"].numpy(), out["reward"].squeeze(1).double().numpy(),
                     out["terminated"].squeeze(1).numpy(), d)
    assert torch.equal(out["done"], out["terminated"])
    # Observation = clip(state) to gym-anm's bounds, in float32.
    np.testing.assert_allclose(out["observation"].numpy(), reference_observation(d, env), rtol=2e-7, atol=STATE_TOL)
    assert stats["terminal"] > 0


def test_reset_replay_from_fixture(fixture_data):
    """The fixture's reset observations (50 seeds) equal ``initial_state`` of the replayed draws."""
    d = fixture_data
    sim = network_simulator(ANM6_EASY)
    draws = [replay_reset_draws(int(s))[0] for s in d["reset_seeds"]]
    state, ok = initial_states(sim, draws)
    assert ok.all()
    low, high = sim.state_bounds()
    obs = torch.clamp(state, low, high).numpy()
    err = np.abs(obs - d["reset_obs"]).max()
    print(f"reset replay over {len(draws)} seeds: max |Δobs| = {err:.2e}")
    assert err <= STATE_TOL


# ----------------------------------------------------------------------------------------------- (c) live
def _gym_env():
    pytest.importorskip("gym_anm")
    from gym_anm.envs import ANM6Easy

    warnings.filterwarnings("ignore", module="gym_anm")
    return ANM6Easy()


def test_live_reset_replay():
    env = _gym_env()
    sim = network_simulator(ANM6_EASY)
    seeds = [0, 1, 2, 3, 4, 17, 123, 2024]
    draws, ref_states, ref_obs = [], [], []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        ref_obs.append(obs)
        ref_states.append(env.state.copy())
        # Two further unseeded resets continue the same stream (the date draw must be consumed).
        for _ in range(2):
            obs, _ = env.reset()
            ref_obs.append(obs)
            ref_states.append(env.state.copy())
        draws += replay_reset_draws(seed, 3)
    state, ok = initial_states(sim, draws)
    assert ok.all()
    err_state = np.abs(state.numpy() - np.array(ref_states)).max()
    low, high = sim.state_bounds()
    err_obs = np.abs(torch.clamp(state, low, high).numpy() - np.array(ref_obs)).max()
    print(f"live reset replay ({len(draws)} resets): max |Δstate| = {err_state:.2e}, |Δobs| = {err_obs:.2e}")
    assert err_state <= 1e-8 and err_obs <= 1e-8
    # The golden reset(seed=0) observation of spec §5.4.
    np.testing.assert_allclose(ref_obs[0], GOLDEN_RESET_OBS, rtol=0, atol=6e-9)


@BACKENDS
def test_live_lockstep_200_steps(backend):
    """~200 steps of gym-anm with mixed actions; each transition is re-simulated from gym-anm's own state."""
    env = _gym_env()
    sim = network_simulator(ANM6_EASY, backend=backend)
    rng = np.random.default_rng(99)
    low = np.array([0, 0, -30, -50, -50, -50], dtype=np.float64)
    high = np.array([30, 50, 30, 50, 50, 50], dtype=np.float64)

    def action(k: int) -> np.ndarray:
        kind = (k // 20) % 5
        if kind == 0:
            a = rng.uniform(low, high)
        elif kind == 1:
            a = np.array([30, 50, 0, 0, 0, 0]) + rng.normal(0, 0.5, 6)
        elif kind == 2:
            a = np.array([30, 50, 0, 0, -50, 0]) + rng.normal(0, 2, 6)  # charge
        elif kind == 3:
            a = np.array([30, 50, 0, 0, 50, 0]) + rng.normal(0, 2, 6)  # discharge
        else:
            a = np.where(rng.random(6) < 0.5, low, high)
            if k % 10 == 0:
                a = np.array(TERMINAL_ACTION, dtype=np.float64)
        return np.clip(np.float32(a).astype(np.float64), low, high)

    env.reset(seed=31)
    states, actions, nexts, rewards, terms = [], [], [], [], []
    for k in range(200):
        a = action(k)
        states.append(env.state.copy())
        _, r, term, _, _ = env.step(a)
        actions.append(a)
        nexts.append(env.state.copy())
        rewards.append(r)
        terms.append(term)
        if term:
            env.reset(seed=1000 + k)
    d = {"next_state": np.array(nexts), "reward": np.array(rewards), "terminated": np.array(terms)}
    nxt, tr = sim.step(torch.as_tensor(np.array(states)), torch.as_tensor(np.array(actions)))
    stats = _compare("live lockstep", nxt.numpy(), tr.reward.numpy(), (~tr.converged).numpy(), d)
    assert stats["terminal"] >= 1
    # Sequential consistency: our own trajectory from the first state follows gym-anm's until its first reset.
    first_term = int(np.argmax(d["terminated"])) if d["terminated"].any() else len(actions)
    s = torch.as_tensor(states[0]).unsqueeze(0)
    for k in range(first_term + 1):
        s, tr = sim.step(s, torch.as_tensor(actions[k]).unsqueeze(0))
        assert np.abs(s[0].numpy() - nexts[k]).max() <= STATE_TOL, k
        assert (not tr.converged.item()) == bool(terms[k])


def test_live_golden_and_do_nothing_day():
    """Spec §5.4 golden steps and the §4.3 do-nothing day, computed by gym-anm now and by us."""
    env = _gym_env()
    sim = network_simulator(ANM6_EASY)
    env.reset(seed=0)
    s_ref = [env.state.copy()]
    r_ref = []
    for action, r, *_ in GOLDEN_STEPS:
        _, rr, term, _, _ = env.step(np.array(action, dtype=np.float64))
        assert not term and rr == pytest.approx(r, abs=1e-9)
        s_ref.append(env.state.copy())
        r_ref.append(rr)
    state = torch.as_tensor(s_ref[0]).unsqueeze(0)
    for k, (action, *_) in enumerate(GOLDEN_STEPS):
        state, tr = sim.step(state, torch.tensor([action], dtype=torch.float64))
        assert np.abs(state[0].numpy() - s_ref[k + 1]).max() <= 1e-7
        assert tr.reward.item() == pytest.approx(r_ref[k], rel=1e-8)
    env.reset(seed=0)
    _, r_term, term, _, _ = env.step(np.array(TERMINAL_ACTION, dtype=np.float64))
    assert term and r_term == TERMINAL_REWARD and np.all(env.state == 0)
    # One day of do-nothing from t = 95 (the first step lands on t = 0).
    env.reset(seed=0)
    env.unwrapped.state[17] = 95
    a = np.array([30, 50, 0, 0, 0, 0], dtype=np.float64)
    states, rewards = [], []
    for _ in range(96):
        states.append(env.state.copy())
        _, r, term, _, _ = env.step(a)
        assert not term
        rewards.append(r)
    nxt, tr = sim.step(torch.as_tensor(np.array(states)), torch.as_tensor(np.tile(a, (96, 1))))
    np.testing.assert_allclose(tr.reward.numpy(), rewards, rtol=1e-8)
    assert sum(rewards) == pytest.approx(-413.84, abs=6e-3)
