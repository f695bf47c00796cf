"""Learned transition models of ANM6-Easy: the PINN chain and data-driven regressors, behind one registry."""

from anm_torchrl.surrogates.registry import (SurrogateKind, available_surrogates, data_driven_surrogates,
                                             load_surrogate, register_surrogate, surrogate_kind)

__all__ = ["SurrogateKind", "available_surrogates", "data_driven_surrogates", "load_surrogate", "register_surrogate",
           "surrogate_kind"]
