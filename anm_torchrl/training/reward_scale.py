"""The PPO reward scale of a network, derived from the do-nothing policy rather than tuned by hand.

``loss.reward_scale=auto`` multiplies every training reward by ``step_reward / |r̄|``, with r̄ the do-nothing
policy's mean reward per step on the run's validation states of the true simulator (the same states, episode
length and termination rule as the evaluation). The default ``step_reward`` (``loss.auto_step_reward`` = 0.043)
is ANM6-Easy's hand-tuned scale expressed in these units: do-nothing's mean step reward there is −4.29 (its
penalty; 4 validation states × 1,000 steps) and ``reward_scale`` = 0.01, so 4.29 × 0.01 = 0.043. On case33bw
(do-nothing r̄ ≈ −2.5e-4, pure line losses) the same rule gives a scale of ≈ 175 instead of 0.01: value targets
O(1..100) again, not O(1e-4), so the critic's error no longer drowns the return differences between actions.
"""

from __future__ import annotations

import torch

from anm_torchrl.evaluation import evaluate_policy


def do_nothing_reward_scale(env, states: torch.Tensor, max_steps: int, step_reward: float) -> dict[str, float]:
    """``step_reward / |mean do-nothing reward per step|`` on ``states`` of ``env`` (the true simulator).

    Args:
        env: a true env (``ANMEnv``/``ANM6Env``) of batch size E, with ``sim``.
        states: (E, state_dim) float64 initial states (the validation states).
        max_steps: episode length T (steps after a termination are not counted).
        step_reward: the scaled magnitude of do-nothing's mean step reward, > 0.

    Returns:
        ``{"reward_scale", "do_nothing_step_reward", "step_reward", "episodes", "max_steps"}``.

    Raises:
        ValueError: ``step_reward`` <= 0, or do-nothing's mean step reward is 0 or not finite (no scale exists).
    """
    from anm_torchrl.baselines import make_baseline

    if not step_reward > 0:
        raise ValueError(f"loss.auto_step_reward must be > 0, got {step_reward}")
    res = evaluate_policy(make_baseline("do_nothing", sim=env.sim), states, max_steps=int(max_steps), env=env)
    mean_step = float(res.returns.sum() / res.steps.sum())
    if not (torch.isfinite(torch.tensor(mean_step)) and mean_step != 0.0):
        raise ValueError(f"do-nothing's mean step reward on the validation states is {mean_step}: "
                         f"loss.reward_scale=auto needs a finite non-zero value; give a number instead")
    return {"reward_scale": float(step_reward) / abs(mean_step), "do_nothing_step_reward": mean_step,
            "step_reward": float(step_reward), "episodes": int(states.shape[0]), "max_steps": int(max_steps)}
