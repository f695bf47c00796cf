"""Which network a dataset or surrogate is built for: the simulator of a registered network name, and default
folders keyed by the network's content.

The datasets, surrogates and recipes take ``network=<registered name>`` (``anm_torchrl.networks.list_networks``)
or a ready ``sim`` (any network, e.g. ``ANMEnv(network=<dict>, ...).sim``). Artifacts of ANM6-Easy keep their
historical default folders; every other network gets the folder suffixed with its
:func:`anm_torchrl.data.storage.network_key` (tables and constants), so a changed network never reads a stale
model or dataset.
"""

from __future__ import annotations

import functools
from pathlib import Path

from anm_torchrl.data.storage import network_key
from anm_torchrl.grid.simulator import GridSimulator, anm6_easy_simulator

ANM6 = "anm6_easy"


def simulator_for(network: str | None = None, device=None, backend: str = "auto") -> GridSimulator:
    """The :class:`GridSimulator` of a registered network (with its registered profiles and env constants), built
    as ``ANMEnv`` and ``make_env(network=name)`` build it (:func:`anm_torchrl.envs.anm_env.build_simulator`:
    gym-anm's defaults filled in), so what a recipe saves under this simulator's network key is what
    ``make_env`` looks up.

    Args:
        network: a name of :func:`anm_torchrl.networks.list_networks`; None or ``"anm6_easy"``: ANM6-Easy.
        device: torch device (None: CPU).
        backend: ``"auto"``, ``"numba"`` or ``"torch"`` (:class:`GridSimulator`).

    Raises:
        ValueError: an unknown name (the message lists the registered ones).
    """
    if network is None or network == ANM6:
        return anm6_easy_simulator(device=device, backend=backend)
    if not isinstance(network, str):
        raise ValueError(f"network must be a registered network name, got {type(network).__name__} "
                         "(for a network dict pass sim=ANMEnv(network=..., load_p=..., gen_p_max=...).sim)")
    from anm_torchrl.envs.anm_env import build_simulator  # here: the envs import torchrl, the data package need not
    from anm_torchrl.networks import get_network

    c = get_network(network)
    return build_simulator(c.network, c.load_p, c.gen_p_max, c.delta_t, c.gamma, c.lamb, c.costs_clipping,
                           device=device, backend=backend)


@functools.lru_cache(maxsize=1)
def _anm6_key() -> str:
    return network_key(anm6_easy_simulator())


def is_anm6(sim: GridSimulator | None) -> bool:
    """Whether ``sim`` is ANM6-Easy's network (None counts as ANM6-Easy, the loaders' default)."""
    return sim is None or network_key(sim) == _anm6_key()


def for_network(folder: Path, sim: GridSimulator | None) -> Path:
    """``folder`` for ANM6-Easy (unchanged defaults), else ``<folder>_<network key>`` for ``sim``'s network."""
    folder = Path(folder)
    return folder if is_anm6(sim) else folder.with_name(f"{folder.name}_{network_key(sim)}")
