"""Baseline policies for ANM6-Easy: do-nothing, uniform random and gym-anm's MPC DC-OPF (spec §7.1)."""

from anm_torchrl.baselines.mpc import DEFAULT_HORIZON, DEFAULT_SAFETY_MARGIN, MPCPolicy
from anm_torchrl.baselines.simple import DoNothingPolicy, RandomPolicy, make_baseline

__all__ = ["DEFAULT_HORIZON", "DEFAULT_SAFETY_MARGIN", "DoNothingPolicy", "MPCPolicy", "RandomPolicy",
           "make_baseline"]
