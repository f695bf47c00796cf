"""Physics-informed surrogate of ANM6-Easy (paper §4.2): KKT-NNs → aggregation → power balance → next state.

* :mod:`.kkt` — generator and storage KKT-NNs; :mod:`.power_balance` — the power-balance PINN;
* :mod:`.losses` — KKT and power-flow losses from :mod:`anm_torchrl.grid.residuals`;
* :mod:`.presets` — training configuration, presets (YAML in ``surrogates/conf/pinn_preset``), design notes;
* :mod:`.model`, :mod:`.tasks`, :mod:`.loop` — the networks, what each is trained on, the training loop
  (physics alone); :mod:`.train` re-exports them;
* :mod:`.io` — the saved file (safetensors, hash-checked); :mod:`.cache` — the default cache and its rules;
* :mod:`.chain` — the ``TensorDictSequential`` surrogate; :mod:`.load` — :func:`load_pinn` (registry name
  ``"pinn"``), from a file or trained on first use;
* :mod:`.evaluate` — accuracy against the exact simulator (``python -m anm_torchrl.surrogates.pinn.evaluate``).

Names load on first use (:mod:`anm_torchrl.lazy`): :mod:`.presets` imports without torch.
"""

from anm_torchrl.lazy import lazy_exports

_HOMES = {"build_chain": "chain", "load_pinn": "load",
          **dict.fromkeys(["PINNTrainConfig", "preset", "save_pinn", "train_pinn"], "train")}
__all__ = sorted(_HOMES)
__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
