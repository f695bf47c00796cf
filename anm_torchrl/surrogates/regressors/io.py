"""Saving and loading a data-driven surrogate folder (layout in :mod:`.defaults`), through
:mod:`anm_torchrl.artifacts`: one atomic save with a manifest, verified before any file is read.

A surrogate runs on the simulator it is loaded on (its foresight features read that simulator's profiles);
that simulator must have the network the surrogate was trained on (``network_key``), else the load raises.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import torch

from anm_torchrl._version import __version__
from anm_torchrl.artifacts import atomic_folder, verify_manifest, write_manifest
from anm_torchrl.data.storage import simulator_settings
from anm_torchrl.grid.identity import network_key
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.strict_json import json_text
from anm_torchrl.surrogates.features import Featurizer, target_layout
from anm_torchrl.surrogates.regressors.backends import load_backend
from anm_torchrl.surrogates.regressors.defaults import FORMAT, FORMAT_VERSION, KINDS, META_FILE, train_command
from anm_torchrl.surrogates.regressors.module import RegressorSurrogate
from anm_torchrl.surrogates.terminal import ModelFileError, TerminalClassifier, check_layout, read_meta


def save_surrogate(sur: RegressorSurrogate, path: str | os.PathLike, extra: dict | None = None,
                   files: dict[str, Any] | None = None, overwrite: bool = True) -> Path:
    """Write ``sur`` (model, description, classifier) and ``files`` into folder ``path`` in one atomic save.

    Args:
        sur: the surrogate (its classifier, if set, is saved alongside).
        path: the folder; an existing one is replaced only with ``overwrite``.
        extra: entries added to ``surrogate.json`` (``dataset``, metrics...).
        files: more content of the folder, name -> ``str``/``bytes`` (written) or a ``Path`` (a file or folder
            copied), e.g. ``metrics.json``, ``config.yaml``, ``tb``.
    """
    scalers = {k: getattr(sur, k) for k in ("x_mean", "x_std", "y_mean", "y_std")}
    bad = sorted(k for k, v in scalers.items() if not bool(torch.isfinite(v).all()))
    if bad:  # written as JSON null, no loader would read the model back (a NaN in its training data)
        raise ValueError(f"refusing to save the {sur.kind} surrogate to {path}: its scalers {bad} are not finite "
                         "(NaN or infinite values in its training data)")
    meta = {**sur.meta, **(extra or {}), "format": FORMAT, "format_version": FORMAT_VERSION, "kind": sur.kind,
            "package_version": __version__, "layout": sur.layout(),
            "foresight": sur.featurizer.foresight, "clip": sur.clip, "simulator": simulator_settings(sur.sim),
            "scalers": {k: v.cpu().tolist() for k, v in scalers.items()}}
    with atomic_folder(path, overwrite=overwrite, kind=FORMAT) as tmp:
        sur.backend.save(tmp)
        if sur.classifier is not None:
            sur.classifier.write_files(tmp)
        (tmp / META_FILE).write_text(json_text(meta, indent=2))
        for name, content in (files or {}).items():
            if isinstance(content, Path):
                (shutil.copytree if content.is_dir() else shutil.copy2)(content, tmp / name)
            else:
                (tmp / name).write_bytes(content.encode() if isinstance(content, str) else content)
        write_manifest(tmp, FORMAT, {"kind": sur.kind, "dataset": meta.get("dataset")})
    sur.meta = meta
    return Path(path)


def read_surrogate_meta(path: str | os.PathLike) -> dict:
    """The description (``surrogate.json``) of the surrogate saved in folder ``path``, read after its manifest
    is verified.

    Raises:
        ArtifactError: no manifest, or a file that changed since the save.
        ModelFileError: a missing or unreadable description, or one of another format or version.
    """
    path = Path(path)
    verify_manifest(path, FORMAT)
    return read_meta(path / META_FILE, "data-driven surrogate", FORMAT, FORMAT_VERSION, "retrain it")


def load_surrogate_folder(path: str | os.PathLike, kind: str | None = None, device="cpu",
                          sim: GridSimulator | None = None, n_jobs: int = 1) -> RegressorSurrogate:
    """Load a surrogate saved by :func:`save_surrogate` to run on ``sim``.

    Args:
        path: the surrogate folder.
        kind: when given, the folder must hold a surrogate of this kind.
        device: torch device of the module (the DNN runs there; tree models predict on the CPU).
        sim: the simulator it runs on (default ANM6-Easy); same network and layout as at training.
        n_jobs: threads for xgboost prediction.

    Raises:
        ArtifactError: no manifest, or a file that changed since the save (checked before reading anything).
        ModelFileError: unreadable files, a model of another kind, another state layout or another network.
    """
    path = Path(path)
    meta = read_surrogate_meta(path)
    stored = meta.get("kind")
    if stored not in KINDS:
        raise ModelFileError(f"{path / META_FILE} names an unknown surrogate kind {stored!r}")
    sim = sim if sim is not None else network_simulator(ANM6_EASY)
    if kind is not None and stored != kind:
        retrain = train_command(kind, meta.get("dataset", "generative"), sim)
        raise ModelFileError(f"{path} holds a {stored!r} surrogate, not {kind!r}: load it with "
                             f"surrogate={stored} or train a {kind!r} one ({retrain})")
    have_net, want_net = meta.get("simulator", {}).get("network_key"), network_key(sim)
    if have_net != want_net:
        raise ModelFileError(f"{path} was trained on network {have_net!r}, the simulator is network {want_net!r}: "
                             f"train a surrogate for this network")
    featurizer = Featurizer(sim, foresight=meta.get("foresight", True))
    idx, names = target_layout(sim)
    want = {"state_dim": sim.state_dim, "action_dim": sim.action_dim, "n_time": sim.n_time,
            "features": list(featurizer.names), "targets": names, "target_index": idx}
    check_layout(meta.get("layout"), want, path / META_FILE)
    nf, nt = featurizer.n_features, len(names)
    backend = load_backend(stored, path, nf, nt, n_jobs)
    sc = meta.get("scalers", {})
    try:
        scalers = {k: torch.tensor(sc[k], dtype=torch.float64) for k in ("x_mean", "x_std", "y_mean", "y_std")}
    except (KeyError, TypeError, ValueError) as err:
        raise ModelFileError(f"{path / META_FILE} has no valid scalers ({err})") from err
    if scalers["x_mean"].shape != (nf,) or scalers["y_mean"].shape != (nt,):
        raise ModelFileError(f"{path / META_FILE} scalers do not fit the state layout")
    classifier = TerminalClassifier.read_files(path, sim=sim, n_jobs=n_jobs)
    out = RegressorSurrogate(stored, backend, sim, featurizer, classifier=classifier, clip=meta.get("clip", True),
                             meta=meta, **scalers)
    return out.to(device)
