"""Networks: gym-anm network dicts with their profiles, by registered name (:func:`get_network`), and the one
function that turns a name, a registered case or a user's dict into a simulator (:func:`simulator`).

:func:`simulator` loads on first use: the registry alone (names, tables) imports without torch, so
``import anm_torchrl.gym`` registers its ids cheaply.
"""

from anm_torchrl.networks.registry import ANM6_EASY, NetworkCase, get_network, list_networks

__all__ = ["ANM6_EASY", "NetworkCase", "get_network", "list_networks", "simulator"]


def __getattr__(name: str):
    if name == "simulator":
        from anm_torchrl.networks.resolve import simulator

        return simulator
    raise AttributeError(f"module 'anm_torchrl.networks' has no attribute {name!r}")
