"""Learned transition models of ANM6-Easy: the PINN chain and data-driven regressors, behind one registry."""

from anm_torchrl.surrogates.registry import (available_surrogates, data_driven_surrogates, load_surrogate,
                                             register_surrogate)

__all__ = ["available_surrogates", "data_driven_surrogates", "load_surrogate", "register_surrogate"]
