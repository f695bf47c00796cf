"""SHAC (short-horizon actor-critic, Xu et al., ICLR 2022) behind the training protocol: the actor is trained by
backpropagating the return of ``loss.horizon``-step rollouts through a differentiable model of the grid, with a
learned value for the tail; the critic regresses TD(λ) targets of the same rollouts. The rollouts act with samples
of the actor's ``TanhNormal`` (as Xu et al.; its scale is the model's ``init_log_std``, then learned) or, with
``loss.noise=false``, with its deterministic action, the one evaluation scores.

Model (``model.dynamics``): ``exact`` — the true transition with its gradients
(:mod:`anm_torchrl.grid.differentiable`: implicit power-flow gradients, active-constraint projections), float64, its
forward Newton–Raphson in torch ops or in the compiled kernel (``env.power_flow``);
``pinn`` — the PINN surrogate chain (:func:`anm_torchrl.surrogates.pinn.load.load_pinn`: the network's cached model,
trained from physics alone on first use; or ``surrogate.path``).
A terminal step (the power flow does not converge / the chain says collapse) takes gym-anm's terminal reward, ends
the gradient path of its row, and the row restarts from a fresh initial state of the true env's reset
distribution (resets are not transitions: no true-env frames).

Budget: ``collector.total_frames`` counts **model** transitions (``budget_unit = "model_frames"``); the summary
reports them as ``model_frames`` and ``frames`` = true-env transitions used for training (0; the protocol's
evaluation episodes aside). One iteration = ``env.num_envs`` x ``loss.horizon`` model frames; the last one runs
``ceil(remaining / env.num_envs)`` steps of every row, so a budget that is not a multiple of ``env.num_envs`` is passed
by fewer than ``env.num_envs`` frames (the recorded runs' counts, e.g. ANM6-Easy's 15,000,064); the summary counts
every model frame run.

The critic (:mod:`~anm_torchrl.training.algorithms.shac_critic`) regresses after each rollout, in this process or,
with ``loss.critic_worker``, in a worker process beside the actor's backward pass (the same updates).

Config groups it reads (``recipes/conf/shac.yaml``): ``model`` (PPO's actor/critic family + ``dynamics``), ``env``
(batch, time limit, forward power flow), ``loss`` (γ, λ, horizon, critic epochs, worker), ``optim``. Logged:
``train/{reward, loss_actor, loss_critic, value, terminated, grad_norm, critic_grad_norm, action_scale,
model_frames}`` and ``time/{rollout, update, fps}``.
"""

from __future__ import annotations

import copy
import functools
import time
from collections.abc import Mapping
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDict

from anm_torchrl.training.algorithms.base import Algorithm, anneal_lr, set_optimizer_options
from anm_torchrl.training.algorithms.ppo import PPO, model_options
from anm_torchrl.training.algorithms.shac_critic import (CriticSettings, CriticWorker, Rollout, move_towards,
                                                        update_critic, value)

DYNAMICS = ("exact", "pinn")


def actor_options(config) -> dict:
    """``model_options`` without SHAC's ``dynamics`` key (the keyword arguments of ``make_ppo_models``); also
    without ``power_flow``, which checkpoints made with that key's first home (``model.power_flow``, now
    ``env.power_flow``) carry: the runs of ANM6-Easy's exact-model leaderboard row among them."""
    return {k: v for k, v in model_options(config).items() if k not in ("dynamics", "power_flow")}


class ExactModel:
    """The true transition with gradients: ``(state (N, D) float64, action (N, A) MW) -> (next state (N, D),
    reward (N,), terminated (N,) bool, observation (N, n_obs) float32)``. ``power_flow`` runs the forward's
    Newton–Raphson: ``torch`` (ops) or ``numba`` (the compiled kernel; the same numbers to float64 round-off)."""

    def __init__(self, env, power_flow: str):
        from anm_torchrl.grid import differentiable

        solver = None
        if power_flow == "numba":
            from anm_torchrl.grid.backends.numba import CompiledPowerFlow, NumbaBackend

            why = NumbaBackend().unusable(env.sim.net)
            if why:
                raise ValueError(f"env.power_flow=numba: {why}")
            solver = CompiledPowerFlow(env.sim.constants)
        self.sim, self.obs_map = env.sim, env.obs_map
        self._step = functools.partial(differentiable.step, solver=solver)

    def __call__(self, state, action):
        nxt, tr = self._step(self.sim, state, action.to(state.dtype))
        term = ~tr.converged
        return nxt, tr.reward, term, self.obs_map.observe(nxt, tr.v, term)


class PINNModel:
    """The PINN chain as a model (same call as :class:`ExactModel`); its observation must come from the state."""

    def __init__(self, env, cfg):
        from omegaconf import OmegaConf

        from anm_torchrl.envs.surrogate import TerminationWatch
        from anm_torchrl.surrogates.pinn.chain import run_chain
        from anm_torchrl.training.factory import load_surrogate_in_home, surrogate_options

        surrogate = cfg.get("surrogate", {})
        # ``surrogate=pinn``'s options (path, terminal, classifier_path, residual_threshold) reach the loader as in
        # PPO's surrogate env (factory.make_env); another surrogate group is not this model's: the defaults
        options = {}
        if surrogate.get("name") == "pinn":
            options = surrogate_options(OmegaConf.to_container(surrogate, resolve=True))
        # the default cache trains on first use (as ``ppo.py surrogate=pinn``); an explicit path must exist
        self.chain = load_surrogate_in_home("pinn", sim=env.sim, progress=False, **options)
        self._run = run_chain  # the chain's modules on plain tensors: no TensorDict per step
        for p in self.chain.parameters():
            p.requires_grad_(False)
        self.obs_map = env.obs_map
        if self.obs_map.needs_grid:
            raise ValueError("model.dynamics=pinn needs an observation computed from the state alone")
        self.termination_watch = TerminationWatch(f"{type(self.chain).__name__} (the PINN)", env.batch_size.numel())

    def __call__(self, state, action):
        out = self._run(self.chain, {"state": state, "action": action.to(state.dtype)})
        term = out["terminated"].reshape(-1)
        self.termination_watch(term)
        nxt = out["next_state"]
        return nxt, out["reward"].reshape(-1), term, self.obs_map.observe(nxt, None, term)


def _short_row_count(env_cfg, n: int) -> int:
    """How many of the ``n`` model rows have short episodes: ``round(env.short_rows * n)`` (0 without a time
    limit)."""
    return 0 if env_cfg.max_steps is None else round(float(env_cfg.get("short_rows", 0.0)) * n)


def _row_time_limits(env_cfg, n: int, device) -> torch.Tensor | None:
    """Each model row's episode length (n,) long: ``env.max_steps``, except the last :func:`_short_row_count`
    rows, whose episodes end after ``env.short_steps`` (more episode starts, where the first hour's penalties are,
    without shortening the other rows' days); None without a time limit."""
    if env_cfg.max_steps is None:
        return None
    limits = torch.full((n,), int(env_cfg.max_steps), dtype=torch.long, device=device)
    short = _short_row_count(env_cfg, n)
    if short:
        limits[n - short:] = int(env_cfg.short_steps)
    return limits


class SHAC(Algorithm):
    """Short-horizon actor-critic through a differentiable grid model (see the module docstring)."""

    name = "shac"
    budget_unit = "model_frames"
    # PPO's actor and critic (make_ppo_models): a PPO run can start from a SHAC run's (checkpoint.init_from)
    architecture_keys, network_family = PPO.architecture_keys, PPO.network_family

    def __init__(self, cfg: DictConfig, *, device, seed: int, budget: int, reward_scale: float,
                 resume: Mapping[str, Any] | None):
        from anm_torchrl.training.factory import make_true_env
        from anm_torchrl.training.models import make_ppo_models

        self.cfg, self.device, self.reward_scale = cfg, device, float(reward_scale)
        self.noise = bool(cfg.loss.noise)
        self.env = make_true_env(int(cfg.env.num_envs), device, seed=seed, init=cfg.env.init, network=cfg.network,
                                 action_mode="clip")
        self.actor, self.critic, self.normalizer = make_ppo_models(
            self.env, obs_stats=resume["obs_norm"] if resume else None, **actor_options(cfg))
        self.actor, self.critic = self.actor.to(device), self.critic.to(device)
        # the actor the rollouts train; ``self.actor`` (evaluated, checkpointed) is it or its running average
        self.ema = float(cfg.optim.actor_ema)
        self.learner = copy.deepcopy(self.actor) if self.ema > 0 else self.actor
        dyn = str(cfg.model.dynamics)
        self.model = (ExactModel(self.env, str(cfg.env.power_flow)) if dyn == "exact"
                      else PINNModel(self.env, cfg))
        adam = dict(eps=float(cfg.optim.eps), weight_decay=float(cfg.optim.weight_decay), betas=(0.7, 0.95))
        self.actor_optim = torch.optim.Adam(self.learner.parameters(), lr=float(cfg.optim.actor_lr), **adam)
        self.critic_optim = torch.optim.Adam(self.critic.parameters(), lr=float(cfg.optim.critic_lr), **adam)
        if resume:
            self.actor.load_state_dict(resume["actor"])
            if self.ema > 0:  # a run resumed without its learner (checkpoint of an ema-less run) starts it there
                self.learner.load_state_dict(resume["state"].get("learner", resume["actor"]))
            self.critic.load_state_dict(resume["state"]["critic"])
            self.actor_optim.load_state_dict(resume["state"]["actor_optimizer"])
            self.critic_optim.load_state_dict(resume["state"]["critic_optimizer"])
            options = dict(eps=cfg.optim.eps, weight_decay=cfg.optim.weight_decay)
            set_optimizer_options(self.actor_optim, lr=cfg.optim.actor_lr, **options)
            set_optimizer_options(self.critic_optim, lr=cfg.optim.critic_lr, **options)
        self.target_critic = copy.deepcopy(self.critic)
        if resume and "target_critic" in resume["state"]:
            self.target_critic.load_state_dict(resume["state"]["target_critic"])
        for p in self.target_critic.parameters():
            p.requires_grad_(False)
        self.model_frames = int(resume["frames"]) if resume else 0
        self.env_frames = 0  # true-env transitions used for training: none (SHAC trains on the model)
        td = self.env.reset()
        self.state, self.obs = td["state"].to(torch.float64), td["observation"].float()
        n = self.state.shape[0]
        self.steps = torch.zeros(n, dtype=torch.long, device=self.state.device)
        self.max_steps = _row_time_limits(cfg.env, n, self.state.device)  # (n,) long, or None
        # short rows reset about every step, and a reset batch solves a power flow per row: they draw from a pool of
        # whole batches; otherwise each reset step draws one batch (as the entries' recorded runs did)
        self._pool = (self.state[:0], self.obs[:0]) if _short_row_count(cfg.env, n) else None
        if cfg.env.get("stagger"):
            # the rows' first episodes are cut after 1..max_steps steps, so later resets spread over the iterations;
            # on resume too: the rows start from fresh states (their counters are not saved)
            self.steps = torch.randint(0, int(cfg.env.max_steps), (n,), device=self.steps.device) % self.max_steps
        loss, optim = cfg.loss, cfg.optim
        self.critic_settings = CriticSettings(
            gamma=float(loss.gamma), td_lambda=float(loss.td_lambda), epochs=int(loss.critic_epochs),
            batch_size=int(loss.critic_batch_size), max_grad_norm=float(optim.max_grad_norm),
            target_tau=float(loss.target_tau))
        self.worker = (CriticWorker(self.critic, self.target_critic, self.critic_optim, self.critic_settings, seed)
                       if loss.get("critic_worker") else None)

    def _fresh(self, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Fresh initial (state, observation) for the ``rows`` (n,) long, from the true env's reset distribution:
        the first rows of a full reset batch, or, with short rows, the next rows of a pool of such batches."""
        k = rows.numel()
        if self._pool is None:
            td = self.env.reset()
            return td["state"][:k].to(torch.float64), td["observation"][:k].float()
        while self._pool[0].shape[0] < k:
            td = self.env.reset()
            self._pool = (torch.cat([self._pool[0], td["state"].to(torch.float64)]),
                          torch.cat([self._pool[1], td["observation"].float()]))
        state, obs = self._pool[0][:k], self._pool[1][:k]
        self._pool = (self._pool[0][k:], self._pool[1][k:])
        return state, obs

    def iterate(self, remaining: int) -> tuple[int, dict[str, float]]:
        """One rollout of ``min(loss.horizon, ceil(remaining / env.num_envs))`` steps of every row (the last one may
        pass ``remaining`` by fewer than ``env.num_envs`` frames: the module docstring)."""
        cfg = self.cfg
        n = self.state.shape[0]
        horizon = max(1, min(int(cfg.loss.horizon), -(-remaining // n)))
        gamma = float(cfg.loss.gamma)
        t0 = time.perf_counter()
        if cfg.optim.anneal_lr:
            total = int(cfg.collector.total_frames)
            start = float(cfg.optim.anneal_start)
            anneal_lr(self.actor_optim, cfg.optim.actor_lr, self.model_frames, total, start)
            anneal_lr(self.critic_optim, cfg.optim.critic_lr, self.model_frames, total, start)
        state, obs, steps = self.state, self.obs, self.steps
        ret = torch.zeros(n, device=state.device)
        disc = torch.ones(n, device=state.device)
        loss = torch.zeros((), device=state.device)
        buf_obs, buf_rew, buf_next, buf_term, buf_end = [], [], [], [], []
        n_term, rewards, scales = 0, [], []
        for t in range(horizon):
            td = TensorDict({"observation": obs}, [n])
            dist = self.learner.get_dist(td)  # writes "loc" and "scale" into td
            action = dist.rsample() if self.noise else dist.deterministic_sample
            nxt, reward, term, next_obs = self.model(state, action)
            r = (reward * self.reward_scale).float()
            r = torch.where(term, r.detach(), r)  # the terminal reward is a constant
            ret = ret + disc * r
            steps = steps + 1
            trunc = (steps >= self.max_steps) if self.max_steps is not None else torch.zeros_like(term)
            last = t == horizon - 1
            boot = (trunc | last) & ~term  # bootstrap with the value at the cut
            if bool(boot.any()):
                v_next = value(self.target_critic, next_obs)
                ret = ret + torch.where(boot, disc * gamma * v_next, 0.0)
            end = term | trunc | last
            loss = loss - torch.where(end, ret, 0.0).sum()
            buf_obs.append(obs.detach()); buf_rew.append(r.detach()); buf_next.append(next_obs.detach())
            buf_term.append(term); buf_end.append(term | trunc)
            n_term += int(term.sum()); rewards.append(reward.detach()); scales.append(td.get("scale").detach())
            ret = torch.where(end, 0.0, ret)
            disc = torch.where(end, 1.0, disc * gamma)
            reset = term | trunc
            if bool(reset.any()):
                rows = reset.nonzero().squeeze(1)
                fresh_s, fresh_o = self._fresh(rows)
                nxt = nxt.clone(); next_obs = next_obs.clone()
                nxt[rows], next_obs[rows] = fresh_s, fresh_o
                steps = torch.where(reset, 0, steps)
            state, obs = nxt, next_obs
        actor_loss = loss / (horizon * n)
        rollout = Rollout(obs=torch.stack(buf_obs), reward=torch.stack(buf_rew), next_obs=torch.stack(buf_next),
                          term=torch.stack(buf_term), end=torch.stack(buf_end))
        if self.worker is not None:  # the critic's update runs beside the actor's backward pass
            self.worker.submit(rollout, float(self.critic_optim.param_groups[0]["lr"]))
        self.actor_optim.zero_grad(set_to_none=True)
        actor_loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.learner.parameters(), float(cfg.optim.max_grad_norm))
        if torch.isfinite(grad_norm):
            self.actor_optim.step()
            if self.ema > 0:
                move_towards(self.actor, self.learner, self.ema)
        t_rollout = time.perf_counter() - t0
        self.state, self.obs, self.steps = state.detach(), obs.detach(), steps

        # critic: TD(λ) targets from the target critic, regression (here, or the worker's, waited for)
        t0 = time.perf_counter()
        if self.worker is None:
            critic = update_critic(self.critic, self.target_critic, self.critic_optim, rollout, self.critic_settings)
        else:
            critic = self.worker.result()
        t_update = time.perf_counter() - t0
        frames = horizon * n
        self.model_frames += frames
        metrics = {"train/reward": torch.stack(rewards).mean(), "train/loss_actor": actor_loss.detach(),
                   "train/loss_critic": critic["loss"], "train/value": critic["value"],
                   "train/terminated": n_term / frames, "train/grad_norm": grad_norm.detach(),
                   "train/critic_grad_norm": critic["grad_norm"],
                   # the exploration noise's scale (0: deterministic rollouts)
                   "train/action_scale": torch.stack(scales).mean() * self.noise,
                   "train/model_frames": self.model_frames,
                   "time/rollout": t_rollout, "time/update": t_update,
                   "time/fps": frames / max(t_rollout + t_update, 1e-9)}
        return frames, metrics

    def state_dict(self) -> dict[str, Any]:
        # with the worker, the critic's optimiser state is the worker's
        critic_optim = self.critic_optim.state_dict() if self.worker is None else self.worker.optim_state
        state = {"critic": self.critic.state_dict(), "target_critic": self.target_critic.state_dict(),
                 "actor_optimizer": self.actor_optim.state_dict(), "critic_optimizer": critic_optim}
        if self.ema > 0:
            state["learner"] = self.learner.state_dict()
        return state

    def close(self, interrupted: bool = False) -> None:
        if self.worker is not None:
            self.worker.close()

    @staticmethod
    def build_actor(env, config: Mapping[str, Any], obs_stats: Mapping[str, Any]):
        from anm_torchrl.training.models import make_ppo_models

        return make_ppo_models(env, obs_stats=obs_stats, **actor_options(config))[0]
