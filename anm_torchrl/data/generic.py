"""Which network a dataset or surrogate is built for: default folders keyed by the network's content.

The datasets, surrogates and recipes take a ready ``sim`` (``anm_torchrl.networks.simulator(<name, case or
dict>)``). Artifacts of ANM6-Easy keep their historical default folders; every other network gets the folder
suffixed with its :func:`anm_torchrl.grid.identity.network_key` (tables and constants), so a changed network never
reads a stale model or dataset.
"""

from __future__ import annotations

from pathlib import Path

from anm_torchrl.grid.identity import network_key
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.networks.resolve import is_anm6


def for_network(folder: Path, sim: GridSimulator) -> Path:
    """``folder`` for ANM6-Easy (unchanged defaults), else ``<folder>_<network key>`` for ``sim``'s network."""
    folder = Path(folder)
    return folder if is_anm6(sim) else folder.with_name(f"{folder.name}_{network_key(sim)}")
