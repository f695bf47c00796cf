"""The algorithms the training protocol (:mod:`anm_torchrl.training.protocol`) can run, by name.

A new algorithm is a new module with one :class:`~anm_torchrl.training.algorithms.base.Algorithm` subclass, a
range check of its config keys in :mod:`anm_torchrl.training.config_checks`, and an entry here; the protocol,
checkpoints and ``recipes/evaluate.py`` then take it. Entries are import paths, resolved on first use, so a config
check does not pay for torch's import.
"""

from __future__ import annotations

import dataclasses
import importlib


@dataclasses.dataclass(frozen=True)
class AlgorithmEntry:
    """Where an algorithm lives: ``"module:Class"`` of its ``Algorithm`` and ``"module:function"`` of its config
    check (light: no torch)."""

    cls: str
    check: str

    def load(self, which: str = "cls"):
        module, name = getattr(self, which).split(":")
        return getattr(importlib.import_module(module), name)


ALGORITHMS = {
    "ppo": AlgorithmEntry("anm_torchrl.training.algorithms.ppo:PPO", "anm_torchrl.training.config_checks:check_ppo_config"),
    "sac": AlgorithmEntry("anm_torchrl.training.algorithms.sac:SAC", "anm_torchrl.training.config_checks:check_sac_config"),
    "shac": AlgorithmEntry("anm_torchrl.training.algorithms.shac:SHAC",
                           "anm_torchrl.training.config_checks:check_shac_config"),
}


def available_algorithms() -> list[str]:
    """Names of the registered algorithms."""
    return sorted(ALGORITHMS)


def _entry(name: str) -> AlgorithmEntry:
    if name not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {name!r}; registered: {', '.join(available_algorithms())}")
    return ALGORITHMS[name]


def get_algorithm(name: str):
    """The :class:`~anm_torchrl.training.algorithms.base.Algorithm` class registered as ``name``.

    Raises:
        ValueError: an unknown name (the message lists the known ones).
    """
    return _entry(name).load("cls")


def check_algorithm_config(cfg) -> None:
    """Range checks of a training config: its ``algorithm``'s check (which covers the keys every algorithm shares).

    Raises:
        ValueError: an unknown algorithm, or the first offending key.
    """
    _entry(str(cfg.algorithm)).load("check")(cfg)
