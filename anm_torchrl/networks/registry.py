"""Registered networks: :func:`get_network` by name, :func:`list_networks` for every name.

``anm6_easy`` is built from :mod:`anm_torchrl.networks.anm6_easy`; the imported feeders load from the
committed case files under ``networks/data/`` (hash-checked, no pandapower needed). How each feeder was made,
its sizes and its citation are in ``NetworkCase.source`` and in ``networks/data/README.md``; re-run an import
with ``python -m anm_torchrl.networks.feeders --name <name>``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from anm_torchrl.grid.identity import case_key
from anm_torchrl.networks import anm6_easy
from anm_torchrl.networks.case_file import load_case

ANM6_EASY = "anm6_easy"  # the one spelling of gym-anm's ANM6-Easy network name; import it, do not re-type it
# Feeders imported from pandapower / SimBench; their case files live in networks/data/.
IMPORTED = ("case33bw", "cigre_mv", "simbench_mv_semiurb")

ANM6_SOURCE = ("gym-anm 2.0.1 ANM6-Easy (Henry & Ernst, 'Gym-ANM: Reinforcement learning environments for "
               "active network management tasks in electricity distribution systems', Energy and AI 5, 2021); "
               "6 buses, 7 devices, 96-step (24 h) deterministic profiles")


@dataclass(frozen=True)
class NetworkCase:
    """A network with its exogenous profiles and the env constants it is meant to run with.

    Attributes:
        name: registered name.
        network: gym-anm dict ``{"baseMVA", "bus", "device", "branch"}``, float64 tables, NaN = gym-anm's None.
        load_p: (T, n_load) MW load injections (gym-anm sign: <= 0), device-ID order.
        gen_p_max: (T, n_gen) MW potentials of every non-slack generator (classical and renewable), ID order.
        delta_t: hours per step.
        gamma: discount factor.
        lamb: penalty factor lambda.
        costs_clipping: (energy-loss clip, penalty clip).
        source: where the data come from (citation text) and what was assumed.
        content_hash: :func:`anm_torchrl.grid.identity.case_key` of the tables, profiles and constants.
        meta: the import record (defaults used, do-nothing power-flow summary); empty for ``anm6_easy``.
    """

    name: str
    network: dict
    load_p: np.ndarray
    gen_p_max: np.ndarray
    delta_t: float
    gamma: float
    lamb: float
    costs_clipping: tuple[float, float]
    source: str
    content_hash: str
    meta: dict = field(default_factory=dict, compare=False)

    @property
    def n_bus(self) -> int:
        """Number of buses."""
        return int(self.network["bus"].shape[0])


def _make(name: str, network: dict, load_p: np.ndarray, gen_p_max: np.ndarray, delta_t: float, gamma: float,
          lamb: float, costs_clipping: tuple, source: str, meta: dict) -> NetworkCase:
    constants = (delta_t, gamma, lamb, tuple(costs_clipping))
    return NetworkCase(name, network, load_p, gen_p_max, delta_t, gamma, lamb, tuple(costs_clipping), source,
                       case_key(network, load_p, gen_p_max, constants), meta)


def _anm6_easy() -> NetworkCase:
    m = anm6_easy
    return _make(ANM6_EASY, m.network(), m.load_p(), m.gen_p_max(), m.DELTA_T, m.GAMMA, m.LAMB,
                 m.COSTS_CLIPPING, ANM6_SOURCE, {})


def _imported(name: str) -> NetworkCase:
    network, load_p, gen_p_max, meta, _ = load_case(name)
    env = meta["env"]
    return _make(name, network, load_p, gen_p_max, env["delta_t"], env["gamma"], env["lamb"],
                 tuple(env["costs_clipping"]), meta["source"], meta)


def list_networks() -> list[str]:
    """Every registered network name, ``anm6_easy`` first."""
    return [ANM6_EASY, *IMPORTED]


def get_network(name: str) -> NetworkCase:
    """The registered network ``name`` (see :func:`list_networks`).

    Raises:
        ValueError: unknown name, or a case file whose sha256 differs from the recorded one.
    """
    if name == ANM6_EASY:
        return _anm6_easy()
    if name in IMPORTED:
        return _imported(name)
    raise ValueError(f"unknown network {name!r}; registered: {list_networks()}")
