"""Training: ``make_env``, the protocol every algorithm shares, the algorithms, models, checkpoints.

Names are imported on first use (module ``__getattr__``), so a config check (``training.config_checks``) does not
pay for torch's import.
"""

from __future__ import annotations

from anm_torchrl.lazy import lazy_exports

_EXPORTS = {
    "load_checkpoint": "anm_torchrl.training.checkpoint",
    "save_checkpoint": "anm_torchrl.training.checkpoint",
    "load_actor": "anm_torchrl.training.checkpoint",
    "make_env": "anm_torchrl.training.factory",
    "make_ppo_models": "anm_torchrl.training.models",
    "make_sac_models": "anm_torchrl.training.models",
    "train": "anm_torchrl.training.protocol",
}
__all__ = sorted(_EXPORTS)


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
