"""Networks: gym-anm network dicts with their profiles, by registered name (:func:`get_network`), and the one
function that turns a name, a registered case or a user's dict into a simulator (:func:`simulator`). A user's
network is registered by name (:func:`register_network`) or saved to a file any recipe takes by path
(:func:`save_network`, ``network=path/to/feeder.npz``).

:func:`simulator` loads on first use: the registry alone (names, tables) imports without torch, so
``import anm_torchrl.gym`` registers its ids cheaply.
"""

from anm_torchrl.lazy import lazy_exports
from anm_torchrl.networks.case import NetworkCase
from anm_torchrl.networks.registry import (ANM6_EASY, check_network_name, get_network, list_networks, register_network,
                                           unregister_network)
from anm_torchrl.networks.user import load_network_file, save_network

__all__ = ["ANM6_EASY", "NetworkCase", "check_network_name", "get_network", "list_networks", "load_network_file",
           "is_anm6", "register_network", "save_network", "simulator", "unregister_network"]


__getattr__, __dir__ = lazy_exports(__name__, dict.fromkeys(["simulator", "is_anm6"], "resolve"))
