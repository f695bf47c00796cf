"""A user's own network: checked as gym-anm checks it (:func:`checked_case`, which
:func:`anm_torchrl.networks.register_network` registers by name), or saved to a network file that any recipe
takes by path (:func:`save_network`; ``python recipes/ppo.py network=path/to/feeder.npz``).

A network file is a NumPy ``.npz`` (``allow_pickle=False``: it cannot run code) holding

* ``format`` (:data:`FORMAT`) and ``format_version`` (:data:`FORMAT_VERSION`);
* ``baseMVA`` and the gym-anm tables ``bus``, ``device``, ``branch`` (float64, NaN where gym-anm takes ``None``);
* ``load_p`` (T, n_load) and ``gen_p_max`` (T, n_gen), MW, float64, device-id order;
* ``meta``: a JSON string with the env constants (``delta_t`` h, ``gamma``, ``lamb``, ``costs_clipping``) and
  the user's ``source`` text.

Every path (a registration, a save, a load) runs the same checks as :func:`anm_torchrl.networks.simulator`
(gym-anm's, :mod:`anm_torchrl.networks.validation`), so an invalid network is refused with the table, row and
column named before anything is stored or trained.
"""

from __future__ import annotations

import io
import json
import math
import os
import zipfile
from pathlib import Path

import numpy as np

from anm_torchrl.networks.case import make_case
from anm_torchrl.networks.case_file import TABLES

FORMAT = "anm_torchrl.network"
FORMAT_VERSION = 1
SUFFIX = ".npz"
# gym-anm's ANMEnv defaults: what a user's network runs with unless told otherwise
DEFAULT_CONSTANTS = {"delta_t": 0.25, "gamma": 0.995, "lamb": 100.0, "costs_clipping": (1.0, 100.0)}
USER_SOURCE = "a user's network"

def is_network_file(name: str) -> bool:
    """Whether a ``network=`` value names a network file (ends with ``.npz``) rather than a registered name."""
    return isinstance(name, (str, os.PathLike)) and str(name).endswith(SUFFIX)


def network_label(value) -> str:
    """A file or folder name part for ``network=``: a network file's stem (its path would nest folders), a
    registered name as it is."""
    return Path(str(value)).stem if is_network_file(value) else str(value)


def network_argument(value, base_dir: str | os.PathLike):
    """A recipe's ``network=`` value with a relative network-file path made absolute against ``base_dir`` (where
    the command was typed: Hydra changes the working directory to the run directory); names pass unchanged."""
    if value is None or not is_network_file(value) or os.path.isabs(str(value)):
        return value
    return str(Path(base_dir) / str(value))


def checked_case(name: str, network: dict, load_p, gen_p_max, *, delta_t=None, gamma=None, lamb=None,
                 costs_clipping=None, source: str = USER_SOURCE, meta: dict | None = None):
    """A :class:`~anm_torchrl.networks.case.NetworkCase` of a user's network after gym-anm's checks
    (tables normalised, profiles as float64 (T, n) MW, constants defaulting to :data:`DEFAULT_CONSTANTS`).

    Raises:
        ValueError: an invalid table (naming table, row and column), profile (naming the profile and the device
            ids it must follow) or constant (naming it).
    """
    from anm_torchrl.networks.validation import check_reward_args, validate_network, validate_profiles

    if not isinstance(network, dict):
        raise ValueError(f"network must be a gym-anm network dict, got {type(network).__name__}")
    given = {"delta_t": delta_t, "gamma": gamma, "lamb": lamb, "costs_clipping": costs_clipping}
    c = {k: DEFAULT_CONSTANTS[k] if v is None else v for k, v in given.items()}
    net = validate_network(network)  # gym-anm's checks; the case keeps the tables as given (NaN = None)
    given_net = {"baseMVA": float(network["baseMVA"]), **{k: np.asarray(network[k], np.float64) for k in TABLES}}
    load_p, gen_p_max = validate_profiles(net, load_p, gen_p_max)
    check_reward_args(c["delta_t"], c["gamma"], c["lamb"], c["costs_clipping"])
    clip = tuple(None if v is None or math.isinf(float(v)) else float(v) for v in c["costs_clipping"])
    return make_case(name, given_net, load_p, gen_p_max, float(c["delta_t"]), float(c["gamma"]), float(c["lamb"]), clip,
                     str(source), dict(meta or {}))


def save_network(path: str | os.PathLike, network: dict, load_p, gen_p_max, *, delta_t: float | None = None,
                 gamma: float | None = None, lamb: float | None = None, costs_clipping=None,
                 source: str = USER_SOURCE) -> Path:
    """Check a user's network (:func:`checked_case`) and write it to the network file ``path``
    (``.npz``; written to a temporary file first, then renamed: an interrupted save leaves any old file intact).

    Returns:
        The path written.

    Raises:
        ValueError: ``path`` does not end with ``.npz``, or the network is invalid (nothing is written then).
    """
    path = Path(path)
    if path.suffix != SUFFIX:
        raise ValueError(f"a network file ends with {SUFFIX}, got {path}")
    case = checked_case(path.stem, network, load_p, gen_p_max, delta_t=delta_t, gamma=gamma, lamb=lamb,
                        costs_clipping=costs_clipping, source=source)
    meta = {"env": {"delta_t": case.delta_t, "gamma": case.gamma, "lamb": case.lamb,
                    "costs_clipping": list(case.costs_clipping)}, "source": case.source}
    buf = io.BytesIO()
    np.savez_compressed(buf, format=np.array(FORMAT), format_version=np.int64(FORMAT_VERSION),
                        baseMVA=np.float64(network["baseMVA"]),  # as given (NaN = None): re-checked at load
                        **{k: np.asarray(network[k], np.float64) for k in TABLES},
                        load_p=np.asarray(case.load_p, np.float64), gen_p_max=np.asarray(case.gen_p_max, np.float64),
                        meta=np.array(json.dumps(meta, sort_keys=True)))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(buf.getvalue())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def load_network_file(path: str | os.PathLike):
    """The :class:`~anm_torchrl.networks.case.NetworkCase` of the network file ``path`` (named by its stem),
    checked as :func:`checked_case` checks a dict.

    Raises:
        ValueError: a missing file, a file that is not a network file (another ``.npz``, a corrupted archive, a
            missing or mistyped entry, another format version), or an invalid network — naming the file and what
            is wrong (for a table: table, row and column).
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"network file {path} does not exist (write one with anm_torchrl.networks.save_network)")
    if not zipfile.is_zipfile(path):  # np.load reads a plain .npy (an array, not an archive) without a word
        raise ValueError(f"{path} is not a readable network file (not an .npz archive; write one with "
                         "anm_torchrl.networks.save_network)")
    try:
        with np.load(path, allow_pickle=False) as z:
            entries = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
        raise ValueError(f"{path} is not a readable network file ({type(err).__name__}: {err})") from None
    if "format" not in entries or str(entries["format"]) != FORMAT:
        raise ValueError(f"{path} is not an anm_torchrl network file (no format={FORMAT!r} entry; write one with "
                         f"anm_torchrl.networks.save_network)")
    try:
        stored = np.asarray(entries.get("format_version", -1))
        if stored.dtype.kind not in "iu" or stored.ndim:  # 1.7 read as 1 before
            raise TypeError(f"an integer, got {stored!r}")
        version = int(stored)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path}: unreadable format_version entry ({type(err).__name__}: {err})") from None
    if version != FORMAT_VERSION:
        raise ValueError(f"{path}: network file format version {version}, this package reads {FORMAT_VERSION}")
    missing = [k for k in ("baseMVA", *TABLES, "load_p", "gen_p_max", "meta") if k not in entries]
    if missing:
        raise ValueError(f"{path}: network file without {missing}")
    # real numbers only: a complex table lost its imaginary part and a string one was parsed without a word
    mistyped = [f"{k} ({entries[k].dtype})" for k in ("baseMVA", *TABLES, "load_p", "gen_p_max")
                if entries[k].dtype.kind not in "fiu"]
    if mistyped:
        raise ValueError(f"{path}: entries {', '.join(mistyped)} must hold real numbers")
    try:
        meta = json.loads(str(entries["meta"]))
        env = meta["env"]
        if not isinstance(meta, dict) or not isinstance(env, dict):
            raise TypeError(f"meta must be a JSON object with an 'env' object, got {str(entries['meta'])[:80]}")
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: unreadable meta entry ({type(err).__name__}: {err})") from None
    try:
        network = {"baseMVA": float(entries["baseMVA"]), **{k: entries[k] for k in TABLES}}
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path}: baseMVA must be one number, got {entries['baseMVA']!r} ({err})") from None
    try:
        return checked_case(path.stem, network, entries["load_p"], entries["gen_p_max"],
                            delta_t=env.get("delta_t"), gamma=env.get("gamma"), lamb=env.get("lamb"),
                            costs_clipping=env.get("costs_clipping"), source=meta.get("source", USER_SOURCE),
                            meta={"file": str(path)})
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None
