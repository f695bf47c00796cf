"""Registered networks: :func:`get_network` by name, :func:`list_networks` for every name.

``anm6_easy`` is built from :mod:`anm_torchrl.networks.anm6_easy`; the imported feeders load from the
committed case files under ``networks/data/`` (hash-checked, no pandapower needed). How each feeder was made,
its sizes and its citation are in ``NetworkCase.source`` and in ``networks/data/README.md``; re-run an import
with ``python -m anm_torchrl.networks.feeders --name <name>``.
"""

from __future__ import annotations

import os

from anm_torchrl.networks import anm6_easy
from anm_torchrl.networks.case import NetworkCase, make_case
from anm_torchrl.networks import user
from anm_torchrl.networks.case_file import load_case
from anm_torchrl.networks.user import USER_SOURCE

ANM6_EASY = "anm6_easy"  # the one spelling of gym-anm's ANM6-Easy network name; import it, do not re-type it
# Feeders imported from pandapower / SimBench; their case files live in networks/data/.
IMPORTED = ("case33bw", "cigre_mv", "simbench_mv_semiurb")

ANM6_SOURCE = ("gym-anm 2.0.1 ANM6-Easy (Henry & Ernst, 'Gym-ANM: Reinforcement learning environments for "
               "active network management tasks in electricity distribution systems', Energy and AI 5, 2021); "
               "6 buses, 7 devices, 96-step (24 h) deterministic profiles")


def _anm6_easy() -> NetworkCase:
    m = anm6_easy
    return make_case(ANM6_EASY, m.network(), m.load_p(), m.gen_p_max(), m.DELTA_T, m.GAMMA, m.LAMB,
                     m.COSTS_CLIPPING, ANM6_SOURCE, {})


def _imported(name: str) -> NetworkCase:
    network, load_p, gen_p_max, meta, _ = load_case(name)
    env = meta["env"]
    return make_case(name, network, load_p, gen_p_max, env["delta_t"], env["gamma"], env["lamb"],
                     tuple(env["costs_clipping"]), meta["source"], meta)


_REGISTERED: dict[str, NetworkCase] = {}  # users' networks (register_network), this process only


def builtin_networks() -> list[str]:
    """The networks this package ships, ``anm6_easy`` first."""
    return [ANM6_EASY, *IMPORTED]


def list_networks() -> list[str]:
    """Every registered network name: the built-in ones, then those this process registered
    (:func:`anm_torchrl.networks.register_network`)."""
    return [*builtin_networks(), *_REGISTERED]


def get_network(name: str) -> NetworkCase:
    """The network ``name``: a registered name (see :func:`list_networks`) or the path of a network file
    (``.npz``, :func:`anm_torchrl.networks.save_network`; checked at load).

    Raises:
        ValueError: unknown name, a case file whose sha256 differs from the recorded one, or a network file that
            is missing, of another kind or invalid (naming the file and what is wrong).
    """
    if name == ANM6_EASY:
        return _anm6_easy()
    if name in IMPORTED:
        return _imported(name)
    if name in _REGISTERED:
        return _REGISTERED[name]
    if user.is_network_file(name):
        return user.load_network_file(name)
    raise ValueError(f"unknown network {name!r}; registered: {list_networks()}, or the path of a network file "
                     f"(.npz, written by anm_torchrl.networks.save_network)")


def check_network_name(value) -> None:
    """Refuse a recipe's ``network=`` value that is neither a registered name nor an existing network file,
    before anything heavy runs (the file's content is checked when it is loaded).

    Raises:
        ValueError: naming the value, the registered names and the file form.
    """
    if isinstance(value, os.PathLike):  # a pathlib.Path of a network file, as get_network takes it
        value = os.fspath(value)
    if isinstance(value, str) and (value in list_networks() or (user.is_network_file(value)
                                                               and os.path.isfile(value))):
        return
    what = "no such network file" if isinstance(value, str) and user.is_network_file(value) else "unknown network"
    raise ValueError(f"network: {what} {value!r}; registered: {list_networks()}, or the path of a network file "
                     f"(.npz, written by anm_torchrl.networks.save_network)")


def register_network(name: str, network: dict, load_p, gen_p_max, *, delta_t: float | None = None,
                     gamma: float | None = None, lamb: float | None = None, costs_clipping=None,
                     source: str = USER_SOURCE, overwrite: bool = False):
    """Register a user's gym-anm network under ``name`` for this process: every entry that takes a network name
    (``make_env(network=name)``, ``networks.simulator(name)``, ``run_recipe``'s ``network``) then accepts it.

    Args:
        name: a new name (letters, digits, ``_``, ``-``; not a registered one unless ``overwrite``).
        network: gym-anm dict ``{"baseMVA", "bus", "device", "branch"}`` (``None``/NaN where gym-anm allows).
        load_p: (T, n_load) MW load injections (<= 0), device-id order.
        gen_p_max: (T, n_gen) MW potentials of the non-slack generators, device-id order.
        delta_t, gamma, lamb, costs_clipping: env constants; None: gym-anm's defaults (:data:`DEFAULT_CONSTANTS`).
        source: where the network comes from (kept with the case).
        overwrite: replace a network this process registered under ``name`` (a built-in name never).

    Returns:
        The registered :class:`~anm_torchrl.networks.case.NetworkCase`.

    Raises:
        ValueError: a bad or taken name, or a network, profile or constant gym-anm would reject.
    """
    if not (isinstance(name, str) and name and all(ch.isalnum() or ch in "_-" for ch in name)):
        raise ValueError(f"network name must be letters, digits, '_' or '-', got {name!r}")
    if name in builtin_networks():
        raise ValueError(f"{name!r} is a built-in network; register yours under another name")
    if name in _REGISTERED and not overwrite:
        raise ValueError(f"a network named {name!r} is already registered in this process; pass overwrite=True")
    case = user.checked_case(name, network, load_p, gen_p_max, delta_t=delta_t, gamma=gamma, lamb=lamb,
                        costs_clipping=costs_clipping, source=source)
    _REGISTERED[name] = case
    return case


def unregister_network(name: str) -> None:
    """Forget a network :func:`register_network` registered (no-op if it is not)."""
    _REGISTERED.pop(name, None)
