"""Does a warm start from the optimum's controller pay? Behaviour cloning of the AC-MPC with DAgger rounds.

Issue 27 asks whether warm starts from the optimum's or the AC-MPC's trajectories close the gap to the optimum.
The expert is the receding-horizon AC-MPC with a perfect forecast (:class:`~anm_torchrl.baselines.acmpc.ACMPCPolicy`,
N = 64: 1.001x the optimum's loss on ANM6-Easy's test states), solved cold from each labelled state. The learner is
PPO's actor (:func:`~anm_torchrl.training.models.make_ppo_models`), fitted by least squares on its deterministic
action in the box's [-1, 1] coordinates, so it could start PPO or SHAC.

* Round 0 labels states drawn so that the storage's SoC covers its range (ANM6-Easy: gym-anm's *intended* reset,
  whose SoC is uniform in MWh; gym-anm's own reset draws it in p.u., below 1 MWh of 100).
* Each DAgger round (Ross et al., 2011) rolls the current policy out from the env's own reset states, labels states
  it visited, and refits on everything labelled so far: cloning alone never sees the states its own errors lead to
  (on ANM6-Easy the cloned policy's SoC drifts to full, where the PV surplus it meant to store overloads a line).
* Rounds are chosen on the validation states; the chosen policy is scored once on the gap table's test states.
  Every expert solve is counted in the wall time.
"""

from __future__ import annotations

import json
import logging
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from typing import Any

import numpy as np
import torch

log = logging.getLogger(__name__)

EXPERT_HORIZON = 64


def _label_chunk(network: str, states: np.ndarray, horizon: int) -> np.ndarray:
    """The expert's actions (n, A) at ``states`` (n, state_dim), in a worker process."""
    from anm_torchrl.baselines.acmpc import ACMPCPolicy
    from anm_torchrl.training.factory import make_true_env

    torch.set_num_threads(1)
    expert = ACMPCPolicy(make_true_env(1, network=network).sim, horizon=horizon)
    return np.stack([expert.act(torch.as_tensor(s).reshape(1, -1))[0].numpy() for s in states])


def label_states(network: str, states: torch.Tensor, horizon: int = EXPERT_HORIZON, jobs: int = 1) -> torch.Tensor:
    """The AC-MPC expert's set-points (n, A) float64 MW/MVAr at ``states`` (n, state_dim), ``jobs`` processes."""
    chunks = np.array_split(states.cpu().numpy(), max(1, min(int(jobs), len(states))))
    if len(chunks) == 1:
        return torch.as_tensor(_label_chunk(network, chunks[0], horizon))
    with ProcessPoolExecutor(len(chunks), mp_context=get_context("spawn")) as pool:
        parts = list(pool.map(_label_chunk, [network] * len(chunks), chunks, [horizon] * len(chunks)))
    return torch.as_tensor(np.concatenate(parts))


def observe(env, states: torch.Tensor) -> torch.Tensor:
    """``env``'s observations (n, obs_dim) float32 at ``states`` (n, state_dim); ``env`` has a batch of n."""
    from anm_torchrl.evaluation import reset_to

    return reset_to(env, states)["observation"].float()


def box_coordinates(actions: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """``actions`` (n, A) mapped to the box's [-1, 1] coordinates (the actor's ``tanh`` of its pre-tanh mean)."""
    return (2 * (actions.float() - low) / (high - low) - 1).clamp(-1.0, 1.0)


def fit(actor, obs: torch.Tensor, targets: torch.Tensor, epochs: int, batch: int = 128, lr: float = 1e-3,
        seed: int = 0) -> float:
    """Least-squares fit of ``actor``'s deterministic action to ``targets`` (n, A) in box coordinates; Adam with a
    cosine schedule; returns the final mean squared error (box coordinates) on all of ``obs`` (n, obs_dim)."""
    net = actor.module[0].module  # normaliser -> MLP -> scale head: (loc, scale)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(1, epochs))
    gen = torch.Generator().manual_seed(int(seed))
    for _ in range(epochs):
        for idx in torch.randperm(len(obs), generator=gen).split(batch):
            loss = ((torch.tanh(net(obs[idx])[0]) - targets[idx]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
    with torch.no_grad():
        return float(((torch.tanh(net(obs)[0]) - targets) ** 2).mean())


def visited_states(actor, env, starts: torch.Tensor, steps: int, count: int, seed: int) -> torch.Tensor:
    """``count`` states (count, state_dim) drawn uniformly (seeded) from ``actor``'s deterministic rollouts of
    ``steps`` steps from ``starts`` on ``env`` (batch ``len(starts)``); terminal steps excluded."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

    from anm_torchrl.evaluation import reset_to

    td = reset_to(env, starts)
    seen = []
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(steps):
            td = env.step(actor(td))
            alive = ~td["next", "terminated"].reshape(-1)
            seen.append(td["next", "state"][alive].clone())
            td = step_mdp(td)
    seen = torch.cat(seen)
    pick = torch.randperm(len(seen), generator=torch.Generator().manual_seed(int(seed)))[:count]
    return seen[pick]


def study(network: str = "anm6_easy", labels: int = 1024, rounds: int = 3, visit_starts: int = 16,
          visit_steps: int = 288, horizon: int = EXPERT_HORIZON, epochs: int = 300, time_features: bool = True,
          seed: int = 2, jobs: int = 2, eval_episodes: int = 16, eval_seed: int = 1,
          eval_steps: int | None = None) -> dict[str, Any]:
    """Clone the expert, ``rounds`` DAgger rounds of ``labels`` states each; the record (JSON-ready).

    Args:
        labels: states labelled per round (each one expert solve).
        visit_starts, visit_steps: a DAgger round's rollouts: from this many reset states, this many steps.
        seed: seed of the labelled and start states (round r uses ``seed + r``); must differ from ``eval_seed``
            and the gap table's test seed.
        eval_steps: steps of a validation episode (None: the gap table's T, which the test states always use).

    Raises:
        ValueError: ``seed + r`` meets the validation or test seed.
    """
    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy
    from anm_torchrl.experiments.leaderboard import against_optimum, gap_table_path, reference_returns
    from anm_torchrl.training.factory import make_true_env
    from anm_torchrl.training.models import make_ppo_models

    t0 = time.perf_counter()
    gap = json.loads(gap_table_path(network).read_text())
    protocol = gap["protocol"]
    test_seed, gamma, steps = int(protocol["seed"]), float(protocol["gamma"]), int(protocol["steps"])
    if {eval_seed, test_seed} & set(range(seed, seed + rounds + 1)):
        raise ValueError(f"seed {seed}..{seed + rounds} must avoid the validation ({eval_seed}) and test "
                         f"({test_seed}) seeds")
    env = make_true_env(labels, network=network, seed=seed)
    sim, low, high = env.sim, env.action_spec.space.low[0].float(), env.action_spec.space.high[0].float()
    torch.manual_seed(seed)
    actor, _, _ = make_ppo_models(env, time_features=time_features)
    cover = "intended" if env.init == "gym_anm" else env.init
    val_env = make_true_env(eval_episodes, network=network, seed=eval_seed)
    val_states = draw_initial_states(eval_episodes, eval_seed, val_env.sim, val_env.init)

    states = draw_initial_states(labels, seed, sim, cover)
    obs, targets, history, best = [], [], [], None
    for r in range(rounds + 1):
        if r > 0:
            starts = draw_initial_states(visit_starts, seed + r, sim, env.init)
            roll_env = make_true_env(visit_starts, network=network, seed=seed + r)
            states = visited_states(actor, roll_env, starts, visit_steps, labels, seed + r)
        t_label = time.perf_counter()
        actions = label_states(network, states, horizon, jobs)
        label_s = time.perf_counter() - t_label
        obs.append(observe(make_true_env(len(states), network=network, seed=seed), states))
        targets.append(box_coordinates(actions, low, high))
        t_fit = time.perf_counter()
        mse = fit(actor, torch.cat(obs), torch.cat(targets), epochs, seed=seed + r)
        fit_s = time.perf_counter() - t_fit
        actor.eval()
        val = evaluate_policy(actor, val_states, max_steps=eval_steps or steps, gamma=gamma, env=val_env).metrics()
        entry = {"round": r, "labelled": int(sum(len(o) for o in obs)), "label_s": label_s, "fit_s": fit_s,
                 "mse_box": mse, "validation": val, "wall_s": time.perf_counter() - t0}
        history.append(entry)
        log.info("round %d: %d states labelled (%.0f s), fit MSE %.2e, validation %.4g (penalty %.4g), %.0f s",
                 r, entry["labelled"], label_s, mse, val["discounted_return"], val["penalty"], entry["wall_s"])
        if best is None or val["discounted_return"] > best[0]["validation"]["discounted_return"]:
            best = (entry, {k: v.clone() for k, v in actor.state_dict().items()})
    actor.load_state_dict(best[1])
    n_test = int(protocol["episodes"])
    test_env = make_true_env(n_test, network=network, seed=test_seed)
    test_states = draw_initial_states(n_test, test_seed, test_env.sim, test_env.init)
    test = evaluate_policy(actor, test_states, max_steps=steps, gamma=gamma, env=test_env).metrics()
    opt, dn = reference_returns(network, gap)
    loss_ratio, gain_pct = against_optimum(test["discounted_return"], opt, dn)
    return {"what": "behaviour cloning of the AC-MPC expert with DAgger rounds (anm_torchrl.experiments.imitation)",
            "network": network, "expert": f"AC-MPC, perfect forecast, N = {horizon}, cold solves",
            "settings": {"labels": labels, "rounds": rounds, "visit_starts": visit_starts, "visit_steps": visit_steps,
                         "epochs": epochs, "time_features": time_features, "seed": seed, "jobs": jobs,
                         "label_cover": cover},
            "validation": {"episodes": eval_episodes, "seed": eval_seed, "steps": eval_steps or steps, "gamma": gamma},
            "rounds": history, "chosen_round": best[0]["round"],
            "test": {**test, "episodes": n_test, "seed": test_seed,
                     "loss_ratio": loss_ratio, "gain_share": gain_pct / 100},
            "optimum": opt, "do_nothing": dn, "wall_s": time.perf_counter() - t0}


def markdown(record: dict) -> str:
    """The record as a short table: one row per round, the chosen round's test score below."""
    lines = [f"{record['network']}: {record['what']}; expert {record['expert']}", "",
             "| round | states labelled | label s | fit s | MSE (box) | validation return | penalty |",
             "|---:|---:|---:|---:|---:|---:|---:|"]
    for r in record["rounds"]:
        v = r["validation"]
        lines.append(f"| {r['round']} | {r['labelled']:,} | {r['label_s']:.0f} | {r['fit_s']:.0f} | "
                     f"{r['mse_box']:.2e} | {v['discounted_return']:.4g} | {v['penalty']:.4g} |")
    t = record["test"]
    ratio = "" if t["loss_ratio"] is None else f", {t['loss_ratio']:.3f}x the optimum's loss"
    lines += ["", f"Round {record['chosen_round']} (chosen on validation) on the {t['episodes']} test states: "
              f"{t['discounted_return']:.4g}{ratio}, {100 * t['gain_share']:.2f} % of the optimum's gain; "
              f"{record['wall_s']:.0f} s in all, expert solves included.", ""]
    return "\n".join(lines)
