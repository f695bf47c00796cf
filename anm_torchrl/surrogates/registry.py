"""Registry of surrogate transition models, keyed by the names users pass as ``surrogate=``.

Entries are imported lazily (``"module:function"``), so asking for ``pinn`` never imports xgboost.

Loader contract: ``loader(sim=..., device=..., **own_kwargs)`` returns a ``TensorDictModuleBase`` obeying the
``SurrogateEnv`` model contract (``state``, ``action`` -> ``next_state``, ``reward``, ``terminated``) that runs
on ``sim``: everything exogenous (next-step loads and renewable potentials, foresight features) is read from
``sim``'s profiles, so a simulator with scaled or shifted profiles gets a model that follows them. ``sim=None``
means ANM6-Easy on ``device``. A model trained for another network (tables, not profiles) raises; a loader
that cannot honour an argument raises (``TypeError`` for an unknown keyword, never silently dropped).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

from tensordict.nn import TensorDictModuleBase

_REGISTRY: dict[str, str | Callable[..., TensorDictModuleBase]] = {
    "pinn": "anm_torchrl.surrogates.pinn.chain:load_pinn",
    "lr": "anm_torchrl.surrogates.regressors.loaders:load_lr",
    "dt": "anm_torchrl.surrogates.regressors.loaders:load_dt",
    "rf": "anm_torchrl.surrogates.regressors.loaders:load_rf",
    "xgb": "anm_torchrl.surrogates.regressors.loaders:load_xgb",
    "dnn": "anm_torchrl.surrogates.regressors.loaders:load_dnn",
}
#: Family of each entry: ``"physics"`` (trained from physics alone) or ``"data"`` (trained on a dataset).
_FAMILY: dict[str, str] = {"pinn": "physics", "lr": "data", "dt": "data", "rf": "data", "xgb": "data", "dnn": "data"}
FAMILIES = ("physics", "data")


def register_surrogate(name: str, loader: str | Callable[..., TensorDictModuleBase], family: str = "physics") -> None:
    """Register ``loader`` (a callable or ``"module:function"``, following the loader contract above) under
    ``name`` in ``family`` (``"physics"`` or ``"data"``); replaces an existing entry."""
    if family not in FAMILIES:
        raise ValueError(f"family must be one of {FAMILIES}, got {family!r}")
    _REGISTRY[name], _FAMILY[name] = loader, family


def available_surrogates(family: str | None = None) -> list[str]:
    """Registered surrogate names, sorted; only those of ``family`` (``"physics"``, ``"data"``) when given."""
    if family is not None and family not in FAMILIES:
        raise ValueError(f"family must be one of {FAMILIES}, got {family!r}")
    return sorted(n for n in _REGISTRY if family is None or _FAMILY[n] == family)


def data_driven_surrogates() -> tuple[str, ...]:
    """The data-driven surrogates in registration order (``lr``, ``dt``, ``rf``, ``xgb``, ``dnn``)."""
    return tuple(n for n in _REGISTRY if _FAMILY[n] == "data")


def load_surrogate(name: str, sim=None, device=None, **kwargs) -> TensorDictModuleBase:
    """Build the transition model registered as ``name``, running on simulator ``sim``.

    Args:
        name: a registered surrogate (:func:`available_surrogates`).
        sim: the ``GridSimulator`` whose network and profiles the model runs on (the env's own simulator,
            ``env.sim``); None: ANM6-Easy on ``device``.
        device: torch device (None: ``sim``'s device, or the CPU).
        **kwargs: the loader's own options (``path``, ``dataset``, ``terminal``, ...).

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
    return loader(sim=sim, device=device, **kwargs)
