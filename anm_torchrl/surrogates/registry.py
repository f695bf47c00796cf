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
from dataclasses import dataclass, field

from tensordict.nn import TensorDictModuleBase

@dataclass(frozen=True)
class SurrogateKind:
    """One registered surrogate: what ``surrogate=<name>`` stands for.

    Attributes:
        name: the name users pass.
        family: ``"physics"`` (trained from physics alone) or ``"data"`` (trained on a dataset).
        loader: a callable or ``"module:function"`` following the loader contract above.
        loader_kwargs: bound keyword arguments of the loader (e.g. the regressor ``kind`` of the shared
            data-driven loader).
    """

    name: str
    family: str
    loader: str | Callable[..., TensorDictModuleBase]
    loader_kwargs: dict = field(default_factory=dict)

    def load(self, **kwargs) -> TensorDictModuleBase:
        loader = self.loader
        if isinstance(loader, str):
            module, func = loader.split(":")
            loader = getattr(importlib.import_module(module), func)
        return loader(**self.loader_kwargs, **kwargs)


_REGRESSOR_LOADER = "anm_torchrl.surrogates.regressors.loaders:load_regressor_surrogate"
_REGISTRY: dict[str, SurrogateKind] = {
    "pinn": SurrogateKind("pinn", "physics", "anm_torchrl.surrogates.pinn.load:load_pinn"),
    **{k: SurrogateKind(k, "data", _REGRESSOR_LOADER, {"kind": k}) for k in ("lr", "dt", "rf", "xgb", "dnn")},
}
FAMILIES = ("physics", "data")


def register_surrogate(name: str, loader: str | Callable[..., TensorDictModuleBase], family: str = "physics") -> None:
    """Register ``loader`` (a callable or ``"module:function"``, following the loader contract above) under
    ``name`` in ``family`` (``"physics"`` or ``"data"``); replaces an existing entry."""
    if family not in FAMILIES:
        raise ValueError(f"family must be one of {FAMILIES}, got {family!r}")
    _REGISTRY[name] = SurrogateKind(name, family, loader)


def surrogate_kind(name: str) -> SurrogateKind:
    """The registered :class:`SurrogateKind` ``name``.

    Raises:
        ValueError: ``name`` is not registered (the message lists the registered names).
    """
    if name not in _REGISTRY:
        raise ValueError(f"unknown surrogate {name!r}; registered: {available_surrogates()} "
                         "(plus 'none' for the true simulator and 'gym_anm' for the original package)")
    return _REGISTRY[name]


def available_surrogates(family: str | None = None) -> list[str]:
    """Registered surrogate names, sorted; only those of ``family`` (``"physics"``, ``"data"``) when given."""
    if family is not None and family not in FAMILIES:
        raise ValueError(f"family must be one of {FAMILIES}, got {family!r}")
    return sorted(n for n, k in _REGISTRY.items() if family is None or k.family == family)


def data_driven_surrogates() -> tuple[str, ...]:
    """The data-driven surrogates in registration order (``lr``, ``dt``, ``rf``, ``xgb``, ``dnn``)."""
    return tuple(n for n, k in _REGISTRY.items() if k.family == "data")


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
    return surrogate_kind(name).load(sim=sim, device=device, **kwargs)
