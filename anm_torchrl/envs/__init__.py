"""TorchRL envs: the true simulator ``ANMEnv`` (any network), its ANM6-Easy preset ``ANM6Env``, and
``SurrogateEnv`` for any learned transition model."""

from anm_torchrl.envs.anm6 import ANM6Env
from anm_torchrl.envs.anm_env import ANMEnv
from anm_torchrl.envs.surrogate import SurrogateEnv

__all__ = ["ANMEnv", "ANM6Env", "SurrogateEnv"]
