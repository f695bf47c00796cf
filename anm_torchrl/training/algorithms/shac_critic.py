"""SHAC's critic: TD(λ) targets of a rollout from the target critic, the critic's regression on them and the target's
Polyak step — in the training process, or in a worker process while the actor's backward pass runs
(``loss.critic_worker``).

With the worker, each iteration hands its rollout's buffers to the worker as soon as the rollout's forward pass is
done, and waits for the update after the actor's backward pass and Adam step: the same updates in the same order as
in the training process (the next rollout bootstraps with the updated target critic), only the critic's minibatch
shuffles come from the worker's own random stream. The two processes exchange pickled tensors (a rollout's buffers one
way, the critic's and its optimiser's state the other: ~1 MB per iteration at 128 rows x 64 steps).
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
    metrics) until ``None``. It ignores Ctrl-C and SIGTERM (a terminal's or a scheduler's signal reaches the whole
    process group): the training process finishes its iteration, then stops it."""
    from anm_torchrl.training.signals import ignore_stop_signals, release_stop_signals

    ignore_stop_signals()
    release_stop_signals()  # forked with them held back (CriticWorker): none arrived before the line above
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
    """``update_critic`` in a forked worker process (see the module docstring): :meth:`submit` a rollout, then
    :meth:`result` loads the updated critic, target critic and optimiser state back into the training process's
    ``critic``, ``target_critic`` and :attr:`optim_state` (copied into the worker at the fork)."""

    def __init__(self, critic, target_critic, optim, settings: CriticSettings, seed: int):
        # fork: the worker starts with the modules and the optimiser as they are (no pickling, no re-import of a
        # recipe's __main__, which spawn would re-run from Hydra's changed working directory)
        if "fork" not in multiprocessing.get_all_start_methods():
            raise ValueError("loss.critic_worker=true needs the 'fork' start method of multiprocessing, which this "
                             "platform does not have; set loss.critic_worker=false")
        if any(p.device.type != "cpu" for p in critic.parameters()):
            raise ValueError("loss.critic_worker=true runs the critic on the CPU only; set loss.critic_worker=false "
                             "on a GPU")
        from anm_torchrl.training.signals import stop_signals_held

        ctx = multiprocessing.get_context("fork")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child, critic, target_critic, optim, settings, seed),
                                 daemon=True, name="anm_torchrl-shac-critic")
        with stop_signals_held():  # the worker ignores them before any can reach it
            self._proc.start()
        child.close()
        self.critic, self.target_critic, self.optim_state = critic, target_critic, optim.state_dict()

    def submit(self, rollout: Rollout, lr: float) -> None:
        """Start the update on ``rollout`` at learning rate ``lr``."""
        try:
            self._conn.send_bytes(pickle.dumps((rollout, lr)))
        except (BrokenPipeError, ConnectionResetError):
            self._ended()

    def _ended(self):
        self._proc.join(timeout=5)
        raise RuntimeError(f"SHAC's critic worker process ended (exit code {self._proc.exitcode}) before returning "
                           "its update; its error, if any, is above") from None

    def result(self) -> dict[str, torch.Tensor]:
        """Wait for the submitted update, load its weights and optimiser state; returns its metrics."""
        try:
            reply = self._conn.recv_bytes()
        except (EOFError, ConnectionResetError):
            self._ended()
        critic, target, self.optim_state, metrics = pickle.loads(reply)
        self.critic.load_state_dict(critic)
        self.target_critic.load_state_dict(target)
        return metrics

    def close(self) -> None:
        """Stop the worker."""
        if self._proc.is_alive():
            try:
                self._conn.send_bytes(pickle.dumps(None))
            except (BrokenPipeError, OSError):
                pass
            self._proc.join(timeout=10)
            if self._proc.is_alive():
                self._proc.terminate()
        self._conn.close()
