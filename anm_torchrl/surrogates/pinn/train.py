"""Training the PINN from physics alone: one import point for the pieces, split by job.

* :mod:`.presets` — :class:`ModuleTrainConfig`, :class:`PINNTrainConfig`, the presets and the design notes;
* :mod:`.model` — :func:`build_modules`; :mod:`.tasks` — per-module Sobol boxes, losses, validation errors;
* :mod:`.loop` — :func:`train_module`, :func:`train_pinn`; :mod:`.io` — the saved file.
"""

from anm_torchrl.surrogates.pinn.io import FILE_NAME, KIND, load_modules, read_pinn_file, resolve_path, save_pinn
from anm_torchrl.surrogates.pinn.loop import train_module, train_pinn
from anm_torchrl.surrogates.pinn.model import build_modules
from anm_torchrl.surrogates.pinn.presets import (FEEDER_DEFAULT, MODULES, PRESETS, ModuleTrainConfig,
                                                 PINNTrainConfig, check_acceptance, from_composed, module_seed,
                                                 network_preset_name, overrides_of, preset, preset_for, preset_keys,
                                                 preset_names)
from anm_torchrl.surrogates.pinn.tasks import TASKS

__all__ = ["FEEDER_DEFAULT", "FILE_NAME", "KIND", "MODULES", "PRESETS", "TASKS", "ModuleTrainConfig",
           "PINNTrainConfig", "build_modules", "check_acceptance", "from_composed", "load_modules", "module_seed",
           "network_preset_name", "overrides_of", "preset", "preset_for", "preset_keys", "preset_names",
           "read_pinn_file", "resolve_path", "save_pinn", "train_module", "train_pinn"]
