"""Which network a dataset or surrogate is built for: default folders keyed by the network's content.

The datasets, surrogates and recipes take a ready ``sim`` (``anm_torchrl.networks.simulator(<name, case or
dict>)``). Artifacts of ANM6-Easy keep their historical default folders; every other network gets the folder
suffixed with its :func:`anm_torchrl.grid.identity.network_key` (tables and constants), so a changed network never
reads a stale model or dataset. A dataset also depends on the profiles (its rows are their transitions), which the
network key leaves out: :func:`for_dataset` suffixes the folder with the simulator fingerprint as well, unless the
profiles are the ones the network ships with.
"""

from __future__ import annotations

import functools
import logging
from pathlib import Path

from anm_torchrl.grid.identity import network_key, simulator_fingerprint
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.networks.registry import builtin_networks
from anm_torchrl.networks.resolve import is_anm6, simulator


def for_network(folder: Path, sim: GridSimulator) -> Path:
    """``folder`` for ANM6-Easy (unchanged defaults), else ``<folder>_<network key>`` for ``sim``'s network."""
    folder = Path(folder)
    return folder if is_anm6(sim) else folder.with_name(f"{folder.name}_{network_key(sim)}")


def for_dataset(folder: Path, sim: GridSimulator) -> Path:
    """The default folder of a dataset of ``sim``: :func:`for_network`, further suffixed with
    ``_<simulator fingerprint>`` (:func:`anm_torchrl.grid.identity.simulator_fingerprint`, which hashes the profiles)
    unless ``sim`` runs a shipped network with its own profiles, whose folders keep their names. Two profile sets of
    one network get two folders: :func:`anm_torchrl.data.load_dataset` refuses a dataset of other profiles, so a
    shared folder would make each profile set refuse the other's dataset."""
    folder = for_network(folder, sim)
    fingerprint = simulator_fingerprint(sim)
    if _shipped_fingerprints().get(network_key(sim)) == fingerprint:
        return folder
    return folder.with_name(f"{folder.name}_{fingerprint}")


@functools.lru_cache(maxsize=1)
def _shipped_fingerprints() -> dict[str, str]:
    """``{network key: simulator fingerprint}`` of every shipped network with its own profiles (built once, ~0.2 s)."""
    # a comparison, not a run on them: their profile clipping is not news for the user's network
    sims = [simulator(name, profile_clip_level=logging.DEBUG) for name in builtin_networks()]
    return {network_key(s): simulator_fingerprint(s) for s in sims}
