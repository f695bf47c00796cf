"""``NetworkCase``: a network with its exogenous profiles and env constants (what a name stands for)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from anm_torchrl.grid.identity import case_key


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


def make_case(name: str, network: dict, load_p: np.ndarray, gen_p_max: np.ndarray, delta_t: float, gamma: float,
          lamb: float, costs_clipping: tuple, source: str, meta: dict) -> NetworkCase:
    """A :class:`NetworkCase` with its content hash (the tables, profiles and constants as given: not checked)."""
    constants = (delta_t, gamma, lamb, tuple(costs_clipping))
    return NetworkCase(name, network, load_p, gen_p_max, delta_t, gamma, lamb, tuple(costs_clipping), source,
                       case_key(network, load_p, gen_p_max, constants), meta)
