"""SAC behind the training protocol: TorchRL's ``Collector`` -> replay buffer -> ``SACLoss`` (twin Q networks,
target networks by Polyak averaging, a learned temperature) -> Adam, as TorchRL's ``sota-implementations/sac/``.

The batched env makes many frames per collection step, so the update count is set per frame: every iteration
collects ``collector.frames_per_batch`` frames (``env.num_envs`` x steps) and draws ``replay.samples_per_frame`` x
that many samples, in minibatches of ``replay.batch_size``. The first ``collector.init_random_frames`` frames (rounded
up to whole iterations, as TorchRL's collector does) are collected by a uniformly random policy (they count in the
budget); unlike TorchRL's recipe, the updates start with the first of them. Only the Q networks step in the updates made
while at most ``optim.actor_delay_frames`` frames have been collected: the actor (and the temperature) keep their
start while the critic learns it, and first step in the update after a batch that takes the count past it.

Config groups it reads (``recipes/conf/sac.yaml``): ``model`` (actor/Q widths), ``collector``, ``replay``, ``loss``
(γ, τ, temperature), ``optim``. Logged: ``train/{reward, episode_return, episode_length, loss_actor, loss_qvalue,
loss_alpha, alpha, entropy, grad_norm, buffer_size}`` and ``time/{collect, update, fps}``.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from typing import Any

import torch
from omegaconf import DictConfig

from anm_torchrl.training.algorithms.base import Algorithm, set_optimizer_options
from anm_torchrl.training.algorithms.ppo import budget_mask, episode_metrics, model_options

log = logging.getLogger(__name__)


def box_target_entropy(action_spec, per_dim: float) -> float:
    """SAC's target entropy (nats): ``per_dim`` nats per action dimension of the action box scaled to [-1, 1].

    The actor's ``TanhNormal`` spans the box in the action's own units (MW, MVAr), so its entropy carries
    ``log h`` per dimension of half-width ``h``: a target in those units asks for a different noise on every network
    (on CIGRE MV and SimBench, whose mean ``log h`` is -3.3, -1 nat per MW dimension is more entropy than a uniform
    action over the box has, and the temperature grows without bound). Summing ``per_dim + log h`` over the
    dimensions asks for the same noise relative to each box.

    A dimension whose range is a single value (half-width 0) is left out: the actor writes it at that value and
    samples nothing there (:class:`~anm_torchrl.training.distributions.PartlyFixedTanhNormal`).

    Args:
        action_spec: the env's ``Bounded`` action spec, shape (..., A), every half-width finite and >= 0, one > 0.
        per_dim: target nats per dimension of the box scaled to [-1, 1] (a uniform action there has log 2).

    Raises:
        ValueError: a dimension's box is inverted or unbounded, or none has a range (no entropy target exists).
    """
    low, high = action_spec.space.low, action_spec.space.high
    half = ((high - low).double() / 2).reshape(-1, action_spec.shape[-1])[0]
    bad = [i for i, h in enumerate(half.tolist()) if not (math.isfinite(h) and h >= 0)]
    if bad or not (half > 0).any():
        raise ValueError(f"SAC's target entropy needs every action dimension's box to be finite, and one to have a "
                         f"range; dimension(s) {bad or list(range(half.numel()))} have half-width "
                         f"{[half[i].item() for i in (bad or range(half.numel()))]}")
    return float((per_dim + half[half > 0].log()).sum())


class SAC(Algorithm):
    """Soft actor-critic (TorchRL ``SACLoss``, version 2: no separate value network)."""

    name = "sac"
    architecture_keys = ("network", "model.actor_cells", "model.critic_cells", "model.activation", "model.obs_clip",
                         "model.time_features", "model.forecast_steps")

    def __init__(self, cfg: DictConfig, *, device, seed: int, budget: int, reward_scale: float,
                 resume: Mapping[str, Any] | None):
        from torchrl.collectors import Collector
        from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        from torchrl.objectives import SACLoss, SoftUpdate

        from anm_torchrl.training.factory import make_train_env, train_env_kwargs
        from anm_torchrl.training.models import make_sac_models

        self.cfg, self.device, self.reward_scale = cfg, device, float(reward_scale)
        env = make_train_env(seed=seed, **train_env_kwargs(cfg, str(device)))
        self.actor, qvalue, self.normalizer = make_sac_models(
            env, obs_stats=resume["obs_norm"] if resume else None, **model_options(cfg))
        self.actor, qvalue = self.actor.to(device), qvalue.to(device)
        target_entropy = box_target_entropy(env.full_action_spec["action"], float(cfg.loss.target_entropy_per_dim))
        self.loss_module = SACLoss(actor_network=self.actor, qvalue_network=qvalue, num_qvalue_nets=2,
                                   loss_function=cfg.loss.loss_function, alpha_init=float(cfg.loss.alpha_init),
                                   target_entropy=target_entropy, action_spec=env.full_action_spec["action"])
        self.loss_module.make_value_estimator(gamma=float(cfg.loss.gamma))
        self.target_updater = SoftUpdate(self.loss_module, tau=float(cfg.loss.tau))
        critic_params = list(self.loss_module.qvalue_network_params.flatten_keys().values())
        actor_params = list(self.loss_module.actor_network_params.flatten_keys().values())
        adam = dict(lr=float(cfg.optim.lr), eps=float(cfg.optim.eps), weight_decay=float(cfg.optim.weight_decay))
        # the temperature's Adam takes only the rate (its eps and weight decay stay torch's defaults)
        options = {"actor": adam, "qvalue": adam, "alpha": dict(lr=float(cfg.optim.lr))}
        params = {"actor": actor_params, "qvalue": critic_params, "alpha": [self.loss_module.log_alpha]}
        self.optims = {name: torch.optim.Adam(params[name], **options[name]) for name in options}
        if resume:
            self.actor.load_state_dict(resume["actor"])
            self.loss_module.load_state_dict(resume["state"]["loss"])
            # the loss state holds the discount and the entropy target as buffers: the config's apply, as its lr does
            self.loss_module.make_value_estimator(gamma=float(cfg.loss.gamma))
            self.loss_module.target_entropy.fill_(target_entropy)
            for name, optim in self.optims.items():
                optim.load_state_dict(resume["state"]["optimizers"][name])
                set_optimizer_options(optim, **options[name])
            log.info("SAC resumes with an empty replay buffer (it is not saved): the first updates replay only "
                     "the frames collected since")
        self.buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(int(cfg.replay.size), device=device),
                                             batch_size=int(cfg.replay.batch_size))
        frames_per_batch = int(cfg.collector.frames_per_batch)
        resumed = int(resume["frames"]) if resume else 0
        self.frames = resumed  # collected so far: the actor's delay counts these
        self._samples_owed = 0.0  # replay samples due but not yet drawn (less than a minibatch)
        self.actor_delay = int(cfg.optim.actor_delay_frames)
        if self.actor_delay >= int(cfg.collector.total_frames):  # a short run's actor would silently stay at its start
            log.warning(
                "optim.actor_delay_frames=%d >= collector.total_frames=%d: the actor never steps in this run (only the "
                "Q networks learn); lower optim.actor_delay_frames or raise the budget", self.actor_delay,
                int(cfg.collector.total_frames))
        self.collector = None
        if budget > 0:
            self.collector = Collector(
                env, self.actor, frames_per_batch=frames_per_batch, device=device,
                total_frames=-(-budget // frames_per_batch) * frames_per_batch,
                # whole iterations: TorchRL rounds up (and warns) otherwise
                init_random_frames=-(-max(int(cfg.collector.init_random_frames) - resumed, 0) // frames_per_batch)
                * frames_per_batch,
                auto_register_policy_transforms=False)
        self._batches = iter(self.collector) if self.collector is not None else iter(())

    def iterate(self, remaining: int) -> tuple[int, dict[str, float]]:
        cfg = self.cfg
        t0 = time.perf_counter()
        data = next(self._batches)
        t_collect = time.perf_counter() - t0
        keep = budget_mask(data.batch_size, remaining)
        kept = (data if keep is None else data[keep]).reshape(-1)
        n_frames = kept.numel()
        self.frames += n_frames
        # before optim.actor_delay_frames, the Q networks learn the initial policy's values alone: an actor that
        # follows an untrained critic leaves its (do-nothing) start within a few steps (sac_validation.json)
        stepped = ["qvalue"] if self.frames <= self.actor_delay else list(self.optims)
        metrics = episode_metrics(kept)
        if self.reward_scale != 1.0:
            kept.set(("next", "reward"), kept.get(("next", "reward")) * self.reward_scale)
        # only what SACLoss reads: a frame of every collected key (gym-anm's float64 state twice, grid diagnostics)
        # is 17 kB on the 115-bus feeder, 17 GB at 1M frames; these keys are a third of that
        self.buffer.extend(kept.select(*self.loss_module.in_keys))

        t0 = time.perf_counter()
        # gradient steps at replay.samples_per_frame on average: the fraction of a minibatch left over carries to the
        # next iteration (rounded up per iteration, 1 sample per frame drew 1,000 per 512 frames at minibatches of
        # 1,000)
        self._samples_owed += float(cfg.replay.samples_per_frame) * n_frames
        n_updates = int(self._samples_owed // int(cfg.replay.batch_size))
        self._samples_owed -= n_updates * int(cfg.replay.batch_size)
        losses = []
        for _ in range(n_updates):
            batch = self.buffer.sample()
            loss = self.loss_module(batch)
            for optim in self.optims.values():
                optim.zero_grad(set_to_none=True)
            sum(loss[f"loss_{name}"] for name in stepped).backward()  # each optimiser's own loss term
            grad_norm = (torch.nn.utils.clip_grad_norm_(self.loss_module.parameters(), cfg.optim.max_grad_norm)
                         if cfg.optim.max_grad_norm else torch.zeros(()))
            for name in stepped:
                self.optims[name].step()
            self.target_updater.step()
            losses.append(loss.select("loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy",
                                      strict=False).detach().set("grad_norm", grad_norm.detach()))
        self.collector.update_policy_weights_()
        t_update = time.perf_counter() - t0
        if losses:
            loss_means = torch.stack(losses).apply(lambda x: x.float().mean(), batch_size=[])
            metrics.update({f"train/{key}": value for key, value in loss_means.items()})
        metrics.update({"train/buffer_size": len(self.buffer), "time/collect": t_collect, "time/update": t_update,
                        "time/fps": n_frames / max(t_collect + t_update, 1e-9)})
        return n_frames, metrics

    def state_dict(self) -> dict[str, Any]:
        # the replay buffer is not saved (hundreds of MB): a resumed run refills it from its own collection
        return {"loss": self.loss_module.state_dict(),
                "optimizers": {name: optim.state_dict() for name, optim in self.optims.items()}}

    def close(self, interrupted: bool = False) -> None:
        if self.collector is not None:
            self.collector.shutdown()
            self.collector = None

    @staticmethod
    def build_actor(env, config: Mapping[str, Any], obs_stats: Mapping[str, Any]):
        from anm_torchrl.training.models import make_sac_models

        return make_sac_models(env, obs_stats=obs_stats, **model_options(config))[0]
