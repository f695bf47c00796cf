"""The default dataset of each kind: what ``recipes/make_dataset.py`` makes with no options, for library callers.

A surrogate trained on first use (``make_env("xgb", network=...)``) is trained on the dataset the recipe would
make, at the path the recipe would write it to (:func:`anm_torchrl.data.default_dataset_dir`), so the two never
make two different datasets under one name. ``recipes/conf/make_dataset.yaml`` is the user-facing home of these
values; ``tests/test_surrogates_generic.py`` checks that this mirror agrees with it key by key.
"""

from __future__ import annotations

from typing import Any

from anm_torchrl.data.options import DEFAULT_FRACTIONS  # its one home (train, validation, test shares)

__all__ = ["DEFAULT_FRACTIONS", "DEFAULT_OPTIONS", "DEFAULT_SEED", "DEFAULT_SIZE"]  # DEFAULT_FRACTIONS: re-exported

DEFAULT_SIZE = 100_000  # rows (train + validation + test)
DEFAULT_SEED = 0
#: per-kind generator options (keyword arguments of :func:`anm_torchrl.data.generate`)
DEFAULT_OPTIONS: dict[str, dict[str, Any]] = {
    "generative": {"chunk": 8192},
    "agent": {"num_envs": 200, "waypoint_every": 8, "random_every": True, "waypoints": "arcsine",
              "max_episode_steps": 480},
}
