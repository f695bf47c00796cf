"""PPO on any registered network (default ANM6-Easy), trained on the true simulator, on gym-anm itself or on any
registered surrogate, and evaluated on the true simulator.

    python recipes/ppo.py                                   # true simulator, defaults in recipes/conf/config.yaml
    python recipes/ppo.py surrogate=pinn seed=1
    python recipes/ppo.py env.num_envs=64 collector.frames_per_batch=2048 collector.total_frames=100_000
    python recipes/ppo.py checkpoint.resume=/abs/path/to/checkpoints/last.pt
    python recipes/ppo.py -m surrogate=none,pinn seed=0,1,2  # Hydra multirun (basic launcher)

Layout follows TorchRL's ``sota-implementations/ppo/ppo_mujoco.py``: Collector -> GAE (recomputed every epoch)
-> minibatches without replacement -> ClipPPOLoss -> Adam (:mod:`anm_torchrl.training.algorithms.ppo`), inside
the training protocol every algorithm shares (:mod:`anm_torchrl.training.protocol`). The run directory (Hydra,
``hydra.job.chdir``) holds ``logs/`` (TensorBoard or CSV), ``checkpoints/{best,last}.pt`` and ``summary.json``.
See recipes/README.md for the logged tags.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from anm_torchrl.training.recipe_help import register as register_help

register_help()  # --help lists only this recipe's config groups


@hydra.main(config_path="conf", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    """:func:`anm_torchrl.training.protocol.run_recipe` with the PPO config."""
    from anm_torchrl.training.protocol import run_recipe

    return run_recipe(cfg)


if __name__ == "__main__":
    main()
