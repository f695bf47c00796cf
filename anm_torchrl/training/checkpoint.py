"""PPO checkpoints: one ``torch.save``'d dict with a kind marker, written atomically.

Layout (format version 1)::

    {"kind": "anm_torchrl.ppo", "format_version": 1,
     "config": {...},                      # resolved Hydra config (plain containers)
     "actor": state_dict, "critic": state_dict, "optimizer": state_dict,
     "obs_norm": {"loc": (obs_dim,), "scale": (obs_dim,)},
     "frames": int, "update": int, "logger_step": int,
     "best_eval": {metric: float, "frames": int, "update": int} | None,
     "evals_since_best": int, "wall_time": float}

:func:`load_checkpoint` loads with ``weights_only=True`` and raises ``ValueError`` naming what it found when the
file is not a PPO checkpoint of a supported version (a surrogate file, a random ``torch.save``'d dict, …).
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path
from typing import Any

import torch

from anm_torchrl.paths import atomic_torch_save

CHECKPOINT_KIND = "anm_torchrl.ppo"
FORMAT_VERSION = 1
REQUIRED_KEYS = ("config", "actor", "critic", "obs_norm", "frames", "update")


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> Path:
    """Write ``payload`` plus the kind marker and format version to ``path`` atomically (tmp file + ``os.replace``).

    An interrupted write leaves the previous file at ``path`` intact. Returns the path.
    """
    data = {"kind": CHECKPOINT_KIND, "format_version": FORMAT_VERSION, **payload}
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
        ValueError: wrong kind, unsupported version or missing entries; the message names what was found.
    """
    if not isinstance(ckpt, dict) or ckpt.get("kind") != CHECKPOINT_KIND:
        raise ValueError(f"{source} is not an anm_torchrl PPO checkpoint (expected a dict with "
                         f"kind={CHECKPOINT_KIND!r}); found {describe(ckpt)}")
    version = ckpt.get("format_version")
    if version != FORMAT_VERSION:
        raise ValueError(f"{source}: unsupported PPO checkpoint format_version {version!r} "
                         f"(this code reads version {FORMAT_VERSION})")
    missing = [k for k in REQUIRED_KEYS if k not in ckpt]
    if missing:
        raise ValueError(f"{source}: PPO checkpoint is missing entries {missing}; found {describe(ckpt)}")
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
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError, ValueError, AttributeError, TypeError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ValueError(f"{path} is not an anm_torchrl PPO checkpoint (expected a torch.save'd dict with "
                         f"kind={CHECKPOINT_KIND!r}); torch.load(weights_only=True) failed: {first}") from err
    return validate_checkpoint(ckpt, source=str(path))


def load_actor(checkpoint: str | os.PathLike | dict[str, Any], env=None, map_location: str | torch.device = "cpu"):
    """The trained PPO actor of a checkpoint (a path or an already loaded dict), in eval mode.

    The networks are rebuilt with the checkpoint's ``model`` config and normalisation statistics for the specs of
    ``env`` (default: a one-grid ``ANM6Env``; every env of the package has the same specs).
    """
    from anm_torchrl.training.ppo_models import make_ppo_models

    ckpt = checkpoint if isinstance(checkpoint, dict) else load_checkpoint(checkpoint, map_location)
    ckpt = validate_checkpoint(ckpt)
    if env is None:
        from anm_torchrl.envs import ANM6Env

        env = ANM6Env(1, seed=0)
    model = dict(ckpt["config"].get("model", {}))
    actor, _, _ = make_ppo_models(env, obs_stats=ckpt["obs_norm"], **model)
    actor.load_state_dict(ckpt["actor"])
    return actor.eval()
