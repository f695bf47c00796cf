"""Surrogate error along episodes of the true simulator (paper Figs. 8–9) and free-running rollouts.

Episodes are driven on the true simulator (``ANM6Env``) by an *expert* agent (gym-anm's MPC DC-OPF with perfect
forecast; do-nothing if the MPC baseline is not available) and by a uniform *random* agent, from the same fixed
initial states (``draw_initial_states``). Then, for every available surrogate:

* **one-step (teacher-forced) error** (paper Fig. 8, and Fig. 9 for the PINN over time): at every step t the
  surrogate env is put in the true state s_t (``reset(..., set_state=True)``), takes the agent's action a_t, and
  its next state is compared with the true s_{t+1}; no error accumulates;
* **free-running (open-loop) error** (beyond the paper): the surrogate starts from the same s_0 and is stepped
  with the same action sequence a_0 … a_{T−1} from its *own* states; the error is against the true s_{t+1}.

Error = mean absolute difference over the 18 state entries (MW, MVAr, MWh, as gym-anm's state), averaged over
episodes at each step; steps after a true termination are masked. Per-variable MAEs are also recorded. The
exogenous entries (load P/Q, renewable potentials, time index) come from the time series in every env, so the
error sits in the device set-points, the slack and the SoC — and in surrogate terminations (zero state).
"""

from __future__ import annotations

import copy
import time
from typing import Any

import torch
from tensordict import TensorDict

from anm_torchrl.evaluation import reset_to
from anm_torchrl.experiments.common import RunContext, label, make_env_or_reason, set_state_and_step
from anm_torchrl.experiments.io import result

STATE_NAMES = ([f"P{i}" for i in range(7)] + [f"Q{i}" for i in range(7)] + ["SoC", "Ppot_PV", "Ppot_wind", "aux"])


def make_agent(kind: str, sim, seed: int = 0, expert: str = "mpc_perfect", mpc_horizon: int = 16,
               ) -> tuple[Any, str]:
    """(policy, description) for ``kind`` ``expert`` or ``random`` (or any baseline name).

    ``expert`` is the baseline named ``expert`` (default gym-anm's MPC with perfect forecast); it falls back to
    do-nothing when that baseline cannot be built (and :func:`run` falls back to it when the expert's episodes
    exceed their time budget: the LP solver is slow on a loaded 2-core machine).
    """
    from anm_torchrl.baselines import make_baseline

    if kind == "random":
        return make_baseline("random", sim, seed=seed), "random"
    if kind != "expert":
        return make_baseline(kind, sim), kind
    try:
        kw = {"horizon": mpc_horizon} if expert.startswith("mpc") else {}
        policy = make_baseline(expert, sim, **kw)
    except Exception as err:  # noqa: BLE001 - osqp missing or baseline not written: fall back
        return make_baseline("do_nothing", sim), f"do_nothing ({expert} not available: {err})"
    return policy, expert


@torch.no_grad()
def true_episodes(policy, initial_states: torch.Tensor, steps: int, sim=None,
                  budget_s: float | None = None) -> dict[str, torch.Tensor]:
    """Roll ``policy`` on the true simulator: states (T+1, N, 18), actions (T, N, 6), alive (T, N) bool mask
    (True where the step starts before any termination), rewards (T, N).

    Raises ``TimeoutError`` when the rollout runs longer than ``budget_s`` seconds."""
    t0 = time.perf_counter()
    from anm_torchrl.envs import ANM6Env

    n = initial_states.shape[0]
    env = ANM6Env(n, seed=0, action_mode="clip", sim=sim)
    td = reset_to(env, initial_states)
    states, actions, rewards, alive = [td["state"].clone()], [], [], []
    ok = torch.ones(n, dtype=torch.bool)
    for _ in range(steps):
        td = policy(td)
        a = td["action"].clone()
        nxt = env.step(td).get("next")
        actions.append(a)
        alive.append(ok.clone())
        rewards.append(nxt["reward"].squeeze(-1))
        states.append(nxt["state"].clone())
        ok = ok & ~nxt["terminated"].squeeze(-1)
        td = TensorDict({"state": nxt["state"], "observation": nxt["observation"]}, [n])
        if (~ok).all():
            break
        if budget_s is not None and time.perf_counter() - t0 > budget_s:
            raise TimeoutError(f"{len(actions)}/{steps} steps in {time.perf_counter() - t0:.0f} s > {budget_s} s")
    return {"states": torch.stack(states), "actions": torch.stack(actions), "alive": torch.stack(alive),
            "rewards": torch.stack(rewards)}


def _mae_curves(pred: torch.Tensor, true: torch.Tensor, alive: torch.Tensor) -> dict[str, Any]:
    """pred/true (T, N, 18), alive (T, N) -> per-step MAE (T,), overall MAE, per-variable MAE (18,)."""
    err = (pred - true).abs()
    w = alive.to(err.dtype)
    per_step = (err.mean(-1) * w).sum(1) / w.sum(1).clamp_min(1)
    per_step = torch.where(w.sum(1) > 0, per_step, torch.full_like(per_step, float("nan")))
    overall = float((err.mean(-1) * w).sum() / w.sum().clamp_min(1))
    per_var = (err * w.unsqueeze(-1)).sum((0, 1)) / w.sum().clamp_min(1)
    return {"mae": overall, "mae_per_step": per_step.tolist(), "mae_per_variable": dict(zip(STATE_NAMES, per_var.tolist()))}


@torch.no_grad()
def one_step_errors(env, ep: dict[str, torch.Tensor]) -> dict[str, Any]:
    """Teacher-forced one-step MAE of ``env`` (batch N) along the episodes ``ep``."""
    T = ep["actions"].shape[0]
    preds = [set_state_and_step(env, ep["states"][t], ep["actions"][t])["state"] for t in range(T)]
    return _mae_curves(torch.stack(preds), ep["states"][1:T + 1], ep["alive"])


@torch.no_grad()
def free_running_errors(env, ep: dict[str, torch.Tensor]) -> dict[str, Any]:
    """Open-loop MAE of ``env`` started from s_0 and stepped with the episodes' action sequence."""
    T, n = ep["actions"].shape[:2]
    td = reset_to(env, ep["states"][0])
    preds = []
    for t in range(T):
        td.set("action", ep["actions"][t].float())
        nxt = env.step(td).get("next")
        preds.append(nxt["state"].clone())
        td = TensorDict({"state": nxt["state"], "observation": nxt["observation"]}, [n])
    return _mae_curves(torch.stack(preds), ep["states"][1:T + 1], ep["alive"])


def run(cfg: dict[str, Any], ctx: RunContext) -> dict:
    """The experiment: :func:`measure` on ANM6-Easy with the run's surrogates and seed."""
    return measure(cfg, list(ctx.surrogates), ctx.seed)


def measure(cfg: dict[str, Any], surrogates: list[dict], seed: int = 0, sim=None, name: str = "rollout_error",
            include_true: bool = True) -> dict:
    """cfg keys: ``episodes``, ``steps``, ``agents`` (``expert``/``random``), ``expert`` (baseline name),
    ``expert_budget_s``, ``mpc_horizon``, ``free_running`` (bool)."""
    from anm_torchrl.evaluation import draw_initial_states

    n, steps = int(cfg.get("episodes", 4)), int(cfg.get("steps", 288))
    init = draw_initial_states(n, seed)
    out: dict[str, Any] = {"agents": {}, "not_available": {}, "episodes": n, "steps": steps}
    envs = {}
    specs = ([{"name": "none"}] if include_true else []) + list(surrogates)
    for spec in specs:
        env, reason = make_env_or_reason(spec, n, seed, sim=sim)
        if env is None:
            out["not_available"][label(spec)] = reason
        else:
            envs[label(spec)] = env
    for kind in cfg.get("agents", ["expert", "random"]):
        policy, desc = make_agent(kind, sim if sim is not None else _default_sim(), seed,
                                  expert=str(cfg.get("expert", "mpc_perfect")),
                                  mpc_horizon=int(cfg.get("mpc_horizon", 16)))
        t0 = time.perf_counter()
        try:
            ep = true_episodes(policy, init, steps, sim=sim, budget_s=cfg.get("expert_budget_s"))
        except TimeoutError as err:
            from anm_torchrl.baselines import make_baseline

            policy, desc = make_baseline("do_nothing", sim), f"do_nothing ({desc} over its time budget: {err})"
            ep = true_episodes(policy, init, steps, sim=sim)
        rec = {"policy": desc, "rollout_s": time.perf_counter() - t0,
               "mean_return": float((ep["rewards"] * ep["alive"]).sum(0).mean()), "surrogates": {}}
        for lab, env in envs.items():
            r = {"one_step": one_step_errors(env, ep)}
            if cfg.get("free_running", True):
                r["free_running"] = free_running_errors(env, ep)
            rec["surrogates"][lab] = r
        out["agents"][kind] = rec
    surrogate_labels = [label(s) for s in surrogates]
    status = "ok" if not out["not_available"] else (
        "partial" if any(lab in envs for lab in surrogate_labels) else "not available")
    reason = None if status != "not available" else "no surrogate available: " + "; ".join(
        f"{k}: {v}" for k, v in out["not_available"].items())
    return result(name, status, out, reason=reason, config=cfg, seed=seed)


def _default_sim():
    from anm_torchrl.networks import ANM6_EASY
    from anm_torchrl.networks import simulator as network_simulator

    return network_simulator(ANM6_EASY)


def scaled_simulator(load: float = 1.0, gen: float = 1.0, sim=None, shift: int = 0):
    """A copy of the ANM6-Easy simulator whose load and renewable-potential series are scaled by ``load`` and
    ``gen`` and rolled ``shift`` time steps later (the physical device limits still clip them, as in gym-anm)."""
    sim = copy.copy(sim if sim is not None else _default_sim())
    sim.load_series = torch.roll(sim.load_series * float(load), int(shift), dims=-1)
    sim.p_max_series = torch.roll(sim.p_max_series * float(gen), int(shift), dims=-1)
    return sim
