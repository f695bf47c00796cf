"""Networks: gym-anm network dicts with their profiles, by registered name (:func:`get_network`)."""

from anm_torchrl.networks.registry import NetworkCase, get_network, list_networks

__all__ = ["NetworkCase", "get_network", "list_networks"]
