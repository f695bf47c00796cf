"""Datasets of simulator transitions for the data-driven surrogates: Generative (Sobol) and Agent-based.

``python recipes/make_dataset.py dataset=generative|agent size=100000 seed=0 [network=case33bw]`` writes one to
:func:`default_dataset_dir` (``anm_torchrl.paths.dataset_dir(kind, size, seed)``, suffixed with the network key
on networks other than ANM6-Easy and with the simulator fingerprint on profiles other than the shipped ones);
:func:`load_dataset` opens and checks it.
"""

from __future__ import annotations

from anm_torchrl.lazy import lazy_exports

# each public name and its home module; imported on first use, so that light submodules (``options``,
# ``registry``) and the recipes' config checks do not pay for torch and tensordict (PEP 562)
_HOMES = {
    **dict.fromkeys(["default_dataset_dir", "ensure_dataset", "generate", "make_dataset"], "api"),
    **dict.fromkeys(["WaypointAgent", "generate_agent"], "agent"),
    **dict.fromkeys(["generate_generative"], "generative"),
    **dict.fromkeys(["for_dataset", "for_network"], "generic"),
    **dict.fromkeys(["available_datasets", "register_dataset"], "registry"),
    **dict.fromkeys(["KINDS", "SPLITS", "DatasetError", "checksum", "load_dataset", "read_meta", "save_dataset",
                     "split"], "storage"),
}
__all__ = sorted(_HOMES)
__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
