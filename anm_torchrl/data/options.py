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


def check_fractions(fractions, name: str = "fractions") -> tuple[float, float, float]:
    """``fractions`` as three non-negative finite floats (train, validation, test) summing to 1 (within 1e-6);
    a ``ValueError`` naming ``name`` otherwise (they are never renormalised silently)."""
    try:
        f = tuple(float(x) for x in fractions if not isinstance(x, (bool, str, bytes)))
        ok = len(f) == len(list(fractions)) == 3
    except (TypeError, ValueError):
        ok = False
    if not ok or any(not math.isfinite(x) or x < 0 for x in f) or not math.isclose(sum(f), 1.0, abs_tol=1e-6):
        shown = list(fractions) if isinstance(fractions, Iterable) and not isinstance(fractions, str) else fractions
        raise ValueError(f"{name} must be three non-negative numbers (train, validation, test) summing to 1, "
                         f"got {shown!r}")
    return f
