"""Default hyper-parameters of the surrogates, one home each (YAML, read by Python and by the Hydra recipes).

``pinn_preset/*.yaml`` (:mod:`anm_torchrl.surrogates.pinn.presets`), ``models/default.yaml``
(:mod:`anm_torchrl.surrogates.regressors.defaults`), ``terminal/default.yaml``
(:mod:`anm_torchrl.surrogates.terminal`). The recipes add this package to Hydra's search path
(``hydra.searchpath: [pkg://anm_torchrl.surrogates.conf]``), so ``pinn_preset=paper`` or
``models.rf.n_estimators=32`` override these files and nothing is typed twice.
"""

from __future__ import annotations

from importlib import resources
from typing import Any

import yaml


def load_defaults(name: str) -> dict[str, Any]:
    """The YAML file ``<name>.yaml`` of this package as a dict, e.g. ``load_defaults("models/default")``."""
    f = resources.files(__name__).joinpath(*f"{name}.yaml".split("/"))
    return yaml.safe_load(f.read_text())
