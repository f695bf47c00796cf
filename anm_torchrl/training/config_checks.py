"""Range checks of the training and evaluation configs, run before any work starts (one function per recipe).

Hydra checks key names and types; these functions check what it cannot: numeric ranges, choices and relations
between keys. Every failure is a ``ValueError`` naming the dotted key, what was expected and what was received,
so ``collector.total_frames=-5`` fails in a second instead of exiting 0 with an untrained checkpoint.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

LOGGER_BACKENDS = ("tensorboard", "csv", "wandb", "mlflow", None)
# loggers TorchRL supports that need a package of their own (not in any extra: pass-through only)
LOGGER_PACKAGES = {"wandb": "wandb", "mlflow": "mlflow"}
ACTION_MODES = ("raise", "clip")
ENV_INITS = (None, "gym_anm", "intended", "uniform")
EVALUATE_ENVS = ("exact", "gym_anm", "anm6")  # anm6: the former name of exact, still accepted
# the surrogate names that are the true simulator (this package's, or gym-anm itself): no model to load or train,
# and their frames are true-env frames
TRUE_SIMULATORS = ("none", "gym_anm")
# the activations of anm_torchrl.training.models.ACTIVATIONS (which checks that they agree), named here without torch
ACTIVATION_NAMES = ("elu", "leaky_relu", "relu", "silu", "tanh", "tanh_sigmoid")


def gym_anm_only(key: str, network) -> ValueError:
    """The error for gym-anm (``surrogate=gym_anm``, ``env=gym_anm``) asked to run another network than
    ANM6-Easy, the only one gym-anm has; naming ``key`` and the network."""
    return ValueError(f"{key}=gym_anm runs gym-anm's ANM6Easy only, got network={network!r}")


def _get(cfg: Mapping, key: str) -> Any:
    node = cfg
    for part in key.split("."):
        node = node[part]
    return node


def _number(cfg: Mapping, key: str) -> float | None:
    value = _get(cfg, key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{key} must be a finite number, got {value!r}")
    return value


def _int(cfg: Mapping, key: str, low: int = 1, optional: bool = False) -> int | None:
    value = _get(cfg, key)
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        expected = f"an integer >= {low}" + (" or null" if optional else "")
        raise ValueError(f"{key} must be {expected}, got {value!r}")
    return value


def _bool(cfg: Mapping, *keys: str) -> None:
    """Each of ``keys`` is true or false (not a string or number that YAML or the command line would coerce)."""
    for key in keys:
        if not isinstance(_get(cfg, key), bool):
            raise ValueError(f"{key} must be true or false, got {_get(cfg, key)!r}")


def _in_range(cfg: Mapping, key: str, low: float, high: float, low_open: bool, high_open: bool,
              optional: bool = False) -> float | None:
    value = _number(cfg, key)
    if value is None:
        if optional:
            return None
        raise ValueError(f"{key} must be a number, got None")
    ok = (low < value if low_open else low <= value) and (value < high if high_open else value <= high)
    if not ok:
        interval = f"{'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
        raise ValueError(f"{key} must be in {interval}" + (" or null" if optional else "") + f", got {value!r}")
    return value


def _choice(cfg: Mapping, key: str, choices: tuple) -> Any:
    value = _get(cfg, key)
    # by type as well: 1 == True and 0 == False in Python, and "1" is no choice of a flag
    if not any(value == c and isinstance(value, bool) == isinstance(c, bool) for c in choices):
        shown = ", ".join("null" if c is None else str(c).lower() if isinstance(c, bool) else str(c) for c in choices)
        raise ValueError(f"{key} must be one of {shown}; got {value!r}")
    return value


def _cells(cfg: Mapping, key: str) -> None:
    value = _get(cfg, key)
    if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__") or any(
            isinstance(c, bool) or not isinstance(c, int) or c < 1 for c in value):
        raise ValueError(f"{key} must be a list of positive layer widths, got {value!r}")


def check_gym_anm_options(init, action_mode, prefix: str = "") -> None:
    """gym-anm's own env starts from its own distribution and asserts its actions lie in the box: another ``init``
    or ``action_mode`` would be ignored (a ``ValueError`` naming the option)."""
    if init not in (None, "gym_anm"):
        raise ValueError(f"{prefix}init={init!r}: surrogate=gym_anm starts every episode from gym-anm's own initial "
                         "distribution (leave init unset, or 'gym_anm')")
    if action_mode != "raise":
        raise ValueError(f"{prefix}action_mode={action_mode!r}: gym-anm's own env asserts its actions lie in the box "
                         "(only 'raise')")


def _check_surrogate(cfg: Mapping) -> None:
    """The surrogate group's choices that would otherwise fail once the run has started (a traceback)."""
    surrogate = cfg.get("surrogate")
    if not isinstance(surrogate, Mapping):
        return
    if surrogate.get("name") == "gym_anm":
        if _get(cfg, "network") != "anm6_easy":
            raise gym_anm_only("surrogate", _get(cfg, "network"))
        env = cfg.get("env") if isinstance(cfg.get("env"), Mapping) else {}
        check_gym_anm_options(env.get("init"), env.get("action_mode", "raise"), prefix="env.")
    if "dataset" in surrogate:
        from anm_torchrl.surrogates.regressors.defaults import DATASETS

        _choice(cfg, "surrogate.dataset", tuple(DATASETS))


def check_protocol_config(cfg: Mapping) -> None:
    """Check the keys every algorithm shares (``anm_torchrl.training.protocol``): network, seed, threads, env,
    budget, logger, eval, checkpoint, and the model group's shared keys (:func:`check_model_group` first).

    Raises:
        ValueError: the first offending key, with the expected range and the value received.
    """
    from anm_torchrl.networks import check_network_name

    check_network_name(_get(cfg, "network"))
    _int(cfg, "seed", low=0)
    _int(cfg, "threads")
    _check_surrogate(cfg)
    # env
    _int(cfg, "env.num_envs")
    _int(cfg, "env.max_steps", optional=True)
    _choice(cfg, "env.action_mode", ACTION_MODES)
    _choice(cfg, "env.init", ENV_INITS)
    _bool(cfg, "env.stagger")
    if _get(cfg, "env.stagger") and _get(cfg, "env.max_steps") is None:
        raise ValueError("env.stagger=true needs a time limit (env.max_steps) to stagger; got env.max_steps=null")
    # budget: frames (reproducible); a wall-clock cap is opt-in
    _int(cfg, "collector.total_frames")
    _in_range(cfg, "collector.max_minutes", 0, math.inf, True, True, optional=True)
    # reward scale (every algorithm scales its training rewards the same way)
    if isinstance(_get(cfg, "loss.reward_scale"), str) and _get(cfg, "loss.reward_scale") != "auto":
        raise ValueError(f"loss.reward_scale must be a number > 0 or auto, got {_get(cfg, 'loss.reward_scale')!r}")
    if _get(cfg, "loss.reward_scale") != "auto":
        _in_range(cfg, "loss.reward_scale", 0, math.inf, True, True)
    _in_range(cfg, "loss.auto_step_reward", 0, math.inf, True, True)
    # logger
    backend = _choice(cfg, "logger.backend", LOGGER_BACKENDS)
    if backend in LOGGER_PACKAGES:
        import importlib.util

        if importlib.util.find_spec(LOGGER_PACKAGES[backend]) is None:
            raise ValueError(f"logger.backend={backend} needs the {LOGGER_PACKAGES[backend]} package "
                             f"(pip install {LOGGER_PACKAGES[backend]}); or use tensorboard or csv")
    _int(cfg, "logger.interval")
    # eval: validation states (model selection) and test states (reported figures) must differ
    _int(cfg, "eval.interval", optional=True)
    _int(cfg, "eval.patience", optional=True)
    _int(cfg, "eval.num_episodes")
    _int(cfg, "eval.test_episodes")
    _int(cfg, "eval.max_steps")
    _int(cfg, "eval.test_max_steps", optional=True)
    _in_range(cfg, "eval.gamma", 0, 1, True, False)
    _choice(cfg, "eval.track_test", (False, True))
    if not (_get(cfg, "eval.background") == "auto" or isinstance(_get(cfg, "eval.background"), bool)):
        raise ValueError(f"eval.background must be auto, true or false; got {_get(cfg, 'eval.background')!r}")
    if _int(cfg, "eval.render_interval", low=0) and _get(cfg, "logger.backend") != "tensorboard":
        raise ValueError(f"eval.render_interval > 0 logs figures to TensorBoard: it needs logger.backend=tensorboard, "
                         f"got {_get(cfg, 'logger.backend')!r}")
    if _int(cfg, "eval.seed", low=0) == _int(cfg, "eval.test_seed", low=0):
        raise ValueError(f"eval.seed (validation states) and eval.test_seed (test states) must differ, both are "
                         f"{_get(cfg, 'eval.seed')}: model selection on the reported states biases the figures")
    # checkpoint
    _int(cfg, "checkpoint.interval")
    # the model: this recipe's group, then the keys every group has
    check_model_group(cfg)
    _check_model(cfg)


def _check_model(cfg: Mapping) -> None:
    _cells(cfg, "model.actor_cells")
    _cells(cfg, "model.critic_cells")
    _choice(cfg, "model.activation", ACTIVATION_NAMES)
    _in_range(cfg, "model.max_obs_scale", 0, math.inf, True, True, optional=True)
    _in_range(cfg, "model.obs_clip", 0, math.inf, True, True)
    _number(cfg, "model.init_log_std")
    _choice(cfg, "model.init_action", ("center", "do_nothing"))
    _in_range(cfg, "model.init_action_clip", 0, 1, True, True)
    _choice(cfg, "model.time_features", (False, True))
    _int(cfg, "model.forecast_steps", low=0)


def _check_collector(cfg: Mapping) -> int:
    """Frames per batch, workers; returns ``collector.frames_per_batch``."""
    n = _int(cfg, "env.num_envs")
    fpb = _int(cfg, "collector.frames_per_batch")
    workers = _int(cfg, "collector.num_workers")
    _bool(cfg, "collector.sync")
    if n % workers:
        raise ValueError(f"env.num_envs ({n}) must be a positive multiple of collector.num_workers ({workers})")
    if fpb < n or fpb % n:
        raise ValueError(f"collector.frames_per_batch ({fpb}) must be a positive multiple of env.num_envs ({n}): "
                         f"frames_per_batch = num_envs x steps per env")
    return fpb


def _check_adam(cfg: Mapping) -> None:
    _in_range(cfg, "optim.lr", 0, math.inf, True, True)
    _in_range(cfg, "optim.eps", 0, math.inf, True, True)
    _in_range(cfg, "optim.weight_decay", 0, math.inf, False, True)
    _in_range(cfg, "optim.max_grad_norm", 0, math.inf, True, True, optional=True)


def _model_group(cfg: Mapping, recipe: str, group: str, foreign: tuple[str, ...]) -> None:
    """Refuse another recipe's model group (its keys would reach this recipe's model factory as unknown arguments,
    a TypeError after the run has started): ``foreign`` are keys only the other groups have."""
    model = _get(cfg, "model")
    extra = [k for k in foreign if isinstance(model, Mapping) and k in model]
    if extra:
        raise ValueError(f"model.{extra[0]} is not a setting of {recipe}'s models: {recipe} takes model={group} "
                         "(model=exact|pinn are recipes/shac.py's, model=sac recipes/sac.py's)")


def check_model_group(cfg: Mapping) -> None:
    """Refuse another recipe's model group for ``cfg.algorithm`` (before the per-network defaults, whose conditions
    read the group's keys)."""
    algorithm = _get(cfg, "algorithm")
    if algorithm == "ppo":
        _model_group(cfg, "ppo.py", "default", ("dynamics",))
    elif algorithm == "sac":
        _model_group(cfg, "sac.py", "sac", ("dynamics", "state_dependent_scale"))
    elif algorithm == "shac" and not (isinstance(_get(cfg, "model"), Mapping) and "dynamics" in _get(cfg, "model")):
        raise ValueError("shac.py takes model=exact or model=pinn (the group that names model.dynamics); model=default "
                         "is ppo.py's, model=sac sac.py's")


def check_ppo_config(cfg: Mapping) -> None:
    """Check every numeric range and choice of ``recipes/conf/config.yaml`` (``recipes/ppo.py``): the shared keys
    (:func:`check_protocol_config`) and PPO's model, collector, loss and optimiser.

    Raises:
        ValueError: the first offending key, with the expected range and the value received.
    """
    check_protocol_config(cfg)
    _choice(cfg, "model.state_dependent_scale", (False, True))
    fpb = _check_collector(cfg)
    _in_range(cfg, "loss.gamma", 0, 1, False, False)  # 0: a contextual bandit (no storage)
    _in_range(cfg, "loss.gae_lambda", 0, 1, False, False)
    _in_range(cfg, "loss.clip_epsilon", 0, math.inf, True, True)
    _int(cfg, "loss.ppo_epochs")
    _bool(cfg, "loss.gae_every_epoch", "loss.compile", "loss.return_norm")
    mini = _int(cfg, "loss.mini_batch_size")
    if mini > fpb:
        raise ValueError(f"loss.mini_batch_size ({mini}) must be <= collector.frames_per_batch ({fpb})")
    _in_range(cfg, "loss.critic_coeff", 0, math.inf, False, True)
    _in_range(cfg, "loss.entropy_coeff", 0, math.inf, False, True)
    _choice(cfg, "loss.loss_critic_type", ("l2", "l1", "smooth_l1"))
    _check_adam(cfg)
    _in_range(cfg, "optim.anneal_start", 0, 1, False, True)


def check_sac_config(cfg: Mapping) -> None:
    """Check ``recipes/conf/sac.yaml`` (``recipes/sac.py``): the shared keys and SAC's model, collector, replay
    buffer, loss and optimiser.

    Raises:
        ValueError: the first offending key, with the expected range and the value received.
    """
    check_protocol_config(cfg)
    fpb = _check_collector(cfg)
    if _get(cfg, "collector.num_workers") != 1:
        raise ValueError(f"collector.num_workers must be 1 for sac (one collector process), got "
                         f"{_get(cfg, 'collector.num_workers')!r}")
    if _get(cfg, "collector.sync") is not True:  # SAC's collector runs in this process, between its updates
        raise ValueError(f"collector.sync must be true for sac (collection and updates take turns), got "
                         f"{_get(cfg, 'collector.sync')!r}")
    _int(cfg, "collector.init_random_frames", low=0)
    buffer = _int(cfg, "replay.size")
    batch = _int(cfg, "replay.batch_size")
    if buffer < fpb:
        raise ValueError(f"replay.size ({buffer}) must be >= collector.frames_per_batch ({fpb})")
    if batch > buffer:
        raise ValueError(f"replay.batch_size ({batch}) must be <= replay.size ({buffer})")
    _in_range(cfg, "replay.samples_per_frame", 0, math.inf, True, True)
    _in_range(cfg, "loss.gamma", 0, 1, False, False)  # 0: a contextual bandit (no storage), the critic a reward model
    _in_range(cfg, "loss.tau", 0, 1, True, False)
    _number(cfg, "loss.alpha_init")
    if not _get(cfg, "loss.alpha_init") > 0:
        raise ValueError(f"loss.alpha_init must be > 0, got {_get(cfg, 'loss.alpha_init')!r}")
    _number(cfg, "loss.target_entropy_per_dim")
    _choice(cfg, "loss.loss_function", ("l2", "l1", "smooth_l1"))
    _check_adam(cfg)
    _int(cfg, "optim.actor_delay_frames", low=0)


def check_make_dataset_config(cfg: Mapping) -> None:
    """Check ``recipes/conf/make_dataset.yaml`` (``recipes/make_dataset.py``) before any sample is drawn.

    Raises:
        ValueError: the first offending key, with the expected range and the value received.
    """
    from anm_torchrl.data.options import WAYPOINT_DISTS, check_agent_split, check_fractions, check_split_units
    from anm_torchrl.data.registry import available_datasets
    from anm_torchrl.networks import check_network_name

    check_network_name(_get(cfg, "network"))
    _choice(cfg, "dataset", tuple(available_datasets()))
    # below 3 rows (or agent envs) a validation or test split is empty: NaN R², a DNN stopped after one epoch
    check_split_units(_int(cfg, "size"), "size")
    _int(cfg, "seed", low=0)
    _int(cfg, "threads")
    check_fractions(_get(cfg, "fractions"))
    if _get(cfg, "dataset") == "generative":
        _int(cfg, "generative.chunk")
    if _get(cfg, "dataset") == "agent":
        check_split_units(_int(cfg, "agent.num_envs"), "agent.num_envs")
        check_agent_split(_int(cfg, "size"), _int(cfg, "agent.num_envs"))
        _int(cfg, "agent.waypoint_every")
        _int(cfg, "agent.max_episode_steps")
        if not isinstance(_get(cfg, "agent.random_every"), bool):
            raise ValueError(f"agent.random_every must be true or false, got {_get(cfg, 'agent.random_every')!r}")
        _choice(cfg, "agent.waypoints", tuple(WAYPOINT_DISTS))


def check_shac_config(cfg: Mapping) -> None:
    """Check ``recipes/conf/shac.yaml`` (``recipes/shac.py``): the shared keys and SHAC's model (with
    ``model.dynamics``), horizon, TD(λ) critic and optimisers.

    Raises:
        ValueError: the first offending key, with the expected range and the value received.
    """
    check_protocol_config(cfg)
    _choice(cfg, "model.state_dependent_scale", (False, True))
    _choice(cfg, "model.dynamics", ("exact", "pinn"))
    _choice(cfg, "env.power_flow", ("torch", "numba"))
    device = str(_get(cfg, "env.device") or "cpu")
    compiled = _get(cfg, "model.dynamics") == "exact" and _get(cfg, "env.power_flow") == "numba"
    if compiled and not device.startswith("cpu"):
        raise ValueError(f"env.power_flow=numba (the default) runs the exact model's power flow on the CPU; with "
                         f"env.device={device} add env.power_flow=torch")
    _bool(cfg, "loss.critic_worker")
    if _get(cfg, "loss.critic_worker") and not device.startswith("cpu"):  # ANM6-Easy's exact-model entry sets it
        raise ValueError(f"loss.critic_worker=true runs SHAC's critic in a CPU process; with env.device={device} add "
                         "loss.critic_worker=false")
    _in_range(cfg, "env.short_rows", 0, 1, False, True)
    _int(cfg, "env.short_steps")
    if _get(cfg, "env.short_rows") and _get(cfg, "env.max_steps") is None:
        raise ValueError("env.short_rows > 0 needs a time limit (env.max_steps); got env.max_steps=null")
    _int(cfg, "loss.horizon")
    _in_range(cfg, "loss.gamma", 0, 1, False, False)  # 0 with horizon 1: a contextual bandit
    _in_range(cfg, "loss.td_lambda", 0, 1, False, False)
    _in_range(cfg, "loss.target_tau", 0, 1, True, False)
    _int(cfg, "loss.critic_epochs")
    _int(cfg, "loss.critic_batch_size")
    _bool(cfg, "loss.noise", "loss.critic_worker", "optim.anneal_lr")
    _in_range(cfg, "optim.actor_lr", 0, math.inf, True, True)
    _in_range(cfg, "optim.critic_lr", 0, math.inf, True, True)
    _in_range(cfg, "optim.eps", 0, math.inf, True, True)
    _in_range(cfg, "optim.weight_decay", 0, math.inf, False, True)
    _in_range(cfg, "optim.max_grad_norm", 0, math.inf, True, True)
    _in_range(cfg, "optim.actor_ema", 0, 1, False, False)
    _in_range(cfg, "optim.anneal_start", 0, 1, False, True)


def check_reproduce_config(cfg: Mapping) -> None:
    """Check ``recipes/conf/reproduce.yaml``'s own keys (``recipes/reproduce.py``; an experiment's preset section is
    :func:`anm_torchrl.experiments.registry.check_section`'s).

    Raises:
        ValueError: the first offending key, with the expected range and the value received.
    """
    _int(cfg, "threads")


def check_evaluate_config(cfg: Mapping) -> None:
    """Check the ranges of ``recipes/conf_evaluate/evaluate.yaml`` (``recipes/evaluate.py``).

    Raises:
        ValueError: the first offending key, with the expected range and the value received.
    """
    from anm_torchrl.networks import check_network_name

    _choice(cfg, "env", EVALUATE_ENVS)
    if _get(cfg, "network") is not None:
        check_network_name(_get(cfg, "network"))
    if _get(cfg, "env") == "gym_anm" and _get(cfg, "network") not in (None, "anm6_easy"):
        raise gym_anm_only("env", _get(cfg, "network"))
    _int(cfg, "seed", low=0, optional=True)
    _int(cfg, "steps", optional=True)
    _int(cfg, "episodes", optional=True)
    _in_range(cfg, "gamma", 0, 1, True, False, optional=True)
    _int(cfg, "threads")
    _bool(cfg, "render", "progress")
