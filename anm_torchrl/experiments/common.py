"""Shared helpers of the experiments: surrogate specs, availability checks, building envs on a given simulator.

A *surrogate spec* is a dict ``{"name": "xgb", "dataset": "agent", "path": None}`` (the keys ``make_env`` takes);
its label is ``name`` or ``name_dataset``. A surrogate whose code or trained artifact is missing is reported as
"not available" with the error message, never raised, so every experiment finishes.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict

log = logging.getLogger(__name__)

TRUE_ENV = "none"


@dataclasses.dataclass(frozen=True)
class RunContext:
    """What a reproduction run gives every experiment, besides the experiment's own config section.

    Every experiment is ``run(cfg: dict, ctx: RunContext) -> dict`` (a record of :func:`.io.result`), listed in
    :data:`anm_torchrl.experiments.registry.EXPERIMENTS`.

    Attributes:
        out_dir: the run directory (PPO runs and other artifacts go under it).
        surrogates: the preset's surrogate specs (the PINN's with the path this run resolved).
        seed: the run's seed.
        seeds: the PPO seeds of the experiments that train once per seed (``ppo_curves``).
        threads: ``torch.set_num_threads`` of the PPO runs the experiments start.
        pinn_logs: folders where the PINN's TensorBoard losses may be (``pinn_losses``), first match wins.
        surrogate_train_s: label -> CPU seconds this run spent training that surrogate (claim 2's time to return).
    """

    out_dir: Path
    surrogates: tuple[dict, ...] = ()
    seed: int = 0
    seeds: tuple[int, ...] = (0,)
    threads: int = 1
    pinn_logs: tuple[Path | None, ...] = ()
    surrogate_train_s: dict[str, float] = dataclasses.field(default_factory=dict)


def label(spec: dict[str, Any] | str) -> str:
    """``"pinn"``, ``"xgb_agent"``… for a surrogate spec (or a bare name)."""
    if isinstance(spec, str):
        return spec
    ds = spec.get("dataset")
    return f"{spec['name']}_{ds}" if ds else str(spec["name"])


def options(spec: dict[str, Any] | str) -> dict[str, Any]:
    """The keyword arguments of ``make_env`` / the loader for a spec (``name`` removed, ``None`` values dropped).

    A data-driven surrogate is not trained on first use in an experiment (``train_if_missing=False`` unless the spec
    says otherwise): a missing model is a row "not available", with its reason, never minutes of hidden training."""
    from anm_torchrl.surrogates import data_driven_surrogates

    name = spec if isinstance(spec, str) else spec["name"]
    base = {"train_if_missing": False} if name in data_driven_surrogates() else {}
    if isinstance(spec, str):
        return base
    return {**base, **{k: v for k, v in spec.items() if k != "name" and v is not None}}


def make_env_or_reason(spec: dict[str, Any] | str, num_envs: int, seed: int = 0, sim=None, **kw):
    """``(env, None)`` or ``(None, "reason")`` for a spec; with ``sim``, the env runs on that simulator.

    With a custom ``sim`` the surrogate model is loaded through the registry for that simulator and wrapped in a
    ``SurrogateEnv`` on it, so every model sees the changed time series (see :func:`load_model_on`).
    """
    name = spec if isinstance(spec, str) else spec["name"]
    try:
        if sim is None:
            from anm_torchrl.training.factory import make_env

            return make_env(name, num_envs=num_envs, seed=seed, action_mode="clip", **options(spec), **kw), None
        from anm_torchrl.envs import ANM6Env, SurrogateEnv

        if name == TRUE_ENV:
            return ANM6Env(num_envs, seed=seed, action_mode="clip", sim=sim, **kw), None
        model = load_model_on(spec, sim)
        return SurrogateEnv(model, num_envs, seed=seed, action_mode="clip", sim=sim, **kw), None
    except Exception as err:  # noqa: BLE001 - any failure means "not available" here
        log.info("%s not available: %s", label(spec), err)
        return None, f"{type(err).__name__}: {err}"


def load_model_on(spec: dict[str, Any], sim) -> Any:
    """A surrogate's transition model built for the simulator ``sim`` (its loads, potentials and time series).

    The registry's loaders take the simulator explicitly (``load_surrogate(kind, sim=..., ...)``); a loader that
    cannot honour ``sim`` raises, and the surrogate is then reported "not available" by the caller.
    """
    from anm_torchrl.surrogates import load_surrogate

    return load_surrogate(spec["name"], sim=sim, **options(spec))


def set_state_and_step(env, state: torch.Tensor, action: torch.Tensor) -> TensorDict:
    """Put every env of the batch in ``state`` (N, 18) and take ``action`` (N, 6); returns the ``next`` TD."""
    from anm_torchrl.evaluation import reset_to

    td = reset_to(env, state)
    td.set("action", action.to(torch.float32))
    return env.step(td).get("next")


