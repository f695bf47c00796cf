"""Registry of surrogate transition models, keyed by the names users pass as ``surrogate=``.

Entries are imported lazily (``"module:function"``), so asking for ``pinn`` never imports xgboost. A loader
takes ``device`` and its own keyword arguments and returns a ``TensorDictModuleBase`` obeying the
``SurrogateEnv`` model contract (``state``, ``action`` -> ``next_state``, ``reward``, ``terminated``).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

from tensordict.nn import TensorDictModuleBase

_REGISTRY: dict[str, str | Callable[..., TensorDictModuleBase]] = {
    "pinn": "anm_torchrl.surrogates.pinn.chain:load_pinn",
    "lr": "anm_torchrl.surrogates.regressors:load_lr",
    "dt": "anm_torchrl.surrogates.regressors:load_dt",
    "rf": "anm_torchrl.surrogates.regressors:load_rf",
    "xgb": "anm_torchrl.surrogates.regressors:load_xgb",
    "dnn": "anm_torchrl.surrogates.regressors:load_dnn",
}


def register_surrogate(name: str, loader: str | Callable[..., TensorDictModuleBase]) -> None:
    """Register ``loader`` (a callable or ``"module:function"``) under ``name``; replaces an existing entry."""
    _REGISTRY[name] = loader


def available_surrogates() -> list[str]:
    """Registered surrogate names."""
    return sorted(_REGISTRY)


def load_surrogate(name: str, device="cpu", **kwargs) -> TensorDictModuleBase:
    """Build the transition model registered as ``name``.

    Raises:
        ValueError: ``name`` is not registered (the message lists the registered names).
    """
    if name not in _REGISTRY:
        raise ValueError(f"unknown surrogate {name!r}; registered: {available_surrogates()} "
                         "(plus 'none' for the true simulator and 'gym_anm' for the original package)")
    loader = _REGISTRY[name]
    if isinstance(loader, str):
        module, func = loader.split(":")
        loader = getattr(importlib.import_module(module), func)
    return loader(device=device, **kwargs)
