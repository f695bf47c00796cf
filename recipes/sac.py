"""SAC on any registered network (default ANM6-Easy), trained on the true simulator or on any registered
surrogate, and evaluated on the true simulator.

    python recipes/sac.py                                   # true simulator, defaults in recipes/conf/sac.yaml
    python recipes/sac.py network=case33bw                  # its entry of recipes/conf/per_network/sac.yaml
    python recipes/sac.py checkpoint.resume=/abs/path/to/checkpoints/last.pt

Layout follows TorchRL's ``sota-implementations/sac/``: Collector -> replay buffer -> SACLoss (twin Q, Polyak
targets, learned temperature) -> Adam (:mod:`anm_torchrl.training.algorithms.sac`), inside the training protocol
every algorithm shares (:mod:`anm_torchrl.training.protocol`): the same run directory (``logs/``,
``checkpoints/{best,last}.pt``, ``summary.json``), validation/test states and budget keys as ``recipes/ppo.py``.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from anm_torchrl.training.recipe_help import register as register_help

register_help()  # --help lists only this recipe's config groups


@hydra.main(config_path="conf", config_name="sac", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    """:func:`anm_torchrl.training.protocol.run_recipe` with the SAC config."""
    from anm_torchrl.training.protocol import run_recipe

    return run_recipe(cfg)


if __name__ == "__main__":
    main()
