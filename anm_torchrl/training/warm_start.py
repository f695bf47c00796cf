"""Start a run from another run's networks (``checkpoint.init_from``): a warm start, not a resume.

The new run takes the checkpoint's actor and critic weights and nothing else: its frame count, optimiser, best
validation result and early-stop count start fresh, and its own config (losses, learning rates, budget) applies.
The source may be a run of another algorithm whose networks are the same family (``Algorithm.network_family``:
PPO's and SHAC's actor and state-value critic are built by :func:`~anm_torchrl.training.models.make_ppo_models`),
trained on the same network with the same architecture keys.

The actor comes whole, its exploration scale included (SHAC's ANM6-Easy entry trains at log-std -6, so PPO after it
samples that narrowly; the run's ``model.init_log_std`` does not apply). The critic predicts discounted returns of
**scaled** rewards: a source trained under another reward scale (SHAC's ``auto`` against PPO's fixed 0.01 on
ANM6-Easy) has its output layer multiplied by ``this scale / source scale``, the same value function in the new
run's units; a source with another discount (``loss.gamma``) or either run with ``loss.return_norm`` keeps the new
run's fresh critic (warned), since no factor converts it.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


def read_init(path: str | Path, algorithm_cls, config: dict, device="cpu") -> dict[str, Any]:
    """The checkpoint at ``path``, checked as a warm start of a run of ``algorithm_cls`` with ``config`` (plain).

    Raises:
        ValueError: the run's algorithm cannot start from another run, the checkpoint's algorithm builds another
            family of networks, an architecture key differs (naming both values), or the checkpoint has no reward
            scale (written before warm starts existed).
        FileNotFoundError / ValueError: an unreadable file (:func:`~anm_torchrl.training.checkpoint.load_checkpoint`).
    """
    from anm_torchrl.training.algorithms import get_algorithm
    from anm_torchrl.training.algorithms.base import Algorithm
    from anm_torchrl.training.checkpoint import architecture_differences, load_checkpoint

    path = Path(path)
    family = algorithm_cls.network_family
    if family is None or algorithm_cls.start_from is Algorithm.start_from:
        raise ValueError(f"checkpoint.init_from: a {algorithm_cls.name} run cannot start from another run's networks "
                         "(ppo can)")
    ckpt = load_checkpoint(path, map_location=device)
    source = get_algorithm(ckpt["algorithm"])
    if source.network_family != family:
        raise ValueError(f"checkpoint.init_from={path}: its networks are {ckpt['algorithm']}'s, another family than "
                         f"{algorithm_cls.name}'s")
    keys = [k for k in algorithm_cls.architecture_keys if k in source.architecture_keys and k != "network"]
    differ = architecture_differences(ckpt["config"], config, keys)
    if differ:
        details = "; ".join(f"{k}: checkpoint {a!r}, this run {b!r}" for k, a, b in differ)
        raise ValueError(f"checkpoint.init_from={path}: its networks have another architecture ({details})")
    if ckpt.get("reward_scale") is None:
        raise ValueError(f"checkpoint.init_from={path}: the checkpoint records no reward scale (written before warm "
                         "starts), so its critic's values cannot be put in this run's units; train the source again")
    return ckpt


#: the PPO run's eval keys its teacher takes: the same validation and test states and score (how often the teacher
#: validates and when it stops early stay its own recipe's)
SHARED_EVAL_KEYS = ("seed", "num_episodes", "max_steps", "gamma", "test_seed", "test_episodes", "test_max_steps",
                    "background")


def teacher_config(cfg, log_now: bool = True):
    """The SHAC config of ``warm_start.algorithm=shac`` for the PPO config ``cfg`` (checked, its network's entry
    applied): through the PINN for ``surrogate=pinn``, through the exact simulator for ``surrogate=none``; the same
    network, seed, threads, surrogate options, logger and validation/test states as the PPO run, PPO's architecture
    keys (so its networks load into PPO's), ``warm_start.overrides`` over SHAC's own defaults. ``log_now``: log the
    network's entry applied.

    Returns:
        ``(config, the network defaults applied)``.

    Raises:
        ValueError: another teacher than shac, a surrogate without gradients, or an override SHAC does not take.
    """
    from hydra.errors import HydraException
    from omegaconf import OmegaConf, open_dict

    from anm_torchrl.training.algorithms import check_algorithm_config, get_algorithm
    from anm_torchrl.training.network_defaults import (RECIPE_CONF, apply_network_defaults, compose_config,
                                                       explicit_keys)

    ws = cfg.warm_start
    if ws.algorithm != "shac":
        raise ValueError(f"warm_start.algorithm must be null or shac, got {ws.algorithm!r}")
    surrogate = str(cfg.surrogate.name)
    if surrogate not in ("pinn", "none"):
        raise ValueError(f"warm_start.algorithm=shac trains through the PINN (surrogate=pinn) or the exact simulator "
                         f"(surrogate=none); surrogate={surrogate} has no gradients to train through")
    user = [str(o) for o in ws.overrides]
    arch = [k for k in get_algorithm(str(cfg.algorithm)).architecture_keys if k.startswith("model.")]
    taken = sorted(k for k in explicit_keys(user, RECIPE_CONF)
                   if k in arch or k in {f"eval.{e}" for e in SHARED_EVAL_KEYS} or k == "env.device")
    if taken:
        raise ValueError(f"warm_start.overrides sets {', '.join(taken)}: the warm start takes these from the PPO run "
                         "(its networks must load into PPO's, its states be PPO's); set them on the command line")
    overrides = [f"model={'pinn' if surrogate == 'pinn' else 'exact'}", *user]
    try:
        teacher = compose_config(overrides, "shac")
    except HydraException as err:  # an unknown key or group option, a malformed override: one line naming it
        raise ValueError(f"warm_start.overrides={user}: {str(err).splitlines()[0]} (the overrides are of "
                         "recipes/shac.py's config: python recipes/shac.py --help)") from None
    with open_dict(teacher):
        teacher.network, teacher.seed, teacher.threads = cfg.network, cfg.seed, cfg.threads
        teacher.surrogate = OmegaConf.to_container(cfg.surrogate, resolve=True)
        teacher.logger = {**OmegaConf.to_container(cfg.logger, resolve=True), "exp_name": "shac_warm_start"}
    explicit = explicit_keys(overrides, RECIPE_CONF) | {"network", "seed", "threads", "logger"} | {
        f"surrogate.{k}" for k in cfg.surrogate}
    defaults = apply_network_defaults(teacher, explicit, log_now=log_now)
    with open_dict(teacher):
        for key in SHARED_EVAL_KEYS:
            teacher.eval[key] = cfg.eval[key]
        teacher.env.device = cfg.env.device
        for key in arch:
            teacher.model[key.split(".", 1)[1]] = cfg.model.get(key.split(".", 1)[1])
    check_algorithm_config(teacher)
    return teacher, defaults


def teacher_record(summary: dict[str, Any]) -> dict[str, Any]:
    """What the PPO run's summary records of its teacher's run (``summary``, its summary.json): algorithm, run
    directory, best.pt, wall time (s), model and true-env frames, best validation and test results.

    Raises:
        ValueError: the teacher ended without a best.pt (no validation pass ran).
    """
    best = summary["checkpoints"]["best"]
    if best is None:
        raise ValueError(f"the warm start's {summary['algorithm']} run ({summary['run_dir']}) wrote no best.pt: it "
                         "ran no validation pass (eval.interval)")
    return {"algorithm": summary["algorithm"], "run_dir": summary["run_dir"], "checkpoint": best,
            "wall_time": summary["wall_time"], "model_frames": summary.get("model_frames"),
            "true_env_frames": summary["true_env_frames"], "best_eval": summary["best_eval"],
            "test": summary["test"]}
