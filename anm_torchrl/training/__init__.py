"""Factories for recipes: envs, PPO models, checkpoints (the evaluation protocol is :mod:`anm_torchrl.evaluation`)."""

from anm_torchrl.training.checkpoint import load_checkpoint, save_checkpoint
from anm_torchrl.training.factory import make_env
from anm_torchrl.training.ppo_models import make_ppo_models

__all__ = ["load_checkpoint", "make_env", "make_ppo_models", "save_checkpoint"]
