"""What an algorithm provides to the training protocol: models, loss and update, nothing else.

The protocol (:func:`anm_torchrl.training.protocol.train`) owns the run directory, resume, budget, validation
and test states, early stop, checkpoints, logging and Ctrl-C; it calls an algorithm through this interface only.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar

from omegaconf import DictConfig

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)


def anneal_lr(optimizer, lr: float, frames: int, total_frames: int, start: float = 0.0) -> None:
    """Set every group of ``optimizer`` to ``lr``, decayed linearly to 0 from ``start`` x ``total_frames`` frames to
    ``total_frames`` (``frames`` done; ``start`` in [0, 1): 0 decays over the whole budget)."""
    left = 1.0 - frames / total_frames
    for group in optimizer.param_groups:
        group["lr"] = float(lr) * min(max(left / (1.0 - start), 0.0), 1.0)


def set_optimizer_options(optimizer, **options: float) -> None:
    """Set every param group of ``optimizer`` to ``options`` (``lr``, ``eps``, ``weight_decay``: the config's).

    Called after ``optimizer.load_state_dict`` on resume, which restores the checkpoint's values: a resumed run takes
    the ones it was given (an ``anneal_lr`` schedule then decays from the new ``lr``, as it reads the config's)."""
    for group in optimizer.param_groups:
        group.update({key: float(value) for key, value in options.items()})


def load_networks(init: dict[str, Any], actor: torch.nn.Module, critic: torch.nn.Module, reward_scale: float,
                  loss: Mapping[str, Any]) -> None:
    """A warm start (:mod:`anm_torchrl.training.warm_start`): copy the checkpoint ``init``'s actor and critic weights
    into ``actor`` and ``critic`` (in place), the critic's output layer rescaled from the source's reward scale to
    ``reward_scale`` (the critic predicts returns of scaled rewards). ``loss``: the run's ``loss`` group; where its
    ``gamma`` differs from the source's or either uses ``return_norm``, the critic stays as built (warned)."""
    import torch

    actor.load_state_dict(init["actor"])
    source = init["config"].get("loss", {})
    if (float(source.get("gamma", -1)) != float(loss.get("gamma")) or source.get("return_norm")
            or loss.get("return_norm")):
        log.warning("checkpoint.init_from: the actor only; the critic starts fresh (the source's loss.gamma %s and "
                    "return_norm %s against this run's %s and %s: its values are of another return)",
                    source.get("gamma"), bool(source.get("return_norm")), loss.get("gamma"),
                    bool(loss.get("return_norm")))
        return
    critic.load_state_dict(init["state"]["critic"])
    ratio = float(reward_scale) / float(init["reward_scale"])
    last = [m for m in critic.modules() if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        last.weight.mul_(ratio)
        last.bias.mul_(ratio)
    log.info("started from the actor and critic of a %s run (%d frames; critic values x %.4g for this run's reward "
             "scale)", init["algorithm"], int(init["frames"]), ratio)


class Algorithm:
    """One training algorithm. Subclasses set the class attributes and implement every method.

    Attributes:
        name: the registry name (``anm_torchrl.training.algorithms.ALGORITHMS``), stored in checkpoints.
        architecture_keys: dotted config keys that fix the saved networks' shapes; resuming or loading with other
            values is an error.
        actor: the policy (a ``ProbabilisticActor`` reading ``"observation"``, writing ``"action"`` inside the box);
            evaluated in deterministic mode, saved as the checkpoint's ``"actor"``.
        normalizer: its observation normaliser (``stats()`` goes into the checkpoint's ``"obs_norm"``).
    """

    name: ClassVar[str]
    architecture_keys: ClassVar[tuple[str, ...]] = ("network",)
    # algorithms of one family build the same actor and critic: a run starts from another's (checkpoint.init_from)
    network_family: ClassVar[str | None] = None

    def __init__(self, cfg: DictConfig, *, device, seed: int, budget: int, reward_scale: float,
                 resume: Mapping[str, Any] | None):
        """Build envs, models, loss and optimisers.

        Args:
            cfg: the recipe's composed config.
            device: torch device of models and envs.
            seed: the run's seed (already offset by the resumed update count).
            budget: training-env frames this run may still use (``collector.total_frames`` minus resumed frames).
            reward_scale: multiplier of training rewards (logged rewards stay unscaled).
            resume: a loaded checkpoint of this algorithm to continue from, or None.
        """
        raise NotImplementedError

    def iterate(self, remaining: int) -> tuple[int, dict[str, float]]:
        """One iteration (collect, update). Uses at most ``remaining`` training-env frames.

        Returns:
            (frames of the training env used, metrics as ``{"train/...": value, "time/...": seconds}``).
        """
        raise NotImplementedError

    def state_dict(self) -> dict[str, Any]:
        """Everything beyond the actor needed to resume (other networks, optimisers, buffers' counters)."""
        raise NotImplementedError

    def start_from(self, init: dict[str, Any]) -> None:
        """Take the actor and critic of ``init``, a checkpoint of this ``network_family`` checked by
        :func:`~anm_torchrl.training.warm_start.read_init` (a warm start: nothing else of that run)."""
        raise NotImplementedError

    def close(self, interrupted: bool = False) -> None:
        """Release collectors and worker processes (after Ctrl-C, workers may already be gone)."""

    @staticmethod
    def build_actor(env, config: Mapping[str, Any], obs_stats: Mapping[str, Any]):
        """The untrained actor for ``env``'s specs with a checkpoint's ``config`` and ``obs_norm`` (to load weights
        into)."""
        raise NotImplementedError
