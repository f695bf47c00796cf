"""The DC-OPF MPC, do-nothing and random baselines on networks other than ANM6-Easy.

Parity: :class:`MPCPolicy` against gym-anm 2.0.1's own ``MPCAgentPerfect`` / ``MPCAgentConstant`` (cvxpy +
Clarabel), driven on a ``gym_anm.ANMEnv`` subclass of the same network and profiles, on the states that env visits
(random actions, reset on termination). Networks: the registered ``case33bw`` (33 buses, 3 renewables, 2 storage
units) and ``radial_mixed`` of the generic parity fixtures (8 buses, a classical generator, 2 renewables, 2 storage
units, a tapped transformer), plus ``radial_mixed`` without its storage units (zero DES).

Tolerances: 1e-6 MW on the actions (the brief's target). Both sides hand Clarabel the same LP, row for row, so the
interior-point iterates agree to round-off; 1e-6 MW = 1e-7 p.u. at baseMVA 10, well above the ~1e-9 MW seen on
ANM6-Easy. Except the P of a classical generator: it costs 1 per p.u. like the slack, so in a lossless DC-OPF every
split between them is optimal (a flat face of the LP) and the interior point's position on it is fixed only to the
solver's stopping tolerance — measured up to 1.4e-4 MW here; 1e-3 MW for those entries, and the objective (gym-anm's
``dc_opf.value``, p.u., discounted sum over the horizon) must agree to 1e-7: both points lie on the same optimal face.
"""

from __future__ import annotations

import importlib.util
import pathlib
import warnings

import numpy as np
import pytest
import torch

from anm_torchrl.baselines import make_baseline
from anm_torchrl.baselines.mpc import MPCPolicy
from anm_torchrl.envs.anm_env import ANMEnv
from anm_torchrl.evaluation import EVAL_GAMMA

torch.set_num_threads(1)

FIXTURES = pathlib.Path(__file__).parent / "fixtures"
_spec = importlib.util.spec_from_file_location("record_generic", FIXTURES / "record_generic.py")
record_generic = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(record_generic)

ACTION_TOL_MW = 1e-6  # see the module docstring
TIED_TOL_MW = 1e-3  # classical generators' P: tied with the slack (module docstring)
OBJECTIVE_TOL = 1e-7
GAMMA, BETA = EVAL_GAMMA, 0.96


def _case(name: str) -> dict:
    """Network dict, profiles (T, ·) MW and reward constants (those of the parity fixtures for our own networks)."""
    if name == "case33bw":
        from anm_torchrl.networks import get_network

        c = get_network(name)  # copies: the registry's arrays must not be shared with gym-anm
        return {"network": {k: np.array(v, copy=True) if isinstance(v, np.ndarray) else v
                            for k, v in c.network.items()}, "load_p": np.asarray(c.load_p), "gen_p_max": np.asarray(c.gen_p_max),
                "delta_t": c.delta_t, "gamma": c.gamma, "lamb": c.lamb, "costs_clipping": tuple(c.costs_clipping)}
    base, keep = name.split("-")[0], name.endswith("-no_des")
    net = record_generic.tables(base)
    load_p, gen_p_max = record_generic.profiles(net, np.random.default_rng(0))
    if keep:  # drop the storage units (ids stay contiguous: they are the last devices of radial_mixed)
        dev = net["device"]
        assert np.all(dev[dev[:, 2] == 3, 0] >= dev[dev[:, 2] != 3, 0].max())
        net = {**net, "device": dev[dev[:, 2] != 3]}
    return {"network": net, "load_p": load_p, "gen_p_max": gen_p_max, "delta_t": 0.25, "gamma": 0.995,
            "lamb": 100.0, "costs_clipping": (1.0, 100.0)}


def _gym_env(case: dict, seed: int):
    """gym-anm's generic env on ``case`` with the ``P_loads`` / ``P_maxs`` series ``MPCAgentPerfect`` reads."""
    from anm_torchrl.networks.case_file import to_gym_anm
    from anm_torchrl.networks.validation import validate_network

    net = validate_network(case["network"])
    gym_net = to_gym_anm(net)  # gym-anm wants None where a value is missing
    env = record_generic.make_env_class()(gym_net, "state", case["load_p"], case["gen_p_max"], seed)
    env.P_loads, env.P_maxs = case["load_p"].T, case["gen_p_max"].T  # (n_load, T), (n_gen, T) MW
    return env


def _sim(case: dict):
    return ANMEnv(**case, num_envs=1).sim


@pytest.mark.parametrize("name,horizon,n_states", [
    pytest.param("case33bw", 4, 24, marks=pytest.mark.slow),  # ~1 min: cvxpy builds 33-bus stages scalar by scalar
    ("radial_mixed", 8, 32), ("radial_mixed-no_des", 8, 16)])
def test_mpc_matches_gym_anm_agents_on_other_networks(name, horizon, n_states):
    pytest.importorskip("cvxpy")
    gym_anm = pytest.importorskip("gym_anm")
    case = _case(name)
    env = _gym_env(case, seed=3)
    sim = _sim(case)
    assert (sim.n_des == 0) == name.endswith("no_des")
    refs = {k: cls(env.simulator, env.action_space, GAMMA, safety_margin=BETA, planning_steps=horizon)
            for k, cls in (("perfect", gym_anm.MPCAgentPerfect), ("constant", gym_anm.MPCAgentConstant))}
    ours = {k: MPCPolicy(sim, horizon=horizon, forecast=k, safety_margin=BETA, gamma=GAMMA, solver="clarabel")
            for k in refs}
    classical = np.array([sim.net.dev_type[i] == 1 for i in sim.gen_ids] + [False] * (sim.action_dim - sim.n_gen))
    tol = np.where(classical, TIED_TOL_MW, ACTION_TOL_MW)
    env.reset(seed=3)
    rng = np.random.default_rng(0)
    worst, compared = 0.0, 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        while compared < n_states:
            s = env.state.copy()
            acts = {}
            for k in refs:
                a_ref = refs[k].act(env)
                plan = ours[k].solve(s)
                a = plan["action"]
                worst = max(worst, float(np.max(np.abs(a - a_ref)[~classical])))
                assert np.all(np.abs(a - a_ref) <= tol), f"{name} {k} t={s[-1]}: {a} vs {a_ref}"
                assert abs(plan["info"]["objective"] - refs[k].dc_opf.value) <= OBJECTIVE_TOL
                acts[k] = a_ref
            compared += 1
            # alternate the MPC's own action and a random one, so the states leave the MPC's trajectory
            a = acts["perfect"] if compared % 2 else env.action_space.sample()
            _, _, terminated, _, _ = env.step(np.clip(a, env.action_space.low, env.action_space.high))
            if terminated:
                env.reset(seed=int(rng.integers(1 << 30)))
    assert worst <= ACTION_TOL_MW


def test_mpc_cost_counts_classical_generators():
    """gym-anm's stage cost is P of every non-renewable generator: the classical one's P enters at weight 1."""
    sim = _sim(_case("radial_mixed"))
    pol = MPCPolicy(sim, horizon=2, solver="clarabel")
    kinds = sim.net.dev_type.tolist()
    costly = {i for i, k in enumerate(kinds) if k in (0, 1)}
    lay = pol._layout
    weights = pol._c[lay["p"]:lay["p"] + sim.net.n_dev]
    assert {i for i, w in enumerate(weights) if w == 1.0} == costly and len(costly) == 2


@pytest.mark.parametrize("name", ["do_nothing", "random", "mpc_constant"])
@pytest.mark.parametrize("network", ["case33bw", "radial_mixed-no_des"])
def test_baselines_step_any_network(name, network):
    """Each baseline gives in-box actions of the network's size and runs a short batched rollout of ANMEnv."""
    case = _case(network)
    env = ANMEnv(**case, num_envs=3, seed=0)
    kw = {"seed": 0} if name == "random" else ({"horizon": 2} if name.startswith("mpc") else {})
    pol = make_baseline(name, sim=env.sim, **kw)
    td = env.reset()
    lo, hi = env.sim.action_bounds()
    for _ in range(3):
        td = pol(td)
        a = td["action"]
        assert a.shape == (3, env.sim.action_dim)
        assert torch.all(a >= lo.float() - 1e-6) and torch.all(a <= hi.float() + 1e-6)
        td = env.step(td)["next"]
    assert td["state"].shape == (3, env.sim.state_dim)
