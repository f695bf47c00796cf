"""TorchRL envs: the true simulator ``ANM6Env`` and ``SurrogateEnv`` for any learned transition model."""

from anm_torchrl.envs.anm6 import ANM6Env
from anm_torchrl.envs.surrogate import SurrogateEnv

__all__ = ["ANM6Env", "SurrogateEnv"]
