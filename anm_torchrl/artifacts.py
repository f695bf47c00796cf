"""Trust on disk: every saver and loader of the package goes through this module.

Five guarantees:

1. **Atomic writes.** :func:`atomic_write` (one file) and :func:`atomic_folder` (a folder) write into a sibling
   temporary path and rename it into place, so a killed save leaves either the previous artifact or the new one,
   never a half-written one. Temporaries of killed saves (their writer process is gone) are removed by the next
   save or load of the same path (:func:`clean_stale`).
2. **Content hashes checked at load.** Tensors are saved as safetensors (a format that cannot run code) with a
   SHA-256 of their content and the artifact ``kind`` in the header (:func:`save_tensors` / :func:`load_tensors`);
   non-finite weights are refused at save and at load. Folders carry a ``manifest.json`` (file -> SHA-256, kind,
   format version) that :func:`verify_manifest` checks *before* anything in the folder is deserialised, so a
   crafted pickle is never unpickled.
3. **Clear errors.** Every failure is an :class:`ArtifactError` (a ``ValueError``) naming the file and what failed.
4. **Exclusive writers.** :func:`exclusive_lock` creates a lock file atomically with its content (written and
   synced in a temporary file, then hard-linked into place): two writers of one path (e.g. two ``make_dataset``
   runs) cannot both write; the second fails with the holder's pid and host. A lock is never seen empty.
   Not ``filelock``: its locks wait or time out without saying who holds them, and its ``fcntl`` lock is advisory
   per host (a cache on a shared filesystem written from two hosts); here the second writer fails at once with the
   holder's pid and host, and the lock of a killed writer on this host is recognised and removed.
5. **Full disks are errors, not crashes.** :func:`reserve_space` allocates the blocks of files that are then
   filled through memory maps (a full disk there is a SIGBUS, not an exception); every saver that meets
   ``ENOSPC`` raises :class:`DiskFullError` naming the path and the space needed and free, leaving nothing behind.

Temporary and lock names (siblings of the artifact ``<dir>/<name>``)::

    .<name>.tmp-<host>-<pid>-<hex>     temporary file or folder of a save in progress
    .<name>.old-<host>-<pid>-<hex>     the previous folder while an overwrite swaps it out
    .<name>.lock                       exclusive lock (JSON: host, pid)

JSON written for users and tools goes through :func:`anm_torchrl.strict_json.json_text` (no bare ``NaN``).
"""

from __future__ import annotations

import contextlib
import errno
import glob
import hashlib
import json
import logging
import os
import shutil
import socket
import sys
import time
import uuid
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import torch

log = logging.getLogger(__name__)

FORMAT = "anm_torchrl.artifact"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
_HEADER_KEY = "anm_torchrl"  # the safetensors metadata entry holding our JSON header
_CHUNK = 1 << 20


class ArtifactError(ValueError):
    """An artifact is missing, corrupted, of the wrong kind, or unsafe to load. The message names the file."""


class LockedError(FileExistsError):
    """Another writer holds the lock of an artifact path."""


class DiskFullError(OSError):
    """The disk cannot hold an artifact (``errno.ENOSPC``); the message names the path and the space needed and
    free."""


# ------------------------------------------------------------------------------------------------- hashing
def sha256_file(path: str | os.PathLike) -> str:
    """SHA-256 (hex) of a file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def tensors_sha256(tensors: Mapping[str, torch.Tensor], header: Mapping[str, Any] | None = None) -> str:
    """SHA-256 (hex) of named tensors (name, dtype, shape, bytes, in sorted name order) and a JSON-able header."""
    h = hashlib.sha256()
    h.update(json.dumps(header or {}, sort_keys=True).encode())
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        h.update(f"|{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


# ---------------------------------------------------------------------------------------- temporary names
_HOST = socket.gethostname().replace("-", "_") or "host"
_UMASK = os.umask(0)  # read once at import (os.umask can only be read by setting it) ...
os.umask(_UMASK)  # ... and restored at once


def _tmp_name(path: Path, tag: str) -> Path:
    return path.parent / f".{path.name}.{tag}-{_HOST}-{os.getpid()}-{uuid.uuid4().hex[:8]}"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


def clean_stale(path: str | os.PathLike) -> list[Path]:
    """Remove temporaries of killed saves of ``path`` (written on this host by a process that no longer exists).

    Temporaries of live writers and of other hosts are left alone. Returns the removed paths.
    """
    path = Path(path)
    if not path.parent.is_dir():
        return []
    removed = []
    for p in path.parent.glob(f".{glob.escape(path.name)}.*-*-*-*"):
        tag_host_pid_hex = p.name[len(path.name) + 2:]
        try:
            rest, pid, _hex = tag_host_pid_hex.rsplit("-", 2)
            tag, host = rest.split("-", 1)
            pid_i = int(pid)
        except ValueError:
            continue
        if tag in ("tmp", "old") and host == _HOST and not _pid_alive(pid_i):
            _remove(p)
            removed.append(p)
    if removed:
        log.info("removed %d stale temporaries of killed saves of %s", len(removed), path)
    return removed


# ------------------------------------------------------------------------------------------- atomic saves
def atomic_write(path: str | os.PathLike, data: bytes | Callable[[Path], Any]) -> Path:
    """Write one file atomically: into a sibling temporary file, synced, then ``os.replace``'d onto ``path``.

    Args:
        path: destination file (its parent folder is created).
        data: the bytes to write, or a callable ``write(tmp_path)`` that writes the file at ``tmp_path``
            (e.g. ``lambda p: booster.save_model(str(p))``).

    Returns:
        ``path``. On any failure (or interruption) the previous file is intact and no temporary remains.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    clean_stale(path)
    tmp = _tmp_name(path, "tmp")
    try:
        if callable(data):
            data(tmp)
            if not tmp.is_file():
                raise ArtifactError(f"saving {path}: the writer did not create the file")
        else:
            with open(tmp, "wb") as f:
                f.write(data)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)  # the usual mode: some writers (safetensors) create files 0600
        os.replace(tmp, path)
    except BaseException as err:
        _remove(tmp)
        _raise_if_disk_full(err, path)
        raise
    return path


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike, overwrite: bool = False, kind: str | None = None) -> Iterator[Path]:
    """Write a folder atomically: ``with atomic_folder(p) as tmp:`` write into ``tmp``; on success it becomes ``p``.

    On an exception (or interruption) inside the block the temporary folder is removed and ``path`` is
    untouched. With ``overwrite`` an existing folder is replaced (it is renamed aside, the new one renamed in,
    then the old one removed) — with ``kind``, only a folder whose manifest names that kind of artifact: a user's
    file or folder given by mistake is never deleted; without ``overwrite`` an existing ``path`` raises
    ``FileExistsError`` before anything is written and again at the rename if it appeared meanwhile.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=true to replace it")
    if path.exists() and kind is not None:
        check_replaceable(path, kind)
    path.parent.mkdir(parents=True, exist_ok=True)
    clean_stale(path)
    tmp = _tmp_name(path, "tmp")
    tmp.mkdir()
    old = None
    try:
        yield tmp
        if path.exists():
            if not overwrite:
                raise FileExistsError(f"{path} appeared while it was being written; pass overwrite=true to replace it")
            if kind is not None:
                check_replaceable(path, kind)
            old = _tmp_name(path, "old")
            os.rename(path, old)
        os.rename(tmp, path)
    except BaseException:
        _remove(tmp)
        if old is not None and not path.exists():
            os.rename(old, path)  # put the previous folder back
            old = None
        _raise_if_disk_full(sys.exc_info()[1], path)
        raise
    finally:
        if old is not None:
            _remove(old)


def check_replaceable(path: Path, kind: str) -> None:
    """``FileExistsError`` unless ``path`` is an empty folder or one saved as a ``kind`` artifact (its manifest says
    so; its files may be damaged: a corrupted artifact may be replaced)."""
    if path.is_dir():
        if not any(path.iterdir()):
            return
        try:
            if json.loads((path / MANIFEST).read_text()).get("kind") == kind:
                return
        except (OSError, ValueError, AttributeError):  # no manifest, or not one of ours
            pass
    what = f"a folder that is not a saved {kind!r} artifact" if path.is_dir() else "a file"
    raise FileExistsError(f"{path} exists and is {what}: it is not replaced; remove it yourself or choose another path")


# ------------------------------------------------------------------------------------------- disk space
def _mb(n: int) -> str:
    return f"{n / 2**20:.1f} MiB"


def disk_full_error(path: str | os.PathLike, needed: int | None = None, err: OSError | None = None,
                    ) -> DiskFullError:
    """The :class:`DiskFullError` (``ENOSPC``) every saver raises on a full disk: it names ``path``, the bytes
    needed (when known) and the bytes free, and says that nothing was left behind."""
    path = Path(path)
    probe = next((p for p in (path, *path.parents) if p.exists()), Path("."))
    free = shutil.disk_usage(probe).free
    need = f"needs about {_mb(needed)}, " if needed is not None else ""
    cause = f" ({err.strerror or err})" if err is not None else ""
    return DiskFullError(errno.ENOSPC, f"no space left on the device of {probe} to write {path}{cause}: {need}"
                                 f"{_mb(free)} free; nothing was written (temporary files and lock removed, any "
                                 f"previous version is intact)")


def _raise_if_disk_full(err: BaseException | None, path: Path) -> None:
    """Re-raise an ``ENOSPC``/``EDQUOT`` ``OSError`` of a save of ``path`` as :class:`DiskFullError`."""
    if isinstance(err, OSError) and not isinstance(err, DiskFullError) and err.errno in (errno.ENOSPC,
                                                                                         errno.EDQUOT):
        raise disk_full_error(path, err=err) from err


def reserve_space(files: Mapping[str | os.PathLike, int], artifact: str | os.PathLike) -> None:
    """Allocate the blocks of the files a memory map will fill (``posix_fallocate``), after checking free space.

    A write through a memory map into a sparse file on a full disk kills the process with SIGBUS (no exception,
    no cleanup); with its blocks allocated first, a full disk is an ``OSError`` here instead.

    Args:
        files: path -> size in bytes of each file to create (parents are created; size-0 files are skipped).
        artifact: the artifact being written, named in the error.

    Raises:
        OSError: ``ENOSPC`` (:func:`disk_full_error`) when the disk cannot hold them.
    """
    files = {Path(f): int(n) for f, n in files.items() if int(n) > 0}
    if not files:
        return
    total = sum(files.values())
    first = next(iter(files))
    first.parent.mkdir(parents=True, exist_ok=True)
    if shutil.disk_usage(first.parent).free < total:
        raise disk_full_error(artifact, total)
    for f, n in files.items():
        f.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(f, os.O_WRONLY | os.O_CREAT, 0o666)
        try:
            if hasattr(os, "posix_fallocate"):
                os.posix_fallocate(fd, 0, n)
            else:  # no fallocate (macOS): write the zeros, so the blocks exist
                for start in range(0, n, _CHUNK):
                    os.write(fd, bytes(min(_CHUNK, n - start)))
        except OSError as err:
            if err.errno in (errno.ENOSPC, errno.EDQUOT):
                raise disk_full_error(artifact, total, err) from err
            raise
        finally:
            os.close(fd)


# --------------------------------------------------------------------------------------------- safetensors
def _check_finite(tensors: Mapping[str, torch.Tensor], where: str) -> None:
    for name, t in tensors.items():
        if (t.is_floating_point() or t.is_complex()) and not bool(torch.isfinite(t).all()):
            raise ArtifactError(f"{where}: tensor {name!r} {tuple(t.shape)} holds NaN or inf values")


def save_tensors(path: str | os.PathLike, tensors: Mapping[str, torch.Tensor], metadata: Mapping[str, Any] | None,
                 kind: str) -> Path:
    """Save named tensors as a safetensors file (atomically) with ``kind``, ``metadata`` and a content hash.

    Args:
        path: destination file (``.safetensors`` by convention).
        tensors: name -> tensor (moved to CPU, made contiguous); every float tensor must be finite.
        metadata: JSON-able dict stored in the header (architecture, training config, ...); covered by the hash.
        kind: artifact kind, e.g. ``"anm_torchrl.pinn"``; :func:`load_tensors` refuses another kind.

    Raises:
        ArtifactError: a tensor holds NaN/inf, or ``metadata`` is not JSON-able.
    """
    from safetensors.torch import save_file

    path = Path(path)
    cpu = {k: v.detach().cpu().contiguous() for k, v in tensors.items()}
    _check_finite(cpu, f"refusing to save {path}")
    header = {"format": FORMAT, "format_version": FORMAT_VERSION, "kind": kind, "metadata": dict(metadata or {})}
    try:
        header_json = json.dumps(header, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as err:
        raise ArtifactError(f"refusing to save {path}: metadata is not JSON-able ({err})") from err
    digest = tensors_sha256(cpu, json.loads(header_json))
    meta = {_HEADER_KEY: header_json, "sha256": digest}
    return atomic_write(path, lambda tmp: save_file(cpu, str(tmp), metadata=meta))


def load_tensors(path: str | os.PathLike, kind: str, device: str | torch.device = "cpu",
                 ) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Load a file written by :func:`save_tensors` and check it before returning anything.

    Returns:
        ``(tensors, metadata)``.

    Raises:
        ArtifactError: the file is missing, not a safetensors file, not an anm_torchrl artifact, of another
            ``kind`` or format version, its content hash does not match, or a float tensor holds NaN/inf.
    """
    from safetensors import SafetensorError, safe_open
    from safetensors.torch import load_file

    path = Path(path)
    clean_stale(path)
    if not path.is_file():
        raise ArtifactError(f"{path}: no such file")
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
        tensors = load_file(str(path))
    except (SafetensorError, OSError, ValueError, RuntimeError) as err:
        raise ArtifactError(f"{path} is not a readable safetensors file ({type(err).__name__}: {err})") from err
    try:
        header = json.loads(meta[_HEADER_KEY])
        recorded = meta["sha256"]
    except (KeyError, ValueError) as err:
        raise ArtifactError(f"{path} is a safetensors file but not an anm_torchrl artifact (no {_HEADER_KEY!r} "
                            f"header with a sha256)") from err
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise ArtifactError(f"{path}: header format is {header.get('format') if isinstance(header, dict) else header!r}"
                            f", expected {FORMAT!r}")
    if header.get("kind") != kind:
        raise ArtifactError(f"{path} holds a {header.get('kind')!r} artifact, expected {kind!r}")
    if header.get("format_version") != FORMAT_VERSION:
        raise ArtifactError(f"{path} has artifact format version {header.get('format_version')}, this package "
                            f"reads version {FORMAT_VERSION}")
    got = tensors_sha256(tensors, header)
    if got != recorded:
        raise ArtifactError(f"{path} is corrupted: content hash {got[:12]}… does not match the recorded "
                            f"{str(recorded)[:12]}…")
    _check_finite(tensors, f"{path} is corrupted")
    return {k: v.to(device) for k, v in tensors.items()}, header["metadata"]


# ------------------------------------------------------------------------------------------------ manifests
def write_manifest(folder: str | os.PathLike, kind: str, metadata: Mapping[str, Any] | None = None) -> Path:
    """Write ``<folder>/manifest.json``: SHA-256 of every other file under ``folder``, ``kind`` and ``metadata``.

    Call it last, inside :func:`atomic_folder`, once every file of the artifact is written.
    """
    folder = Path(folder)
    files = {p.relative_to(folder).as_posix(): sha256_file(p)
             for p in sorted(folder.rglob("*")) if p.is_file() and p.name != MANIFEST}
    doc = {"format": FORMAT, "format_version": FORMAT_VERSION, "kind": kind, "files": files,
           "metadata": dict(metadata or {})}
    try:
        text = json.dumps(doc, indent=2, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as err:
        raise ArtifactError(f"refusing to write {folder / MANIFEST}: metadata is not JSON-able ({err})") from err
    return atomic_write(folder / MANIFEST, text.encode())


def verify_manifest(folder: str | os.PathLike, kind: str) -> dict[str, Any]:
    """Check every file of ``folder`` against its manifest before anything in it is deserialised.

    Returns:
        The manifest's ``metadata``.

    Raises:
        ArtifactError: no folder or manifest, wrong kind or format version, a listed file missing or with another
            hash, or a file present that the manifest does not list.
    """
    folder = Path(folder)
    clean_stale(folder)
    mf = folder / MANIFEST
    if not folder.is_dir():
        raise ArtifactError(f"{folder}: no such artifact folder")
    if not mf.is_file():
        raise ArtifactError(f"{folder} has no {MANIFEST} (not a saved anm_torchrl artifact, or its save did not "
                            f"finish): nothing in it is loaded")
    try:
        doc = json.loads(mf.read_text())
        files = dict(doc["files"])
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ArtifactError(f"{mf} is not a valid manifest ({type(err).__name__}: {err})") from err
    if doc.get("format") != FORMAT or doc.get("kind") != kind:
        raise ArtifactError(f"{mf} describes a {doc.get('kind')!r} artifact (format {doc.get('format')!r}), "
                            f"expected {kind!r}")
    if doc.get("format_version") != FORMAT_VERSION:
        raise ArtifactError(f"{mf} has artifact format version {doc.get('format_version')}, this package reads "
                            f"version {FORMAT_VERSION}")
    present = {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file() and p.name != MANIFEST}
    extra = sorted(present - set(files))
    if extra:
        raise ArtifactError(f"{folder} holds files its manifest does not list: {extra}; nothing in it is loaded")
    for name, want in files.items():
        f = folder / name
        if not f.is_file():
            raise ArtifactError(f"{f} is missing (listed in {mf})")
        got = sha256_file(f)
        if got != want:
            raise ArtifactError(f"{f} is corrupted: sha256 {got[:12]}… does not match the manifest's {want[:12]}…")
    return dict(doc.get("metadata") or {})


# ------------------------------------------------------------------------------------------------- locking
def _lock_path(path: Path) -> Path:
    return path.parent / f".{path.name}.lock"


def _read_lock(lock: Path) -> dict[str, Any]:
    try:
        holder = json.loads(lock.read_text())
    except (OSError, ValueError):
        return {}
    return holder if isinstance(holder, dict) else {}


STALE_EMPTY_LOCK_S = 10.0  # an empty or unreadable lock older than this is the debris of a failed lock write


def _write_lock(lock: Path, content: bytes) -> bool:
    """Create ``lock`` holding ``content``, atomically: the content is written and synced in a temporary file that
    is then hard-linked to ``lock`` (``os.link`` fails if ``lock`` exists), so a lock is never seen empty or half
    written. Returns False if ``lock`` exists; on any failure (a full disk) nothing is left behind."""
    tmp = _tmp_name(lock, "tmp")
    try:
        fd = os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        try:
            os.write(fd, content)
            os.fsync(fd)
        finally:
            os.close(fd)
        try:
            os.link(tmp, lock)
        except FileExistsError:
            return False
        except OSError as err:  # file systems without hard links: exclusive create, then write (not atomic)
            if err.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK):
                raise
            try:
                fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                return False
            try:
                os.write(fd, content)
                os.fsync(fd)
            except BaseException:
                os.close(fd)
                lock.unlink()
                raise
            os.close(fd)
        return True
    except OSError as err:
        if err.errno in (errno.ENOSPC, errno.EDQUOT):
            raise disk_full_error(lock, len(content), err) from err
        raise
    finally:
        _remove(tmp)


def _is_stale(lock: Path, holder: dict[str, Any]) -> bool:
    """A lock of a killed writer on this host, or an empty/unreadable one older than :data:`STALE_EMPTY_LOCK_S`."""
    if holder.get("host") == _HOST and isinstance(holder.get("pid"), int):
        return not _pid_alive(holder["pid"])
    if not {"host", "pid"} <= set(holder):
        try:
            age = time.time() - lock.stat().st_mtime
        except FileNotFoundError:
            return False
        return age > STALE_EMPTY_LOCK_S
    return False


@contextlib.contextmanager
def exclusive_lock(path: str | os.PathLike) -> Iterator[Path]:
    """Hold the exclusive write lock of ``path`` (a sibling ``.<name>.lock``, created atomically with its content).

    A lock left by a killed writer on this host (its pid no longer exists), or an empty or unreadable lock older
    than :data:`STALE_EMPTY_LOCK_S` seconds (left by a failed lock write of an earlier version), is broken, under
    a second exclusive lock so that two processes cannot both break it.

    Raises:
        LockedError: another live writer (or one on another host) holds the lock; the message names it.
        DiskFullError: the lock cannot be written (nothing is left behind).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lock = _lock_path(path)
    clean_stale(lock)
    me = json.dumps({"host": _HOST, "pid": os.getpid()}).encode()
    for attempt in range(2):
        if _write_lock(lock, me):
            break
        holder = _read_lock(lock)
        if attempt == 0 and _is_stale(lock, holder) and _break_stale(lock, holder):
            continue
        if not {"host", "pid"} <= set(holder):
            raise LockedError(f"{path} is locked by {lock}, which is empty or unreadable (a lock write that did not "
                              f"finish, or one in progress); it is treated as stale once older than "
                              f"{STALE_EMPTY_LOCK_S:.0f} s: retry then, or remove it if no writer runs") from None
        raise LockedError(f"{path} is being written by another process (lock {lock}: host "
                          f"{holder.get('host')!r}, pid {holder.get('pid')}); wait for it, or remove the lock "
                          f"file if no such process runs") from None
    try:
        yield lock
    finally:
        if _read_lock(lock).get("pid") == os.getpid():
            with contextlib.suppress(FileNotFoundError):
                lock.unlink()


def _break_stale(lock: Path, holder: dict[str, Any]) -> bool:
    """Remove ``lock`` if it still holds ``holder`` (a dead writer), under an exclusive ``.break`` lock."""
    breaker = lock.with_name(lock.name + ".break")
    try:
        fd = os.open(breaker, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    os.close(fd)
    try:
        if _read_lock(lock) == holder:
            lock.unlink()
            log.warning("removed the stale lock %s (%s)", lock, f"a killed writer, pid {holder['pid']}"
                        if "pid" in holder else "empty or unreadable: a lock write that did not finish")
            return True
        return False
    finally:
        breaker.unlink()
