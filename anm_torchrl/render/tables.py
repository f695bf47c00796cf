"""The network tables the figures need, read from a :class:`~anm_torchrl.grid.network.Network` (any network)."""

from __future__ import annotations

import dataclasses

import numpy as np

from anm_torchrl.grid.devices import SOC_MAX
from anm_torchrl.grid.network import CLASSICAL_GEN, LOAD, RENEWABLE, SLACK, STORAGE, Network


@dataclasses.dataclass(frozen=True)
class NetworkTables:
    """Topology, limits and the gym-anm state/action layout of a network, as numpy arrays.

    Attributes:
        n_bus: number of buses (bus 0 is the slack).
        f_bus, t_bus: (n_branch,) int, branch end buses.
        rate_mva: (n_branch,) branch ratings, MVA (inf where none is given).
        v_min, v_max: (n_bus,) voltage limits, p.u.
        dev_bus, dev_type, dev_id: (n_dev,) int, bus, gym-anm type code and DEV_ID of each device row.
        gen_ids, des_ids, load_ids: device rows (ascending DEV_ID) of non-slack generators, storage units and loads;
            ``dev_id[row]`` is the id a label shows (ids need not be 0..n_dev-1).
        soc_max: (n_des,) storage capacity, MWh.
        delta_t: hours per step.
    """

    n_bus: int
    f_bus: np.ndarray
    t_bus: np.ndarray
    rate_mva: np.ndarray
    v_min: np.ndarray
    v_max: np.ndarray
    dev_bus: np.ndarray
    dev_type: np.ndarray
    dev_id: np.ndarray
    gen_ids: np.ndarray
    des_ids: np.ndarray
    load_ids: np.ndarray
    soc_max: np.ndarray
    delta_t: float

    @property
    def n_dev(self) -> int:
        return int(self.dev_bus.shape[0])

    def state_slices(self) -> dict[str, slice]:
        """gym-anm ``STATE_VARIABLES`` blocks of the state vector (one auxiliary variable: the time index)."""
        n, d, g = self.n_dev, len(self.des_ids), len(self.gen_ids)
        return {"dev_p": slice(0, n), "dev_q": slice(n, 2 * n), "des_soc": slice(2 * n, 2 * n + d),
                "gen_p_max": slice(2 * n + d, 2 * n + d + g), "aux": slice(2 * n + d + g, 2 * n + d + g + 1)}

    def bus_kind(self) -> np.ndarray:
        """(n_bus,) the most notable device kind at each bus: slack > storage > renewable > classical > load."""
        rank = {SLACK: 5, STORAGE: 4, RENEWABLE: 3, CLASSICAL_GEN: 2, LOAD: 1}
        kind = np.full(self.n_bus, LOAD - 1)  # -2: no device
        for bus, t in zip(self.dev_bus, self.dev_type):
            if kind[bus] == LOAD - 1 or rank[int(t)] > rank[int(kind[bus])]:
                kind[bus] = t
        return kind


def network_tables(net: Network) -> NetworkTables:
    """:class:`NetworkTables` of ``net`` (p.u. tables converted to MVA / MWh where the figures show them)."""
    np_ = lambda t: t.detach().cpu().numpy()  # noqa: E731
    dev_type = np_(net.dev_type).astype(int)
    ids = lambda *kinds: np.flatnonzero(np.isin(dev_type, kinds))  # noqa: E731
    des_ids = ids(STORAGE)
    return NetworkTables(
        n_bus=net.n_bus, f_bus=np_(net.branches.f_bus).astype(int), t_bus=np_(net.branches.t_bus).astype(int),
        rate_mva=np_(net.branches.rate) * net.base_mva, v_min=np_(net.v_min), v_max=np_(net.v_max),
        dev_bus=np_(net.dev_bus).astype(int), dev_type=dev_type, dev_id=np_(net.dev[:, 0]).astype(int),
        gen_ids=ids(CLASSICAL_GEN, RENEWABLE),
        des_ids=des_ids, load_ids=ids(LOAD), soc_max=np_(net.dev)[des_ids, SOC_MAX] * net.base_mva,
        delta_t=float(net.delta_t))
