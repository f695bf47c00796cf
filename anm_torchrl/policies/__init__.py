"""Trained policies shipped with the package, to try at once: ``recipes/evaluate.py checkpoint=pretrained:<name>``.

Each is a training checkpoint (``anm_torchrl.training.checkpoint``, any algorithm) whose sha256 is listed in
``SHA256SUMS`` next to it; :func:`pretrained_path` checks it before anything is loaded, and the checkpoint's own
content hash is checked at load. ``README.md`` in this folder says how each was trained and what it scores.
"""

from __future__ import annotations

from pathlib import Path

from anm_torchrl.artifacts import sha256_file

FOLDER = Path(__file__).resolve().parent
SUMS = FOLDER / "SHA256SUMS"
PREFIX = "pretrained:"


def _sums() -> dict[str, str]:
    if not SUMS.is_file():
        return {}
    rows = (line.split() for line in SUMS.read_text().splitlines() if line.strip())
    return {Path(name).stem: digest for digest, name in rows}


def available_pretrained() -> list[str]:
    """Names of the shipped policies (``pretrained:<name>``)."""
    return sorted(_sums())


def pretrained_path(name: str) -> Path:
    """The checkpoint file of a shipped policy, after checking its sha256 against ``SHA256SUMS``.

    Raises:
        ValueError: an unknown name (the message lists the shipped ones), or a file whose hash differs.
        FileNotFoundError: a listed policy whose file is missing from the install.
    """
    sums = _sums()
    if name not in sums:
        raise ValueError(f"no pretrained policy {name!r}; shipped: {', '.join(sorted(sums)) or 'none'}")
    path = FOLDER / f"{name}.pt"
    if not path.is_file():
        raise FileNotFoundError(f"pretrained policy {name!r} is listed in {SUMS} but {path} is missing")
    got = sha256_file(path)
    if got != sums[name]:
        raise ValueError(f"{path} is corrupted: sha256 {got[:12]}… differs from {sums[name][:12]}… in {SUMS.name}")
    return path


def resolve(checkpoint: str | Path) -> Path:
    """``pretrained:<name>`` -> the shipped file (hash-checked); any other value -> itself as a path."""
    text = str(checkpoint)
    return pretrained_path(text[len(PREFIX):]) if text.startswith(PREFIX) else Path(text)


def publish(checkpoint: str | Path, name: str) -> Path:
    """Copy a training checkpoint into this folder as ``<name>.pt`` (validated first, and refused without its
    network's key) and record its sha256."""
    from anm_torchrl.artifacts import atomic_write
    from anm_torchrl.training.checkpoint import load_checkpoint

    ckpt = load_checkpoint(checkpoint)  # refuse anything that is not a valid checkpoint
    if ckpt.get("network_key") is None:  # evaluate.py could not tell a policy of another version of its network
        raise ValueError(f"{checkpoint} records no network key (a checkpoint from before they were recorded): "
                         f"a shipped policy must name the network it was trained on; retrain it")
    target = atomic_write(FOLDER / f"{name}.pt", Path(checkpoint).read_bytes())
    sums = {**_sums(), name: sha256_file(target)}
    atomic_write(SUMS, "".join(f"{d}  {n}.pt\n" for n, d in sorted(sums.items())).encode())
    return target
