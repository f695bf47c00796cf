"""The experiments ``recipes/reproduce.py`` runs, by name, all behind one signature.

Every experiment is a function ``run(cfg, ctx) -> record``: ``cfg`` is its section of the preset
(``preset.<name>``), ``ctx`` the :class:`~anm_torchrl.experiments.common.RunContext` of the run (run directory,
surrogates, seeds, threads); the record (:func:`~anm_torchrl.experiments.io.result`) is written as
``<out_dir>/<name>.json``. An experiment reports what it cannot measure (a missing surrogate, optional package or
trained file) as status "not available" or "partial" in its record; any other error is a bug and propagates.
"""

from __future__ import annotations

import dataclasses
import importlib
from typing import TYPE_CHECKING, Any, Callable

if TYPE_CHECKING:
    from anm_torchrl.experiments.common import RunContext

Experiment = Callable[[dict[str, Any], "RunContext"], dict]


@dataclasses.dataclass(frozen=True)
class Entry:
    """One experiment: its module (``anm_torchrl.experiments.<module>``, whose ``run`` is imported on first use,
    so that checking a preset's names costs no torch import), what it measures (one line) and its study (the folder
    ``results/<study>/`` its published record lives in)."""

    module: str
    measures: str
    study: str = "reproduction"

    @property
    def run(self) -> Experiment:
        return importlib.import_module(f"anm_torchrl.experiments.{self.module}").run


# name (record file and preset key) -> entry; in the order of the paper's figures, then beyond it
EXPERIMENTS: dict[str, Entry] = {
    "pinn_losses": Entry("pinn_losses", "Fig. 5: the PINN's training losses, read from its TensorBoard run"),
    "speed": Entry("speed", "Fig. 6: seconds per transition of gym-anm, the true env and every surrogate"),
    "accuracy": Entry("accuracy", "Fig. 7: one-step accuracy of the data-driven surrogates (their training metrics)"),
    "rollout_error": Entry("rollout_error", "Figs. 8-9: one-step and episode errors of every surrogate along "
                           "expert and random rollouts"),
    "adaptability": Entry("adaptability", "the surrogates on scaled or shifted load and renewable series"),
    "sweep": Entry("sweep", "Figs. 10-11: PPO on a surrogate over n_envs x buffer"),
    "ppo_curves": Entry("ppo_curves", "Fig. 12: PPO training curves on the true env, gym-anm and every surrogate"),
    "test_returns": Entry("heldout_returns", "README's PPO table: returns on the held-out test states, PPO and "
                          "the baselines"),
    "payoff": Entry("payoff", "issue 13: when does a surrogate pay off (cost, accuracy and PPO time against bus "
                    "count)", study="payoff"),
}


def check(name: str) -> None:
    """Raise ``ValueError`` unless ``name`` is in :data:`EXPERIMENTS` (nothing is imported)."""
    if name not in EXPERIMENTS:
        raise ValueError(f"unknown experiment {name!r}; expected one of {list(EXPERIMENTS)}")


#: preset entries that count something (at least 1) or last a time (seconds, more than 0), in any experiment's
#: section; recipe keys (``base``, ``per_env``) and baseline options are checked where they are used
COUNTS = ("n_transitions", "gym_steps", "repeats", "episodes", "steps", "test_episodes", "max_steps", "last_k",
          "batch_sizes", "n_envs", "buffer")
DURATIONS = ("timeout_s", "baseline_budget_s", "expert_budget_s")


def check_section(name: str, section: Any) -> None:
    """Raise ``ValueError`` naming ``preset.<name>.<key>`` for a count below 1 or a duration not above 0 in an
    experiment's preset section (they failed only after the run had started, e.g. ``repeats=-1``: no median)."""
    if not isinstance(section, dict):
        return
    for key, value in section.items():
        values = value if isinstance(value, list) else [value]
        if value is None or key not in COUNTS + DURATIONS:
            continue
        for v in values:
            ok = (isinstance(v, int) and not isinstance(v, bool) and v >= 1 if key in COUNTS
                  else isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0)
            if not ok:
                what = "an integer >= 1 (or a list of them)" if key in COUNTS else "a number of seconds > 0"
                raise ValueError(f"preset.{name}.{key} must be {what}, got {value!r}")


def get(name: str) -> Experiment:
    """The ``run`` function of experiment ``name``.

    Raises:
        ValueError: ``name`` is not in :data:`EXPERIMENTS`.
    """
    check(name)
    return EXPERIMENTS[name].run
