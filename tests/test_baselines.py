"""Baselines: do-nothing, random, and the MPC DC-OPF (constraints of its plan, parity with gym-anm's agents)."""

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from anm_torchrl.baselines import DoNothingPolicy, MPCPolicy, RandomPolicy, make_baseline
from anm_torchrl.evaluation import EVAL_GAMMA
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.grid import devices as dv
from anm_torchrl.grid import reset as grid_reset

torch.set_num_threads(1)

A_LOW = np.array([0, 0, -30, -50, -50, -50], dtype=np.float64)
A_HIGH = np.array([30, 50, 30, 50, 50, 50], dtype=np.float64)
GAMMA = EVAL_GAMMA  # gym-anm-exp's MPC discount


@pytest.fixture(scope="module")
def sim():
    return network_simulator(ANM6_EASY)


@pytest.fixture(scope="module")
def states(sim):
    """Initial states plus states after a few random-policy steps (non-trivial SoC), float64 (N, 18)."""
    g = torch.Generator().manual_seed(3)
    s0 = grid_reset.gym_anm_reset(sim, 6, generator=g, intended=True)[0]
    s = s0
    pol = RandomPolicy(seed=1, sim=sim)
    for _ in range(3):
        a = pol(TensorDict({"state": s}, [s.shape[0]]))["action"].double()
        s, tr = sim.step(s, a)
        assert bool(tr.converged.all())
    return torch.cat([s0, s])


def _td(states):
    return TensorDict({"state": states, "observation": states.float()}, batch_size=states.shape[:-1])


# ------------------------------------------------------------------------------------------------ simple
def test_do_nothing_exact_action_any_batch_shape(sim, states):
    pol = DoNothingPolicy(sim)
    out = pol(_td(states))["action"]
    assert out.dtype == torch.float32 and out.shape == (states.shape[0], 6)
    assert torch.equal(out, torch.tensor([30, 50, 0, 0, 0, 0], dtype=torch.float32).expand_as(out))
    out2 = pol(_td(states[:6].reshape(2, 3, 18)))["action"]
    assert out2.shape == (2, 3, 6) and torch.equal(out2[1, 2], out[0])
    assert torch.equal(make_baseline("do_nothing")(_td(states[:1]))["action"][0], out[0])


def test_random_in_box_and_seeded(sim, states):
    td = _td(states.repeat(50, 1))
    a1 = RandomPolicy(seed=7, sim=sim)(td.clone())["action"]
    a2 = make_baseline("random", sim, seed=7)(td.clone())["action"]
    a3 = RandomPolicy(seed=8, sim=sim)(td.clone())["action"]
    assert a1.dtype == torch.float32 and a1.shape == (td.shape[0], 6)
    assert torch.equal(a1, a2) and not torch.equal(a1, a3)
    a = a1.double().numpy()
    assert (a >= A_LOW).all() and (a <= A_HIGH).all()
    # roughly uniform: every dimension spans most of its range
    assert ((a.max(0) - a.min(0)) > 0.9 * (A_HIGH - A_LOW)).all()
    pol = RandomPolicy(seed=7, sim=sim)
    b1, b2 = pol(td.clone())["action"], pol(td.clone())["action"]
    assert torch.equal(b1, a1) and not torch.equal(b1, b2)  # a stream: successive calls differ
    pol.reseed(7)
    assert torch.equal(pol(td.clone())["action"], a1)


def test_make_baseline_unknown():
    with pytest.raises(ValueError):
        make_baseline("nope")


# ------------------------------------------------------------------------------------------------ MPC plan
def _check_plan(pol, sim, state, plan, tol=1e-7):
    """Every constraint of gym-anm's DC-OPF (spec §7.1) on the returned plan, in p.u."""
    net, n = sim.net, pol.horizon
    dev = net.dev.numpy()
    b = net.y_bus.imag.numpy()
    f, t = net.branches.f_bus.numpy(), net.branches.t_bus.numpy()
    theta, p, soc = plan["theta"], plan["p_dev"], plan["soc"]
    assert theta.shape == (n, 6) and p.shape == (n, 7) and soc.shape == (n + 1, 1)
    # DC power balance at every bus and stage: Σ device P = Σ_branches B_ij (θ_i − θ_j).
    p_bus = p @ net.incidence.numpy()
    flows = np.zeros((n, 6))
    for i, j in zip(f, t):
        flows[:, i] += b[i, j] * (theta[:, i] - theta[:, j])
        flows[:, j] += b[j, i] * (theta[:, j] - theta[:, i])
    np.testing.assert_allclose(p_bus, flows, atol=tol)
    np.testing.assert_allclose(plan["p_branch"], b[f, t] * (theta[:, f] - theta[:, t]), atol=1e-12)
    # angles
    assert np.all(np.abs(theta[:, 0]) <= tol) and np.all(np.abs(theta) <= math.pi + tol)
    # loads = forecast; forecasts as documented
    sl = sim.state_slices()
    if pol.forecast == "perfect":
        idx = (int(state[-1]) + 1 + np.arange(n)) % 96
        np.testing.assert_array_equal(plan["p_load_forecast"], sim.load_series[:, idx].T.numpy())
        np.testing.assert_array_equal(plan["p_pot_forecast"], sim.p_max_series[:, idx].T.numpy())
    else:
        np.testing.assert_allclose(plan["p_load_forecast"], np.tile(state[[1, 3, 5]] / 100, (n, 1)), rtol=1e-15)
        np.testing.assert_allclose(plan["p_pot_forecast"], np.tile(state[sl["gen_p_max"]] / 100, (n, 1)),
                                   rtol=1e-15)
    np.testing.assert_allclose(p[:, sim.load_ids], plan["p_load_forecast"], atol=tol)
    # generators: 0 ≤ P ≤ min(PMAX, forecast P_pot)
    pg = p[:, sim.gen_ids]
    assert np.all(pg >= -tol) and np.all(pg <= np.minimum(dev[sim.gen_ids, dv.PMAX], plan["p_pot_forecast"]) + tol)
    # DES: bounds, split, SoC chain and bounds
    pd = p[:, sim.des_ids]
    assert np.all(pd >= -0.5 - tol) and np.all(pd <= 0.5 + tol)
    assert np.all(plan["p_ch"] >= -tol) and np.all(plan["p_dis"] >= -tol)
    np.testing.assert_allclose(pd, plan["p_dis"] - plan["p_ch"], atol=tol)
    np.testing.assert_allclose(soc[0], state[sl["des_soc"]] / 100, rtol=1e-15)
    np.testing.assert_allclose(np.diff(soc, axis=0), 0.25 * (0.9 * plan["p_ch"] - plan["p_dis"] / 0.9), atol=1e-12)
    assert np.all(soc >= -tol) and np.all(soc <= 1.0 + tol)
    # objective Σ γ^k [P_slack + λ Σ max(0, |P_ij| − β rate)] is what the solver minimised
    stage = p[:, 0] + sim.lamb * plan["overload"].sum(1)
    np.testing.assert_allclose(plan["info"]["objective"], (pol.gamma ** np.arange(n) * stage).sum(), atol=1e-6)
    # action: first-stage P in MW, Q = 0, inside the box
    a = plan["action"]
    np.testing.assert_allclose(a[[0, 1, 4]], np.clip(p[0, [2, 4, 6]] * 100, A_LOW[[0, 1, 4]], A_HIGH[[0, 1, 4]]),
                               atol=1e-12)
    assert np.all(a[[2, 3, 5]] == 0) and np.all(a >= A_LOW) and np.all(a <= A_HIGH)


@pytest.mark.parametrize("forecast", ["perfect", "constant"])
def test_mpc_plan_satisfies_dcopf_constraints(sim, states, forecast):
    pol = MPCPolicy(sim, horizon=8, forecast=forecast, safety_margin=0.96)
    extra = states[:1].clone()
    extra[0, 17] = 95.0  # horizon wraps around midnight
    extra2 = states[:1].clone()
    extra2[0, 17], extra2[0, 14] = 50.0, 99.5  # noon, DES almost full: SoC upper bound binds
    for s in torch.cat([states, extra, extra2]).numpy():
        _check_plan(pol, sim, s, pol.solve(s))


def test_mpc_perfect_forecast_sees_raw_pv_and_charges_at_noon(sim):
    pol = MPCPolicy(sim, horizon=8, forecast="perfect")
    state = grid_reset.initial_state(sim, torch.tensor([48]), torch.zeros(1, 2), torch.tensor([[50.0]]))[0][0].numpy()
    plan = pol.solve(state)
    assert np.isclose(plan["p_pot_forecast"][:, 0].max(), 0.3675)  # the raw 36.75 MW PV value (spec §2.2)
    _check_plan(pol, sim, state, plan)


def test_mpc_policy_batched_equals_single(sim, states):
    pol = make_baseline("mpc_constant", sim, horizon=4)
    td = _td(states[:4].reshape(2, 2, 18))
    out = pol(td)["action"]
    assert out.shape == (2, 2, 6) and out.dtype == torch.float32
    single = np.stack([pol.solve(s)["action"] for s in states[:4].numpy()])
    np.testing.assert_allclose(out.reshape(4, 6).numpy(), single.astype(np.float32), rtol=0, atol=0)
    assert len(pol.last_info) == 4 and not any(i["fallback"] for i in pol.last_info)


# ------------------------------------------------------------------------------------------------ gym-anm parity
def test_mpc_matches_gym_anm_agents(sim):
    """Same action as gym-anm's MPCAgentPerfect / MPCAgentConstant (cvxpy + Clarabel) on the same states.

    States: reset(seed=0) (t = 81, empty DES), then do-nothing to noon and MPC steps there, where several
    PV/wind/DES splits reach the same optimal cost (the action still agrees: same solver, same rows).
    """
    pytest.importorskip("cvxpy")
    gym_anm = pytest.importorskip("gym_anm")
    from gym_anm.envs import ANM6Easy

    env = ANM6Easy()
    env.reset(seed=0)
    n, beta = 16, 0.96
    refs = {"perfect": gym_anm.MPCAgentPerfect(env.simulator, env.action_space, GAMMA, safety_margin=beta,
                                               planning_steps=n),
            "constant": gym_anm.MPCAgentConstant(env.simulator, env.action_space, GAMMA, safety_margin=beta,
                                                 planning_steps=n)}
    ours = {k: MPCPolicy(sim, horizon=n, forecast=k, safety_margin=beta, gamma=GAMMA, solver="clarabel")
            for k in refs}

    def compare():
        s = env.state.copy()
        acts = {}
        for k in refs:
            a_ref = refs[k].act(env)
            plan = ours[k].solve(s)
            np.testing.assert_allclose(plan["action"], a_ref, atol=1e-4, err_msg=f"{k} at t={s[-1]}")
            assert abs(plan["info"]["objective"] - refs[k].dc_opf.value) < 1e-5
            acts[k] = a_ref
        return acts

    env.step(compare()["perfect"])  # t = 81
    compare()  # t = 82
    for _ in range(64):  # do-nothing until t = 50
        env.step(np.array([30.0, 50.0, 0, 0, 0, 0]))
    assert int(env.state[-1]) == 50
    for _ in range(4):  # t = 50 … 53: the PV peak, branch limits bind
        env.step(compare()["perfect"])


# ------------------------------------------------------------------------------------------------ TorchRL env
@pytest.mark.parametrize("name", ["do_nothing", "random", "mpc_perfect", "mpc_constant"])
def test_rollout_in_env(name):
    envs = pytest.importorskip("anm_torchrl.envs")
    env = envs.ANM6Env(2, seed=0)
    kw = {"seed": 0} if name == "random" else {"horizon": 4} if name.startswith("mpc") else {}
    policy = make_baseline(name, env.sim, **kw)
    td = env.rollout(20, policy, break_when_any_done=False)
    assert td.batch_size == (2, 20)
    a = td["action"]
    assert a.dtype == torch.float32 and torch.isfinite(a).all()
    assert torch.isfinite(td["next", "reward"]).all()


def test_mpc_falls_back_when_the_lp_is_infeasible():
    """Bug: Clarabel's last iterate of an infeasible LP was applied as the MPC's action (fallback False). Here the PV
    of ANM6-Easy gets PMIN = 5 MW while its raw perfect forecast is 0 MW at night: no feasible plan exists."""
    import copy
    import warnings

    from anm_torchrl.envs import ANMEnv
    from anm_torchrl.networks import anm6_easy as a

    net = copy.deepcopy(a.network())
    net["device"] = [list(d) for d in net["device"]]
    net["device"][2][5] = 5.0  # PMIN of the PV
    sim = network_simulator(net, a.load_p(), a.gen_p_max())
    env = ANMEnv(sim=sim, num_envs=1, seed=0)
    state = env.reset()["state"].clone()
    state[0, -1] = 0  # midnight
    td = env.reset(TensorDict({"state": state}, [1]), set_state=True)
    mpc = MPCPolicy(sim, horizon=4)
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        action = mpc(td)["action"]
    assert mpc.last_info[0]["fallback"] and not mpc.last_info[0]["found"]
    torch.testing.assert_close(action, DoNothingPolicy(sim)(td.clone())["action"])


def test_counts_must_be_integers():
    """Bug: fractional counts were cut (horizon 2.5 -> 2, num_episodes 2.5 -> 2 states, seed 0.9 -> seed 0's states,
    max_steps 2.5 -> 2 steps), max_steps 0 raised an IndexError and max_rounds 1 an UnboundLocalError."""
    from anm_torchrl.baselines.optimal import solve_optimal
    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy

    sim = network_simulator(ANM6_EASY)
    with pytest.raises(ValueError, match="horizon must be an integer >= 1, got 2.5"):
        MPCPolicy(sim, horizon=2.5)
    with pytest.raises(ValueError, match="num_episodes must be an integer >= 1, got 2.5"):
        draw_initial_states(2.5, 0)
    with pytest.raises(ValueError, match="seed must be an integer >= 0, got 0.9"):
        draw_initial_states(2, 0.9)
    states = draw_initial_states(2, 0)
    for steps in (0, 2.5):
        with pytest.raises(ValueError, match=f"max_steps must be an integer >= 1, got {steps}"):
            evaluate_policy(DoNothingPolicy(sim), states, max_steps=steps)
    with pytest.raises(ValueError, match="max_rounds must be an integer >= 2, got 1"):
        solve_optimal(sim, states[0].numpy(), horizon=2, warm_start="do_nothing", max_rounds=1)
