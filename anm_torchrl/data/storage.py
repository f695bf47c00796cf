"""Datasets of simulator transitions on disk: a TensorDict memmap plus a metadata JSON, with fixed splits.

Layout of a dataset folder (``anm_torchrl.data.default_dataset_dir(kind, size, seed, sim)`` by default)::

    <dir>/dataset.json   metadata: layout marker and version, kind, size, seed, package version, simulator
                         settings and fingerprint, generator options, split sizes, field shapes/dtypes, checksum
    <dir>/data/          ``TensorDict.memmap_`` of the rows (batch size [size])
    <dir>/manifest.json  SHA-256 of every file (:mod:`anm_torchrl.artifacts`), checked at load before reading

Writes are atomic (a temporary folder renamed into place) and exclusive (:func:`anm_torchrl.artifacts.
exclusive_lock`: two writers of one path cannot both write; the second fails naming the first).

Fields (one row per transition, N = size; S = state_dim, A = action_dim of the network, 18 and 6 on ANM6-Easy):

==========================  ==========  =======  ===================================================================
key                         shape       dtype    meaning
==========================  ==========  =======  ===================================================================
``state``                   (N, S)      float64  gym-anm state before the step (MW, MVAr, MWh, time index)
``action``                  (N, A)      float64  action (MW / MVAr), inside the action box
``next_state``              (N, S)      float64  state after the step; zeros on terminal rows (as gym-anm)
``reward``                  (N, 1)      float64  gym-anm reward; −100/(1−γ) on terminal rows
``terminated``              (N, 1)      bool     the power flow of the step did not converge
``("grid", k)``             (N, ·)      float64  e_loss, penalty, curtailment (MW), v_magn (p.u.), branch_s (MVA)
``split``                   (N,)        int8     0 train, 1 validation, 2 test (fixed when generated)
``episode``, ``step``       (N,)        int64    agent-based only: episode id and step within the episode
==========================  ==========  =======  ===================================================================

Loading checks everything it can and raises :class:`DatasetError` with the command that regenerates the data
instead of returning a corrupted or mismatched dataset.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import inspect
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from anm_torchrl._version import __version__
from anm_torchrl.artifacts import (ArtifactError, DiskFullError, atomic_folder, disk_full_error, exclusive_lock,
                                  reserve_space, verify_manifest, write_manifest)
from anm_torchrl.data.options import DEFAULT_FRACTIONS, check_fractions, check_split_units
from anm_torchrl.data.registry import available_datasets, dataset_generator
from anm_torchrl.grid.identity import network_key, simulator_fingerprint
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.strict_json import json_text

LAYOUT = "anm_torchrl.transitions"
LAYOUT_VERSION = 2  # 2: manifest.json (atomic, hash-checked saves)
META_FILE = "dataset.json"
DATA_DIR = "data"
KINDS = available_datasets()
SPLITS = {"train": 0, "val": 1, "test": 2}


class DatasetError(ValueError):
    """A dataset is missing, corrupted, or does not match what was asked for (a user's input error, as
    :class:`~anm_torchrl.artifacts.ArtifactError` is)."""


#: the fields a model is fitted on: every row's must be finite (a terminal row's next state is zeros)
FINITE_FIELDS = ("state", "action", "next_state", "reward")


def non_finite(td: TensorDictBase) -> str | None:
    """The first field of :data:`FINITE_FIELDS` in ``td`` holding a NaN or infinite value, with its first row, or
    None."""
    for key in FINITE_FIELDS:
        value = td.get(key, None)
        if value is None or not value.is_floating_point():
            continue
        bad = ~torch.isfinite(value.reshape(value.shape[0], -1)).all(-1)
        if bool(bad.any()):
            return f"field {key!r} is not finite in {int(bad.sum())} rows (first: row {int(bad.nonzero()[0])})"
    return None


def make_command(kind: str | None, size: int | None, seed: int | None) -> str:
    """The shell command that (re)generates a dataset."""
    parts = ["python recipes/make_dataset.py"]
    if kind is not None:
        parts.append(f"dataset={kind}")
    if size is not None:
        parts.append(f"size={size}")
    if seed is not None:
        parts.append(f"seed={seed}")
    return " ".join(parts)


# ------------------------------------------------------------------------------------------------ simulator
def simulator_settings(sim: GridSimulator) -> dict[str, Any]:
    """The simulator constants a dataset (or a surrogate) depends on, JSON-ready."""
    return {
        "state_dim": sim.state_dim, "action_dim": sim.action_dim, "n_time": sim.n_time,
        "n_dev": sim.net.n_dev, "n_bus": sim.net.n_bus, "base_mva": float(sim.net.base_mva),
        "delta_t": float(sim.net.delta_t), "gamma": float(sim.gamma), "lamb": float(sim.lamb),
        "costs_clipping": [float(c) for c in sim.costs_clipping], "fingerprint": simulator_fingerprint(sim),
        "network_key": network_key(sim),
    }


# ------------------------------------------------------------------------------------------------- splits
def split_codes(n_units: int, fractions=DEFAULT_FRACTIONS, generator: torch.Generator | None = None) -> torch.Tensor:
    """Assign ``n_units`` units (rows or trajectories) to train/val/test, (n_units,) int8, seeded permutation.

    Every split gets at least one unit (the fractions are positive, :func:`.options.check_fractions`; where rounding
    left the training split empty, the larger of the other two gives one up); ``n_units`` < 3
    (:data:`.options.MIN_SPLIT_UNITS`) raises a ``ValueError`` (:func:`.options.check_split_units`).
    """
    check_split_units(n_units, "n_units")
    f = torch.tensor(check_fractions(fractions), dtype=torch.float64)
    f = f / f.sum()  # round-off only: the sum is 1 within 1e-6
    n_val = max(int(round(f[1].item() * n_units)), 1)
    n_test = max(int(round(f[2].item() * n_units)), 1)
    while n_units - n_val - n_test < 1:  # n_units >= 3: the larger of the two holds >= 2 units here
        if n_val >= n_test:
            n_val -= 1
        else:
            n_test -= 1
    n_train = n_units - n_val - n_test
    codes = torch.cat([torch.full((n_train,), 0), torch.full((n_val,), 1), torch.full((n_test,), 2)]).to(torch.int8)
    perm = torch.randperm(n_units, generator=generator)
    out = torch.empty_like(codes)
    out[perm] = codes
    return out


def split(td: TensorDictBase, name: str) -> TensorDict:
    """Rows of ``td`` in split ``name`` (``"train"``, ``"val"`` or ``"test"``), materialised in memory."""
    if name not in SPLITS:
        raise ValueError(f"split must be one of {list(SPLITS)}, got {name!r}")
    mask = torch.as_tensor(td.get("split")) == SPLITS[name]
    return td[mask].to_tensordict()


# ------------------------------------------------------------------------------------------------ checksum
def _leaves(td: TensorDictBase) -> list[tuple[str, torch.Tensor]]:
    def name(k) -> str:
        return k if isinstance(k, str) else ".".join(k)

    keys = sorted(td.keys(include_nested=True, leaves_only=True), key=name)
    return [(name(k), td.get(k)) for k in keys]


def field_layout(td: TensorDictBase) -> dict[str, dict[str, Any]]:
    """``{field: {"shape": [...], "dtype": "torch.float64"}}`` for every leaf of ``td`` (nested keys joined by '.')."""
    return {k: {"shape": list(v.shape), "dtype": str(v.dtype)} for k, v in _leaves(td)}


def checksum(td: TensorDictBase) -> str:
    """SHA-256 (hex) of every leaf's name, dtype, shape and bytes, in sorted key order."""
    h = hashlib.sha256()
    for k, v in _leaves(td):
        h.update(f"{k}|{v.dtype}|{tuple(v.shape)}|".encode())
        arr = np.ascontiguousarray(torch.as_tensor(v).detach().cpu().numpy())
        h.update(arr.view(np.uint8).reshape(-1))
    return h.hexdigest()


# ------------------------------------------------------------------------------------------------ save/load
def save_dataset(td: TensorDictBase, path: str | os.PathLike, meta: dict[str, Any], overwrite: bool = False,
                 lock: bool = True) -> Path:
    """Write ``td`` (batch size [N]) and ``meta`` to ``path`` atomically, with a manifest.

    ``meta`` must hold ``kind``, ``size`` and ``seed``; the layout marker, package version, field layout and
    checksum are added here. ``lock=False`` when the caller already holds ``path``'s exclusive lock.

    The data files' blocks are allocated before they are filled through memory maps, so a full disk raises
    instead of killing the process with SIGBUS.

    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is False.
        LockedError: another process is writing ``path``.
        OSError: ``ENOSPC``, the disk is full; the message names the path and the space needed and free, and
            nothing is left behind (no temporary folder, no lock; a previous dataset is intact).
    """
    path = Path(path)
    bad = non_finite(td)
    if bad is not None:
        raise DatasetError(f"refusing to write dataset {path}: {bad}")
    for key in ("kind", "size", "seed"):
        if key not in meta:
            raise ValueError(f"dataset metadata needs {key!r}")
    if td.batch_size != torch.Size([int(meta["size"])]):
        raise ValueError(f"dataset has batch size {tuple(td.batch_size)}, metadata says size {meta['size']}")
    full = {"layout": LAYOUT, "layout_version": LAYOUT_VERSION, "package_version": __version__,
            **meta, "fields": field_layout(td), "checksum": checksum(td)}
    sizes = {Path(*k.split(".")).with_suffix(".memmap"): v.numel() * v.element_size() for k, v in _leaves(td)}
    try:
        with exclusive_lock(path) if lock else contextlib.nullcontext():
            with atomic_folder(path, overwrite=overwrite, kind=LAYOUT) as tmp:
                reserve_space({tmp / DATA_DIR / f: n for f, n in sizes.items()}, path)
                td.to_tensordict().memmap_(prefix=str(tmp / DATA_DIR))
                (tmp / META_FILE).write_text(json_text(full, indent=2, sort_keys=True))
                write_manifest(tmp, LAYOUT, {"kind": meta["kind"], "size": int(meta["size"]), "seed": meta["seed"]})
    except OSError as err:
        if err.errno in (errno.ENOSPC, errno.EDQUOT):  # named for the dataset, free space measured after cleanup
            cause = err.__cause__ if isinstance(err, DiskFullError) else err
            raise disk_full_error(path, sum(sizes.values()), cause if isinstance(cause, OSError) else None) from err
        raise
    return path


def read_meta(path: str | os.PathLike) -> dict[str, Any]:
    """The metadata of the dataset at ``path`` (raises :class:`DatasetError` if missing or unreadable)."""
    path = Path(path)
    f = path / META_FILE
    if not f.is_file():
        raise DatasetError(f"{path} is not a dataset folder: {META_FILE} is missing")
    try:
        meta = json.loads(f.read_text())
    except (OSError, ValueError) as err:
        raise DatasetError(f"dataset metadata {f} is corrupted ({err})") from err
    if not isinstance(meta, dict) or meta.get("layout") != LAYOUT:
        raise DatasetError(f"{f} is not an anm_torchrl transition dataset (layout marker {LAYOUT!r} missing)")
    if meta.get("layout_version") != LAYOUT_VERSION:
        raise DatasetError(f"{f} has dataset layout version {meta.get('layout_version')}, this package reads "
                           f"version {LAYOUT_VERSION}")
    return meta


def load_dataset(path: str | os.PathLike, kind: str | None = None, size: int | None = None, seed: int | None = None,
                 sim: GridSimulator | None = None, verify: bool = True,
                 options: Mapping[str, Any] | None = None) -> tuple[TensorDict, dict[str, Any]]:
    """Open the dataset at ``path`` (memory-mapped) and check it.

    Args:
        path: dataset folder.
        kind, size, seed: when given, the metadata must match them.
        sim: when given, the dataset must come from a simulator with the same settings and fingerprint.
        options: when given, the generator options (``fractions`` included) the dataset must have been made with;
            those not given are the generator's defaults (:func:`check_options`).
        verify: check every file against the manifest and recompute the checksum (reads every byte twice;
            0.23 s for 50,000 generative rows, 22 MB, measured on the shared 2-core machine).

    Returns:
        ``(td, meta)``: the rows (memory-mapped TensorDict, batch size [size]) and the metadata.

    Raises:
        DatasetError: missing, corrupted or mismatched dataset; the message says how to regenerate it.
    """
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"no dataset at {path}; generate it with: {make_command(kind, size, seed)}"
                           + ("" if kind is None else f" (or out={path})"))
    meta = read_meta(path)
    redo = (f"delete {path} and regenerate it: {make_command(meta.get('kind'), meta.get('size'), meta.get('seed'))}"
            f" out={path} overwrite=true")
    for key, want in (("kind", kind), ("size", size), ("seed", seed)):
        if want is not None and meta.get(key) != want:
            raise DatasetError(f"dataset {path} has {key}={meta.get(key)!r}, expected {want!r}")
    if sim is not None:
        have, want = meta.get("simulator", {}), simulator_settings(sim)
        diff = sorted(k for k in want if have.get(k) != want[k])
        if "network_key" in diff:  # another network's dataset is fine as it is: make one for this network
            raise DatasetError(f"dataset {path} belongs to another network (network_key {have.get('network_key')} "
                               f"vs this one's {want['network_key']}); generate one for this network: "
                               f"{make_command(meta.get('kind'), meta.get('size'), meta.get('seed'))} network=<this "
                               "network> out=<a new folder>")
        if diff:
            raise DatasetError(f"dataset {path} was generated by a different simulator ({', '.join(diff)} differ: "
                               f"{ {k: have.get(k) for k in diff} } vs { {k: want[k] for k in diff} }); {redo}")
    if options is not None:
        check_options(path, meta, options)
    if verify:
        try:
            verify_manifest(path, LAYOUT)
        except ArtifactError as err:
            raise DatasetError(f"dataset {path} is corrupted: {err}; {redo}") from err
    _check_files(path, meta, redo)  # before mapping: tensordict silently zero-extends a truncated file
    try:
        td = TensorDict.load_memmap(str(path / DATA_DIR))
    except Exception as err:  # noqa: BLE001 - any failure here means unreadable data files
        raise DatasetError(f"dataset {path} is corrupted: its data files cannot be read ({type(err).__name__}: "
                           f"{err}); {redo}") from err
    layout = field_layout(td)
    if layout != meta.get("fields") or td.batch_size != torch.Size([int(meta["size"])]):
        missing = sorted(set(meta.get("fields", {})) ^ set(layout))
        wrong = sorted(k for k in layout if k in meta.get("fields", {}) and layout[k] != meta["fields"][k])
        raise DatasetError(f"dataset {path} is corrupted: fields differ from its metadata (missing/extra "
                           f"{missing}, wrong shape/dtype {wrong}); {redo}")
    if verify:
        got = checksum(td)
        if got != meta.get("checksum"):
            raise DatasetError(f"dataset {path} is corrupted: checksum {got[:12]}… does not match the recorded "
                               f"{str(meta.get('checksum'))[:12]}…; {redo}")
        bad = non_finite(td)  # written before this check existed, or by other code: no model fits it
        if bad is not None:
            raise DatasetError(f"dataset {path}: {bad}; {redo}")
    return td, meta


# options that change how a dataset is computed, not its rows (generative.chunk: memory and speed only)
DATA_NEUTRAL_OPTIONS = {"generative": ("chunk",)}
_NOT_OPTIONS = ("size", "seed", "sim", "progress")  # generator arguments that are not generator options
_MISSING = object()  # an option the metadata does not record


def check_options(path: str | os.PathLike, meta: dict[str, Any], options: Mapping[str, Any]) -> None:
    """Raise :class:`DatasetError` unless the dataset of ``meta`` at ``path`` was made with generator ``options``
    (``fractions`` included; the generator's defaults for the options not given). The metadata records them under
    ``generator`` and ``split_fractions``; an option it does not record (an older dataset) counts as different, as
    a missing simulator setting does."""
    kind, size = meta.get("kind"), meta.get("size")
    try:
        params = inspect.signature(dataset_generator(kind)).parameters.values()
    except ValueError:  # a kind this process has not registered: only the options given can be compared
        params = ()
    want = {p.name: p.default for p in params if p.default is not p.empty and p.name not in _NOT_OPTIONS}
    want.update(options)
    recorded = meta.get("generator") if isinstance(meta.get("generator"), dict) else {}
    diff = []
    for name, value in sorted(want.items()):
        if name in DATA_NEUTRAL_OPTIONS.get(kind, ()):
            continue
        if name == "fractions":
            stored = meta.get("split_fractions", _MISSING)
            value = [float(f) for f in check_fractions(value)]
            same = isinstance(stored, list) and len(stored) == 3 and all(
                isinstance(a, (int, float)) and math.isclose(a, b, rel_tol=0, abs_tol=1e-9)
                for a, b in zip(stored, value))
        else:
            stored = recorded.get(name, _MISSING)
            if kind == "agent" and name == "num_envs" and isinstance(value, int) and isinstance(size, int):
                value = min(value, size)  # the agent generator caps num_envs at size and records the capped count
            same = stored == value
        if not same:
            shown = "none (not recorded: made by an older version)" if stored is _MISSING else repr(stored)
            diff.append(f"{name}: stored {shown}, requested {value!r}")
    if diff:
        raise DatasetError(f"dataset {path} was made with other generator options than requested "
                           f"({'; '.join(diff)}); it is never reused for other options: delete {path} to have it "
                           f"regenerated with the requested ones, or write the new one to another folder (path=, "
                           f"make_dataset.py out=); to use this one as it is, load it by its folder (load_dataset, "
                           f"train_surrogate.py data.{kind}=<folder>)")


def _check_files(path: Path, meta: dict, redo: str) -> None:
    """Every field's memmap file exists and has exactly the size its recorded shape and dtype imply."""
    fields = meta.get("fields")
    if not isinstance(fields, dict) or not fields:
        raise DatasetError(f"dataset {path} is corrupted: its metadata lists no fields; {redo}")
    for key, spec in fields.items():
        f = path / DATA_DIR / Path(*key.split(".")).with_suffix(".memmap")
        try:
            dtype = getattr(torch, str(spec["dtype"]).removeprefix("torch."))
            want = int(np.prod(spec["shape"])) * torch.empty((), dtype=dtype).element_size()
        except (AttributeError, KeyError, TypeError, ValueError) as err:
            raise DatasetError(f"dataset {path} is corrupted: bad field description for {key!r}; {redo}") from err
        if not f.is_file():
            raise DatasetError(f"dataset {path} is corrupted: data file {f} of field {key!r} is missing; {redo}")
        have = f.stat().st_size
        if have != want:
            raise DatasetError(f"dataset {path} is corrupted: {f} has {have} bytes, field {key!r} "
                               f"{spec['shape']} {spec['dtype']} needs {want}; {redo}")


# ------------------------------------------------------------------------------------------------- rows
def transition_rows(sim: GridSimulator, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                    tr) -> TensorDict:
    """The dataset fields (all but ``split``) of a batch of steps ``next_state, tr = sim.step(state, action)``."""
    b = sim.net.base_mva
    n = state.shape[0]
    grid = {"e_loss": tr.e_loss.unsqueeze(-1), "penalty": tr.penalty.unsqueeze(-1),
            "curtailment": (tr.curtailment * b).unsqueeze(-1), "v_magn": tr.v.abs(),
            "branch_s": tr.s_apparent_max * b}
    return TensorDict(
        {"state": state, "action": action, "next_state": next_state, "reward": tr.reward.unsqueeze(-1),
         "terminated": (~tr.converged).unsqueeze(-1), "grid": {k: v.to(torch.float64) for k, v in grid.items()}},
        batch_size=[n])
