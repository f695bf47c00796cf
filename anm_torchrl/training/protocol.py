"""The training protocol every algorithm shares: one function, :func:`train`, read top to bottom.

An algorithm (``anm_torchrl/training/algorithms/``, chosen by the config's ``algorithm`` key) provides models, loss
and update behind :class:`~anm_torchrl.training.algorithms.base.Algorithm`; everything else lives here, once:

* the run directory (``logs/`` TensorBoard or CSV, ``checkpoints/{best,last}.pt``, ``summary.json``);
* resume from a checkpoint (``checkpoint.resume``), refusing another algorithm or architecture;
* the budget: ``collector.total_frames`` frames of the training env (exact), optionally a wall-clock cap
  (``collector.max_minutes``, opt-in: a result that depends on machine load is not reproducible);
* two disjoint sets of initial states of the network's **true** simulator: the **validation** states
  (``eval.seed``) are evaluated every ``eval.interval`` iterations and choose ``best.pt`` and the early stop
  (``eval.patience``); the **test** states (``eval.test_seed``) are evaluated once at the end, for ``best.pt`` and
  ``last.pt`` (``test/*`` tags, ``summary.json["test"]``): every reported figure comes from them;
* Ctrl-C: ``last.pt`` and ``summary.json`` (``"interrupted": true``) are written, then ``KeyboardInterrupt``;
  under :func:`run_recipe` SIGTERM too, and the first of either lets the current iteration finish
  (:mod:`anm_torchrl.training.signals`).
"""

from __future__ import annotations

import copy
import logging
import shutil
import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from anm_torchrl.strict_json import json_text
from anm_torchrl.training.config_checks import TRUE_SIMULATORS
from anm_torchrl.training.signals import graceful, stop_requested, stop_signals

log = logging.getLogger(__name__)

# keys a resumed run may change without a warning
EXCLUDED_CONFIG_DIFF = ("checkpoint", "logger", "collector.total_frames", "collector.max_minutes", "eval.patience")
EVAL_KEYS = ("return", "discounted_return", "e_loss", "penalty", "steps", "terminated")


def reward_scale_of(cfg: DictConfig, eval_env, val_states) -> dict:
    """``{"reward_scale": s, ...}``: ``loss.reward_scale`` as given, or derived once per run from do-nothing on the
    validation states (``auto``, :mod:`anm_torchrl.training.reward_scale`)."""
    if cfg.loss.reward_scale != "auto":
        return {"reward_scale": float(cfg.loss.reward_scale)}
    from anm_torchrl.training.reward_scale import do_nothing_reward_scale

    info = do_nothing_reward_scale(eval_env, val_states, int(cfg.eval.max_steps), float(cfg.loss.auto_step_reward))
    log.info("loss.reward_scale=auto: %.4g (do-nothing mean step reward %.4g on the validation states)",
             info["reward_scale"], info["do_nothing_step_reward"])
    return info


def read_resume(cfg: DictConfig, algorithm: str, device="cpu") -> tuple[Path, dict, list[str]]:
    """The checkpoint of ``checkpoint.resume``, checked against the run's config: ``(path, checkpoint, the dotted
    keys that differ)`` (those the protocol does not compare left out).

    Raises:
        ValueError: another algorithm's checkpoint, another architecture (naming both values), or an unreadable
            file (:func:`~anm_torchrl.training.checkpoint.load_checkpoint`).
    """
    from anm_torchrl.training.checkpoint import check_resume_config, load_checkpoint

    path = Path(str(cfg.checkpoint.resume)).expanduser().resolve()
    resume = load_checkpoint(path, map_location=device)
    if resume["algorithm"] != algorithm:
        raise ValueError(f"cannot resume from {path}: it was trained by {resume['algorithm']!r}, this run is "
                         f"{algorithm!r}")
    # a checkpoint with its network's key is matched by it (check_network, where the run builds its network)
    changed = [k for k in check_resume_config(resume["config"], OmegaConf.to_container(cfg, resolve=True),
                                              source=str(path), network_by_key=resume.get("network_key") is not None)
               if not any(k == e or k.startswith(e + ".") for e in EXCLUDED_CONFIG_DIFF)]
    return path, resume, changed


def _with_newest_best(resume: dict, best_path: Path, resume_path: Path) -> dict:
    """``resume`` with the best validation result of ``best_path`` (the run's best.pt) where that one is better
    than the checkpoint's own (best.pt is written at every new best, last.pt every ``checkpoint.interval`` updates: a
    crash between the two leaves last.pt's best stale), its early-stop count then the passes last.pt recorded after
    it. A resumed run keeps the better policy instead of overwriting it with the first that beats the stale one.

    Raises:
        ValueError: best_path exists but is not a checkpoint of this run's kind (:func:`load_checkpoint`)."""
    from anm_torchrl.training.checkpoint import load_checkpoint

    if not best_path.is_file() or best_path.resolve() == resume_path.resolve():
        return resume
    on_disk = load_checkpoint(best_path).get("best_eval")
    own = resume.get("best_eval")
    if on_disk is None or (own is not None and own["discounted_return"] >= on_disk["discounted_return"]):
        return resume
    if on_disk["update"] in {tag["update"] for tag in resume.get("pending", [])}:
        return resume  # the pass the resumed run validates first: it records that best again, counting no miss
    log.warning("%s holds a better validation result (%.4g at update %d) than %s (%s): kept as the best so far",
                best_path, on_disk["discounted_return"], on_disk["update"], resume_path,
                "none" if own is None else f"{own['discounted_return']:.4g}")
    after = sum(1 for point in resume.get("curve", []) if point["update"] > on_disk["update"])
    return {**resume, "best_eval": on_disk, "evals_since_best": after}


def train(cfg: DictConfig, run_dir: str | Path,  # noqa: C901 - a training loop, read top to bottom
          network_defaults: dict | None = None) -> dict:
    """Train ``cfg.algorithm`` as configured by ``cfg`` (a recipe's composed config) into ``run_dir``; returns the
    summary (also written to ``run_dir/summary.json``).

    ``cfg`` is used as given: a recipe first applies the network's entry of ``cfg.per_network``
    (:func:`~anm_torchrl.training.network_defaults.apply_network_defaults`) and passes what it applied as
    ``network_defaults`` (written to the summary); a programmatic caller does the same or sets the keys itself.

    ``cfg.checkpoint.resume`` is a path (absolute, or relative to the current directory). Every range of ``cfg`` is
    checked first. With ``cfg.warm_start.algorithm`` (PPO) and neither ``checkpoint.resume`` nor
    ``checkpoint.init_from``, that algorithm is trained first into ``run_dir/warm_start``
    (:func:`~anm_torchrl.training.warm_start.teacher_config`) and the run starts from its ``best.pt``; the summary
    records it and the run's wall time counts it.

    Raises:
        ValueError: a config value out of range, or a resume checkpoint of another algorithm or architecture.
        KeyboardInterrupt: re-raised after a Ctrl-C, once ``last.pt`` and ``summary.json`` (``"interrupted":
            true``) are written.
    """
    from anm_torchrl.training.algorithms import check_algorithm_config, get_algorithm

    check_algorithm_config(cfg)  # before the heavy imports: a bad value fails in a second
    import torch

    algorithm_cls = get_algorithm(str(cfg.algorithm))

    torch.set_num_threads(int(cfg.threads))
    from torchrl.record.loggers import generate_exp_name, get_logger
    from tqdm import tqdm

    from anm_torchrl.grid.identity import network_key, profiles_key
    from anm_torchrl.training.checkpoint import check_network, load_checkpoint, save_checkpoint
    from anm_torchrl.evaluation import draw_initial_states
    from anm_torchrl.training.factory import make_true_env
    from anm_torchrl.training.validation import BackgroundValidation, InlineValidation, evaluate, use_background

    warm_start = None
    if (cfg.get("warm_start", {}).get("algorithm") and not cfg.checkpoint.resume
            and not cfg.checkpoint.get("init_from")):
        from anm_torchrl.training.warm_start import teacher_config, teacher_record

        teacher_cfg, teacher_defaults = teacher_config(cfg)
        teacher_dir = Path(run_dir).resolve() / "warm_start"
        log.info("warm start: %s through the %s first, into %s", teacher_cfg.algorithm,
                 "PINN" if teacher_cfg.model.dynamics == "pinn" else "exact simulator", teacher_dir)
        try:
            warm_start = teacher_record(train(teacher_cfg, teacher_dir, network_defaults=teacher_defaults))
        except KeyboardInterrupt:
            log.warning("the warm start was interrupted: continue it with python recipes/shac.py (its config is in %s) "
                        "and checkpoint.resume=%s, then start PPO from its best.pt with checkpoint.init_from",
                        teacher_dir / "summary.json", teacher_dir / "checkpoints" / "last.pt")
            raise

    t_start = time.perf_counter()
    config = OmegaConf.to_container(cfg, resolve=True)
    device = torch.device(cfg.env.device)
    run_dir = Path(run_dir).resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    ckpt_dir = run_dir / "checkpoints"
    log.info("%s run directory: %s", algorithm_cls.name, run_dir)

    # ---- resume -------------------------------------------------------------------------------------------
    resume = None
    if cfg.checkpoint.resume:
        resume_path, resume, changed = read_resume(cfg, algorithm_cls.name, device)
        if changed:
            log.warning("resuming with a config that differs from the checkpoint's in: %s", ", ".join(changed))
        log.info("resuming from %s at %d frames, update %d", resume_path, resume["frames"], resume["update"])
        if (resume_path.parent / "best.pt").is_file() and resume_path.parent != ckpt_dir:
            ckpt_dir.mkdir(parents=True, exist_ok=True)  # the best policy so far stays next to the new last.pt
            shutil.copy2(resume_path.parent / "best.pt", ckpt_dir / "best.pt")
        resume = _with_newest_best(resume, ckpt_dir / "best.pt", resume_path)
    if resume:  # a resumed warm-started run keeps its warm start's record (its time is in the checkpoint's)
        warm_start = resume.get("warm_start")
    frames = int(resume["frames"]) if resume else 0
    update = int(resume["update"]) if resume else 0
    seed = int(cfg.seed) + update  # a resumed run does not replay the first run's random streams
    torch.manual_seed(seed)
    total_frames = int(cfg.collector.total_frames)
    forecast_steps = int(cfg.model.get("forecast_steps", 0) or 0)
    if forecast_steps:
        log.warning("model.forecast_steps=%d: the policy reads the next %d steps of the network's loads and potentials "
                    "from its profiles, a perfect forecast a controller in the field does not have (as MPC-perfect)",
                    forecast_steps, forecast_steps)

    # ---- evaluation states: the network's true simulator, from its reset distribution -----------------------------
    eval_env = make_true_env(int(cfg.eval.num_episodes), device, seed=int(cfg.eval.seed), network=cfg.network)
    test_env = make_true_env(int(cfg.eval.test_episodes), device, seed=int(cfg.eval.test_seed), network=cfg.network)
    val_states = draw_initial_states(int(cfg.eval.num_episodes), int(cfg.eval.seed), eval_env.sim, eval_env.init)
    test_states = draw_initial_states(int(cfg.eval.test_episodes), int(cfg.eval.test_seed), test_env.sim,
                                      test_env.init)
    reward_scale = reward_scale_of(cfg, eval_env, val_states)
    trained_network, trained_profiles = network_key(eval_env.sim), profiles_key(eval_env.sim)
    if resume:
        check_network(resume, eval_env.sim, str(resume_path))

    init = None
    # the caller's config is not changed: it still reads as composed (a study compares it with its cell's)
    init_path = cfg.checkpoint.get("init_from") or (warm_start or {}).get("checkpoint")
    if init_path and not resume:
        from anm_torchrl.training.warm_start import read_init

        init = read_init(init_path, algorithm_cls, config, device)
        check_network(init, eval_env.sim, str(init_path))

    # ---- the algorithm: its envs, models, loss, optimisers ---------------------------------------------------------
    algo = algorithm_cls(cfg, device=device, seed=seed, budget=max(total_frames - frames, 0),
                         reward_scale=reward_scale["reward_scale"], resume=resume)
    if init is not None:
        algo.start_from(init)
    actor = algo.actor

    # ---- logger -------------------------------------------------------------------------------------------
    logger = None
    if cfg.logger.backend:
        exp_name = generate_exp_name(algorithm_cls.name.upper(), f"{cfg.logger.exp_name}_{cfg.surrogate.name}")
        logger = get_logger(cfg.logger.backend, logger_name=str(run_dir / "logs"), experiment_name=exp_name,
                            **OmegaConf.to_container(cfg.logger.kwargs, resolve=True))
        if hasattr(logger.experiment, "add_text"):
            logger.experiment.add_text("config", "```yaml\n" + OmegaConf.to_yaml(cfg, resolve=True) + "```", frames)

    def log_metrics(metrics: dict, step: int) -> None:
        if logger is not None:
            for name, value in metrics.items():
                logger.log_scalar(name, float(value), step=step)

    # ---- evaluation and checkpoints ----------------------------------------------------------------------------
    best = resume.get("best_eval") if resume else None
    evals_since_best = int(resume.get("evals_since_best", 0)) if resume else 0
    n_evals = 0
    last_eval = resume.get("last_eval") if resume else None
    # a resumed run's time so far (its warm start's included), or its warm start's
    wall_before = float(resume.get("wall_time", 0.0)) if resume else float((warm_start or {}).get("wall_time", 0.0))
    # learning curve (summary.json "curve"): validation and, with eval.track_test, test returns per validation point
    curve: list[dict] = list(resume.get("curve", [])) if resume else []
    track_s = float(resume.get("track_seconds", 0.0)) if resume else 0.0
    # the budget counts training-env frames; an algorithm that trains on a model (SHAC) counts model transitions
    # instead (budget_unit) and reports the true-env frames it used for training (env_frames) as "frames"
    unit = getattr(algorithm_cls, "budget_unit", "frames")

    # a surrogate's frames are no true-simulator frames (gym_anm is the original simulator itself)
    on_true_env = str(cfg.surrogate.get("name", "none")) in TRUE_SIMULATORS

    def env_frames() -> int:  # summary["frames"]: the training env's frames (SHAC: the true env's it used)
        return frames if unit == "frames" else int(getattr(algo, "env_frames", 0))

    def true_env_frames() -> int:
        return env_frames() if on_true_env or unit != "frames" else 0

    def checkpoint_payload() -> dict:
        return {"algorithm": algorithm_cls.name, "config": config, "actor": actor.state_dict(),
                "obs_norm": algo.normalizer.stats(), "state": algo.state_dict(), "frames": frames, "update": update,
                "logger_step": frames, "best_eval": best, "evals_since_best": evals_since_best, "last_eval": last_eval,
                "wall_time": wall_before + time.perf_counter() - t_start, "curve": curve, "track_seconds": track_s,
                "network_key": trained_network, "profiles_key": trained_profiles,
                "reward_scale": reward_scale["reward_scale"], "warm_start": warm_start}

    test_max_steps = int(cfg.eval.max_steps if cfg.eval.test_max_steps is None else cfg.eval.test_max_steps)

    def run_eval(policy, states, env, trained: tuple[int, int] | None = None, steps: int = int(cfg.eval.max_steps)
                 ) -> dict:
        """Metrics of ``policy`` on ``states`` over ``steps`` steps, tagged with the (frames, update) it was trained
        for."""
        at_frames, at_update = trained if trained is not None else (frames, update)
        return {**evaluate(policy, states, env, steps, float(cfg.eval.gamma)), "frames": at_frames,
                "update": at_update}

    # ---- training loop ----------------------------------------------------------------------------------------
    eval_interval, patience = cfg.eval.interval, cfg.eval.patience
    render_interval = int(cfg.eval.render_interval)
    max_minutes = cfg.collector.max_minutes
    stopped_early = out_of_time = interrupted = False
    if frames >= total_frames:
        log.warning("checkpoint already has %d >= collector.total_frames=%d frames; nothing to train", frames,
                    total_frames)
    pbar = tqdm(total=total_frames, initial=frames, unit="frames", dynamic_ncols=True,
                disable=not cfg.logger.progress)
    # validation passes here, or beside the training in a second process (eval.background): the same results
    background = eval_interval is not None and use_background(cfg.eval.background, device, int(cfg.threads),
                                                               int(cfg.eval.max_steps))
    validation = (BackgroundValidation if background else InlineValidation)(
        actor, val_states, eval_env, int(cfg.eval.max_steps), float(cfg.eval.gamma))
    if background:
        log.info("validation passes run in a second process beside the training (eval.background=%s)",
                 cfg.eval.background)

    def record(snapshot: dict, result: dict) -> None:
        """Take one finished validation pass of the policy as it was at ``snapshot``: best.pt, the early-stop
        count, the curve, the logs."""
        nonlocal best, evals_since_best, last_eval
        last_eval = {**result, "frames": snapshot["frames"], "update": snapshot["update"]}
        # when the pass's result existed: the policy's moment plus the pass's own time, in either mode (a background
        # pass is read one iteration later; the moment of reading would put its point one iteration late)
        point = {"frames": snapshot["frames"], "true_env_frames": snapshot["true_env_frames"],
                 "update": snapshot["update"], "wall_s": snapshot["wall_s"] + float(result["seconds"]),
                 "validation": last_eval["discounted_return"]}
        eval_metrics = {f"eval/{k}": last_eval[k] for k in EVAL_KEYS}
        eval_metrics["time/eval"] = last_eval["seconds"]
        if "tracked" in snapshot:
            point["test"] = snapshot["tracked"]["discounted_return"]
            eval_metrics.update({f"track/{k}": snapshot["tracked"][k] for k in EVAL_KEYS})
            eval_metrics["time/track"] = snapshot["tracked"]["seconds"]
        if best is None or last_eval["discounted_return"] > best["discounted_return"]:
            best, evals_since_best = dict(last_eval), 0
            payload = snapshot["payload"] or checkpoint_payload()
            # its own point in its curve: a run resumed from best.pt continues the curve after it
            save_checkpoint(ckpt_dir / "best.pt", {**payload, "best_eval": best, "evals_since_best": 0,
                                                   "last_eval": last_eval, "curve": [*payload["curve"], point]})
        else:
            evals_since_best += 1
        curve.append(point)
        log_metrics(eval_metrics, step=snapshot["frames"])
        pbar.set_postfix(eval=f"{last_eval['discounted_return']:.4g}", best=f"{best['discounted_return']:.4g}")
        log.info("update %d, %d frames, %.0f s: eval/discounted_return %.4g (best %.4g), return %.4g, "
                 "penalty %.3g, terminated %.2f", snapshot["update"], snapshot["frames"],
                 time.perf_counter() - t_start, last_eval["discounted_return"], best["discounted_return"],
                 last_eval["return"], last_eval["penalty"], last_eval["terminated"])

    def take_snapshot(payload: dict | None) -> dict:
        """The run at a validation point: frames, update, ``payload`` (best.pt's content, or None to take the run's
        when the pass is recorded), with ``eval.track_test`` the test states' figures, and the wall time without
        the tracking's."""
        nonlocal track_s
        snapshot = {"frames": frames, "update": update, "true_env_frames": true_env_frames(), "payload": payload}
        if cfg.eval.track_test:  # a measurement only: nothing the training does reads it
            t_track = time.perf_counter()
            snapshot["tracked"] = run_eval(actor, test_states, test_env, steps=test_max_steps)
            track_s += time.perf_counter() - t_track
        snapshot["wall_s"] = wall_before + time.perf_counter() - t_start - track_s
        return snapshot

    def take_results(wait: bool) -> None:
        for snapshot, result in validation.results(wait=wait):
            record(snapshot, result)

    # passes last.pt held as still running when it was saved (a crash came before their results), run first
    unrecorded: list[dict] = list(resume.get("pending", [])) if resume else []

    def last_payload() -> dict:
        """last.pt's content: the run now, and the validation passes not recorded yet (at most one in the second
        process, and those of the checkpoint resumed from): a run resumed from it runs them first, so no validation
        point is lost to a crash."""
        return {**checkpoint_payload(), "pending": [*unrecorded, *(dict(tag) for tag in validation.pending_tags)]}

    try:
        with graceful():  # a signal here stops the run after its iteration (training.signals)
            while unrecorded:
                policy = copy.deepcopy(actor)
                policy.load_state_dict(unrecorded[0]["payload"]["actor"])
                record(unrecorded[0], evaluate(policy, val_states, eval_env, int(cfg.eval.max_steps),
                                               float(cfg.eval.gamma)))
                unrecorded.pop(0)
            if stop_requested():
                raise KeyboardInterrupt
            if resume and patience is not None and evals_since_best >= int(patience) and frames < total_frames:
                stopped_early = True  # a run resumed after its early stop: no batch more that nothing would validate
                log.warning("checkpoint stopped early (%d evaluations without improvement, eval.patience=%s); "
                            "nothing to train (raise eval.patience to train on)", evals_since_best, patience)
            if init is not None and eval_interval is not None:
                # the networks a warm start begins with compete for best.pt: training must beat them
                record(take_snapshot(None), run_eval(actor, val_states, eval_env))
            while frames < total_frames and not stopped_early:
                n_frames, train_metrics = algo.iterate(total_frames - frames)
                frames += n_frames  # counted once the update is done: an interrupted update is not a trained batch
                update += 1
                pbar.update(n_frames)

                # evaluation on the true simulator, deterministic policy, fixed validation states
                is_last = frames >= total_frames
                evaluated = eval_interval is not None and (update % int(eval_interval) == 0 or is_last)
                decisive = False
                if evaluated:
                    take_results(wait=True)  # one pass queued at a time: the curve lags by one pass at most
                    # best.pt's content if this pass is the best: training goes on while it runs
                    snapshot = take_snapshot(copy.deepcopy(checkpoint_payload()) if background else None)
                    n_evals += 1
                    if render_interval and n_evals % render_interval == 0:
                        log_episode_figure(logger, actor, val_states[:1], cfg, frames)
                    validation.submit(actor.state_dict() if background else None, snapshot)
                    # wait where this pass decides the run: the end, or an early stop (as if evaluated here)
                    decisive = is_last or (patience is not None and evals_since_best + 1 >= int(patience))
                take_results(wait=decisive)
                train_metrics["time/total_fps"] = frames / (wall_before + time.perf_counter() - t_start)
                if update % int(cfg.logger.interval) == 0 or evaluated:
                    log_metrics(train_metrics, step=frames)

                stopped_early = patience is not None and evals_since_best >= int(patience)
                out_of_time = max_minutes is not None and time.perf_counter() - t_start >= 60 * float(max_minutes)
                if out_of_time:
                    take_results(wait=True)
                if update % int(cfg.checkpoint.interval) == 0 or is_last or stopped_early or out_of_time:
                    save_checkpoint(ckpt_dir / "last.pt", last_payload())
                if stop_requested():
                    raise KeyboardInterrupt
                if stopped_early:
                    log.info("early stop: %d evaluations without improvement of eval/discounted_return",
                             evals_since_best)
                    break
                if out_of_time:
                    log.info("stop: collector.max_minutes=%s of wall time used", max_minutes)
                    break
    except KeyboardInterrupt:
        interrupted = True
        log.warning("interrupted (Ctrl-C or SIGTERM) after %d frames: writing last.pt and summary.json", frames)
        try:
            take_results(wait=True)  # the second process ignores the Ctrl-C: its pass finishes
        except (RuntimeError, KeyboardInterrupt) as err:
            log.warning("the validation pass queued at the interruption is not recorded: %s", err)
    finally:
        validation.close()

    pbar.close()
    algo.close(interrupted=interrupted)
    # with the passes an interruption left unrecorded (a second Ctrl-C while waiting for one), as last.pt held them
    save_checkpoint(ckpt_dir / "last.pt", last_payload())

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

    # what a user gets, against no controller at all on the same validation states: a run that never beat doing
    # nothing says so (its best.pt would be worse than leaving the grid alone). Not after a Ctrl-C: the user wants out
    from anm_torchrl.baselines import make_baseline

    do_nothing = None
    if not interrupted:
        try:
            do_nothing = evaluate(make_baseline("do_nothing", sim=eval_env.sim), val_states, eval_env,
                                  int(cfg.eval.max_steps), float(cfg.eval.gamma))["discounted_return"]
        except KeyboardInterrupt:
            interrupted = True
            log.warning("do-nothing's validation pass interrupted (Ctrl-C): summary.json has no do-nothing figure")
    if best is not None and do_nothing is not None and best["discounted_return"] < do_nothing:
        log.warning("best.pt is worse than doing nothing on the validation states (eval/discounted_return %.4g "
                    "against do-nothing's %.4g): this policy should not control a grid", best["discounted_return"],
                    do_nothing)
    unit_keys = {} if unit == "frames" else {"budget_unit": unit, unit: frames}
    summary = {"algorithm": algorithm_cls.name, "best_eval": best, "final_eval": last_eval,
               "frames": env_frames(), "true_env_frames": true_env_frames(), **unit_keys,
               "updates": update, "stopped_early": stopped_early, "out_of_time": out_of_time,
               "interrupted": interrupted, "wall_time": wall_before + time.perf_counter() - t_start,
               "run_dir": str(run_dir),
               "validation": {"seed": int(cfg.eval.seed), "num_episodes": int(cfg.eval.num_episodes),
                              "max_steps": int(cfg.eval.max_steps), "gamma": float(cfg.eval.gamma),
                              "do_nothing_discounted_return": do_nothing},
               "test": test, "curve": curve, "track_seconds": track_s, "reward_scale": reward_scale,
               "network_defaults": network_defaults,
               "warm_start": warm_start,
               "init_from": None if init is None else {"path": str(init_path),
                                                       "algorithm": init["algorithm"], "frames": int(init["frames"])},
               "checkpoints": {name: str(ckpt_dir / f"{name}.pt") if (ckpt_dir / f"{name}.pt").is_file() else None
                               for name in ("best", "last")},
               "config": config}
    from anm_torchrl.artifacts import atomic_write

    atomic_write(run_dir / "summary.json", json_text(summary, indent=2).encode())
    if logger is not None and hasattr(logger.experiment, "flush"):
        logger.experiment.flush()
    log.info("done: %d frames in %.0f s, best eval/discounted_return %s (do-nothing on the same validation states: "
             "%s), test/best/discounted_return %s", frames, summary["wall_time"],
             None if best is None else f"{best['discounted_return']:.4g}",
             None if do_nothing is None else f"{do_nothing:.4g}",
             f"{test['best']['discounted_return']:.4g}" if "best" in test else None)
    if interrupted:
        raise KeyboardInterrupt
    return summary


def log_episode_figure(logger, actor, state, cfg: DictConfig, step: int) -> None:
    """Log the episode figure (:func:`anm_torchrl.render.episode_figure`) of ``actor`` from one validation state
    (1, D) on the true simulator, ``eval.max_steps`` steps, to TensorBoard as ``eval/episode`` at ``step`` frames."""
    import torch
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from anm_torchrl.evaluation import reset_to
    from anm_torchrl.render import episode_figure, episode_from_rollout, network_tables
    from anm_torchrl.training.factory import make_true_env

    env = make_true_env(1, state.device, seed=int(cfg.eval.seed), network=cfg.network)
    td = reset_to(env, state)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        roll = env.rollout(int(cfg.eval.max_steps), actor, tensordict=td, auto_reset=False, break_when_any_done=True)
    fig = episode_figure(episode_from_rollout(roll, env.sim.net.base_mva), network_tables(env.sim.net),
                         title=f"validation state 0 after {step} frames")
    logger.experiment.add_figure("eval/episode", fig, global_step=step, close=True)


def run_recipe(cfg: DictConfig) -> dict:
    """The body of a training recipe under ``hydra.main`` (``recipes/ppo.py``, ``recipes/sac.py``): train into the
    Hydra run directory (the working directory, ``hydra.job.chdir``), printing it when the run starts and when it
    ends (finished, failed or interrupted). Ctrl-C exits with status 130 after ``summary.json`` is written with
    ``"interrupted": true``; SIGTERM (a scheduler's preemption) likewise, with status 143; the first of either in
    the training loop lets its iteration finish (:func:`~anm_torchrl.training.signals.stop_signals`).

    A config error (a value out of range, an unknown algorithm or network) exits with one line naming the key,
    before anything heavy is imported, and removes the run directory Hydra made for it (it holds only Hydra's own
    files then).
    """
    import hydra
    from hydra.core.hydra_config import HydraConfig

    from anm_torchrl.networks import check_network_name
    from anm_torchrl.networks.user import network_argument
    from anm_torchrl.training.algorithms import check_algorithm_config
    from anm_torchrl.training.config_checks import check_model_group
    from anm_torchrl.training.recipe_errors import (check_artifact_cache, check_device, defined_keys,
                                                    refuse_appended_keys, user_errors)
    from anm_torchrl.training.network_defaults import apply_network_defaults, explicit_keys, log_network_defaults

    run_dir = Path.cwd()
    with user_errors(f"{HydraConfig.get().job.name}.py", run_dir):
        # the surrogate group's keys go to its loader, which names one it does not take
        refuse_appended_keys(f"{HydraConfig.get().job.name}.py", HydraConfig.get().overrides.task,
                             allowed=("surrogate",), defined=defined_keys())
        # a network file's path is relative to where the command was typed, not to the run directory
        cfg.network = network_argument(cfg.network, hydra.utils.get_original_cwd())
        check_network_name(cfg.network)  # before its defaults are applied (and logged)
        hydra_cfg = HydraConfig.get()
        conf_dir = next((src.path for src in hydra_cfg.runtime.config_sources
                         if src.provider == "main" and src.schema == "file"), None)
        check_model_group(cfg)  # another recipe's model group lacks the keys the per-network conditions read
        # logged once the config has passed its checks: a wrong value is then the only line printed
        defaults = apply_network_defaults(cfg, explicit_keys(hydra_cfg.overrides.task, conf_dir), log_now=False)
        warm = cfg.get("warm_start", {}).get("algorithm")
        check_algorithm_config(cfg)
        check_device(cfg.env.device)
        check_artifact_cache(cfg.surrogate)  # a surrogate trained on first use is saved under ANM_TORCHRL_HOME
        if cfg.checkpoint.resume and cfg.checkpoint.get("init_from"):
            raise ValueError("checkpoint.resume and checkpoint.init_from: give one (resume continues a run, init_from "
                             "starts a new one from another run's networks)")
        if warm and cfg.checkpoint.get("init_from"):
            raise ValueError(f"warm_start.algorithm={warm} and checkpoint.init_from: give one (both choose the "
                             "networks the run starts from)")
        for key in ("resume", "init_from"):  # relative to where the command was typed, not to the run directory
            if cfg.checkpoint.get(key):
                cfg.checkpoint[key] = hydra.utils.to_absolute_path(str(cfg.checkpoint[key]))
                if not Path(cfg.checkpoint[key]).is_file():
                    raise FileNotFoundError(f"checkpoint.{key}: no file {cfg.checkpoint[key]}")
        for key in ("path", "classifier_path"):  # a trained surrogate's file or folder: likewise
            if cfg.surrogate.get(key):
                cfg.surrogate[key] = hydra.utils.to_absolute_path(str(cfg.surrogate[key]))
                if not Path(cfg.surrogate[key]).exists():
                    raise FileNotFoundError(f"surrogate.{key}: nothing at {cfg.surrogate[key]}")
        # last: it builds the network's simulator (torch), after every check that needs nothing heavy; before a
        # surrogate is trained for it or a model is built
        from anm_torchrl.networks.resolve import check_controllable

        sim = check_controllable(cfg.network)
        surrogate = OmegaConf.to_container(cfg.surrogate, resolve=True)
        if surrogate["name"] == "pinn" or cfg.model.get("dynamics") == "pinn":  # before it is trained on first use
            from anm_torchrl.surrogates.pinn.load import check_pinn_options
            from anm_torchrl.surrogates.pinn.model import check_pinn_network
            from anm_torchrl.training.factory import surrogate_options

            check_pinn_network(sim)
            if surrogate["name"] == "pinn":  # its keys go to load_pinn (SHAC's model=pinn: the same surrogate group)
                check_pinn_options(**surrogate_options(surrogate))
        if surrogate.get("path") and surrogate["name"] not in TRUE_SIMULATORS:
            # a given model of another network, kind or a damaged file: one line now, not a traceback in train()
            from anm_torchrl.training.factory import load_surrogate_in_home, surrogate_options

            load_surrogate_in_home(surrogate["name"], sim=sim, progress=False, **surrogate_options(surrogate))
        if cfg.checkpoint.resume:  # the checkpoint's algorithm, architecture and network: one line, not a traceback
            from anm_torchrl.training.checkpoint import check_network

            _, resume, _ = read_resume(cfg, str(cfg.algorithm))
            check_network(resume, sim, str(cfg.checkpoint.resume))
        if cfg.checkpoint.get("init_from"):  # likewise for a warm start's source
            from anm_torchrl.training.algorithms import get_algorithm
            from anm_torchrl.training.checkpoint import check_network
            from anm_torchrl.training.warm_start import read_init

            init = read_init(cfg.checkpoint.init_from, get_algorithm(str(cfg.algorithm)),
                             OmegaConf.to_container(cfg, resolve=True))
            check_network(init, sim, str(cfg.checkpoint.init_from))
        if warm and not cfg.checkpoint.resume:  # a resumed run continues after its warm start
            from anm_torchrl.training.warm_start import teacher_config

            teacher_config(cfg, log_now=False)  # its config's errors now, not after the PINN's training
    log_network_defaults(defaults)
    print(f"run directory: {run_dir}", flush=True)
    with stop_signals():
        try:
            return train(cfg, run_dir, network_defaults=defaults)
        except KeyboardInterrupt:
            raise SystemExit(143 if stop_requested() == "SIGTERM" else 130) from None
        finally:
            print(f"run directory: {run_dir}", flush=True)
