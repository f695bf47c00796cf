"""Learned transition models of ANM6-Easy: the PINN chain and data-driven regressors, behind one registry.

Names load on first use (:mod:`anm_torchrl.lazy`), so light submodules (presets, request checks) import without
torch."""

from anm_torchrl.lazy import lazy_exports

__all__ = ["SurrogateKind", "available_surrogates", "data_driven_surrogates", "load_surrogate", "register_surrogate",
           "surrogate_kind"]
__getattr__, __dir__ = lazy_exports(__name__, dict.fromkeys(__all__, "registry"))
