"""Registry of dataset kinds, keyed by the names users pass as ``dataset=``.

Entries are ``"module:function"`` generators ``generate(size, seed, sim=..., progress=..., **options) ->
(td, meta)`` imported lazily. Every list of dataset names in the package derives from :func:`available_datasets`.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

_REGISTRY: dict[str, str | Callable] = {
    "generative": "anm_torchrl.data.generative:generate_generative",
    "agent": "anm_torchrl.data.agent:generate_agent",
}


def register_dataset(name: str, generator: str | Callable) -> None:
    """Register a dataset generator (a callable or ``"module:function"``) under ``name``."""
    _REGISTRY[name] = generator


def available_datasets() -> tuple[str, ...]:
    """Registered dataset kinds, in registration order (``generative``, ``agent``)."""
    return tuple(_REGISTRY)


def dataset_generator(name: str) -> Callable:
    """The generator of dataset kind ``name``.

    Raises:
        ValueError: ``name`` is not registered (the message lists the registered kinds).
    """
    if name not in _REGISTRY:
        raise ValueError(f"dataset kind must be one of {list(_REGISTRY)}, got {name!r}")
    gen = _REGISTRY[name]
    if isinstance(gen, str):
        module, func = gen.split(":")
        gen = getattr(importlib.import_module(module), func)
    return gen
