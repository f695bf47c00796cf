"""A user's mistake in a recipe is one line naming it, not a traceback, and leaves no empty run directory.

Every recipe (``recipes/*.py``) runs its checks — config ranges, network names and files, devices, missing
extras, folders it will write in — inside :func:`user_errors` before any heavy work, so
``make_dataset.py generative.chunk=0`` prints ``make_dataset.py: generative.chunk must be an integer >= 1, got 0``
and exits with status 1. Errors raised later, during the work itself, keep their traceback: by then they are bugs
or faults, not typos.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path

from anm_torchrl._extras import MissingExtraError
from anm_torchrl.overrides import parse_override


class NotWritableError(OSError):
    """A folder the run will write in can neither be written nor created (:func:`check_writable`)."""


#: what a user's input can raise before the work starts (a bad value, a wrong kind, a missing file or extra, a
#: folder that cannot be written)
USER_ERRORS = (ValueError, TypeError, KeyError, FileNotFoundError, FileExistsError, NotADirectoryError,
               PermissionError, MissingExtraError, NotWritableError)


def remove_hydra_only_dir(run_dir: Path) -> None:
    """Remove ``run_dir`` if it holds nothing but what Hydra writes at start (``.hydra/``, ``<job>.log``), and
    then up to three parents that this left empty (Hydra's ``outputs/<job>/<date>/`` levels), never the
    working directory."""
    run_dir = Path(run_dir).resolve()
    if run_dir.is_dir() and all(p.name == ".hydra" or p.suffix == ".log" for p in run_dir.iterdir()):
        if Path.cwd().resolve() == run_dir:  # hydra.job.chdir made it the working directory
            os.chdir(_original_cwd() or run_dir.parent)
        shutil.rmtree(run_dir)
        for parent in run_dir.parents[:3]:
            if parent == Path.cwd().resolve() or any(parent.iterdir()):
                break
            parent.rmdir()


def _original_cwd() -> str | None:
    """Where the command was typed (Hydra's ``runtime.cwd``), or None outside a Hydra run."""
    from hydra.core.hydra_config import HydraConfig

    return HydraConfig.get().runtime.cwd if HydraConfig.initialized() else None


@contextlib.contextmanager
def user_errors(recipe: str, run_dir: str | os.PathLike | None = None) -> Iterator[None]:
    """Turn :data:`USER_ERRORS` raised in the block into ``SystemExit("<recipe>: <message>")`` (status 1) and
    remove ``run_dir`` if it holds only Hydra's start-up files.

    Args:
        recipe: the script's name as the user typed it, e.g. ``"make_dataset.py"``.
        run_dir: the Hydra run directory made for this run, or None.
    """
    try:
        yield
    except USER_ERRORS as err:
        if run_dir is not None:
            remove_hydra_only_dir(Path(run_dir))
        message = err.args[0] if isinstance(err, KeyError) and err.args else err
        raise SystemExit(f"{recipe}: {message}") from None


def defined_keys() -> Callable[[str], bool]:
    """Inside a recipe (a running Hydra app): whether a key is in its config as composed from the command line
    without its ``++`` overrides (composed on the first question)."""
    from hydra import compose
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf

    base = []

    def defined(key: str) -> bool:
        if not base:
            hc = HydraConfig.get()
            base.append(compose(hc.job.config_name, [o for o in hc.overrides.task if not o.startswith("++")]))
        return OmegaConf.select(base[0], key, default=_ABSENT) is not _ABSENT

    return defined


_ABSENT = object()


def refuse_appended_keys(recipe: str, overrides: Iterable[str], allowed: tuple[str, ...] = (),
                         defined: Callable[[str], bool] | None = None) -> None:
    """Refuse Hydra's ``+key=value`` (a key added to the config) outside the groups whose every key the recipe
    passes on (``allowed``): elsewhere no recipe reads a key it does not define, so the value was ignored without a
    word. Hydra itself answers ``key=value`` for an unknown key with "To append to your config use +key=value",
    which leads here.

    Args:
        recipe: the script's name as the user typed it, e.g. ``"ppo.py"`` (for its ``--help``).
        overrides: the command line's overrides (``HydraConfig.get().overrides.task``).
        allowed: key prefixes whose added keys the recipe passes on and checks there (``pinn_preset``: its
            dataclasses; ``surrogate``: the surrogate's loader's options; ``models``: the regressors' estimators).
        defined: whether a key exists without the ``++`` overrides (:func:`defined_keys`): ``++key=value`` (set or
            add) is then refused as ``+key`` is where it adds a key; None: ``++`` is not checked.

    Raises:
        ValueError: naming the first such override.
    """
    for item in overrides:
        prefix, key, _ = parse_override(item)
        if prefix == "++" and (defined is None or defined(key)):  # Hydra's override of a key that exists
            continue
        if prefix not in ("+", "++"):
            continue
        if any(key == a or key.startswith(a + ".") for a in allowed):
            continue
        raise ValueError(f"{item}: {key!r} is not one of this recipe's keys (an added key is not read); "
                         f"python recipes/{recipe} --help lists its groups and keys")


def check_device(device: str, key: str = "env.device") -> None:
    """``device`` names a device this torch build has (``cpu``, or ``cuda[:i]`` / ``mps`` where available).

    Raises:
        ValueError: naming ``key``, the device and what this build offers.
    """
    if str(device) == "cpu":
        return
    import torch

    try:
        dev = torch.device(str(device))
    except RuntimeError as err:
        raise ValueError(f"{key}: {device!r} is not a torch device ({err})") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"{key}={device}: this torch build ({torch.__version__}) has no usable CUDA device; "
                             f"use {key}=cpu, or install a CUDA build of torch on a machine with a GPU")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"{key}={device}: only {torch.cuda.device_count()} CUDA device(s) here")
    elif dev.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"{key}={device}: MPS is not available here; use {key}=cpu")
    elif dev.type not in ("cuda", "mps"):
        raise ValueError(f"{key}={device}: expected cpu, cuda[:i] or mps")


def _unwritable(folder: Path) -> str | None:
    """Why files cannot be written in ``folder`` (made with its parents where missing), or None; creates nothing."""
    existing = next(p for p in (folder, *folder.parents) if p.exists())
    if not existing.is_dir():
        return f"{existing} is not a folder"
    if not os.access(existing, os.W_OK | os.X_OK):  # also false on a read-only file system, even for root
        return f"{existing} is not writable"
    return None


def check_writable(folder: str | os.PathLike, key: str) -> None:
    """``folder`` is, or can be made, a folder this process may write in (creates nothing).

    Raises:
        NotWritableError: naming ``key`` and ``folder``.
    """
    folder = Path(folder).expanduser()
    if (reason := _unwritable(folder)) is not None:
        raise NotWritableError(f"{key}={folder}: cannot write there ({reason})")


def check_artifact_cache(surrogate: Mapping) -> None:
    """A surrogate config (``name``, ``path``, ``dataset``) that loads from the default cache, where a missing
    model is trained and saved on first use, finds that folder filled already (a read-only shared cache is fine)
    or writable; ``none``, ``gym_anm`` and an explicit ``path`` need no cache.

    Raises:
        NotWritableError: naming ``ANM_TORCHRL_HOME``.
    """
    from anm_torchrl.paths import artifact_home, surrogate_dir
    from anm_torchrl.training.config_checks import TRUE_SIMULATORS

    if surrogate["name"] in TRUE_SIMULATORS or surrogate.get("path") is not None:
        return
    folder = surrogate_dir(surrogate["name"], surrogate.get("dataset"))
    if folder.is_dir() and os.access(folder, os.R_OK | os.X_OK) and any(folder.iterdir()):
        return
    if (reason := _unwritable(folder)) is not None:
        raise NotWritableError(f"cannot write the artifact cache {artifact_home()} ({reason}); set ANM_TORCHRL_HOME "
                               "to a writable folder, or give surrogate.path=")
