"""Factories for recipes: envs, PPO models, evaluation, checkpoints."""

from anm_torchrl.training.checkpoint import load_checkpoint, save_checkpoint
from anm_torchrl.training.evaluation import draw_initial_states, evaluate_policy
from anm_torchrl.training.factory import make_env
from anm_torchrl.training.models import make_ppo_models

__all__ = ["draw_initial_states", "evaluate_policy", "load_checkpoint", "make_env", "make_ppo_models",
           "save_checkpoint"]
