"""Registered networks: :func:`get_network` by name, :func:`list_networks` for every name.

``anm6_easy`` is built from :mod:`anm_torchrl.networks.anm6_easy`; the imported feeders load from the
committed case files under ``networks/data/`` (hash-checked, no pandapower needed). How each feeder was made,
its sizes and its citation are in ``NetworkCase.source`` and in ``networks/data/README.md``; re-run an import
with ``python -m anm_torchrl.networks.pandapower_import --name <name>``.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field

import numpy as np

from anm_torchrl.networks import anm6_easy
from anm_torchrl.networks.case_file import load_case

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
        content_hash: sha256 over the tables, profiles and constants (identifies the case).
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


def content_hash(network: dict, load_p: np.ndarray, gen_p_max: np.ndarray, constants: tuple) -> str:
    """sha256 over the float64 bytes of the tables and profiles and the JSON of the constants."""
    h = hashlib.sha256()
    h.update(np.float64(network["baseMVA"]).tobytes())
    for a in (network["bus"], network["device"], network["branch"], load_p, gen_p_max):
        a = np.ascontiguousarray(a, dtype=np.float64)
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    h.update(json.dumps(list(constants)).encode())
    return h.hexdigest()


def _make(name: str, network: dict, load_p: np.ndarray, gen_p_max: np.ndarray, delta_t: float, gamma: float,
          lamb: float, costs_clipping: tuple, source: str, meta: dict) -> NetworkCase:
    constants = (delta_t, gamma, lamb, tuple(costs_clipping))
    return NetworkCase(name, network, load_p, gen_p_max, delta_t, gamma, lamb, tuple(costs_clipping), source,
                       content_hash(network, load_p, gen_p_max, constants), meta)


def _anm6_easy() -> NetworkCase:
    m = anm6_easy
    return _make("anm6_easy", m.network(), m.load_p(), m.gen_p_max(), m.DELTA_T, m.GAMMA, m.LAMB,
                 m.COSTS_CLIPPING, ANM6_SOURCE, {})


def _imported(name: str) -> NetworkCase:
    network, load_p, gen_p_max, meta, _ = load_case(name)
    env = meta["env"]
    return _make(name, network, load_p, gen_p_max, env["delta_t"], env["gamma"], env["lamb"],
                 tuple(env["costs_clipping"]), meta["source"], meta)


def list_networks() -> list[str]:
    """Every registered network name, ``anm6_easy`` first."""
    return ["anm6_easy", *IMPORTED]


def get_network(name: str) -> NetworkCase:
    """The registered network ``name`` (see :func:`list_networks`).

    Raises:
        ValueError: unknown name, or a case file whose sha256 differs from the recorded one.
    """
    if name == "anm6_easy":
        return _anm6_easy()
    if name in IMPORTED:
        return _imported(name)
    raise ValueError(f"unknown network {name!r}; registered: {list_networks()}")
