"""Baseline policies: do-nothing, uniform random, gym-anm's MPC DC-OPF (spec §7.1), the perfect-foresight AC
optimum and AC-MPC (CasADi + IPOPT; imported on use: :func:`make_baseline`)."""

from anm_torchrl.baselines.mpc import DEFAULT_HORIZON, DEFAULT_SAFETY_MARGIN, MPCPolicy
from anm_torchrl.baselines.simple import DoNothingPolicy, RandomPolicy, available_baselines, make_baseline

__all__ = ["DEFAULT_HORIZON", "DEFAULT_SAFETY_MARGIN", "DoNothingPolicy", "MPCPolicy", "RandomPolicy",
           "available_baselines", "make_baseline"]
