"""Training checkpoints of every algorithm: one ``torch.save``'d dict with a kind marker, the algorithm's name and
a content hash, written atomically.

Layout (format version 3)::

    {"kind": "anm_torchrl.checkpoint", "format_version": 3, "sha256": str,
     "algorithm": "ppo" | "sac" | ...,     # anm_torchrl.training.algorithms.ALGORITHMS
     "config": {...},                      # resolved Hydra config (plain containers)
     "actor": state_dict,                  # the policy evaluate.py loads
     "obs_norm": {"loc": (obs_dim,), "scale": (obs_dim,)},
     "state": {...},                       # the algorithm's other networks and optimisers (to resume)
     "frames": int, "update": int, "logger_step": int,
     "best_eval": {metric: float, "frames": int, "update": int} | None,
     "evals_since_best": int, "wall_time": float,
     "network_key": str,                   # the trained network's identity (anm_torchrl.grid.identity.network_key)
     "profiles_key": str}                  # its load and generation profiles (identity.profiles_key; optional)

Version 2 files (``kind: anm_torchrl.ppo``, PPO's ``critic`` and ``optimizer`` at the top level) are read as PPO
checkpoints of this layout, after the same checks.

``sha256`` is :func:`anm_torchrl.artifacts.tensors_sha256` of every tensor of the payload (named by its path,
e.g. ``actor.module.0.module.1.0.weight``) and of the JSON of everything else, so one flipped byte in a weight or
in the config fails the load. :func:`load_checkpoint` loads with ``torch.load(weights_only=True)`` (no code can
run), then checks the kind, the version, the hash and that every float tensor is finite; every failure is a
``ValueError`` naming the file. Version 1 files (no hash) are refused: they cannot be checked.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import torch

from anm_torchrl.artifacts import tensors_sha256
from anm_torchrl.paths import atomic_torch_save

CHECKPOINT_KIND = "anm_torchrl.checkpoint"
FORMAT_VERSION = 3
PPO_V2_KIND = "anm_torchrl.ppo"  # format version 2: PPO only
REQUIRED_KEYS = ("algorithm", "config", "actor", "state", "obs_norm", "frames", "update")


def _split(obj: Any, prefix: str, tensors: dict[str, torch.Tensor]) -> Any:
    """``obj`` with every tensor replaced by its path (collected into ``tensors``); containers become JSON-able."""
    if isinstance(obj, torch.Tensor):
        tensors[prefix] = obj
        return f"<tensor {prefix}>"
    if isinstance(obj, dict):
        return {str(k): _split(v, f"{prefix}.{k}" if prefix else str(k), tensors) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_split(v, f"{prefix}.{i}", tensors) for i, v in enumerate(obj)]
    return obj


def content_hash(payload: dict[str, Any]) -> str:
    """SHA-256 (hex) of a checkpoint payload (without its ``sha256`` entry): its tensors and the JSON of the rest."""
    tensors: dict[str, torch.Tensor] = {}
    rest = _split({k: v for k, v in payload.items() if k != "sha256"}, "", tensors)
    return tensors_sha256(tensors, json.loads(json.dumps(rest, sort_keys=True, default=float)))


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> Path:
    """Write ``payload`` plus the kind marker, format version and content hash to ``path`` atomically.

    An interrupted write leaves the previous file at ``path`` intact. Returns the path.
    """
    data = {"kind": CHECKPOINT_KIND, "format_version": FORMAT_VERSION, **payload}
    data["sha256"] = content_hash(data)
    return atomic_torch_save(data, path)


def describe(obj: Any) -> str:
    """A short description of a loaded object for error messages."""
    if isinstance(obj, dict):
        keys = sorted(map(str, obj.keys()))
        shown = ", ".join(keys[:8]) + (f", … ({len(keys)} keys)" if len(keys) > 8 else "")
        kind = obj.get("kind", None)
        return f"a dict with kind={kind!r} and keys [{shown}]"
    return f"an object of type {type(obj).__module__}.{type(obj).__qualname__}"


def _tensors(obj: Any, prefix: str = ""):
    """(path, tensor) of every tensor nested in dicts and lists."""
    if isinstance(obj, torch.Tensor):
        yield prefix, obj
    elif isinstance(obj, dict):
        for k, v in obj.items():
            yield from _tensors(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _tensors(v, f"{prefix}.{i}")


def _from_v2(ckpt: dict[str, Any]) -> dict[str, Any]:
    """A version-2 PPO checkpoint (hash already checked) in the version-3 layout."""
    out = {k: v for k, v in ckpt.items() if k not in ("critic", "optimizer")}
    out.update(kind=CHECKPOINT_KIND, format_version=FORMAT_VERSION, algorithm="ppo",
               state={"critic": ckpt["critic"], "optimizer": ckpt.get("optimizer", {})})
    return out


def validate_checkpoint(ckpt: Any, source: str = "checkpoint") -> dict[str, Any]:
    """Check a loaded object is a training checkpoint this code can read; returns it (version 3 layout).

    Raises:
        ValueError: wrong kind, unsupported version, an unknown algorithm, missing entries, a content hash that
            does not match or non-finite weights; the message names what was found.
    """
    from anm_torchrl.training.algorithms import ALGORITHMS

    kind = ckpt.get("kind") if isinstance(ckpt, dict) else None
    if kind not in (CHECKPOINT_KIND, PPO_V2_KIND):
        raise ValueError(f"{source} is not an anm_torchrl training checkpoint (expected a dict with "
                         f"kind={CHECKPOINT_KIND!r}); found {describe(ckpt)}")
    version = ckpt.get("format_version")
    if (kind, version) not in ((CHECKPOINT_KIND, FORMAT_VERSION), (PPO_V2_KIND, 2)):
        raise ValueError(f"{source}: unsupported checkpoint format_version {version!r} of kind {kind!r} "
                         f"(this code reads version {FORMAT_VERSION}, and version 2 of {PPO_V2_KIND!r})")
    required = ("config", "actor", "critic", "obs_norm", "frames", "update") if version == 2 else REQUIRED_KEYS
    missing = [k for k in required + ("sha256",) if k not in ckpt]
    if missing:
        raise ValueError(f"{source}: checkpoint is missing entries {missing}; found {describe(ckpt)}")
    types = {"config": dict, "actor": dict, "obs_norm": dict, "frames": int, "update": int, "sha256": str,
             **({"critic": dict} if version == 2 else {"state": dict, "algorithm": str})}
    wrong = [f"{k} is {type(ckpt[k]).__name__} (expected {t.__name__})" for k, t in types.items()
             if not isinstance(ckpt[k], t)]
    wrong += [f"{name}[{k!r}] is {type(v).__name__} (expected Tensor)" for name in ("actor", "obs_norm")
              if isinstance(ckpt[name], dict) for k, v in ckpt[name].items() if not isinstance(v, torch.Tensor)]
    if wrong:
        raise ValueError(f"{source}: malformed checkpoint: {'; '.join(wrong)}")
    got = content_hash(ckpt)
    if got != ckpt["sha256"]:
        raise ValueError(f"{source} is corrupted: content hash {got[:12]}… does not match the recorded "
                         f"{str(ckpt['sha256'])[:12]}…")
    if version == 2:
        ckpt = _from_v2(ckpt)
    if ckpt["algorithm"] not in ALGORITHMS:
        raise ValueError(f"{source} was trained by algorithm {ckpt['algorithm']!r}, which this code does not know "
                         f"(registered: {', '.join(sorted(ALGORITHMS))})")
    bad = [path for path, t in _tensors({"actor": ckpt["actor"], "state": ckpt["state"]})
           if t.is_floating_point() and not bool(torch.isfinite(t).all())]
    if bad:
        raise ValueError(f"{source} is corrupted: tensors {bad} hold NaN or inf values")
    return ckpt


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load and validate a training checkpoint (any algorithm).

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: not a training checkpoint (not loadable by ``torch.load(weights_only=True)``, or the wrong kind or
            version); the message names the file and what it holds.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # noqa: BLE001 - arbitrary bytes make the unpickler raise anything (KeyError, ...)
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ValueError(f"{path} is not an anm_torchrl training checkpoint (expected a torch.save'd dict with "
                         f"kind={CHECKPOINT_KIND!r}); torch.load(weights_only=True) failed: {first}") from err
    return validate_checkpoint(ckpt, source=str(path))


def load_actor(checkpoint: str | os.PathLike | dict[str, Any], env=None, map_location: str | torch.device = "cpu"):
    """The trained actor of a checkpoint (a path or an already loaded dict) of any registered algorithm, in eval
    mode.

    The actor is rebuilt by the checkpoint's algorithm (``build_actor``) with its config and normalisation
    statistics for the specs of ``env`` (default: one grid of the checkpoint's ``network``, ANM6-Easy for runs that
    predate that key; a true env and every surrogate of one network have the same specs).
    """
    from anm_torchrl.training.algorithms import get_algorithm

    ckpt = checkpoint if isinstance(checkpoint, dict) else load_checkpoint(checkpoint, map_location)
    ckpt = validate_checkpoint(ckpt)
    if env is None:
        from anm_torchrl.training.factory import make_true_env

        env = make_true_env(1, seed=0, network=ckpt["config"].get("network"))
    check_network(ckpt, env.sim, "the checkpoint" if isinstance(checkpoint, dict) else str(checkpoint))
    actor = get_algorithm(ckpt["algorithm"]).build_actor(env, ckpt["config"], ckpt["obs_norm"])
    actor.load_state_dict(ckpt["actor"])
    return actor.eval()


def check_network(ckpt: dict[str, Any], sim, source: str = "the checkpoint") -> None:
    """Refuse a checkpoint trained on another network than ``sim``'s (a :class:`GridSimulator`): its
    ``network_key`` (tables and reward constants) against ``sim``'s; a network file rewritten under the same name
    with other tables is caught here. Other profiles (``profiles_key``: the same grid under other loads and
    generation) are allowed, with a warning: figures on them are not the run's. Checkpoints that predate a key pass
    its check.

    Raises:
        ValueError: naming both keys and the network the checkpoint's config names.
    """
    from anm_torchrl.grid.identity import network_key, profiles_key

    saved = ckpt.get("network_key")
    if saved is not None and saved != network_key(sim):
        raise ValueError(f"{source} was trained on another network (key {saved}) than this one (key "
                         f"{network_key(sim)}); its config names network={ckpt['config'].get('network')!r}: another "
                         "network, or that file with its tables or reward constants changed since")
    saved = ckpt.get("profiles_key")
    if saved is not None and saved != profiles_key(sim):
        logging.getLogger(__name__).warning(
            "%s was trained on other load and generation profiles of this network (key %s, now %s: a network file "
            "rewritten with new profiles?): what is measured here is on the profiles it holds now, not the run's",
            source, saved, profiles_key(sim))


def config_diff(old: dict, new: dict, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two nested config dicts (a key missing on one side differs)."""
    out = []
    for key in sorted(set(old) | set(new)):
        name = f"{prefix}{key}"
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += config_diff(a, b, name + ".")
        elif a != b:
            out.append(name)
    return out


def check_resume_config(saved: dict, config: dict, source: str = "checkpoint", network_by_key: bool = False
                        ) -> list[str]:
    """Compare the config saved in a checkpoint with the config of the run that resumes from it.

    ``network_by_key``: the checkpoint holds its network's key, which the caller compares
    (:func:`check_network`): the ``network`` entries (a name or a file's path as typed) are then not compared, so
    the same file by another path, moved or copied, resumes.

    Returns:
        The dotted keys that differ (the caller decides what to ignore and what to warn about).

    Raises:
        ValueError: one of the algorithm's ``architecture_keys`` (network, layer widths, ...) differs (the saved
            weights belong to another network); the message gives both values.
    """
    from anm_torchrl.training.algorithms import get_algorithm

    # checkpoints that predate the keys: PPO on ANM6-Easy
    saved = {"network": "anm6_easy", "algorithm": "ppo", **saved}
    keys = [k for k in get_algorithm(saved["algorithm"]).architecture_keys if not (k == "network" and network_by_key)]
    arch = architecture_differences(saved, config, keys)
    if arch:
        details = "; ".join(f"{k}: checkpoint {a!r}, this run {b!r}" for k, a, b in arch)
        raise ValueError(f"cannot resume from {source}: its networks were built with another architecture "
                         f"({details}); pass the checkpoint's values or start a new run")
    return config_diff(saved, config)


def config_value(cfg: dict, key: str) -> Any:
    """The value of a dotted ``key`` in a nested config dict (None where a level is missing)."""
    for part in key.split("."):
        cfg = cfg.get(part) if isinstance(cfg, dict) else None
    return cfg


def architecture_differences(saved: dict, config: dict, keys) -> list[tuple[str, Any, Any]]:
    """``(key, saved value, config value)`` of each of ``keys`` (dotted) whose values differ between a checkpoint's
    config and a run's. A flag or count added after the checkpoint was written (absent there) was off (0) when it
    was: absent against False or 0 does not differ."""
    out = []
    for key in keys:
        a, b = config_value(saved, key), config_value(config, key)
        if a != b and not (a is None and b in (False, 0)):
            out.append((key, a, b))
    return out
