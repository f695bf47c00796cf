"""SHAC on any registered network (default ANM6-Easy): the actor is trained by backpropagating short-horizon
returns through a differentiable grid model (the exact simulator's gradients, or the PINN chain), with a learned
value for the tail, and evaluated on the true simulator.

    python recipes/shac.py                                  # model=exact, defaults in recipes/conf/shac.yaml
    python recipes/shac.py model=pinn                       # through the cached PINN surrogate
    python recipes/shac.py network=case33bw loss.horizon=16

:mod:`anm_torchrl.training.algorithms.shac` inside the training protocol every algorithm shares
(:mod:`anm_torchrl.training.protocol`): the same run directory (``logs/``, ``checkpoints/{best,last}.pt``,
``summary.json``) and validation/test states as ``recipes/ppo.py``; ``collector.total_frames`` counts model frames.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from anm_torchrl.training.recipe_help import register as register_help

register_help()  # --help lists only this recipe's config groups


@hydra.main(config_path="conf", config_name="shac", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    """:func:`anm_torchrl.training.protocol.run_recipe` with the SHAC config."""
    from anm_torchrl.training.protocol import run_recipe

    return run_recipe(cfg)


if __name__ == "__main__":
    main()
