"""Factories for recipes: envs, PPO models, evaluation."""

from anm_torchrl.training.factory import make_env

__all__ = ["make_env"]
