"""Baseline policies: do-nothing, uniform random, gym-anm's MPC DC-OPF (spec §7.1), the perfect-foresight AC
optimum and AC-MPC (CasADi + IPOPT; imported on use: :func:`make_baseline`). Names load on first use
(:mod:`anm_torchrl.lazy`): :mod:`.names` imports without torch."""

from anm_torchrl.lazy import lazy_exports

_HOMES = {
    **dict.fromkeys(["DEFAULT_HORIZON", "DEFAULT_SAFETY_MARGIN", "MPCPolicy"], "mpc"),
    **dict.fromkeys(["DoNothingPolicy", "RandomPolicy", "make_baseline"], "simple"),
    "available_baselines": "names",
}
__all__ = sorted(_HOMES)
__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
