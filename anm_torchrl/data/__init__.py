"""Datasets of simulator transitions for the data-driven surrogates: Generative (Sobol) and Agent-based.

``python recipes/make_dataset.py dataset=generative|agent size=100000 seed=0 [network=case33bw]`` writes one to
:func:`default_dataset_dir` (``anm_torchrl.paths.dataset_dir(kind, size, seed)``, suffixed with the network key
on networks other than ANM6-Easy); :func:`load_dataset` opens and checks it.
"""

from __future__ import annotations

import importlib
from typing import Any

# each public name and its home module; imported on first use, so that light submodules (``options``,
# ``registry``) and the recipes' config checks do not pay for torch and tensordict (PEP 562)
_HOMES = {
    **dict.fromkeys(["default_dataset_dir", "ensure_dataset", "generate", "make_dataset"], "api"),
    **dict.fromkeys(["WaypointAgent", "generate_agent"], "agent"),
    **dict.fromkeys(["generate_generative"], "generative"),
    **dict.fromkeys(["for_network"], "generic"),
    **dict.fromkeys(["available_datasets", "register_dataset"], "registry"),
    **dict.fromkeys(["KINDS", "SPLITS", "DatasetError", "checksum", "load_dataset", "read_meta", "save_dataset",
                     "split"], "storage"),
}
__all__ = sorted(_HOMES)


def __getattr__(name: str) -> Any:
    if name not in _HOMES:
        raise AttributeError(f"module 'anm_torchrl.data' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"anm_torchrl.data.{_HOMES[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_HOMES])
