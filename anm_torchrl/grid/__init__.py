"""Pure batched torch physics of gym-anm networks (float64, no TorchRL)."""

from anm_torchrl.grid.simulator import GridSimulator, Transition, anm6_easy_simulator

__all__ = ["GridSimulator", "Transition", "anm6_easy_simulator"]
