"""Where a trained policy and the perfect-foresight optimum differ, on one test state of the gap table.

The trained policy is evaluated on every test state of the gap protocol (:func:`anm_torchrl.evaluation.
draw_initial_states`, the gap table's episodes, T and γ); the state where its discounted return falls furthest
below the optimum's recorded one is chosen (the largest absolute gap: where a reader learns most), the optimum is
solved there again (:func:`anm_torchrl.baselines.optimal.solve_optimal`, a few minutes on ANM6-Easy) and both are
rolled out on the true simulator. The record keeps, for each of them, the discounted return and its parts
(discounted energy loss, of which curtailment, and penalty, in p.u.·h: reward = −(loss + penalty) inside the env's
clipping), per-day sums over the episode, and the storage unit's SoC at the end of each day; the figure shows the
day-window where the discounted gap piles up, plus the cumulative discounted gap over the whole episode.

Command (the record ``results/where/<network>.json`` and figure ``.png``)::

    python -m anm_torchrl.cli.where_they_differ --checkpoint pretrained:anm6_easy --out results/where/anm6_easy
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from anm_torchrl.baselines.optimal import OptimalPolicy
from anm_torchrl.evaluation import EVAL_GAMMA, EVAL_MAX_STEPS, draw_initial_states, evaluate_policy
from anm_torchrl.provenance import machine_info, versions
from anm_torchrl.strict_json import json_text
from anm_torchrl.training.checkpoint import load_actor, load_checkpoint
from anm_torchrl.training.factory import make_true_env

log = logging.getLogger(__name__)

GAP_RECORD = Path(__file__).resolve().parents[2] / "results" / "gap" / "optimal_gap_8states.json"
TERMS = ("reward", "e_loss", "penalty", "curtailment")


def rollout_terms(policy: TensorDictModuleBase, network: str, state: torch.Tensor, steps: int) -> dict[str, np.ndarray]:
    """Roll ``policy`` out for ``steps`` steps from ``state`` (state_dim,) on the true env of ``network``.

    Returns per-step arrays (T,) in the reward's unit (p.u.·h, i.e. baseMVA·h): ``reward``, ``e_loss`` and
    ``penalty`` (the reward's terms before clipping: reward = −(e_loss + penalty) inside the clipping),
    ``curtailment`` (the part of ``e_loss`` that is curtailed renewable energy); ``soc`` (T, n_storage) MWh after
    each step; ``terminated`` (bool)."""
    env = make_true_env(1, seed=0, network=network)
    sl = env.sim.state_slices()
    td = env.reset(TensorDict({"state": state.reshape(1, -1).to(torch.float64)}, [1]), set_state=True)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        roll = env.rollout(int(steps), policy, tensordict=td, auto_reset=False, break_when_any_done=True)
    nxt = roll.get("next")
    out = {k: nxt.get(k if k == "reward" else ("grid", k)).reshape(-1).double().numpy() for k in TERMS}
    out["curtailment"] = out["curtailment"] * float(env.sim.net.delta_t) / float(env.sim.net.base_mva)  # MW -> p.u.·h
    out["soc"] = nxt.get("state")[0, :, sl["des_soc"]].double().numpy()
    out["terminated"] = nxt.get("terminated").reshape(-1).numpy()
    return out


def discounted(x: np.ndarray, gamma: float) -> float:
    """Σ_t γ^t x_t."""
    return float(np.sum(x * gamma ** np.arange(len(x))))


def per_day(x: np.ndarray, steps_per_day: int) -> list[float]:
    """Sums of ``x`` over consecutive days of ``steps_per_day`` steps (the last day may be partial)."""
    return [float(x[i:i + steps_per_day].sum()) for i in range(0, len(x), steps_per_day)]


def summarise(terms: dict[str, np.ndarray], gamma: float, steps_per_day: int) -> dict[str, Any]:
    """The record entry of one rollout: discounted sums, per-day sums and end-of-day SoC."""
    return {"discounted": {k: discounted(terms[k], gamma) for k in TERMS},
            "terminated": bool(terms["terminated"].any()), "steps": int(len(terms["reward"])),
            "per_day": {k: per_day(terms[k], steps_per_day) for k in TERMS},
            "soc_end_of_day_mwh": terms["soc"][steps_per_day - 1::steps_per_day].round(4).tolist()}


def choose_state(policy_returns: list[float], optimum_returns: list[float]) -> int:
    """The test state with the largest discounted-return gap (optimum − policy)."""
    return int(np.argmax(np.asarray(optimum_returns) - np.asarray(policy_returns)))


def run(checkpoint: str, out: str | Path, gap_record: str | Path = GAP_RECORD, state_index: int | None = None,
        window_days: int = 3) -> dict[str, Any]:
    """Measure, write ``<out>.json`` and ``<out>.png``, return the record (module docstring).

    Args:
        checkpoint: a training checkpoint or ``pretrained:<name>``.
        out: path stem of the record and the figure.
        gap_record: the gap study's record of the optimum on the test states (its protocol is used).
        state_index: a test state to show instead of the one with the largest gap.
        window_days: days shown in the time-series panels.
    """
    from anm_torchrl.policies import resolve

    t0 = time.perf_counter()
    gap = json.loads(Path(gap_record).read_text())
    proto = gap["protocol"]
    network, gamma, steps = proto.get("network", "anm6_easy"), float(proto["gamma"]), int(proto["steps"])
    if state_index is not None and not 0 <= int(state_index) < int(proto["episodes"]):
        raise ValueError(f"state {state_index}: the gap record {gap_record} holds test states "
                         f"0..{proto['episodes'] - 1}")
    if (gamma, steps) != (EVAL_GAMMA, EVAL_MAX_STEPS):
        raise ValueError(f"{gap_record}: protocol γ={gamma}, T={steps} differs from the evaluation's "
                         f"({EVAL_GAMMA}, {EVAL_MAX_STEPS})")
    path = resolve(checkpoint)
    ckpt = load_checkpoint(path)
    if ckpt["config"].get("network", "anm6_easy") != network:
        raise ValueError(f"{checkpoint} was trained on {ckpt['config'].get('network')!r}, the gap record is of "
                         f"{network!r}")
    actor = load_actor(ckpt)
    env = make_true_env(1, seed=0, network=network)
    sim = env.sim
    states = draw_initial_states(int(proto["episodes"]), int(proto["seed"]), sim=sim)
    pol = evaluate_policy(actor, states, steps, gamma, env=make_true_env(len(states), seed=0, network=network))
    policy_returns = pol.discounted_returns.tolist()
    optimum_returns = gap["rows"]["optimal"]["discounted_return"]
    k = choose_state(policy_returns, optimum_returns) if state_index is None else int(state_index)
    log.info("policy vs optimum per test state: %s; showing state %d",
             [f"{p:.2f}/{o:.2f}" for p, o in zip(policy_returns, optimum_returns)], k)
    t_solve = time.perf_counter()
    optimum = OptimalPolicy(sim, horizon=steps, gamma=gamma)
    opt_terms = rollout_terms(optimum, network, states[k], steps)
    solve_s = time.perf_counter() - t_solve
    pol_terms = rollout_terms(actor, network, states[k], steps)
    steps_per_day = int(round(24 / float(sim.net.delta_t)))
    rec = {
        "what": "a trained policy and the perfect-foresight optimum on the test state where they differ most",
        "network": network, "checkpoint": str(checkpoint), "protocol": proto, "state_index": k,
        "chosen_by": "largest optimum - policy discounted return" if state_index is None else "given",
        "per_state": {"policy": policy_returns, "optimum": optimum_returns},
        "steps_per_day": steps_per_day,
        "policy": summarise(pol_terms, gamma, steps_per_day),
        "optimum": {**summarise(opt_terms, gamma, steps_per_day),
                    "recorded_discounted_return": optimum_returns[k], "solve_s": solve_s},
        "wall_s": time.perf_counter() - t0, "machine": machine_info(), "versions": versions(),
        "command": f"python -m anm_torchrl.cli.where_they_differ --checkpoint {checkpoint} --out {out}",
    }
    rec["gap_discounted"] = {t: rec["optimum"]["discounted"][t] - rec["policy"]["discounted"][t] for t in TERMS}
    stem = Path(out)
    stem.parent.mkdir(parents=True, exist_ok=True)
    draw(pol_terms, opt_terms, rec, gamma, steps_per_day, window_days).savefig(stem.with_suffix(".png"), dpi=90)
    stem.with_suffix(".json").write_text(json_text(rec, indent=1) + "\n")
    return rec


def gap_window(pol: dict[str, np.ndarray], opt: dict[str, np.ndarray], gamma: float, steps_per_day: int,
               days: int) -> tuple[int, int]:
    """The ``days``-day window (start, stop steps) holding the largest share of the discounted reward gap."""
    n = min(len(pol["reward"]), len(opt["reward"]))
    gap = (opt["reward"][:n] - pol["reward"][:n]) * gamma ** np.arange(n)
    width = min(days * steps_per_day, n)
    sums = np.convolve(gap, np.ones(width), "valid")[::steps_per_day]
    start = int(np.argmax(sums)) * steps_per_day
    return start, start + width


def draw(pol: dict[str, np.ndarray], opt: dict[str, np.ndarray], rec: dict[str, Any], gamma: float,
         steps_per_day: int, days: int):
    """The comparison figure: SoC, curtailment, energy loss and penalty in the gap window, then the cumulative
    discounted gap over the episode."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    a, b = gap_window(pol, opt, gamma, steps_per_day, days)
    hours = np.arange(a, b) / steps_per_day * 24
    fig = Figure(figsize=(11, 12), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(5, 1)
    style = {"policy": {"color": "C0", "lw": 1.2}, "optimum": {"color": "k", "lw": 1.0, "ls": "--"}}
    for name, terms in (("policy", pol), ("optimum", opt)):
        for j in range(terms["soc"].shape[1]):
            axes[0].plot(hours, terms["soc"][a:b, j], label=f"{name}, storage {j}" if terms["soc"].shape[1] > 1
                         else name, **style[name])
        for ax, key in zip(axes[1:4], ("curtailment", "e_loss", "penalty")):
            ax.plot(hours, terms[key][a:b], label=name, **style[name])
    labels = ("state of charge (MWh)", "curtailment (p.u.·h per step)", "energy loss, curtailment included\n(p.u.·h per step)",
              "penalty (p.u.·h per step)")
    for ax, lab in zip(axes[:4], labels):
        ax.set_ylabel(lab)
        ax.set_xlabel("hours from the episode's start")
        ax.legend(loc="upper right", fontsize=8)
    n = min(len(pol["reward"]), len(opt["reward"]))
    disc = gamma ** np.arange(n)
    for key, colour in (("reward", "k"), ("curtailment", "C2"), ("e_loss", "C1"), ("penalty", "C3")):
        sign = 1.0 if key == "reward" else -1.0  # a cost the optimum avoids is a gain: plot gains as positive
        axes[4].plot(np.arange(n) / steps_per_day, np.cumsum(sign * (opt[key][:n] - pol[key][:n]) * disc),
                     color=colour, label={"reward": "return (total)", "e_loss": "energy loss"}.get(key, key))
    axes[4].axvspan(a / steps_per_day, b / steps_per_day, color="0.9")
    axes[4].set_xlabel("days from the episode's start")
    axes[4].set_ylabel("cumulative discounted gain\nof the optimum over the policy")
    axes[4].legend(loc="lower right", fontsize=8)
    p, o = rec["policy"]["discounted"]["reward"], rec["optimum"]["discounted"]["reward"]
    fig.suptitle(f"{rec['network']}, test state {rec['state_index']}: policy {p:.2f} vs optimum {o:.2f} "
                 f"(discounted return, γ = {gamma}, T = {n}); window: days {a // steps_per_day}–"
                 f"{b // steps_per_day}")
    return fig
