"""The PPO training loop on any registered network, as a library function: ``recipes/ppo.py`` and the experiments
(:mod:`anm_torchrl.experiments.ppo_runs`) both call :func:`train_ppo` with a composed config of
``recipes/conf/config.yaml`` and a run directory.

Layout follows TorchRL's ``sota-implementations/ppo/ppo_mujoco.py``: Collector -> GAE (recomputed every epoch)
-> TensorDictReplayBuffer(SamplerWithoutReplacement) -> ClipPPOLoss -> Adam. The run directory holds ``logs/``
(TensorBoard or CSV), ``checkpoints/{best,last}.pt`` and ``summary.json``. See recipes/README.md for the tags.

Two disjoint sets of initial states: the **validation** states (``eval.seed``) are evaluated after every
``eval.interval`` updates and choose ``best.pt`` and the early stop; the **test** states (``eval.test_seed``) are
evaluated once at the end, for ``best.pt`` and ``last.pt`` (``test/*`` tags, ``summary.json["test"]``): every
reported figure comes from them.
"""

from __future__ import annotations

import copy
import json
import logging
import shutil
import time
from functools import partial
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)

# keys a resumed run may change without a warning
EXCLUDED_CONFIG_DIFF = ("checkpoint", "logger", "collector.total_frames", "eval.patience")
EVAL_KEYS = ("return", "discounted_return", "e_loss", "penalty", "steps", "terminated")


def make_train_env(surrogate: dict, num_envs: int, max_steps: int | None, seed: int, action_mode: str,
                   init: str | None, device: str, threads: int, network: str | None = None):
    """The training env: ``make_env`` + ``RewardSum`` (episode returns for logging). Also a collector-worker factory."""
    import torch
    from torchrl.envs import RewardSum, TransformedEnv

    from anm_torchrl import make_env

    torch.set_num_threads(int(threads))
    options = {k: v for k, v in surrogate.items() if k != "name"}
    env = make_env(surrogate["name"], num_envs=num_envs, max_steps=max_steps, device=device, seed=seed,
                   action_mode=action_mode, init=init, network=network, **options)
    return env.append_transform(RewardSum()) if isinstance(env, TransformedEnv) else TransformedEnv(env, RewardSum())


def budget_mask(batch_size, remaining: int):
    """Frames of a collected batch ``[..., T]`` that fit in the remaining budget of ``remaining`` frames.

    Returns:
        None when the whole batch fits, else a bool mask of ``batch_size`` keeping the first ``remaining`` frames in
        time order (every env's step t before any env's step t + 1), so ``collector.total_frames`` is exact.
    """
    import torch

    n_steps = int(batch_size[-1])
    n_envs = batch_size.numel() // n_steps
    if n_envs * n_steps <= remaining:
        return None
    rank = torch.arange(n_steps)[None, :] * n_envs + torch.arange(n_envs)[:, None]  # [envs, T], time-major order
    return (rank < remaining).reshape(batch_size)


def train_ppo(cfg: DictConfig, run_dir: str | Path) -> dict:  # noqa: C901 - a training loop, read top to bottom
    """Train PPO as configured by ``cfg`` (the recipe's composed config) into ``run_dir``; returns the summary.

    ``cfg.checkpoint.resume`` is a path (absolute, or relative to the current directory). Every range of ``cfg`` is
    checked first (:func:`~anm_torchrl.training.config_checks.check_ppo_config`).

    Raises:
        ValueError: a config value out of range, or a resume checkpoint of another architecture.
        KeyboardInterrupt: re-raised after a Ctrl-C, once ``last.pt`` and ``summary.json`` (``"interrupted":
            true``) are written.
    """
    from anm_torchrl.training.config_checks import check_ppo_config

    check_ppo_config(cfg)  # before the heavy imports: a bad value fails in a second
    import torch

    torch.set_num_threads(int(cfg.threads))
    from torchrl.collectors import Collector
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
    from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
    from torchrl.objectives import ClipPPOLoss
    from torchrl.objectives.value import GAE
    from torchrl.record.loggers import generate_exp_name, get_logger
    from tqdm import tqdm

    from anm_torchrl.training.checkpoint import check_resume_config, load_checkpoint, save_checkpoint
    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy
    from anm_torchrl.training.factory import make_true_env
    from anm_torchrl.training.ppo_models import make_ppo_models

    t_start = time.perf_counter()
    config = OmegaConf.to_container(cfg, resolve=True)
    device = torch.device(cfg.env.device)
    run_dir = Path(run_dir).resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    ckpt_dir = run_dir / "checkpoints"

    # ---- resume -------------------------------------------------------------------------------------------
    resume = None
    if cfg.checkpoint.resume:
        resume_path = Path(str(cfg.checkpoint.resume)).expanduser().resolve()
        resume = load_checkpoint(resume_path, map_location=device)
        changed = [k for k in check_resume_config(resume["config"], config, source=str(resume_path))
                   if not any(k == e or k.startswith(e + ".") for e in EXCLUDED_CONFIG_DIFF)]
        if changed:
            log.warning("resuming with a config that differs from the checkpoint's in: %s", ", ".join(changed))
        log.info("resuming from %s at %d frames, update %d", resume_path, resume["frames"], resume["update"])
        if (resume_path.parent / "best.pt").is_file() and resume_path.parent != ckpt_dir:
            ckpt_dir.mkdir(parents=True, exist_ok=True)  # the best policy so far stays next to the new last.pt
            shutil.copy2(resume_path.parent / "best.pt", ckpt_dir / "best.pt")
    frames = int(resume["frames"]) if resume else 0
    update = int(resume["update"]) if resume else 0
    seed = int(cfg.seed) + update  # a resumed run does not replay the first run's random streams
    torch.manual_seed(seed)

    # ---- envs and models ------------------------------------------------------------------------------------
    num_workers = int(cfg.collector.num_workers)
    env_kwargs = dict(surrogate=OmegaConf.to_container(cfg.surrogate, resolve=True),
                      num_envs=int(cfg.env.num_envs) // num_workers, max_steps=cfg.env.max_steps,
                      action_mode=cfg.env.action_mode, init=cfg.env.init, device=str(device),
                      threads=int(cfg.threads), network=cfg.network)
    train_env = make_train_env(seed=seed, **env_kwargs)
    actor, critic, normalizer = make_ppo_models(
        train_env, actor_cells=cfg.model.actor_cells, critic_cells=cfg.model.critic_cells,
        activation=cfg.model.activation, max_obs_scale=cfg.model.max_obs_scale, obs_clip=cfg.model.obs_clip,
        init_log_std=cfg.model.init_log_std, obs_stats=resume["obs_norm"] if resume else None,
        init_action=cfg.model.init_action, init_action_clip=cfg.model.init_action_clip)
    actor, critic = actor.to(device), critic.to(device)
    if resume:
        actor.load_state_dict(resume["actor"])
        critic.load_state_dict(resume["critic"])

    # the network's true simulator, states from its reset distribution: validation states choose best.pt and the
    # early stop; test states are only evaluated at the end
    eval_env = make_true_env(int(cfg.eval.num_episodes), device, seed=int(cfg.eval.seed), network=cfg.network)
    test_env = make_true_env(int(cfg.eval.test_episodes), device, seed=int(cfg.eval.test_seed), network=cfg.network)
    val_states = draw_initial_states(int(cfg.eval.num_episodes), int(cfg.eval.seed), eval_env.sim, eval_env.init)
    test_states = draw_initial_states(int(cfg.eval.test_episodes), int(cfg.eval.test_seed), test_env.sim,
                                      test_env.init)
    reward_scale_info = None
    if cfg.loss.reward_scale == "auto":  # derived once per run from do-nothing on the validation states
        from anm_torchrl.training.reward_scale import do_nothing_reward_scale

        reward_scale_info = do_nothing_reward_scale(eval_env, val_states, int(cfg.eval.max_steps),
                                                    float(cfg.loss.auto_step_reward))
        log.info("loss.reward_scale=auto: %.4g (do-nothing mean step reward %.4g on the validation states)",
                 reward_scale_info["reward_scale"], reward_scale_info["do_nothing_step_reward"])

    # ---- collector ------------------------------------------------------------------------------------------
    total_frames = int(cfg.collector.total_frames)
    frames_per_batch = int(cfg.collector.frames_per_batch)
    remaining = max(total_frames - frames, 0)
    # whole batches; the last one is cut to the budget by budget_mask (the env steps beyond it are discarded)
    collected = -(-remaining // frames_per_batch) * frames_per_batch
    collector_kwargs = dict(policy=actor, frames_per_batch=frames_per_batch, total_frames=collected,
                            device=device, auto_register_policy_transforms=False)
    # traj_format only matters with trajs_per_batch (not used): batches are [envs, steps] (or [workers, envs, steps])
    if remaining == 0:  # resumed from a finished run: nothing to collect
        collector = None
        log.warning("checkpoint already has %d >= collector.total_frames=%d frames; nothing to train", frames,
                    total_frames)
    elif num_workers == 1:
        collector = Collector(train_env, **collector_kwargs)
    else:
        train_env.close()
        factories = [partial(make_train_env, seed=seed + 1000 * i, **env_kwargs) for i in range(num_workers)]
        collector = Collector(factories, num_collectors=num_workers, sync=bool(cfg.collector.sync),
                              **collector_kwargs)

    # ---- loss, advantage, optimiser, buffer ------------------------------------------------------------------
    adv_module = GAE(gamma=cfg.loss.gamma, lmbda=cfg.loss.gae_lambda, value_network=critic, average_gae=False,
                     device=device)
    loss_module = ClipPPOLoss(actor_network=actor, critic_network=critic, clip_epsilon=cfg.loss.clip_epsilon,
                              loss_critic_type=cfg.loss.loss_critic_type, entropy_coeff=cfg.loss.entropy_coeff,
                              critic_coeff=cfg.loss.critic_coeff, normalize_advantage=cfg.loss.normalize_advantage)
    optim = torch.optim.Adam(loss_module.parameters(), lr=cfg.optim.lr, eps=cfg.optim.eps,
                             weight_decay=cfg.optim.weight_decay)
    if resume:
        optim.load_state_dict(resume["optimizer"])
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(frames_per_batch, device=device),
                                    sampler=SamplerWithoutReplacement(), batch_size=int(cfg.loss.mini_batch_size))

    # ---- logger -------------------------------------------------------------------------------------------
    logger = None
    if cfg.logger.backend:
        exp_name = generate_exp_name("PPO", f"{cfg.logger.exp_name}_{cfg.surrogate.name}")
        logger = get_logger(cfg.logger.backend, logger_name=str(run_dir / "logs"), experiment_name=exp_name)
        logger.experiment.add_text("config", "```yaml\n" + OmegaConf.to_yaml(cfg, resolve=True) + "```", frames)

    def log_metrics(metrics: dict, step: int) -> None:
        if logger is not None:
            for name, value in metrics.items():
                logger.log_scalar(name, float(value), step=step)

    # ---- evaluation and checkpoints ----------------------------------------------------------------------------
    best = resume.get("best_eval") if resume else None
    evals_since_best = int(resume.get("evals_since_best", 0)) if resume else 0
    n_evals = 0
    last_eval = None
    wall_before = float(resume.get("wall_time", 0.0)) if resume else 0.0

    def checkpoint_payload() -> dict:
        return {"config": config, "actor": actor.state_dict(), "critic": critic.state_dict(),
                "optimizer": optim.state_dict(), "obs_norm": normalizer.stats(), "frames": frames,
                "update": update, "logger_step": frames, "best_eval": best, "evals_since_best": evals_since_best,
                "wall_time": wall_before + time.perf_counter() - t_start}

    test_max_steps = int(cfg.eval.max_steps if cfg.eval.test_max_steps is None else cfg.eval.test_max_steps)

    def run_eval(policy, states, env, trained: tuple[int, int] | None = None, steps: int = int(cfg.eval.max_steps)
                 ) -> dict:
        """Metrics of ``policy`` on ``states`` over ``steps`` steps, tagged with the (frames, update) it was trained
        for."""
        policy.eval()
        result = evaluate_policy(policy, states, max_steps=steps, gamma=float(cfg.eval.gamma), env=env)
        policy.train()
        at_frames, at_update = trained if trained is not None else (frames, update)
        return {**result.metrics(), "frames": at_frames, "update": at_update, "seconds": result.wall_time}

    # ---- training loop ----------------------------------------------------------------------------------------
    lr0 = float(cfg.optim.lr)
    reward_scale = float(cfg.loss.reward_scale if reward_scale_info is None else reward_scale_info["reward_scale"])
    eval_interval, patience = cfg.eval.interval, cfg.eval.patience
    render_interval = int(cfg.eval.render_interval)
    max_minutes = cfg.collector.max_minutes
    stopped_early = out_of_time = interrupted = False
    pbar = tqdm(total=total_frames, initial=frames, unit="frames", dynamic_ncols=True,
                disable=not cfg.logger.progress)
    t_collect0 = time.perf_counter()
    try:
        for data in collector if collector is not None else []:
            t_collect = time.perf_counter() - t_collect0
            # data: [num_envs, T] (one process) or [workers, envs per worker, T] (multi-process); time is last
            keep = budget_mask(data.batch_size, total_frames - frames)  # None except for a cut last batch
            kept = data if keep is None else data[keep]
            n_frames = kept.numel()

            train_metrics = {"train/reward": kept["next", "reward"].mean(), "train/action_scale": kept["scale"].mean()}
            done = kept["next", "done"]
            if done.any():
                train_metrics["train/episode_return"] = kept["next", "episode_reward"][done].mean()
            if reward_scale != 1.0:
                data.set(("next", "reward"), data.get(("next", "reward")) * reward_scale)

            # PPO update: GAE recomputed before every epoch (on the whole batch: its bootstrap needs every step),
            # minibatches without replacement over the kept frames
            t0 = time.perf_counter()
            if cfg.optim.anneal_lr:
                for group in optim.param_groups:
                    group["lr"] = lr0 * max(1.0 - frames / total_frames, 0.0)
            losses = []
            for _ in range(int(cfg.loss.ppo_epochs)):
                with torch.no_grad():
                    data = adv_module(data)
                buffer.empty()
                buffer.extend(data.reshape(-1) if keep is None else data[keep])
                for batch in buffer:
                    loss = loss_module(batch.to(device))
                    total = loss["loss_objective"] + loss["loss_critic"] + loss["loss_entropy"]
                    optim.zero_grad(set_to_none=True)
                    total.backward()
                    grad_norm = (torch.nn.utils.clip_grad_norm_(loss_module.parameters(), cfg.optim.max_grad_norm)
                                 if cfg.optim.max_grad_norm else torch.zeros(()))
                    optim.step()
                    losses.append(loss.select("loss_objective", "loss_critic", "loss_entropy", "entropy",
                                              "clip_fraction", "kl_approx", strict=False).detach()
                                  .set("grad_norm", grad_norm.detach()))
            collector.update_policy_weights_()
            t_update = time.perf_counter() - t0
            frames += n_frames  # counted once the update is done: an interrupted update is not a trained batch
            update += 1
            pbar.update(n_frames)
            loss_means = torch.stack(losses).apply(lambda x: x.float().mean(), batch_size=[])
            for key, value in loss_means.items():
                train_metrics[f"train/{key}"] = value
            train_metrics["train/lr"] = optim.param_groups[0]["lr"]
            train_metrics.update({"time/collect": t_collect, "time/update": t_update,
                                  "time/fps": n_frames / max(t_collect + t_update, 1e-9)})

            # evaluation on the true simulator, deterministic policy, fixed validation states
            is_last = frames >= total_frames
            eval_metrics = {}
            if eval_interval is not None and (update % int(eval_interval) == 0 or is_last):
                last_eval = run_eval(actor, val_states, eval_env)
                n_evals += 1
                eval_metrics = {f"eval/{k}": last_eval[k] for k in EVAL_KEYS}
                eval_metrics["time/eval"] = last_eval["seconds"]
                if best is None or last_eval["discounted_return"] > best["discounted_return"]:
                    best, evals_since_best = dict(last_eval), 0
                    save_checkpoint(ckpt_dir / "best.pt", checkpoint_payload())
                else:
                    evals_since_best += 1
                if render_interval and n_evals % render_interval == 0:
                    log_episode_figure(logger, actor, val_states[:1], cfg, frames)
                pbar.set_postfix(eval=f"{last_eval['discounted_return']:.1f}", best=f"{best['discounted_return']:.1f}")
                log.info("update %d, %d frames, %.0f s: eval/discounted_return %.2f (best %.2f), return %.1f, "
                         "penalty %.1f, terminated %.2f", update, frames, time.perf_counter() - t_start,
                         last_eval["discounted_return"], best["discounted_return"], last_eval["return"],
                         last_eval["penalty"], last_eval["terminated"])
            train_metrics["time/total_fps"] = frames / (wall_before + time.perf_counter() - t_start)
            if update % int(cfg.logger.interval) == 0 or eval_metrics:
                log_metrics({**train_metrics, **eval_metrics}, step=frames)

            stopped_early = patience is not None and evals_since_best >= int(patience)
            out_of_time = max_minutes is not None and time.perf_counter() - t_start >= 60 * float(max_minutes)
            if update % int(cfg.checkpoint.interval) == 0 or is_last or stopped_early or out_of_time:
                save_checkpoint(ckpt_dir / "last.pt", checkpoint_payload())
            if stopped_early:
                log.info("early stop: %d evaluations without improvement of eval/discounted_return",
                         evals_since_best)
                break
            if out_of_time:
                log.info("stop: collector.max_minutes=%s of wall time used", max_minutes)
                break
            if is_last:
                break
            t_collect0 = time.perf_counter()
    except KeyboardInterrupt:
        interrupted = True
        log.warning("interrupted (Ctrl-C) after %d frames: writing last.pt and summary.json", frames)

    pbar.close()
    if collector is not None:
        try:
            collector.shutdown()
        except Exception as err:  # noqa: BLE001 - after Ctrl-C, worker processes got the SIGINT too
            if not interrupted:
                raise
            log.warning("collector shutdown after Ctrl-C: %s", err)
    save_checkpoint(ckpt_dir / "last.pt", checkpoint_payload())

    # ---- test states: best.pt and last.pt, once -----------------------------------------------------------------
    test = {"seed": int(cfg.eval.test_seed), "num_episodes": int(cfg.eval.test_episodes),
            "max_steps": test_max_steps, "gamma": float(cfg.eval.gamma)}
    try:
        policies = {}
        if (ckpt_dir / "best.pt").is_file():
            best_ckpt = load_checkpoint(ckpt_dir / "best.pt", map_location=device)
            policies["best"] = (copy.deepcopy(actor), (best_ckpt["frames"], best_ckpt["update"]))
            policies["best"][0].load_state_dict(best_ckpt["actor"])
        policies["last"] = (actor, (frames, update))
        for name, (policy, trained) in policies.items():
            test[name] = run_eval(policy, test_states, test_env, trained=trained, steps=test_max_steps)
            log_metrics({f"test/{name}/{k}": test[name][k] for k in EVAL_KEYS}, step=frames)
    except KeyboardInterrupt:
        interrupted = True
        log.warning("test evaluation interrupted (Ctrl-C): summary.json has no test figures")

    summary = {"best_eval": best, "final_eval": last_eval, "frames": frames, "updates": update,
               "stopped_early": stopped_early, "out_of_time": out_of_time, "interrupted": interrupted,
               "wall_time": wall_before + time.perf_counter() - t_start, "run_dir": str(run_dir),
               "validation": {"seed": int(cfg.eval.seed), "num_episodes": int(cfg.eval.num_episodes),
                              "max_steps": int(cfg.eval.max_steps), "gamma": float(cfg.eval.gamma)},
               "test": test, "reward_scale": reward_scale_info or {"reward_scale": reward_scale},
               "checkpoints": {name: str(ckpt_dir / f"{name}.pt") if (ckpt_dir / f"{name}.pt").is_file() else None
                               for name in ("best", "last")},
               "config": config}
    from anm_torchrl.artifacts import atomic_write

    atomic_write(run_dir / "summary.json", json.dumps(summary, indent=2, default=float).encode())
    if logger is not None and hasattr(logger.experiment, "flush"):
        logger.experiment.flush()
    log.info("done: %d frames, best eval/discounted_return %s, test/best/discounted_return %s", frames,
             None if best is None else f"{best['discounted_return']:.2f}",
             f"{test['best']['discounted_return']:.2f}" if "best" in test else None)
    if interrupted:
        raise KeyboardInterrupt
    return summary


def log_episode_figure(logger, actor, state, cfg: DictConfig, step: int) -> None:
    """Log the episode figure (:func:`anm_torchrl.render.episode_figure`) of ``actor`` from one validation state
    (1, D) on the true simulator, ``eval.max_steps`` steps, to TensorBoard as ``eval/episode`` at ``step`` frames."""
    import torch
    from tensordict import TensorDict
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from anm_torchrl.render import episode_figure, episode_from_rollout, network_tables
    from anm_torchrl.training.factory import make_true_env

    env = make_true_env(1, state.device, seed=int(cfg.eval.seed), network=cfg.network)
    td = env.reset(TensorDict({"state": state.to(torch.float64)}, [1], device=env.device), set_state=True)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        roll = env.rollout(int(cfg.eval.max_steps), actor, tensordict=td, auto_reset=False, break_when_any_done=True)
    fig = episode_figure(episode_from_rollout(roll, env.sim.net.base_mva), network_tables(env.sim.net),
                         title=f"validation state 0 after {step} frames")
    logger.experiment.add_figure("eval/episode", fig, global_step=step, close=True)
