"""Re-step recorded transitions in gym-anm 2.0.1 itself, with its QP projections solved accurately.

gym-anm projects each device's set-point onto its feasible region with ``cvxpy.Problem.solve()`` on cvxpy's
default solver and tolerances (``gym_anm/simulator/components/devices.py``, ``map_pq``). That solve is inexact
on rare rows: a projection can land ~1e-6 p.u. (1e-4 MW on a 100 MVA base) from the true projection, which
this package computes exactly (closed form on the capability polygon). On such a row a recording of gym-anm
differs from this package by more than the parity tolerance, and the difference is gym-anm's solver, not its
model. :func:`replay` re-steps chosen rows in gym-anm from their recorded state and action with every
projection solved by OSQP at ``eps_abs = eps_rel = 1e-12``, polished (:func:`accurate_qp`), so the parity
tools (:mod:`.parity`) can tell those rows (equal to the accurate replay) from real differences.

Needs the ``gym-anm`` extra (gym-anm, cvxpy, osqp).
"""

from __future__ import annotations

import contextlib
import functools
import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np

#: OSQP settings of the accurate projection (p.u.): far below the parity tolerance of 1e-6 MW on any base.
ACCURATE_QP = {"eps_abs": 1e-12, "eps_rel": 1e-12, "polish": True, "max_iter": 1_000_000}


def generic_network(d: dict[str, np.ndarray]) -> dict[str, Any]:
    """The gym-anm network dict (baseMVA, bus, device, branch tables) stored in a generic fixture."""
    return {"baseMVA": float(d["baseMVA"]), "bus": d["bus"], "device": d["device"], "branch": d["branch"]}


def observation_arg(obs: str | list) -> str | list:
    """The JSON observation of a generic fixture as gym-anm takes it (branch ids as tuples)."""
    if obs == "state":
        return obs
    return [(q, ids if ids == "all" else [tuple(i) if isinstance(i, list) else i for i in ids], u)
            for q, ids, u in obs]


@contextlib.contextmanager
def accurate_qp() -> Iterator[None]:
    """Within the block, every ``cvxpy.Problem.solve()`` called with no arguments (gym-anm's projections) runs
    OSQP with :data:`ACCURATE_QP`; the default solve is restored on exit."""
    from anm_torchrl._extras import require

    cp = require("cvxpy", extra="gym-anm", what="gym-anm's accurate replay (parity tools)")
    original = cp.Problem.solve

    @functools.wraps(original)
    def solve(self, *args, **kwargs):
        if not args and not kwargs:
            kwargs = {"solver": cp.OSQP, **ACCURATE_QP}
        return original(self, *args, **kwargs)

    cp.Problem.solve = solve
    try:
        yield
    finally:
        cp.Problem.solve = original


def profile_env_class():
    """gym-anm's generic ``ANMEnv`` reading fixed profiles (K = 1, aux = time index, row ``(t + 1) mod T``), as
    the generic parity fixtures were recorded (``tests/fixtures/record_generic.py``); ``init_state`` draws a
    random state (devices uniform in their boxes, SoC at a bound or between) unless :attr:`replay_state` is set,
    which it then returns (MW / MVAr / MWh, gym-anm's state layout)."""
    from anm_torchrl._extras import require

    require("gym_anm", extra="gym-anm")
    from gym_anm import ANMEnv

    class ProfileEnv(ANMEnv):
        replay_state: np.ndarray | None = None

        def __init__(self, network, observation, load_p, gen_p_max, seed):
            self.load_p, self.gen_p_max = load_p, gen_p_max
            super().__init__(network, observation, K=1, delta_t=0.25, gamma=0.995, lamb=100,
                             costs_clipping=(1, 100), seed=seed)

        def init_state(self):
            if self.replay_state is not None:
                return np.array(self.replay_state, dtype=np.float64)
            sim, rng = self.simulator, self.np_random
            n_dev, n_des, n_gen = sim.N_device, sim.N_des, sim.N_non_slack_gen
            s = np.zeros(2 * n_dev + n_des + n_gen + 1)
            t0 = int(rng.integers(0, len(self.load_p)))
            s[-1] = t0
            li = gi = di = 0
            for k, dev in enumerate(sim.devices.values()):
                base = sim.baseMVA
                if dev.type == -1:
                    s[k] = self.load_p[t0, li]
                    s[n_dev + k] = s[k] * dev.qp_ratio
                    li += 1
                elif dev.type in (1, 2):
                    s[2 * n_dev + n_des + gi] = self.gen_p_max[t0, gi]
                    s[k] = rng.uniform(dev.p_min, dev.p_max) * base
                    s[n_dev + k] = rng.uniform(dev.q_min, dev.q_max) * base
                    gi += 1
                elif dev.type == 3:
                    u = rng.random()
                    soc = dev.soc_min if u < 1 / 3 else dev.soc_max if u < 2 / 3 else rng.uniform(dev.soc_min,
                                                                                                  dev.soc_max)
                    s[2 * n_dev + di] = soc * base
                    s[k] = rng.uniform(dev.p_min, dev.p_max) * base
                    s[n_dev + k] = rng.uniform(dev.q_min, dev.q_max) * base
                    di += 1
            return s

        def next_vars(self, s_t):
            t = int((s_t[-1] + 1) % len(self.load_p))
            return np.concatenate([self.load_p[t], self.gen_p_max[t], [t]])

    return ProfileEnv


def _anm6_replay_env():
    from anm_torchrl._extras import require

    require("gym_anm", extra="gym-anm")
    from gym_anm.envs import ANM6Easy

    class ReplayANM6Easy(ANM6Easy):
        replay_state: np.ndarray | None = None

        def init_state(self):
            return super().init_state() if self.replay_state is None else np.array(self.replay_state)

    return ReplayANM6Easy()


def replay_env(d: dict[str, np.ndarray], anm6: bool) -> Any:
    """The gym-anm env a fixture was recorded with: ANM6-Easy, or :func:`profile_env_class` on the fixture's
    network, profiles and observation (``d``: a fixture's arrays)."""
    if anm6:
        return _anm6_replay_env()
    import json

    from anm_torchrl.networks.case_file import to_gym_anm

    return profile_env_class()(to_gym_anm(generic_network(d)), observation_arg(json.loads(str(d["observation"]))),
                               d["load_p"], d["gen_p_max"], seed=0)


def replay(d: dict[str, np.ndarray], rows, anm6: bool, accurate: bool = True) -> dict[str, np.ndarray]:
    """Re-step rows of a fixture in gym-anm: reset to each recorded ``state``, step its ``action``.

    Args:
        d: the fixture's arrays (``state`` (n, S), ``action`` (n, A), profiles and tables for a generic one).
        rows: indices into the fixture (k,).
        anm6: the fixture is ANM6-Easy's (else a generic network's).
        accurate: solve gym-anm's projections with :func:`accurate_qp` (False: gym-anm's default solve).

    Returns:
        ``next_state`` (k, S) MW / MVAr / MWh (as the recorder stores it), ``reward`` (k,), ``terminated`` (k,).
    """
    rows = np.asarray(rows, dtype=np.int64).reshape(-1)
    env = replay_env(d, anm6)
    out = {"next_state": np.zeros((len(rows), d["state"].shape[1])), "reward": np.zeros(len(rows)),
           "terminated": np.zeros(len(rows), dtype=bool)}
    ctx = accurate_qp() if accurate else contextlib.nullcontext()
    with ctx, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # gym-anm's own deprecation and rank warnings
        for j, i in enumerate(rows):
            env.replay_state = d["state"][i]
            env.reset(seed=0)
            _, r, term, _, _ = env.step(np.asarray(d["action"][i], dtype=np.float64))
            out["next_state"][j], out["reward"][j], out["terminated"][j] = env.state, r, term
    return out
