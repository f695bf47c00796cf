"""PPO checkpoints: one ``torch.save``'d dict with a kind marker and a content hash, written atomically.

Layout (format version 2)::

    {"kind": "anm_torchrl.ppo", "format_version": 2, "sha256": str,
     "config": {...},                      # resolved Hydra config (plain containers)
     "actor": state_dict, "critic": state_dict, "optimizer": state_dict,
     "obs_norm": {"loc": (obs_dim,), "scale": (obs_dim,)},
     "frames": int, "update": int, "logger_step": int,
     "best_eval": {metric: float, "frames": int, "update": int} | None,
     "evals_since_best": int, "wall_time": float}

``sha256`` is :func:`anm_torchrl.artifacts.tensors_sha256` of every tensor of the payload (named by its path,
e.g. ``actor.module.0.module.1.0.weight``) and of the JSON of everything else, so one flipped byte in a weight or
in the config fails the load. :func:`load_checkpoint` loads with ``torch.load(weights_only=True)`` (no code can
run), then checks the kind, the version, the hash and that every float tensor is finite; every failure is a
``ValueError`` naming the file. Version 1 files (no hash) are refused: they cannot be checked.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

from anm_torchrl.artifacts import tensors_sha256
from anm_torchrl.paths import atomic_torch_save

CHECKPOINT_KIND = "anm_torchrl.ppo"
FORMAT_VERSION = 2
REQUIRED_KEYS = ("config", "actor", "critic", "obs_norm", "frames", "update")
# config keys that define the networks' shapes and functions: resuming with other values is an error
ARCHITECTURE_KEYS = ("network", "model.actor_cells", "model.critic_cells", "model.activation", "model.obs_clip")


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


def validate_checkpoint(ckpt: Any, source: str = "checkpoint") -> dict[str, Any]:
    """Check a loaded object is a PPO checkpoint this code can read; returns it.

    Raises:
        ValueError: wrong kind, unsupported version, missing entries, a content hash that does not match or
            non-finite weights; the message names what was found.
    """
    if not isinstance(ckpt, dict) or ckpt.get("kind") != CHECKPOINT_KIND:
        raise ValueError(f"{source} is not an anm_torchrl PPO checkpoint (expected a dict with "
                         f"kind={CHECKPOINT_KIND!r}); found {describe(ckpt)}")
    version = ckpt.get("format_version")
    if version != FORMAT_VERSION:
        raise ValueError(f"{source}: unsupported PPO checkpoint format_version {version!r} "
                         f"(this code reads version {FORMAT_VERSION})")
    missing = [k for k in REQUIRED_KEYS + ("sha256",) if k not in ckpt]
    if missing:
        raise ValueError(f"{source}: PPO checkpoint is missing entries {missing}; found {describe(ckpt)}")
    types = {"config": dict, "actor": dict, "critic": dict, "obs_norm": dict, "frames": int, "update": int,
             "sha256": str}
    wrong = [f"{k} is {type(ckpt[k]).__name__} (expected {t.__name__})" for k, t in types.items()
             if not isinstance(ckpt[k], t)]
    wrong += [f"{name}[{k!r}] is {type(v).__name__} (expected Tensor)" for name in ("actor", "critic", "obs_norm")
              if isinstance(ckpt[name], dict) for k, v in ckpt[name].items() if not isinstance(v, torch.Tensor)]
    if wrong:
        raise ValueError(f"{source}: malformed PPO checkpoint: {'; '.join(wrong)}")
    got = content_hash(ckpt)
    if got != ckpt["sha256"]:
        raise ValueError(f"{source} is corrupted: content hash {got[:12]}… does not match the recorded "
                         f"{str(ckpt['sha256'])[:12]}…")
    for name in ("actor", "critic"):
        bad = [k for k, t in ckpt[name].items() if t.is_floating_point() and not bool(torch.isfinite(t).all())]
        if bad:
            raise ValueError(f"{source} is corrupted: {name} tensors {bad} hold NaN or inf values")
    return ckpt


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load and validate a PPO checkpoint.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: not a PPO checkpoint (not loadable by ``torch.load(weights_only=True)``, or the wrong kind or
            version); the message names the file and what it holds.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # noqa: BLE001 - arbitrary bytes make the unpickler raise anything (KeyError, ...)
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ValueError(f"{path} is not an anm_torchrl PPO checkpoint (expected a torch.save'd dict with "
                         f"kind={CHECKPOINT_KIND!r}); torch.load(weights_only=True) failed: {first}") from err
    return validate_checkpoint(ckpt, source=str(path))


def load_actor(checkpoint: str | os.PathLike | dict[str, Any], env=None, map_location: str | torch.device = "cpu"):
    """The trained PPO actor of a checkpoint (a path or an already loaded dict), in eval mode.

    The networks are rebuilt with the checkpoint's ``model`` config and normalisation statistics for the specs of
    ``env`` (default: one grid of the checkpoint's ``network``, ANM6-Easy for runs that predate that key; a true
    env and every surrogate of one network have the same specs).
    """
    from anm_torchrl.training.ppo_models import make_ppo_models

    ckpt = checkpoint if isinstance(checkpoint, dict) else load_checkpoint(checkpoint, map_location)
    ckpt = validate_checkpoint(ckpt)
    if env is None:
        from anm_torchrl.training.factory import make_true_env

        env = make_true_env(1, seed=0, network=ckpt["config"].get("network"))
    model = dict(ckpt["config"].get("model", {}))
    actor, _, _ = make_ppo_models(env, obs_stats=ckpt["obs_norm"], **model)
    actor.load_state_dict(ckpt["actor"])
    return actor.eval()


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


def check_resume_config(saved: dict, config: dict, source: str = "checkpoint") -> list[str]:
    """Compare the config saved in a checkpoint with the config of the run that resumes from it.

    Returns:
        The dotted keys that differ (the caller decides what to ignore and what to warn about).

    Raises:
        ValueError: an :data:`ARCHITECTURE_KEYS` entry differs (the saved weights belong to another network); the
            message gives both values.
    """
    saved = {"network": "anm6_easy", **saved}  # checkpoints that predate the key were trained on ANM6-Easy
    changed = config_diff(saved, config)
    arch = [k for k in changed if k in ARCHITECTURE_KEYS]
    if arch:
        def value(cfg: dict, key: str):
            for part in key.split("."):
                cfg = cfg.get(part) if isinstance(cfg, dict) else None
            return cfg

        details = "; ".join(f"{k}: checkpoint {value(saved, k)!r}, this run {value(config, k)!r}" for k in arch)
        raise ValueError(f"cannot resume from {source}: its networks were built with another architecture "
                         f"({details}); pass the checkpoint's values or start a new run")
    return changed
