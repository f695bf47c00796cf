"""Dataset options and their checks, without torch: what ``recipes/make_dataset.py`` checks before any heavy
import (:func:`anm_torchrl.training.config_checks.check_make_dataset_config`)."""

from __future__ import annotations

import math
from collections.abc import Iterable

DEFAULT_FRACTIONS = (0.8, 0.1, 0.1)  # train, validation, test shares of a dataset's units
WAYPOINT_DISTS = ("arcsine", "uniform")  # the Agent-based dataset's waypoint distributions
# fewest split units (rows, or the agent's envs) of a dataset: one each for train, validation and test, since an
# empty validation or test split gives a NaN R² and stops a DNN after one epoch on a validation MSE of 0
MIN_SPLIT_UNITS = 3


def check_split_units(value, name: str) -> None:
    """Refuse ``value`` (a dataset's ``size`` or ``num_envs``) below :data:`MIN_SPLIT_UNITS`, a ``ValueError``
    naming ``name`` and the minimum."""
    if value < MIN_SPLIT_UNITS:
        raise ValueError(f"{name} must be >= {MIN_SPLIT_UNITS} (at least one unit each for the train, validation and "
                         f"test splits), got {value!r}")


def check_agent_split(size: int, num_envs: int) -> None:
    """The agent dataset splits by env: ``size`` rows over ``num_envs`` envs take ceil(size / num_envs) steps each
    and fill ceil(size / steps) envs, which must be at least :data:`MIN_SPLIT_UNITS` (``size=4`` over 3 envs fills
    2). A ``ValueError`` naming both otherwise."""
    steps = -(-int(size) // int(num_envs))
    filled = -(-int(size) // steps)
    if filled < MIN_SPLIT_UNITS:
        raise ValueError(f"size={size} rows over agent.num_envs={num_envs} envs fill {filled} envs ({steps} steps "
                         f"each); the agent dataset splits by env and needs >= {MIN_SPLIT_UNITS}: raise size")


def check_fractions(fractions, name: str = "fractions") -> tuple[float, float, float]:
    """``fractions`` as three positive finite floats (train, validation, test) summing to 1 (within 1e-6); a
    ``ValueError`` naming ``name`` otherwise (they are never renormalised silently). A zero share would leave its split
    empty (see :data:`MIN_SPLIT_UNITS`): a DNN kept its first epoch, metrics came out null."""
    try:
        f = tuple(float(x) for x in fractions if not isinstance(x, (bool, str, bytes)))
        ok = len(f) == len(list(fractions)) == 3
    except (TypeError, ValueError):
        ok = False
    if not ok or any(not math.isfinite(x) or x <= 0 for x in f) or not math.isclose(sum(f), 1.0, abs_tol=1e-6):
        shown = list(fractions) if isinstance(fractions, Iterable) and not isinstance(fractions, str) else fractions
        raise ValueError(f"{name} must be three positive numbers (train, validation, test) summing to 1 (each split "
                         f"needs rows), got {shown!r}")
    return f
