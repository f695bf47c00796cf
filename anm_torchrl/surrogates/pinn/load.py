"""``load_pinn``: the PINN surrogate chain of a network, from a saved file or trained (and cached) on first use.

Above :mod:`.chain` (the model), :mod:`.cache` and :mod:`.train` (the training): the one module that needs both,
so neither imports the other. Registry name ``"pinn"`` (:mod:`anm_torchrl.surrogates.registry`).
"""

from __future__ import annotations

import inspect
import logging
from pathlib import Path

import torch
from tensordict.nn import TensorDictSequential

from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.surrogates.pinn import cache
from anm_torchrl.surrogates.pinn import train as tr
from anm_torchrl.surrogates.pinn.chain import (DEFAULT_RESIDUAL_THRESHOLD, DEFAULT_V_RANGE, TERMINALS, PhysicsTerminal,
                                               build_chain)
from anm_torchrl.surrogates.pinn.presets import MODULES

log = logging.getLogger(__name__)


def check_pinn_options(terminal: str = "physics", classifier_path=None, residual_threshold: float | None = None,
                       v_range: tuple[float, float] | None = None, **options) -> None:
    """Refuse, before any work, options :func:`load_pinn` would refuse (a recipe's ``surrogate=pinn`` keys): an
    unknown key, a bad ``terminal``, a classifier terminal without its folder, a bad threshold or voltage range
    (``options``: load_pinn's others, checked by name).

    Raises:
        ValueError: naming the option.
    """
    unknown = sorted(set(options) - set(inspect.signature(load_pinn).parameters))
    if unknown:
        raise ValueError(f"{unknown[0]!r} is not an option of the PINN surrogate (load_pinn takes "
                         f"{', '.join(inspect.signature(load_pinn).parameters)})")
    if terminal not in TERMINALS:
        raise ValueError(f"terminal must be one of {TERMINALS}, got {terminal!r}")
    if terminal == "classifier" and classifier_path is None:
        raise ValueError("terminal='classifier' needs classifier_path (a folder saved by TerminalClassifier)")
    PhysicsTerminal(DEFAULT_RESIDUAL_THRESHOLD if residual_threshold is None else residual_threshold,
                    DEFAULT_V_RANGE if v_range is None else v_range)


def load_pinn(sim: GridSimulator | None = None, device=None, path: str | Path | None = None,
              terminal: str = "physics", classifier_path: str | Path | None = None,
              residual_threshold: float | None = None, v_range: tuple[float, float] | None = None,
              train_if_missing: bool | None = None, preset: str = "default", overwrite_cache: bool = False,
              progress: bool = True, log_dir: str | Path | None = None, seed: int = 0,
              duals: bool = False) -> TensorDictSequential:
    """The PINN surrogate chain on ``sim``, loaded from ``path`` or trained (and cached) on first use.

    The chain reads everything exogenous — loads and renewable potentials of the next step — from ``sim``'s
    profiles, so a simulator with scaled or shifted profiles gets a chain that follows them. Its network
    (tables, not profiles) must be the one the saved model was trained on.

    Args:
        sim: the simulator (network, profiles, constants) the chain runs on; default ANM6-Easy on ``device``.
        device: torch device; with ``sim`` given it must be ``sim``'s device (or None).
        path: a saved file or a folder holding ``pinn.safetensors``; default the network's cache
            (:func:`.cache.default_path`).
        terminal: ``"physics"`` (default, needs no data) or ``"classifier"`` (needs ``classifier_path``).
        classifier_path: folder of a ``TerminalClassifier`` (``anm_torchrl.surrogates.terminal``), loaded on ``sim``.
        residual_threshold, v_range: of the physics terminal check (validated: finite, threshold > 0); None:
            :data:`DEFAULT_RESIDUAL_THRESHOLD` (p.u.) and :data:`DEFAULT_V_RANGE` (p.u.), their one home.
        train_if_missing: train when nothing is saved there; default True for the default cache and False for
            an explicit ``path`` (a mistyped path is an error, not a multi-minute training).
        preset: training preset used when training (``default``, ``paper``, ``smoke``...; ``default`` is the
            feeder preset on a network other than ANM6-Easy: :func:`.presets.network_preset_name`).
        overwrite_cache: let a training without (or failing) its acceptance bar replace the default cache.
        progress: show a tqdm bar while training.
        log_dir: TensorBoard folder for that training (default ``<folder>/tb``).
        seed: training seed.
        duals: the chain also writes the KKT-NNs' multipliers (:func:`.chain.build_chain`).

    Raises:
        ValueError: bad ``terminal`` / threshold / ``v_range`` / device, or a file that is not a PINN file,
            corrupted, or trained on another network (``ArtifactError``).
        FileNotFoundError: nothing at ``path`` and training not requested.
        CacheRejectedError: a training for the default cache failed its acceptance bar.
    """
    check_pinn_options(terminal, classifier_path, residual_threshold, v_range)  # before any work
    residual_threshold = DEFAULT_RESIDUAL_THRESHOLD if residual_threshold is None else residual_threshold
    v_range = DEFAULT_V_RANGE if v_range is None else v_range
    if sim is None:
        sim = network_simulator(ANM6_EASY, device=device if device is not None else "cpu")
    elif device is not None and torch.device(device) != sim.net.dev.device:
        raise ValueError(f"device={device!r} differs from the simulator's device {sim.net.dev.device}; pass one")
    classifier = None
    if terminal == "classifier":
        from anm_torchrl.surrogates.terminal import TerminalClassifier

        classifier = TerminalClassifier.load(classifier_path, sim=sim)
    file = tr.resolve_path(path) if path is not None else cache.default_path(sim)
    if not file.is_file():
        train = train_if_missing if train_if_missing is not None else path is None
        if not train:
            raise FileNotFoundError(f"no trained PINN at {file}; train one with: python recipes/train_pinn.py "
                                    f"network=<this network> path={file} (or pass train_if_missing=True)")
        preset = tr.network_preset_name(preset, sim)
        cfg = tr.preset(preset, seed=seed)
        log.warning("no trained PINN at %s: training the %r preset from physics alone, %d Adam steps in 3 stages "
                    "(ANM6-Easy's default: ~1.5 min on a free 2-core CPU, ~2.5 min in one process; the stages are "
                    "logged at INFO)", file, preset, sum(getattr(cfg, m).max_steps for m in MODULES))
        cache.train_and_save(cfg, sim, path=file, overwrite_cache=overwrite_cache,
                             log_dir=log_dir if log_dir is not None else file.parent / "tb", progress=progress)
    modules, _, report = tr.load_modules(file, sim)
    if report.get("accepted") is False:  # e.g. a smoke preset given by path: say so here, naming the file
        failures = list(report.get("acceptance_failures") or [])
        log.warning("the PINN at %s failed its acceptance bar when it was trained (%s%s): a policy trained on it "
                    "learns from an inaccurate model; train one with python recipes/train_pinn.py (default preset)",
                    file, "; ".join(map(str, failures[:3])) or "no bar", " ..." if len(failures) > 3 else "")
    return build_chain(sim, modules["generator"], modules["storage"], modules["power_balance"], terminal=terminal,
                       classifier=classifier, residual_threshold=residual_threshold, v_range=v_range,
                       duals=duals)
