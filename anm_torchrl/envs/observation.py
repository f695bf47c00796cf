"""gym-anm's observation lists ``[(quantity, ids | "all", unit), ...]`` as a batched map with its bounds.

Every quantity of gym-anm's ``STATE_VARIABLES`` in each of its units, computed for a batch from the state and
the bus voltages, and clipped to the bounds of gym-anm's ``Simulator.get_state_space()`` (quirks included:
the slack bus's |V| bound is (VMAX, VMAX), a generator's ``gen_p_max`` upper bound in MW is QMAX, a bus's P/Q
bounds are sums of its devices' bounds, ``branch_i_magn`` is ``sign(I_from)·|I_from|`` with NumPy 2's
complex sign, i.e. Re(I_from) up to round-off, and is only offered in p.u.).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from anm_torchrl.grid import devices as dv
from anm_torchrl.grid.network import LOAD, branch_flows

# gym_anm/simulator/components/constants.py STATE_VARIABLES (first unit = default). gym-anm lists
# branch_i_magn's units as the string "pu", so its default unit is "p" and only "pu" works; we default to "pu".
STATE_VARIABLES = {
    "bus_p": ("MW", "pu"), "bus_q": ("MVAr", "pu"), "bus_v_magn": ("pu", "kV"), "bus_v_ang": ("degree", "rad"),
    "bus_i_magn": ("pu", "kA"), "bus_i_ang": ("degree", "rad"), "dev_p": ("MW", "pu"), "dev_q": ("MVAr", "pu"),
    "des_soc": ("MWh", "pu"), "gen_p_max": ("MW", "pu"), "branch_p": ("MW", "pu"), "branch_q": ("MVAr", "pu"),
    "branch_s": ("MVA", "pu"), "branch_i_magn": ("pu",), "branch_i_ang": ("degree", "rad"), "aux": (None,),
}
_ANGLES = ("bus_v_ang", "bus_i_ang", "branch_i_ang")
_POWER_UNITS = ("MW", "MVAr", "MVA", "MWh")


class ObservationMap:
    """A gym-anm observation list for a :class:`~anm_torchrl.grid.simulator.GridSimulator`.

    Args:
        sim: the simulator (its network gives ids, base kV and bounds).
        observation: ``"state"`` or a list of ``(quantity, ids | "all"[, unit])`` (ids: bus ids, device ids,
            storage / non-slack generator device ids, branch ``(f_bus, t_bus)`` tuples, or ``[0]`` for ``aux``).
        aux_bounds: (low, high) of the auxiliary variable.

    Attributes:
        low, high: (n_obs,) float64 bounds, as gym-anm's ``observation_bounds()``.
        needs_grid: whether the map reads bus voltages (anything beyond the state vector).
    """

    def __init__(self, sim, observation, aux_bounds: tuple[float, float]):
        self.sim = sim
        net = sim.net
        dev_ids = [int(i) for i in net.dev[:, 0].tolist()]
        branches = list(zip(net.branches.f_bus.tolist(), net.branches.t_bus.tolist()))
        self.ids = {
            "bus": list(range(net.n_bus)), "dev": dev_ids, "des": [dev_ids[i] for i in sim.des_ids],
            "gen": [dev_ids[i] for i in sim.gen_ids], "branch": branches, "aux": [0],
        }
        self._pos = {k: {v: j for j, v in enumerate(ids)} for k, ids in self.ids.items()}
        if isinstance(observation, str) and observation == "state":
            spec = [("dev_p", "all", "MW"), ("dev_q", "all", "MVAr"), ("des_soc", "all", "MWh"),
                    ("gen_p_max", "all", "MW"), ("aux", "all", None)]
        elif isinstance(observation, Sequence) and not isinstance(observation, str):
            spec = list(observation)
        else:
            raise ValueError(f"observation must be 'state' or a list of (quantity, ids, unit), got {observation!r}")
        self.entries = [self._entry(o) for o in spec]
        if not self.entries:
            raise ValueError("observation list is empty")
        self.is_state = isinstance(observation, str)
        self.needs_grid = any(not k.startswith(("dev_", "des_", "gen_", "aux")) for k, _, _ in self.entries)
        lows, highs = zip(*(self._bounds(k, rows, u, aux_bounds) for k, rows, u in self.entries))
        self.low, self.high = torch.cat(lows), torch.cat(highs)

    @staticmethod
    def _kind(key: str) -> str:
        return "aux" if key == "aux" else key.split("_")[0]

    def _entry(self, o) -> tuple[str, torch.Tensor, str | None]:
        if not isinstance(o, (tuple, list)) or len(o) not in (2, 3):
            raise ValueError(f"observation entry {o!r} must be (quantity, ids) or (quantity, ids, unit)")
        key, ids = o[0], o[1]
        if key not in STATE_VARIABLES:
            raise ValueError(f"observation quantity {key!r} is not one of {list(STATE_VARIABLES)}")
        unit = o[2] if len(o) == 3 else STATE_VARIABLES[key][0]
        if unit not in STATE_VARIABLES[key]:
            raise ValueError(f"unit {unit!r} of {key!r} must be one of {STATE_VARIABLES[key]}")
        kind = self._kind(key)
        if isinstance(ids, str) and ids == "all":
            ids = self.ids[kind]
        elif isinstance(ids, str) or not isinstance(ids, Sequence):
            raise ValueError(f"ids of {key!r} must be 'all' or a list, got {ids!r}")
        rows = []
        for i in ids:
            i = tuple(int(x) for x in i) if kind == "branch" else int(i)
            if i not in self._pos[kind]:
                raise ValueError(f"{key!r} has no element with id {i!r}; valid ids: {self.ids[kind]}")
            rows.append(self._pos[kind][i])
        return key, torch.tensor(rows, dtype=torch.long, device=self.sim.net.dev.device), unit

    # ---------------------------------------------------------------------------------------------- bounds
    def _bounds(self, key: str, rows: torch.Tensor, unit: str | None, aux_bounds) -> tuple[torch.Tensor, torch.Tensor]:
        sim, net = self.sim, self.sim.net
        dev, b = net.dev, net.base_mva
        ones = torch.ones(rows.numel(), dtype=torch.float64, device=dev.device)
        inf = ones * math.inf
        if key in _ANGLES:
            half = math.pi if unit == "rad" else 180.0
            lo, hi = -half * ones, half * ones
            if key == "bus_v_ang":  # the slack bus angle is fixed at 0
                lo, hi = torch.where(rows == 0, 0.0, lo), torch.where(rows == 0, 0.0, hi)
            return lo, hi
        if key == "aux":
            return ones * aux_bounds[0], ones * aux_bounds[1]
        if key == "bus_v_magn":
            scale = net.base_kv[rows] if unit == "kV" else 1.0
            slack = rows == 0  # gym-anm: (v_slack, v_slack) with v_slack = VMAX of the slack bus
            return (torch.where(slack, net.v_max[rows] * scale, -inf), torch.where(slack, net.v_max[rows] * scale, inf))
        if key.startswith("branch_") or key == "bus_i_magn":
            return -inf, inf
        p_lo, p_hi = dev[:, dv.PMIN], dev[:, dv.PMAX]
        is_load = net.dev_type == LOAD
        q_lo = torch.where(is_load, dev[:, 3] * p_lo, dev[:, dv.QMIN])
        q_hi = torch.where(is_load, dev[:, 3] * p_hi, dev[:, dv.QMAX])
        lo_hi = {
            "dev_p": (p_lo, p_hi), "dev_q": (q_lo, q_hi),
            "des_soc": (dev[sim.des_idx, dv.SOC_MIN], dev[sim.des_idx, dv.SOC_MAX]),
            "gen_p_max": (dev[sim.gen_idx, dv.PMIN], dev[sim.gen_idx, dv.QMAX if unit == "MW" else dv.PMAX]),
            "bus_p": (p_lo @ net.incidence, p_hi @ net.incidence), "bus_q": (q_lo @ net.incidence, q_hi @ net.incidence),
        }[key]
        scale = b if unit in _POWER_UNITS else 1.0
        return lo_hi[0][rows] * scale, lo_hi[1][rows] * scale

    # ---------------------------------------------------------------------------------------------- values
    def __call__(self, state: torch.Tensor, v: torch.Tensor | None) -> torch.Tensor:
        """Observation (N, n_obs) float64 (before clipping) from ``state`` (N, state_dim) MW… and bus voltages
        ``v`` (N, n_bus) complex p.u. (needed only when :attr:`needs_grid`)."""
        sim, net = self.sim, self.sim.net
        b = net.base_mva
        sl = sim.state_slices()
        cache: dict[str, torch.Tensor] = {}

        def pu(key: str) -> torch.Tensor:  # (N, n_items) in gym-anm's p.u. / rad
            if key in cache:
                return cache[key]
            if key in ("dev_p", "dev_q", "des_soc", "gen_p_max"):
                out = state[:, sl[key]] / b
            elif key == "aux":
                out = state[:, sl["aux"]]
            elif key in ("bus_p", "bus_q"):
                dev_x = state[:, sl["dev_p" if key == "bus_p" else "dev_q"]] / b
                out = dev_x @ net.incidence
                out[:, 0] = dev_x[:, sim.slack_ids[0]]  # gym-anm: the slack bus injects what the slack device does
            elif key.startswith("bus_v"):
                out = v.abs() if key == "bus_v_magn" else torch.angle(v)
            elif key.startswith("bus_i"):
                i_bus = v @ net.y_bus.T
                out = i_bus.abs() if key == "bus_i_magn" else torch.angle(i_bus)
            else:
                flows = cache.get("_flows") or branch_flows(v, net.branches)
                cache["_flows"] = flows
                i_f, s_f = flows["i_from"], flows["s_from"]
                if key == "branch_i_magn":  # NumPy 2: sign(z) = z / |z| (0 at 0), so this is Re(I) up to round-off
                    mag = i_f.abs()
                    out = torch.where(mag == 0, 0.0, (i_f / mag).real) * mag
                else:
                    out = {"branch_p": lambda: s_f.real, "branch_q": lambda: s_f.imag,
                           "branch_s": lambda: flows["s_apparent_max"], "branch_i_ang": lambda: torch.angle(i_f)}[key]()
            cache[key] = out
            return out

        cols = []
        for key, rows, unit in self.entries:
            if key in ("dev_p", "dev_q", "des_soc", "gen_p_max", "aux") and unit != "pu":
                cols.append(state[:, sl[key]][:, rows])  # the state holds them in MW / MVAr / MWh already
                continue
            x = pu(key)[:, rows]
            if unit in _POWER_UNITS:
                x = x * b
            elif unit == "degree":
                x = x * 180 / math.pi
            elif unit == "kV":
                x = x * net.base_kv[rows]
            elif unit == "kA":
                x = x * b / net.base_kv[rows]
            cols.append(x)
        return torch.cat(cols, 1)

    def observe(self, state: torch.Tensor, v: torch.Tensor | None, terminal: torch.Tensor) -> torch.Tensor:
        """float32 observation: the map clipped to its bounds; zeros on ``terminal`` (N,) rows, as gym-anm."""
        obs = state if self.is_state else self(state, v)
        obs = torch.minimum(torch.maximum(obs, self.low), self.high)  # np.clip order: high wins if low > high
        return torch.where(terminal.unsqueeze(1), torch.zeros_like(obs), obs).to(torch.float32)
