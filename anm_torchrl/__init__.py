"""anm_torchrl: gym-anm's ANM6-Easy as a batched TorchRL environment, its surrogates and PPO recipes.

Importing the package imports nothing heavy (no torch, no gymnasium): ``make_env`` and the ``gym`` subpackage
load on first use. ``import anm_torchrl.gym`` registers the gymnasium ids ``anm_torchrl/<Name>-v0``
(``gymnasium.make("anm_torchrl.gym:anm_torchrl/ANM6Easy-v0")`` imports it for you).
"""

from __future__ import annotations

import importlib
from typing import Any

from anm_torchrl._version import __version__

__all__ = ["__version__", "gym", "make_env"]


def __getattr__(name: str) -> Any:
    """Lazy attributes: ``make_env`` (:func:`anm_torchrl.training.factory.make_env`) and the ``gym`` subpackage."""
    if name == "make_env":
        from anm_torchrl.training.factory import make_env

        return make_env
    if name == "gym":
        return importlib.import_module("anm_torchrl.gym")  # registers the gymnasium ids
    raise AttributeError(f"module 'anm_torchrl' has no attribute {name!r}")
