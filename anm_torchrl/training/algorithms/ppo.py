"""PPO behind the training protocol: TorchRL's ``Collector`` -> GAE (recomputed every epoch, or once per batch:
``loss.gae_every_epoch``) -> minibatches without replacement -> ``ClipPPOLoss`` -> Adam, as TorchRL's
``sota-implementations/ppo/ppo_mujoco.py``.

Config groups it reads: ``model`` (actor/critic), ``collector`` (frames per update, workers), ``loss`` (PPO/GAE),
``optim`` (Adam, schedule, clipping). Logged: ``train/{reward, episode_return, episode_length, loss_objective,
loss_critic, loss_entropy, entropy, clip_fraction, kl_approx, grad_norm, explained_variance, lr, action_scale}``
and ``time/{collect, update, fps}``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from functools import partial
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDict

from anm_torchrl.training.algorithms.base import Algorithm, anneal_lr, load_networks, set_optimizer_options


# what ClipPPOLoss reads once GAE has written the advantage and value target
LOSS_KEYS = ("observation", "action", "action_log_prob", "advantage", "value_target", "state_value")


def model_options(config) -> dict:
    """The ``model`` group of a config (a composed ``DictConfig`` or a checkpoint's plain dict) as the keyword
    arguments of :func:`~anm_torchrl.training.models.make_ppo_models` / ``make_sac_models`` (the keys are named
    alike); ``init_action=do_nothing`` on ``surrogate=gym_anm`` as ANM6-Easy's do-nothing action."""
    from omegaconf import OmegaConf

    model = config.get("model", {})
    options = dict(OmegaConf.to_container(model, resolve=True) if OmegaConf.is_config(model) else model)
    if options.get("init_action") == "do_nothing" and (config.get("surrogate") or {}).get("name") == "gym_anm":
        # gym-anm's own env has no simulator object to read do-nothing from: ANM6-Easy's is the same policy
        from anm_torchrl.baselines.simple import DoNothingPolicy
        from anm_torchrl.networks import ANM6_EASY, simulator

        options["init_action"] = DoNothingPolicy(simulator(ANM6_EASY)).action_value
    return options


def budget_mask(batch_size, remaining: int):
    """Frames of a collected batch ``[..., T]`` that fit in the remaining budget of ``remaining`` frames.

    Returns:
        None when the whole batch fits, else a bool mask of ``batch_size`` keeping the first ``remaining`` frames in
        time order (every env's step t before any env's step t + 1), so ``collector.total_frames`` is exact.
    """
    n_steps = int(batch_size[-1])
    n_envs = batch_size.numel() // n_steps
    if n_envs * n_steps <= remaining:
        return None
    rank = torch.arange(n_steps)[None, :] * n_envs + torch.arange(n_envs)[:, None]  # [envs, T], time-major order
    return (rank < remaining).reshape(batch_size)


def make_collector(cfg: DictConfig, policy, device, seed: int, budget: int, env=None):
    """TorchRL's collector over the training env, collecting whole batches of ``collector.frames_per_batch`` up to
    ``budget`` frames (the last batch is cut by :func:`budget_mask`):

    * one worker, ``collector.sync`` true: ``Collector`` in this process (``env`` if given); collection and the
      update take turns;
    * one worker, ``sync`` false: ``AsyncCollector``, one process that builds its own env and collects the next batch
      while this one updates, with the weights from before that update (the data one update behind the learner);
    * ``collector.num_workers`` = k > 1: k processes with ``env.num_envs / k`` grids each, ``MultiSyncCollector``
      (``sync``) or ``MultiAsyncCollector``.

    Returns None for a budget of 0. ``env`` is closed wherever it is not the collector's."""
    from torchrl.collectors import AsyncCollector, Collector

    from anm_torchrl.training.factory import make_train_env, train_env_kwargs
    from anm_torchrl.training.signals import in_worker

    num_workers, sync = int(cfg.collector.num_workers), bool(cfg.collector.sync)
    if budget <= 0 or num_workers > 1 or not sync:
        if env is not None:
            env.close()
        env = None
    if budget <= 0:
        return None
    frames_per_batch = int(cfg.collector.frames_per_batch)
    env_kwargs = train_env_kwargs(cfg, str(device), num_workers)
    kwargs = dict(policy=policy, frames_per_batch=frames_per_batch, device=device,
                  total_frames=-(-budget // frames_per_batch) * frames_per_batch, auto_register_policy_transforms=False)
    if num_workers == 1 and sync:
        return Collector(env if env is not None else make_train_env(seed=seed, **env_kwargs), **kwargs)
    # TorchRL sets this process's thread count to the cores left over by its workers unless told: keep ``threads``
    kwargs["num_threads"] = int(cfg.threads)
    # the workers ignore Ctrl-C and SIGTERM: the training process stops them (anm_torchrl.training.signals)
    if num_workers == 1:
        return AsyncCollector(partial(in_worker, os.getpid(), make_train_env, seed=seed, **env_kwargs), **kwargs)
    factories = [partial(in_worker, os.getpid(), make_train_env, seed=seed + 1000 * i, **env_kwargs)
                 for i in range(num_workers)]
    return Collector(factories, num_collectors=num_workers, sync=sync, **kwargs)


def episode_metrics(kept: TensorDict) -> dict[str, torch.Tensor]:
    """``train/reward`` and, over the episodes that ended in ``kept``, ``train/episode_return`` and
    ``train/episode_length`` (frames to the end: termination or time limit)."""
    out = {"train/reward": kept["next", "reward"].mean()}
    done = kept["next", "done"]
    if done.any():
        out["train/episode_return"] = kept["next", "episode_reward"][done].mean()
        if ("next", "step_count") in kept.keys(True):
            out["train/episode_length"] = kept["next", "step_count"][done].float().mean()
    return out


class PPO(Algorithm):
    """Clipped PPO with GAE (TorchRL ``ClipPPOLoss``), the PPO recipe's defaults in ``recipes/conf/``."""

    name = "ppo"
    architecture_keys = ("network", "model.actor_cells", "model.critic_cells", "model.activation", "model.obs_clip",
                         "model.time_features", "model.state_dependent_scale", "model.forecast_steps")
    network_family = "ppo"

    def __init__(self, cfg: DictConfig, *, device, seed: int, budget: int, reward_scale: float,
                 resume: Mapping[str, Any] | None):
        from torchrl.objectives import ClipPPOLoss
        from torchrl.objectives.value import GAE

        from anm_torchrl.training.models import make_ppo_models
        from anm_torchrl.training.factory import make_train_env, train_env_kwargs

        self.cfg, self.device, self.reward_scale = cfg, device, float(reward_scale)
        # one env to build the models from; with one worker it is also the collector's
        spec_env = make_train_env(seed=seed, **train_env_kwargs(cfg, str(device), int(cfg.collector.num_workers)))
        self.actor, self.critic, self.normalizer = make_ppo_models(
            spec_env, obs_stats=resume["obs_norm"] if resume else None, **model_options(cfg))
        self.actor, self.critic = self.actor.to(device), self.critic.to(device)
        # deactivate_vmap: the critic on observations and next observations in two plain calls instead of one
        # vmap, same values; on this CPU 3.2 against 4.1 ms per GAE pass at 4,096 frames, 9.5 against 12.2 at 16,384
        self.adv_module = GAE(gamma=cfg.loss.gamma, lmbda=cfg.loss.gae_lambda, value_network=self.critic,
                              average_gae=False, device=device, deactivate_vmap=True)
        self.loss_module = ClipPPOLoss(
            actor_network=self.actor, critic_network=self.critic, clip_epsilon=cfg.loss.clip_epsilon,
            loss_critic_type=cfg.loss.loss_critic_type, entropy_coeff=cfg.loss.entropy_coeff,
            critic_coeff=cfg.loss.critic_coeff, normalize_advantage=cfg.loss.normalize_advantage,
            # a zero coefficient needs no entropy estimate (TanhNormal's is sampled: 23 % of an epoch's CPU time)
            entropy_bonus=float(cfg.loss.entropy_coeff) > 0,
            # the modules' own parameters instead of a functional copy swapped in on every call: the same gradients
            # bit for bit, a minibatch's loss and backward ~10 % faster on this CPU
            functional=False)
        # opt-in (loss.compile): the minibatch loss through inductor; parameters stay the loss module's own
        self._loss = torch.compile(self.loss_module, dynamic=False) if cfg.loss.compile else self.loss_module
        self.optim = torch.optim.Adam(self.loss_module.parameters(), lr=cfg.optim.lr, eps=cfg.optim.eps,
                                      weight_decay=cfg.optim.weight_decay)
        self.return_norm = None
        if cfg.loss.get("return_norm", False):
            from anm_torchrl.training.return_norm import ReturnNormalizer

            self.return_norm = ReturnNormalizer(float(cfg.loss.gamma))
        if resume:
            self.actor.load_state_dict(resume["actor"])
            self.critic.load_state_dict(resume["state"]["critic"])
            self.optim.load_state_dict(resume["state"]["optimizer"])
            set_optimizer_options(self.optim, lr=cfg.optim.lr, eps=cfg.optim.eps, weight_decay=cfg.optim.weight_decay)
            if self.return_norm is not None and resume["state"].get("return_norm") is not None:
                self.return_norm.load_state_dict(resume["state"]["return_norm"])
        self.total_frames = int(cfg.collector.total_frames)
        self.frames = int(resume["frames"]) if resume else 0
        self.collector = make_collector(cfg, self.actor, device, seed, budget, env=spec_env)
        self._batches = iter(self.collector) if self.collector is not None else iter(())

    def iterate(self, remaining: int) -> tuple[int, dict[str, float]]:
        cfg, optim = self.cfg, self.optim
        t0 = time.perf_counter()
        data = next(self._batches)
        t_collect = time.perf_counter() - t0
        # data: [num_envs, T] (one process) or [workers, envs per worker, T] (multi-process); time is last
        keep = budget_mask(data.batch_size, remaining)  # None except for a cut last batch
        kept = data if keep is None else data[keep]
        n_frames = kept.numel()
        metrics = {**episode_metrics(kept), "train/action_scale": kept["scale"].mean()}
        if self.reward_scale != 1.0:
            data.set(("next", "reward"), data.get(("next", "reward")) * self.reward_scale)
        if self.return_norm is not None:  # after the fixed scale, which it then only sets the start of
            data.set(("next", "reward"), self.return_norm(data.get(("next", "reward")), data.get(("next", "done"))))
            metrics["train/return_std"] = self.return_norm.var ** 0.5

        # GAE recomputed before every epoch (on the whole batch: its bootstrap needs every step), minibatches
        # without replacement over the kept frames
        t0 = time.perf_counter()
        if cfg.optim.anneal_lr:
            anneal_lr(optim, cfg.optim.lr, self.frames, self.total_frames, float(cfg.optim.anneal_start))
        mini = int(cfg.loss.mini_batch_size)
        losses = []
        for epoch in range(int(cfg.loss.ppo_epochs)):
            if epoch == 0 or cfg.loss.gae_every_epoch:
                with torch.no_grad():
                    data = self.adv_module(data)
            # only what the loss reads: indexing a minibatch out of every collected key (grid diagnostics, next
            # states, ...) cost as much as the loss itself
            flat = (data.reshape(-1) if keep is None else data[keep]).select(*LOSS_KEYS)
            perm = torch.randperm(flat.numel(), device=flat.device)
            for start in range(0, flat.numel(), mini):
                batch = flat[perm[start:start + mini]]
                loss = self._loss(batch)
                total = loss["loss_objective"] + loss["loss_critic"] + loss.get("loss_entropy", 0.0)
                optim.zero_grad(set_to_none=True)
                total.backward()
                grad_norm = (torch.nn.utils.clip_grad_norm_(self.loss_module.parameters(), cfg.optim.max_grad_norm)
                             if cfg.optim.max_grad_norm else torch.zeros(()))
                optim.step()
                losses.append(loss.select("loss_objective", "loss_critic", "loss_entropy", "entropy",
                                          "clip_fraction", "kl_approx", "explained_variance", strict=False).detach()
                              .set("grad_norm", grad_norm.detach()))
        self.collector.update_policy_weights_()
        t_update = time.perf_counter() - t0
        self.frames += n_frames
        loss_means = torch.stack(losses).apply(lambda x: x.float().mean(), batch_size=[])
        metrics.update({f"train/{key}": value for key, value in loss_means.items()})
        metrics["train/lr"] = optim.param_groups[0]["lr"]
        metrics.update({"time/collect": t_collect, "time/update": t_update,
                        "time/fps": n_frames / max(t_collect + t_update, 1e-9)})
        return n_frames, metrics

    def start_from(self, init: dict[str, Any]) -> None:
        load_networks(init, self.actor, self.critic, self.reward_scale, self.cfg.loss)
        if self.collector is not None:  # a collector in other processes holds its own copy of the weights
            self.collector.update_policy_weights_()

    def state_dict(self) -> dict[str, Any]:
        return {"critic": self.critic.state_dict(), "optimizer": self.optim.state_dict(),
                "return_norm": None if self.return_norm is None else self.return_norm.state_dict()}

    def close(self, interrupted: bool = False) -> None:
        if self.collector is None:
            return
        try:
            self.collector.shutdown()
        except Exception as err:  # noqa: BLE001 - after Ctrl-C, worker processes got the SIGINT too
            if not interrupted:
                raise
            import logging

            logging.getLogger(__name__).warning("collector shutdown after Ctrl-C: %s", err)
        finally:
            # a multi-process collector's shutdown hands its workers' threads back to this process
            torch.set_num_threads(int(self.cfg.threads))
        self.collector = None

    @staticmethod
    def build_actor(env, config: Mapping[str, Any], obs_stats: Mapping[str, Any]):
        from anm_torchrl.training.models import make_ppo_models

        return make_ppo_models(env, obs_stats=obs_stats, **model_options(config))[0]
