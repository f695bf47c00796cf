"""The baselines' names: what :func:`~anm_torchrl.baselines.simple.make_baseline` accepts, importable without torch
(the recipes check ``policy=`` before anything heavy)."""

from __future__ import annotations

BASELINES = ("do_nothing", "random", "mpc_perfect", "mpc_constant", "optimal", "acmpc")


def available_baselines() -> tuple[str, ...]:
    """Names :func:`~anm_torchrl.baselines.simple.make_baseline` accepts (the registry's list; do not re-type it)."""
    return BASELINES
