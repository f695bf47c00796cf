"""The experiments ``recipes/reproduce.py`` runs, by name, all behind one signature.

Every experiment is a function ``run(cfg, ctx) -> record``: ``cfg`` is its section of the preset
(``preset.<name>``), ``ctx`` the :class:`~anm_torchrl.experiments.common.RunContext` of the run (run directory,
surrogates, seeds, threads); the record (:func:`~anm_torchrl.experiments.io.result`) is written as
``<out_dir>/<name>.json``. An experiment reports what it cannot measure (a missing surrogate, optional package or
trained file) as status "not available" or "partial" in its record; any other error is a bug and propagates.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

from anm_torchrl.experiments import (accuracy, adaptability, heldout_returns, payoff, pinn_losses, ppo_curves,
                                     rollout_error, speed, sweep)
from anm_torchrl.experiments.common import RunContext

Experiment = Callable[[dict[str, Any], RunContext], dict]


@dataclasses.dataclass(frozen=True)
class Entry:
    """One experiment: its ``run``, what it measures (one line) and its study (the folder ``results/<study>/``
    its published record lives in)."""

    run: Experiment
    measures: str
    study: str = "reproduction"


# name (record file and preset key) -> entry; in the order of the paper's figures, then beyond it
EXPERIMENTS: dict[str, Entry] = {
    "pinn_losses": Entry(pinn_losses.run, "Fig. 5: the PINN's training losses, read from its TensorBoard run"),
    "speed": Entry(speed.run, "Fig. 6: seconds per transition of gym-anm, the true env and every surrogate"),
    "accuracy": Entry(accuracy.run, "Fig. 7: one-step accuracy of the data-driven surrogates (their training metrics)"),
    "rollout_error": Entry(rollout_error.run, "Figs. 8-9: one-step and episode errors of every surrogate along "
                           "expert and random rollouts"),
    "adaptability": Entry(adaptability.run, "the surrogates on scaled or shifted load and renewable series"),
    "sweep": Entry(sweep.run, "Figs. 10-11: PPO on a surrogate over n_envs x buffer"),
    "ppo_curves": Entry(ppo_curves.run, "Fig. 12: PPO training curves on the true env, gym-anm and every surrogate"),
    "test_returns": Entry(heldout_returns.run, "README's PPO table: returns on the held-out test states, PPO and "
                          "the baselines"),
    "payoff": Entry(payoff.run, "issue 13: when does a surrogate pay off (cost, accuracy and PPO time against bus "
                    "count)", study="payoff"),
}


def get(name: str) -> Experiment:
    """The ``run`` function of experiment ``name``.

    Raises:
        ValueError: ``name`` is not in :data:`EXPERIMENTS`.
    """
    if name not in EXPERIMENTS:
        raise ValueError(f"unknown experiment {name!r}; expected one of {list(EXPERIMENTS)}")
    return EXPERIMENTS[name].run
