"""The perfect-foresight optimum of an episode: the best achievable discounted return from one initial state.

A gym-anm episode is deterministic once its initial state is fixed (loads and potentials follow the profiles), so
its best return is the optimum of one NLP over all T steps (:class:`~anm_torchrl.baselines.nlp_model.ACHorizonNLP`,
CasADi + IPOPT). :func:`solve_optimal` solves it in rounds, each warm-started from the previous one:

1. from a warm start (the DC-OPF MPC's closed-loop trajectory by default; do-nothing or random set-points to
   test that the local optimum does not depend on it), with the exact power flow and a free storage split;
2. with each step's storage direction pinned (charge or discharge, from round 1), which makes the SoC chain
   gym-anm's exactly — the **exact-physics optimum**;
3. and on, with the env's power-flow error as offsets (:class:`~anm_torchrl.baselines.nlp_model.PowerFlowOffsets`,
   measured by replaying the set-points), until the replayed return agrees with the NLP's to ``rtol`` — the
   **env optimum**, the bound a policy evaluated on ``ANM6Env`` is measured against.

:class:`OptimalPolicy` wraps it as a TorchRL policy usable by
:func:`~anm_torchrl.evaluation.evaluate_policy`: it solves the horizon when it meets a state that is on
none of its plans (an episode's first state) and then replays the plan step by step.

The gap study (``python -m anm_torchrl.cli.gap --help``) lives in :mod:`anm_torchrl.experiments.gap`.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from anm_torchrl.baselines.nlp_model import (IPOPT_OPTIONS, ACHorizonNLP, NLPResult, PowerFlowOffsets,
                                             check_ipopt_options, exogenous, rollout, storage_direction, time_indices)
from anm_torchrl.envs.specs import check_integer
from anm_torchrl.evaluation import EVAL_GAMMA, EVAL_MAX_STEPS, reset_to
from anm_torchrl.grid.simulator import GridSimulator

log = logging.getLogger(__name__)

WARM_STARTS = ("mpc", "do_nothing", "random")
WARM_MPC_HORIZON = 16  # DC-OPF MPC warm start: perfect forecast, N = 16, β = 0.92 (cheap and close enough)
WARM_MPC_MARGIN = 0.92


def warm_start_actions(sim: GridSimulator, state: np.ndarray, n: int, kind: str = "mpc",
                       seed: int = 0) -> np.ndarray:
    """Set-points (n, action_dim) MW/MVAr to start the NLP from.

    ``"mpc"``: gym-anm's DC-OPF MPC (perfect forecast, N = 16, β = 0.92) run in closed loop on ``sim``;
    ``"do_nothing"``: renewables at PMAX, everything else 0; ``"random"``: uniform over the action box (seeded).
    """
    lo, hi = (b.cpu().numpy() for b in sim.action_bounds())
    if kind == "mpc":
        from anm_torchrl.baselines.mpc import MPCPolicy

        mpc = MPCPolicy(sim, horizon=WARM_MPC_HORIZON, forecast="perfect", safety_margin=WARM_MPC_MARGIN,
                        gamma=EVAL_GAMMA)
        acts: list[np.ndarray] = []

        def act(s: np.ndarray) -> np.ndarray:
            acts.append(mpc.solve(s)["action"])
            return acts[-1]

        rollout(sim, state, act, n=n)
        return np.stack(acts)
    if kind == "do_nothing":
        a = np.zeros(sim.action_dim)
        a[:sim.n_gen] = hi[:sim.n_gen]
        return np.tile(a, (n, 1))
    if kind == "random":
        return lo + np.random.default_rng(seed).random((n, sim.action_dim)) * (hi - lo)
    raise ValueError(f"warm_start must be one of {WARM_STARTS}, got {kind!r}")


@dataclasses.dataclass
class OptimalResult:
    """The optimum of one episode.

    Attributes:
        setpoints: (T, action_dim) MW/MVAr, the env optimum's set-points (inside every device's polygon).
        states: (T + 1, state_dim) the states their float64 replay on the simulator visits (row 0 the start).
        discounted_return: the env optimum's return as the NLP reports it (exact physics + the env's power-flow
            offsets).
        exact_return: the exact-physics optimum's return (round 2).
        replay_return: Σ γ^t r_t of the float64 replay on the simulator; ``replay_gap`` its relative difference
            to ``discounted_return``.
        warm_start: the warm start's name; ``warm_return`` its own replayed return over the solved steps (one
            period on a storage-free network, :func:`solve_horizon`).
        rounds: :meth:`NLPResult.summary` of every round (with ``replay_return`` and ``replay_gap``), over the
            solved steps.
        wall_time: s, warm start and all rounds.  warm_time: s, the warm start alone.
        cpu_time: process CPU s of the same (the wall time of an idle core; on a shared machine the wall time
            is longer).
        result: the last round's :class:`NLPResult`.
    """

    setpoints: np.ndarray
    states: np.ndarray
    discounted_return: float
    exact_return: float
    replay_return: float
    replay_gap: float
    warm_start: str
    warm_return: float
    rounds: list[dict]
    wall_time: float
    warm_time: float
    cpu_time: float
    result: NLPResult

    def summary(self) -> dict:
        """JSON-ready record (no arrays)."""
        return {k: getattr(self, k) for k in ("discounted_return", "exact_return", "replay_return", "replay_gap",
                                              "warm_start", "warm_return", "rounds", "wall_time", "warm_time",
                                              "cpu_time")}


def _discounted(reward: np.ndarray, gamma: float) -> float:
    return float(np.dot(gamma ** np.arange(len(reward)), reward))


def solve_horizon(sim: GridSimulator, horizon: int) -> int:
    """How many steps the NLP of a ``horizon``-step optimum spans: ``horizon``, or the profiles' period
    ``sim.n_time`` when it is shorter and the network has no storage unit.

    Without storage no state variable couples the steps: every step's reward depends only on its set-points and
    its time index (loads and potentials; gym-anm has no ramp limits), so the optimum separates per step and
    repeats with the time index, which wraps modulo ``n_time``. One ``n_time``-step solve then gives every step of
    a longer episode exactly (the SimBench feeder: 672 steps instead of 3,000).
    """
    horizon = check_integer("horizon", horizon, low=1)
    if sim.n_des == 0 and sim.next_vars_hook is None and horizon > sim.n_time:
        return int(sim.n_time)
    return horizon


def solve_optimal(sim: GridSimulator, state: np.ndarray, horizon: int = EVAL_MAX_STEPS, gamma: float = EVAL_GAMMA,
                  warm_start: str = "mpc", seed: int = 0, formulation: str = "polar",
                  nlp: ACHorizonNLP | None = None, rtol: float = 1e-7, max_rounds: int = 6,
                  ipopt: dict | None = None) -> OptimalResult:
    """The perfect-foresight optimum of the episode from ``state`` (state_dim,) MW/MVAr/MWh over ``horizon`` steps.

    Args:
        warm_start: one of :data:`WARM_STARTS` (``seed`` for ``"random"``).
        formulation: ``"polar"`` or ``"rectangular"`` voltages.
        nlp: a built :class:`ACHorizonNLP` of ``solve_horizon(sim, horizon)`` steps and ``gamma`` to reuse
            (building costs seconds). Over a storage-free network's period, the plan is repeated to ``horizon``
            steps (:func:`solve_horizon`), and the return and replay cover all of them.
        rtol: stop once the replayed return agrees with the NLP's to this relative difference.
        max_rounds: at most this many solves (rounds 1 and 2 plus offset rounds).
        ipopt: IPOPT option overrides (only when ``nlp`` is not given).

    Raises:
        RuntimeError: a round's IPOPT solve failed, or the replay left the power flow's convergence region.
    """
    state = np.asarray(torch.as_tensor(state, dtype=torch.float64).cpu().numpy()).reshape(-1)
    if state.shape != (sim.state_dim,):
        raise ValueError(f"state must have shape ({sim.state_dim},), got {state.shape}")
    n = solve_horizon(sim, horizon)
    check_integer("max_rounds", max_rounds, low=2)  # rounds 1 and 2 are the method; a replay needs round 2
    if nlp is None:
        nlp = ACHorizonNLP(sim, n, gamma, formulation, ipopt)
    elif (nlp.horizon, nlp.gamma) != (n, float(gamma)):
        raise ValueError(f"nlp has horizon {nlp.horizon} and gamma {nlp.gamma}, expected {n} and {gamma}")
    t0, c0 = time.perf_counter(), time.process_time()
    soc0 = state[sim.state_slices()["des_soc"]] / sim.net.base_mva
    p_load, p_pot = exogenous(sim, time_indices(sim, state, n))
    warm = rollout(sim, state, warm_start_actions(sim, state, n, warm_start, seed))
    warm_time = time.perf_counter() - t0
    res = nlp.solve(soc0, p_load, p_pot, nlp.guess(warm.p_dev, warm.q_dev, warm.v, warm.soc))
    rounds = [_round(res, "free split, exact power flow")]
    _check(res, 1)
    direction = storage_direction(sim, res.setpoints)
    offsets, exact_return = None, float("nan")
    for k in range(2, max_rounds + 1):
        res = nlp.solve(soc0, p_load, p_pot, res.x, direction=direction, offsets=offsets, lam_x0=res.lam_x,
                        lam_g0=res.lam_g)
        _check(res, k)
        replay = rollout(sim, state, res.setpoints)
        if not replay.converged.all():
            raise RuntimeError(f"round {k}: the replay's power flow did not converge at steps "
                               f"{np.flatnonzero(~replay.converged)[:5].tolist()}")
        ret = _discounted(replay.reward, gamma)
        gap = abs(ret - res.discounted_return) / abs(res.discounted_return)
        rounds.append({**_round(res, "pinned split, " + ("exact power flow" if offsets is None else "env offsets")),
                       "replay_return": ret, "replay_gap": gap})
        log.info("optimum round %d: NLP %.9f, replay %.9f (gap %.2e), %d iterations, %.1f s", k,
                 res.discounted_return, ret, gap, res.iterations, res.solve_time)
        if offsets is None:
            exact_return, exact_reward = res.discounted_return, res.points.reward
        elif gap <= rtol:
            break
        offsets = PowerFlowOffsets.measure(sim, replay.v, res.points.v)
    setpoints, nlp_return = res.setpoints, res.discounted_return
    if n < horizon:  # the period's plan, repeated: every step's reward is the one solved at its time index
        tile = np.arange(horizon) % n
        setpoints, nlp_return = setpoints[tile], _discounted(res.points.reward[tile], gamma)
        exact_return = _discounted(exact_reward[tile], gamma)
        replay = rollout(sim, state, setpoints)
        if not replay.converged.all():
            raise RuntimeError("the repeated plan's replay did not converge at steps "
                               f"{np.flatnonzero(~replay.converged)[:5].tolist()}")
        ret = _discounted(replay.reward, gamma)
        gap = abs(ret - nlp_return) / abs(nlp_return)
    return OptimalResult(setpoints=setpoints, states=replay.states, discounted_return=nlp_return,
                         exact_return=exact_return, replay_return=ret, replay_gap=gap, warm_start=warm_start,
                         warm_return=_discounted(warm.reward * warm.converged, gamma), rounds=rounds,
                         wall_time=time.perf_counter() - t0, warm_time=warm_time,
                         cpu_time=time.process_time() - c0, result=res)


def _round(res: NLPResult, what: str) -> dict:
    return {"round": what, **res.summary()}


def _check(res: NLPResult, k: int) -> None:
    if res.slack_at_bound:
        raise RuntimeError(f"optimum round {k}: a penalty slack reached its bound SLACK_MAX (nlp_model)")
    if not res.success:
        raise RuntimeError(f"optimum round {k}: IPOPT returned {res.status} after {res.iterations} iterations "
                           f"(primal infeasibility {res.inf_pr:.2e}, dual {res.inf_du:.2e})")


def replay_in_env(setpoints: np.ndarray, state: np.ndarray, gamma: float = EVAL_GAMMA,
                  sim: GridSimulator | None = None, env=None) -> dict:
    """Step set-points (T, action_dim) MW/MVAr (float64) through an env from ``state`` (set with
    ``reset(..., set_state=True)``); returns the ``discounted_return``, the ``rewards`` (T,) and ``terminated``.

    Args:
        sim: simulator of the default env, ``ANM6Env(1, sim=sim)`` (None: ANM6-Easy's).
        env: an env of batch size 1 to replay in instead (e.g. ``ANMEnv`` of another network); not with ``sim``.
    """
    from anm_torchrl.envs import ANM6Env

    if env is not None and sim is not None:
        raise ValueError("replay_in_env: pass sim= (for ANM6Env) or env=, not both")
    if env is None:
        env = ANM6Env(1, seed=0, sim=sim)
    elif tuple(env.batch_size) != (1,):
        raise ValueError(f"replay_in_env: env batch size must be (1,), got {tuple(env.batch_size)}")
    td = reset_to(env, torch.as_tensor(state, dtype=torch.float64).reshape(1, -1))
    rewards, terminated = [], False
    for a in np.asarray(setpoints, dtype=np.float64):
        td.set("action", torch.as_tensor(a).reshape(1, -1))
        td = env.step(td)
        rewards.append(float(td["next", "reward"]))
        terminated = bool(td["next", "terminated"])
        if terminated:
            break
        td = td["next"]
    r = np.asarray(rewards)
    return {"discounted_return": _discounted(r, gamma), "rewards": r, "terminated": terminated}


#: the keyword arguments of :func:`solve_optimal` an :class:`OptimalPolicy` passes on
SOLVE_OPTIONS = frozenset({"warm_start", "seed", "formulation", "rtol", "max_rounds", "ipopt"})


class OptimalPolicy(TensorDictModuleBase):
    """The perfect-foresight optimum as a policy: plan at an episode's first state, then replay the plan.

    A state is *on a plan* at step k when its time index equals the plan's and its SoC is within ``soc_tol``
    MWh of the plan's (float32 actions move the SoC by ~1e-6 MWh a step). Any other state — an episode's first,
    or one off its plan — gets a new plan solved from it (:func:`solve_optimal`, ``horizon`` steps; minutes for
    3,000), and the plan is followed from there. Each solve is logged and kept in ``plans``.

    Args:
        sim: the :class:`GridSimulator`.
        horizon: planning horizon T (the evaluation's episode length).
        gamma: discount.
        in_key: TensorDict key of the gym-anm state (..., state_dim).
        soc_tol: MWh.
        **solve_kw: passed to :func:`solve_optimal` (``warm_start``, ``formulation``, ``rtol``…).
    """

    def __init__(self, sim: GridSimulator, horizon: int = EVAL_MAX_STEPS, gamma: float = EVAL_GAMMA,
                 in_key: str = "state", soc_tol: float = 1e-2, **solve_kw):
        super().__init__()
        self.in_keys, self.out_keys = [in_key], ["action"]
        self.sim, self.gamma, self.soc_tol, self.solve_kw = sim, float(gamma), float(soc_tol), solve_kw
        self.horizon = check_integer("horizon", horizon, low=1)
        unknown = sorted(set(solve_kw) - SOLVE_OPTIONS)
        if unknown:
            raise ValueError(f"optimal policy: unknown option(s) {unknown}; known: {sorted(SOLVE_OPTIONS)}")
        if solve_kw.get("ipopt"):  # an IPOPT option error now, not after the first state's seconds of setup
            check_ipopt_options({**IPOPT_OPTIONS, **solve_kw["ipopt"]})
        self.plans: list[OptimalResult] = []
        self._cursor: list[int] = []
        self._nlp: ACHorizonNLP | None = None
        sl = sim.state_slices()
        self._aux, self._soc = sl["aux"], sl["des_soc"]
        lo, hi = sim.action_bounds()
        self._lo, self._hi = lo.cpu().numpy(), hi.cpu().numpy()

    def _on_plan(self, s: np.ndarray, plan: OptimalResult, k: int) -> bool:
        ref = plan.states[k]
        return (k < len(plan.setpoints) and s[self._aux][0] == ref[self._aux][0]
                and bool(np.all(np.abs(s[self._soc] - ref[self._soc]) <= self.soc_tol)))

    def _new_plan(self, s: np.ndarray) -> int:
        if self._nlp is None:
            self._nlp = ACHorizonNLP(self.sim, solve_horizon(self.sim, self.horizon), self.gamma,
                                     self.solve_kw.get("formulation", "polar"), self.solve_kw.get("ipopt"))
        kw = {k: v for k, v in self.solve_kw.items() if k not in ("formulation", "ipopt")}
        plan = solve_optimal(self.sim, s, self.horizon, self.gamma, nlp=self._nlp, **kw)
        log.info("optimal policy: new plan from t = %d, return %.6f (%.0f s)", int(s[self._aux][0]),
                 plan.discounted_return, plan.wall_time)
        self.plans.append(plan)
        self._cursor.append(0)
        return len(self.plans) - 1

    def act(self, states: torch.Tensor) -> torch.Tensor:
        """Actions (..., action_dim) float32 MW/MVAr for states (..., state_dim)."""
        flat = states.detach().reshape(-1, states.shape[-1]).cpu().double().numpy()
        out = np.empty((flat.shape[0], self.sim.action_dim))
        cursor = list(self._cursor)  # rows matched against the cursors at the start of this call
        advance: dict[int, int] = {}
        for i, s in enumerate(flat):
            j = next((j for j, p in enumerate(self.plans) if self._on_plan(s, p, cursor[j])), None)
            if j is None:
                j = self._new_plan(s)
                cursor.append(0)
            out[i] = self.plans[j].setpoints[cursor[j]]
            advance[j] = cursor[j] + 1
        for j, k in advance.items():
            self._cursor[j] = k
        out = np.clip(out, self._lo, self._hi)  # inside the polygons up to round-off; the env raises outside
        return torch.as_tensor(out, dtype=torch.float32, device=states.device).reshape(
            *states.shape[:-1], self.sim.action_dim)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict.set(self.out_keys[0], self.act(tensordict.get(self.in_keys[0])))
        return tensordict

