"""Network description as float64 torch tensors, the branch π-model, Y-bus and branch flows.

General over any radial or meshed network given as gym-anm style tables (bus 0 is the slack; the tables are
checked and given gym-anm's defaults by :func:`anm_torchrl.networks.validation.validate_network`). All
quantities are in p.u. on ``base_mva`` unless a name says otherwise.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
import torch

DTYPE = torch.float64
CDTYPE = torch.complex128

# Device type codes (gym_anm/simulator/components/constants.py).
LOAD, SLACK, CLASSICAL_GEN, RENEWABLE, STORAGE = -1, 0, 1, 2, 3


@dataclasses.dataclass(frozen=True)
class Branches:
    """Branch π-model parameters, each of shape (n_branch,); tap on the from side."""

    f_bus: torch.Tensor  # long
    t_bus: torch.Tensor  # long
    y_series: torch.Tensor  # complex, 1 / (r + jx)
    y_shunt: torch.Tensor  # complex, j b / 2
    tap: torch.Tensor  # complex, TAP * exp(j SHIFT)
    rate: torch.Tensor  # p.u. (inf when not given)


def make_branches(rows: Sequence[Sequence[float]], base_mva: float, device=None) -> Branches:
    """Build :class:`Branches` from rows ``F_BUS, T_BUS, R, X, B, RATE (MVA), TAP, SHIFT (deg)``.

    ``None``/NaN fields take gym-anm's defaults (r = x = b = 0, rate = inf, tap = 1, shift = 0).
    """
    arr = np.array([[np.nan if v is None else v for v in row] for row in rows], dtype=np.float64)

    def col(j: int, default: float) -> np.ndarray:
        c = arr[:, j].copy()
        c[np.isnan(c)] = default
        return c

    r, x, b = col(2, 0.0), col(3, 0.0), col(4, 0.0)
    tap = col(6, 1.0) * np.exp(1j * col(7, 0.0) * math.pi / 180)
    c = lambda a: torch.as_tensor(a, device=device)  # noqa: E731
    return Branches(
        f_bus=c(arr[:, 0].astype(np.int64)),
        t_bus=c(arr[:, 1].astype(np.int64)),
        y_series=c(1.0 / (r + 1j * x)),
        y_shunt=c(1j * b / 2),
        tap=c(tap),
        rate=c(col(5, np.inf) / base_mva),
    )


def build_y_bus(branches: Branches, n_bus: int) -> torch.Tensor:
    """Nodal admittance matrix (n_bus, n_bus) complex128 from the π-model of every branch."""
    y, ysh, t = branches.y_series, branches.y_shunt, branches.tap
    f, to = branches.f_bus, branches.t_bus
    y_bus = torch.zeros(n_bus, n_bus, dtype=CDTYPE, device=y.device)
    y_bus.index_put_((f, to), -y / t.conj(), accumulate=True)
    y_bus.index_put_((to, f), -y / t, accumulate=True)
    y_bus.index_put_((f, f), (y + ysh) / (t.abs() ** 2), accumulate=True)
    y_bus.index_put_((to, to), y + ysh, accumulate=True)
    return y_bus


def branch_flows(v: torch.Tensor, branches: Branches) -> dict[str, torch.Tensor]:
    """Branch currents and apparent powers for bus voltages ``v`` (..., n_bus) complex.

    Returns ``i_from``, ``i_to``, ``s_from``, ``s_to`` (..., n_branch) complex p.u. and ``s_apparent_max``
    = sign(P_from)·max(|S_from|, |S_to|) (..., n_branch) real p.u., as gym-anm reports it.
    """
    y, ysh, t = branches.y_series, branches.y_shunt, branches.tap
    v_f, v_t = v[..., branches.f_bus], v[..., branches.t_bus]
    i_from = (y + ysh) * v_f / (t.abs() ** 2) - y * v_t / t.conj()
    i_to = (y + ysh) * v_t - y * v_f / t
    s_from = v_f * i_from.conj()
    s_to = v_t * i_to.conj()
    s_max = torch.sign(s_from.real) * torch.maximum(s_from.abs(), s_to.abs())
    return {"i_from": i_from, "i_to": i_to, "s_from": s_from, "s_to": s_to, "s_apparent_max": s_max}


@dataclasses.dataclass(frozen=True)
class Network:
    """A distribution network with its devices, in p.u.; every tensor float64 unless noted.

    Attributes:
        base_mva: MVA base.
        delta_t: time step (h).
        y_bus: (n_bus, n_bus) complex admittance matrix.
        branches: π-model parameters and ratings.
        v_min, v_max: (n_bus,) voltage magnitude limits.
        dev_bus: (n_dev,) long, bus of each device; dev_type: (n_dev,) long type codes.
        dev: (n_dev, 15) device table in p.u. (MW/MVAr/MWh columns divided by ``base_mva``).
        incidence: (n_dev, n_bus) 0/1 matrix so that ``p_bus = p_dev @ incidence``.
        base_kv: (n_bus,) base voltage (kV) of each bus (kV / kA units of observations).
    """

    base_mva: float
    delta_t: float
    y_bus: torch.Tensor
    branches: Branches
    v_min: torch.Tensor
    v_max: torch.Tensor
    dev_bus: torch.Tensor
    dev_type: torch.Tensor
    dev: torch.Tensor
    incidence: torch.Tensor
    base_kv: torch.Tensor | None = None

    @property
    def n_bus(self) -> int:
        return self.y_bus.shape[0]

    @property
    def n_dev(self) -> int:
        return self.dev_bus.shape[0]

    def to(self, device) -> "Network":
        """A copy with every tensor on ``device``."""

        def move(v):
            if isinstance(v, torch.Tensor):
                return v.to(device)
            if isinstance(v, Branches):
                return Branches(*(getattr(v, f.name).to(device) for f in dataclasses.fields(v)))
            return v

        return Network(**{f.name: move(getattr(self, f.name)) for f in dataclasses.fields(self)})


def make_network(buses, branches, devices, base_mva: float, delta_t: float, device=None) -> Network:
    """Build a :class:`Network` from gym-anm style tables (bus rows, branch rows, device rows)."""
    bus = torch.as_tensor(np.asarray(buses, dtype=np.float64), device=device)
    dev = torch.as_tensor(np.asarray(devices, dtype=np.float64), device=device)
    n_bus = bus.shape[0]
    if not torch.equal(bus[:, 0].long(), torch.arange(n_bus, device=bus.device)) or bus[0, 1] != 0:
        raise ValueError("bus ids must be 0..n_bus-1 with the slack bus at index 0")
    br = make_branches(branches, base_mva, device=device)
    dev_pu = dev.clone()
    dev_pu[:, 4:14] = dev[:, 4:14] / base_mva  # PMAX ... SOC_MIN (MW, MVAr, MWh)
    # gym-anm's Load never divides PMAX by baseMVA (devices.py): a load's PMAX (<= 0, usually 0) is used as p.u.
    is_load = dev[:, 2] == LOAD
    dev_pu[is_load, 4] = dev[is_load, 4]
    dev_bus = dev[:, 1].long()
    incidence = torch.zeros(dev.shape[0], n_bus, dtype=DTYPE, device=bus.device)
    incidence[torch.arange(dev.shape[0]), dev_bus] = 1.0
    return Network(
        base_mva=base_mva,
        delta_t=delta_t,
        y_bus=build_y_bus(br, n_bus),
        branches=br,
        v_min=bus[:, 4].clone(),
        v_max=bus[:, 3].clone(),
        dev_bus=dev_bus,
        dev_type=dev[:, 2].long(),
        dev=dev_pu,
        incidence=incidence,
        base_kv=bus[:, 2].clone(),
    )

