"""Committed network cases on disk: one ``.npz`` per feeder under ``networks/data/``, hash-checked at load.

A case file holds the gym-anm network tables (float64, NaN where gym-anm takes ``None``), the exogenous
profiles in gym-anm's injection sign convention (``load_p`` <= 0, ``gen_p_max`` >= 0, MW, float32 to keep the
files small; widened to float64 at load) and a JSON ``meta`` string (source, citation, import defaults,
do-nothing power-flow summary). The sha256 of every file is listed in ``data/SHA256SUMS``; :func:`load_case`
refuses a file whose hash differs. NumPy's ``allow_pickle=False`` keeps the format unable to run code.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from pathlib import Path

import numpy as np

DATA_DIR = Path(__file__).with_name("data")
SUMS_FILE = DATA_DIR / "SHA256SUMS"
TABLES = ("bus", "device", "branch")


def sha256(path: Path) -> str:
    """Hex sha256 of a file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _read_sums() -> dict[str, str]:
    if not SUMS_FILE.exists():
        return {}
    sums = {}
    for line in SUMS_FILE.read_text().splitlines():
        if line.strip():
            digest, name = line.split()
            sums[name] = digest
    return sums


def save_case(name: str, network: dict, load_p: np.ndarray, gen_p_max: np.ndarray, meta: dict) -> Path:
    """Write ``data/<name>.npz`` atomically and record its sha256 in ``data/SHA256SUMS``.

    Args:
        name: registered network name.
        network: gym-anm dict (``baseMVA`` and float64 ``bus``/``device``/``branch`` tables, NaN = None).
        load_p: (T, n_load) MW load injections (<= 0), device-ID order.
        gen_p_max: (T, n_gen) MW potentials of the non-slack generators, device-ID order.
        meta: JSON-serialisable description (source, citation, defaults, checks).
    """
    buf = io.BytesIO()
    np.savez_compressed(
        buf, baseMVA=np.float64(network["baseMVA"]), **{k: np.asarray(network[k], np.float64) for k in TABLES},
        load_p=np.asarray(load_p, np.float32), gen_p_max=np.asarray(gen_p_max, np.float32),
        meta=np.array(json.dumps(meta, sort_keys=True)))
    DATA_DIR.mkdir(exist_ok=True)
    path = DATA_DIR / f"{name}.npz"
    tmp = path.with_suffix(".npz.tmp")
    tmp.write_bytes(buf.getvalue())
    os.replace(tmp, path)
    sums = _read_sums()
    sums[path.name] = sha256(path)
    SUMS_FILE.write_text("".join(f"{d}  {n}\n" for n, d in sorted(sums.items())))
    return path


def case_names() -> list[str]:
    """Names of the cases listed in ``data/SHA256SUMS`` (sorted)."""
    return sorted(n.removesuffix(".npz") for n in _read_sums())


def load_case(name: str) -> tuple[dict, np.ndarray, np.ndarray, dict, str]:
    """Read ``data/<name>.npz`` after checking its sha256.

    Returns:
        ``(network, load_p (T, n_load) float64 MW, gen_p_max (T, n_gen) float64 MW, meta, sha256)``.

    Raises:
        ValueError: the case is not listed, or the file's hash differs from ``SHA256SUMS``.
    """
    path = DATA_DIR / f"{name}.npz"
    sums = _read_sums()
    if path.name not in sums:
        raise ValueError(f"network case {name!r} is not listed in {SUMS_FILE} (listed: {case_names()})")
    digest = sha256(path)
    if digest != sums[path.name]:
        raise ValueError(f"{path}: sha256 {digest} differs from the recorded {sums[path.name]} (file changed)")
    with np.load(path, allow_pickle=False) as z:
        network = {"baseMVA": float(z["baseMVA"]), **{k: z[k].astype(np.float64) for k in TABLES}}
        load_p, gen_p_max = z["load_p"].astype(np.float64), z["gen_p_max"].astype(np.float64)
        meta = json.loads(str(z["meta"]))
    return network, load_p, gen_p_max, meta, digest


def to_gym_anm(network: dict) -> dict:
    """The dict as gym-anm 2.0.1 reads it: object tables with ``None`` where this package stores NaN.

    gym-anm tests ``x is None`` for its defaults; a NaN would pass through its checks and poison the physics.
    """
    def obj(a: np.ndarray) -> np.ndarray:
        out = np.asarray(a, dtype=np.float64).astype(object)
        out[np.isnan(np.asarray(a, dtype=np.float64))] = None
        return out

    return {"baseMVA": network["baseMVA"], **{k: obj(network[k]) for k in TABLES}}
