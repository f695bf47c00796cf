"""``TransitionConstants``: every network table the numba backend reads, as ONE structure.

A ``NamedTuple`` of NumPy arrays and scalars (p.u.), built once per simulator by :func:`build_constants`. The
numba backend (:mod:`anm_torchrl.grid.backends.numba`) takes it as one argument and reads its fields by name; the
torch backend reads the same tables from its :class:`~anm_torchrl.grid.network.Network` (torch tensors,
any device). The content keys of a network live in :mod:`anm_torchrl.grid.identity`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from anm_torchrl.grid.devices import DES_SOC_ROWS, GEN_PPOT_ROW
from anm_torchrl.grid.powerflow import MAX_ITER, TOL
from anm_torchrl.grid.tree_solve import BANDED_MIN_BUS, bus_tree  # their one home


class TransitionConstants(NamedTuple):
    """The network as the transition sees it (float64 / int64 / complex128 arrays, p.u.).

    Attributes (n_dev devices, n_gen non-slack generators, n_des storage units, n_bus buses, n_br branches):
        dev: (n_dev, 15) device table in p.u. (gym-anm column order).
        lid, gid, did: device rows of the loads, non-slack generators (classical and renewable), storage units.
        renewable: (n_gen,) 1.0 for renewable generators (their curtailment counts in ΔE), 0.0 for classical.
        slack: device row of the slack generator.  dev_bus: (n_dev,) bus of each device.
        counted: (n_dev,) 1.0 for devices whose P counts in ΔE (generators, slack, loads).
        gen_poly, des_poly: projection data of the generator / storage polygons (kernel layout).
        gen_h0, des_h0: (n_gen, 7), (n_des, 10) constant right-hand sides (+inf in state-dependent rows).
        gen_ppot_row, des_soc_rows: rows of ``h`` filled from P_pot and from the SoC.
        y: (n_bus, n_bus) Y-bus; ycsr: its non-zeros as (row pointers, column indices, values).
        dense: the ``"dense"`` layout (small networks): the kernel's Newton step reads Y densely, with the
            Jacobian in gym-anm's layout and no index indirection.
        lu0, piv0, ok0: LU factors of the flat-start Jacobian (shared by all envs).
        ix: (2 n_bus - 2,) position of each Newton–Raphson variable / equation ([θ, |V|] of the non-slack
            buses) in the Jacobian; kl, ku: its lower / upper bandwidth; parent: (k,) tree of the ``"tree"``
            solver (position of each bus's parent, -1 for roots), empty otherwise (see :func:`jacobian_ordering`).
        f_bus, t_bus: (n_br,) branch ends.  y_ff, y_ft, y_tf, y_tt: π-model coefficients
            (i_from = y_ff v_f - y_ft v_t, i_to = y_tt v_t - y_tf v_f).  rate: (n_br,) p.u.
        v_min, v_max: (n_bus,) p.u.  delta_t (h), lamb, c0, c1 (costs clipping), term_reward.
        tol, max_iter: Newton–Raphson stopping rule.
    """

    dev: np.ndarray
    lid: np.ndarray
    gid: np.ndarray
    did: np.ndarray
    renewable: np.ndarray
    slack: int
    dev_bus: np.ndarray
    counted: np.ndarray
    gen_poly: tuple
    des_poly: tuple
    gen_h0: np.ndarray
    des_h0: np.ndarray
    gen_ppot_row: int
    des_soc_rows: np.ndarray
    y: np.ndarray
    ycsr: tuple
    dense: bool
    lu0: np.ndarray
    piv0: np.ndarray
    ok0: bool
    ix: np.ndarray
    kl: int
    ku: int
    parent: np.ndarray
    f_bus: np.ndarray
    t_bus: np.ndarray
    y_ff: np.ndarray
    y_ft: np.ndarray
    y_tf: np.ndarray
    y_tt: np.ndarray
    rate: np.ndarray
    v_min: np.ndarray
    v_max: np.ndarray
    delta_t: float
    lamb: float
    c0: float
    c1: float
    term_reward: float
    tol: float
    max_iter: int


def _npy(x: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().cpu().numpy())




def jacobian_ordering(y_bus: np.ndarray, solver: str = "auto") -> tuple[np.ndarray, int, int, np.ndarray]:
    """Where each Newton–Raphson unknown goes in the Jacobian, and the resulting bandwidths.

    ``"dense"``: gym-anm's layout [θ_1..θ_k, |V|_1..|V|_k] with full bandwidth (plain dense LU).
    ``"band"``: non-slack buses in reverse Cuthill–McKee order of Y's pattern, θ and |V| of a bus interleaved,
    so that the Jacobian is banded with kl = ku = 2·(bus bandwidth) + 1; the LU then costs O(n·kl·(kl+ku))
    instead of O(n³). ``"tree"`` (radial networks only): buses eliminated leaves first, θ and |V| interleaved,
    a 2×2-block LU without fill in O(n) and without pivoting across buses. ``"auto"``: from
    :data:`BANDED_MIN_BUS` buses on, ``"tree"`` for radial networks and ``"band"`` for meshed ones.

    Returns:
        ix (2k,) int64, kl, ku, parent (k,) int64 (empty unless ``"tree"``).
    """
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    if solver not in ("auto", "dense", "band", "tree"):
        raise ValueError(f"solver must be 'auto', 'dense', 'band' or 'tree', got {solver!r}")
    k = y_bus.shape[0] - 1
    no_tree = np.zeros(0, dtype=np.int64)
    if solver == "dense" or (solver == "auto" and y_bus.shape[0] < BANDED_MIN_BUS):
        return np.arange(2 * k, dtype=np.int64), 2 * k - 1, 2 * k - 1, no_tree
    forest = bus_tree(y_bus)
    if solver == "tree" and forest is None:
        raise ValueError("linear_solver='tree' needs a radial network (the non-slack buses form a forest)")
    if forest is not None and solver in ("tree", "auto"):
        return _tree_ordering(*forest)
    pattern = csr_matrix((y_bus[1:, 1:] != 0).astype(np.int8))
    order = np.asarray(reverse_cuthill_mckee(pattern, symmetric_mode=True), dtype=np.int64)
    pos = np.empty(k, dtype=np.int64)
    pos[order] = np.arange(k)
    rows, cols = pattern.nonzero()
    bw = int(np.abs(pos[rows] - pos[cols]).max()) if rows.size else 0
    ix = np.concatenate([2 * pos, 2 * pos + 1]).astype(np.int64)
    band = min(2 * bw + 1, 2 * k - 1)
    return ix, band, band, no_tree


def _tree_ordering(bfs: list[int], parent: np.ndarray) -> tuple[np.ndarray, int, int, np.ndarray]:
    """Leaves-first elimination order of a forest of buses (see :func:`jacobian_ordering`)."""
    k = parent.shape[0]
    order = np.array(bfs[::-1], dtype=np.int64)  # every bus before its parent
    pos = np.empty(k, dtype=np.int64)
    pos[order] = np.arange(k)
    parent_pos = np.array([pos[parent[i]] if parent[i] >= 0 else -1 for i in order], dtype=np.int64)
    ix = np.concatenate([2 * pos, 2 * pos + 1]).astype(np.int64)
    return ix, 0, 0, parent_pos


def build_constants(sim, solver: str = "auto") -> TransitionConstants:
    """The :class:`TransitionConstants` of a :class:`~anm_torchrl.grid.simulator.GridSimulator` (``solver``: the
    Jacobian layout of :func:`jacobian_ordering`)."""
    from anm_torchrl.grid.backends.numba import _flat_start_lu, _polygon_arrays

    net, br = sim.net, sim.net.branches
    gen_poly, gen_h0 = _polygon_arrays(sim.gen_polygons, sim.gen_h0)
    des_poly, des_h0 = _polygon_arrays(sim.des_polygons, sim.des_h0)
    ys, ysh, tp = (_npy(x) for x in (br.y_series, br.y_shunt, br.tap))
    y_bus = _npy(net.y_bus)
    ix, kl, ku, parent = jacobian_ordering(y_bus, solver)
    dense = parent.size == 0 and kl == ix.size - 1 and bool(np.array_equal(ix, np.arange(ix.size)))
    rows, cols = np.nonzero(y_bus)  # row-major: columns ascending within a row, as the dense loop visits them
    ycsr = (np.searchsorted(rows, np.arange(y_bus.shape[0] + 1)).astype(np.int64), cols.astype(np.int64),
            np.ascontiguousarray(y_bus[rows, cols]))
    return TransitionConstants(
        dev=_npy(net.dev).astype(np.float64), lid=_npy(sim.load_idx), gid=_npy(sim.gen_idx), did=_npy(sim.des_idx),
        renewable=_npy(sim.renewable).astype(np.float64), slack=int(sim.slack_ids[0]), dev_bus=_npy(net.dev_bus),
        counted=_npy(sim.counted).astype(np.float64), gen_poly=gen_poly, des_poly=des_poly, gen_h0=gen_h0,
        des_h0=des_h0, gen_ppot_row=GEN_PPOT_ROW, des_soc_rows=np.array(DES_SOC_ROWS, dtype=np.int64), y=y_bus,
        ycsr=ycsr, dense=dense,
        **dict(zip(("lu0", "piv0", "ok0"), _flat_start_lu(y_bus, ycsr, dense, ix, kl, ku, parent))),
        ix=ix, kl=kl, ku=ku, parent=parent,
        f_bus=_npy(br.f_bus), t_bus=_npy(br.t_bus),
        y_ff=np.ascontiguousarray((ys + ysh) / np.abs(tp) ** 2), y_ft=np.ascontiguousarray(ys / tp.conj()),
        y_tf=np.ascontiguousarray(ys / tp), y_tt=np.ascontiguousarray(ys + ysh), rate=_npy(br.rate),
        v_min=_npy(net.v_min), v_max=_npy(net.v_max), delta_t=float(net.delta_t), lamb=float(sim.lamb),
        c0=float(sim.costs_clipping[0]), c1=float(sim.costs_clipping[1]), term_reward=float(sim.terminal_reward),
        tol=TOL, max_iter=MAX_ITER)

