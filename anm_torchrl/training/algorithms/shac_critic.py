"""SHAC's critic: TD(λ) targets of a rollout from the target critic, the critic's regression on them and the target's
Polyak step — in the training process, or in a worker process beside the next rollout (``loss.critic_worker``).

With the worker, iteration i's critic update runs while the actor's rollout i + 1 runs, so that rollout bootstraps
with the target critic of update i - 1 (one update older than in the sequential order); the updates themselves,
targets included, are the sequential order's. The two processes exchange pickled tensors (a rollout's buffers one
way, the critic's weights the other: ~1 MB per iteration at 128 rows x 64 steps), no shared memory to leak.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import pickle

import torch


@dataclasses.dataclass
class Rollout:
    """One rollout's critic data, time first: ``obs``, ``next_obs`` (T, N, n_obs) float32, ``reward`` (T, N) scaled,
    ``term`` (T, N) bool (terminal: no bootstrap), ``end`` (T, N) bool (terminal or time limit: the row restarts)."""

    obs: torch.Tensor
    reward: torch.Tensor
    next_obs: torch.Tensor
    term: torch.Tensor
    end: torch.Tensor


@dataclasses.dataclass(frozen=True)
class CriticSettings:
    """The ``loss``/``optim`` keys the critic's update reads."""

    gamma: float
    td_lambda: float
    epochs: int
    batch_size: int
    max_grad_norm: float
    target_tau: float


def value(net, obs: torch.Tensor) -> torch.Tensor:
    """The critic ``net``'s value of ``obs`` (..., n_obs) -> (...)."""
    return net.module(obs).squeeze(-1)


@torch.no_grad()
def move_towards(average: torch.nn.Module, source: torch.nn.Module, weight: float) -> None:
    """Polyak step of ``average``'s parameters: ``avg <- avg + weight (source - avg)`` (the target critic, the
    actor's running average)."""
    for p_avg, p in zip(average.parameters(), source.parameters()):
        p_avg.lerp_(p, weight)


@torch.no_grad()
def td_lambda_targets(target_critic, rollout: Rollout, gamma: float, lam: float) -> torch.Tensor:
    """TD(λ) value targets (T, N) of ``rollout``, backwards from its last step, from ``target_critic``'s values of
    the next observations (a row's return restarts at ``end``; nothing is bootstrapped after ``term``)."""
    rew, term, end = rollout.reward, rollout.term, rollout.end
    v_next = value(target_critic, rollout.next_obs)
    target = torch.zeros_like(rew)
    horizon = rew.shape[0]
    g = v_next[-1]
    for t in reversed(range(horizon)):
        if t == horizon - 1:
            g = rew[t] + gamma * torch.where(term[t], 0.0, v_next[t])
        else:
            mixed = (1 - lam) * v_next[t] + lam * g
            g = rew[t] + gamma * torch.where(term[t], 0.0, torch.where(end[t], v_next[t], mixed))
        target[t] = g
    return target


def update_critic(critic, target_critic, optim, rollout: Rollout, s: CriticSettings) -> dict[str, torch.Tensor]:
    """Regress ``critic`` on ``rollout``'s TD(λ) targets (``s.epochs`` passes of shuffled minibatches, Adam
    ``optim``, gradient norm clipped), then move ``target_critic`` towards it. Returns the mean loss, mean gradient
    norm and mean target as 0-d tensors."""
    target = td_lambda_targets(target_critic, rollout, s.gamma, s.td_lambda)
    flat_obs, flat_target = rollout.obs.reshape(-1, rollout.obs.shape[-1]), target.reshape(-1)
    mini = min(s.batch_size, flat_obs.shape[0])
    losses, norms = [], []
    for _ in range(s.epochs):
        perm = torch.randperm(flat_obs.shape[0], device=flat_obs.device)
        for start in range(0, flat_obs.shape[0], mini):
            idx = perm[start:start + mini]
            loss = ((value(critic, flat_obs[idx]) - flat_target[idx]) ** 2).mean()
            optim.zero_grad(set_to_none=True)
            loss.backward()
            norms.append(torch.nn.utils.clip_grad_norm_(critic.parameters(), s.max_grad_norm))
            optim.step()
            losses.append(loss.detach())
    move_towards(target_critic, critic, s.target_tau)
    return {"loss": torch.stack(losses).mean(), "grad_norm": torch.stack(norms).mean(), "value": flat_target.mean()}


def _serve(conn, critic, target_critic, optim, settings: CriticSettings, seed: int) -> None:
    """The worker process: answers each ``(rollout, lr)`` with (critic, target critic and optimiser state dicts,
    metrics) until ``None``."""
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    while (msg := pickle.loads(conn.recv_bytes())) is not None:
        rollout, lr = msg
        for group in optim.param_groups:
            group["lr"] = lr
        metrics = update_critic(critic, target_critic, optim, rollout, settings)
        conn.send_bytes(pickle.dumps((critic.state_dict(), target_critic.state_dict(), optim.state_dict(), metrics)))
    conn.close()


class CriticWorker:
    """``update_critic`` in a forked worker process, one update in flight (see the module docstring).

    Built from the training process's ``critic``, ``target_critic`` and ``optim`` (copied into the worker at
    the fork); :meth:`exchange` loads each finished update's weights back into the modules and keeps the
    optimiser's state (:attr:`optim_state`), so a checkpoint never waits for the update in flight: it holds the
    critic the next rollout bootstraps with (a run resumed from it repeats no update and loses the one in flight).
    """

    def __init__(self, critic, target_critic, optim, settings: CriticSettings, seed: int):
        # fork: the worker starts with the modules and the optimiser as they are (no pickling, no re-import of a
        # recipe's __main__, which spawn would re-run from Hydra's changed working directory)
        ctx = multiprocessing.get_context("fork")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child, critic, target_critic, optim, settings, seed),
                                 daemon=True, name="anm_torchrl-shac-critic")
        self._proc.start()
        child.close()
        self.critic, self.target_critic, self.optim_state = critic, target_critic, optim.state_dict()
        self._waiting = False

    def _apply(self) -> dict[str, torch.Tensor] | None:
        """Wait for the update in flight, if any, and load its result; returns its metrics."""
        if not self._waiting:
            return None
        critic, target, self.optim_state, metrics = pickle.loads(self._conn.recv_bytes())
        self._waiting = False
        self.critic.load_state_dict(critic)
        self.target_critic.load_state_dict(target)
        return metrics

    def exchange(self, rollout: Rollout, lr: float) -> dict[str, torch.Tensor] | None:
        """Load the result of the update in flight into the training process's critic and target critic, and
        start the update on ``rollout`` at learning rate ``lr``. Returns the finished update's metrics (None
        before the first)."""
        metrics = self._apply()
        self._conn.send_bytes(pickle.dumps((rollout, lr)))
        self._waiting = True
        return metrics

    def close(self) -> None:
        """Load the last update's result (for the last checkpoint) and stop the worker."""
        if self._proc.is_alive():
            try:
                self._apply()
                self._conn.send_bytes(pickle.dumps(None))
            except (BrokenPipeError, EOFError, OSError):
                pass
            self._proc.join(timeout=10)
            if self._proc.is_alive():
                self._proc.terminate()
        self._conn.close()
