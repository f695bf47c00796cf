"""PPO on ANM6-Easy, trained on the true simulator, on gym-anm itself or on any registered surrogate, and
evaluated on the true simulator after every update.

    python recipes/ppo.py                                   # true simulator, defaults in recipes/conf/
    python recipes/ppo.py surrogate=pinn seed=1
    python recipes/ppo.py env.num_envs=64 collector.frames_per_batch=2048 collector.total_frames=100_000
    python recipes/ppo.py checkpoint.resume=/abs/path/to/checkpoints/last.pt
    python recipes/ppo.py -m surrogate=none,pinn seed=0,1,2  # Hydra multirun (basic launcher)

Layout follows TorchRL's ``sota-implementations/ppo/ppo_mujoco.py``: Collector -> GAE (recomputed every epoch)
-> TensorDictReplayBuffer(SamplerWithoutReplacement) -> ClipPPOLoss -> Adam. The run directory (Hydra,
``hydra.job.chdir``) holds ``logs/`` (TensorBoard or CSV), ``checkpoints/{best,last}.pt`` and ``summary.json``.
See recipes/README.md for the logged tags.
"""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from anm_torchrl.training.ppo_loop import train_ppo
from anm_torchrl.training.recipe_help import register as register_help

register_help()  # --help lists only this recipe's config groups


@hydra.main(config_path="conf", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    """Train into the Hydra run directory (the working directory, ``hydra.job.chdir``); the loop is
    :func:`anm_torchrl.training.ppo_loop.train_ppo`, which the experiments call too. Prints the run directory when
    the run ends (finished, failed or interrupted); Ctrl-C exits with status 130 after ``summary.json`` is written
    with ``"interrupted": true``."""
    if cfg.checkpoint.resume:  # relative to where the command was typed, not to the run directory
        cfg.checkpoint.resume = hydra.utils.to_absolute_path(str(cfg.checkpoint.resume))
    run_dir = Path.cwd()
    try:
        return train_ppo(cfg, run_dir)
    except KeyboardInterrupt:
        raise SystemExit(130) from None
    finally:
        print(f"run directory: {run_dir}", flush=True)


if __name__ == "__main__":
    main()
