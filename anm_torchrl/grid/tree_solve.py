"""Batched Newton steps on radial networks in O(n) per env: the polar Jacobian as 2×2 blocks on the bus tree.

On a radial network the non-slack buses form a forest (roots: the slack's neighbours), and the Jacobian of the
power-flow mismatch has a 2×2 block per bus (rows ΔP_i, ΔQ_i; columns θ_i, |V|_i) and one per branch. Eliminating
the buses leaves first makes no fill (the numba kernel's ``"tree"`` solver, :mod:`anm_torchrl.grid.backends.numba`),
so a step costs O(n) instead of the dense LU's O(n³) and O(n) memory instead of O(n²). Here every bus of one depth
is eliminated at once, batched over envs: 2 × depth small tensor ops per solve, whatever the batch.

No pivoting across buses (as the numba kernel): a singular diagonal block gives a non-finite step, which the
caller treats as a singular Jacobian (NaN, as gym-anm's ``spsolve``). The same blocks, transposed, solve ``Jᵀ``
(the implicit power flow's backward).
"""

from __future__ import annotations

import dataclasses
import weakref

import numpy as np
import torch

#: buses from which the numba kernel's tree block LU (radial) or band LU (meshed) replaces the dense LU, and
#: below which the torch backend never leaves its dense LU either. Measured on radial
# feeders (results/benchmarks/bench_env_solver.md, ``python -m anm_torchrl.benchmarks.env --solver-sweep --out
# results/benchmarks/bench_env_solver``): tree / dense 1.2x at 6 buses, 2.7x at 16, 5.6x at 33, 59x at 120; band / dense
# 0.8-1.2x up to 10 buses, 1.6x at 16. Below 13 buses the dense LU is kept: ANM6-Easy's outputs stay
# bit-identical to earlier releases for a gain of at most ~20 %.
BANDED_MIN_BUS = 13

#: the work (rows × (2k)³, the dense batched LU's flops up to a constant) per unit of tree depth from which a batch
#: is solved on the tree: the dense LU is one fast library call, the tree 2 × depth small ops per step whatever the
#: batch. Measured with ``python -m anm_torchrl.benchmarks.tree_solve --out results/benchmarks/torch_tree_solve``
#: (2 shared cores, 1 thread), dense / tree time: case33bw (k = 32, depth 17) 0.16 at 1 row, 1.33 at 256, 1.99
#: at 1,024 (tree from ~260 rows here); the 115-bus SimBench feeder (k = 114, depth 23) 0.27 at 1 row, 1.68 at 16,
#: 10.1 at 256 (tree from 8 rows).
TREE_WORK = 4e6


@dataclasses.dataclass(frozen=True)
class BusForest:
    """The non-slack buses (0..k-1, bus ``i + 1`` of Y) as a forest.

    Attributes:
        parent: (k,) long, the parent of each bus, -1 for a root (a neighbour of the slack only).
        levels: bus indices per depth, roots first; each (m_d,) long.
    """

    parent: torch.Tensor
    levels: tuple[torch.Tensor, ...]


# id(y_bus) -> (a weak reference to it, its version, its forest); tensors cannot be keys of a WeakKeyDictionary
# (their == is elementwise), so the entry is dropped when the tensor is freed
_FORESTS: dict[int, tuple[weakref.ref, int, BusForest | None]] = {}


def bus_tree(y_bus: np.ndarray) -> tuple[list[int], np.ndarray] | None:
    """Breadth-first order and parents (-1: root) of the non-slack buses, or ``None`` if they hold a loop."""
    k = y_bus.shape[0] - 1
    adj = [[int(q) - 1 for q in np.flatnonzero(y_bus[i + 1]) if q != 0 and q != i + 1] for i in range(k)]
    parent, seen, bfs = np.full(k, -1), np.zeros(k, bool), []
    for root in range(k):
        if seen[root]:
            continue
        seen[root], queue = True, [root]
        while queue:
            i = queue.pop(0)
            bfs.append(i)
            for q in adj[i]:
                if not seen[q]:
                    seen[q], parent[q] = True, i
                    queue.append(q)
    if sum(len(a) for a in adj) // 2 != k - int((parent < 0).sum()):  # a forest has k - (#trees) edges
        return None
    return bfs, parent


def bus_forest(y_bus: torch.Tensor) -> BusForest | None:
    """The forest of ``y_bus``'s (n, n) non-slack buses, or None if they hold a loop (cached per tensor and
    version)."""
    cached = _FORESTS.get(id(y_bus))
    if cached is not None and cached[0]() is y_bus and cached[1] == y_bus._version:
        return cached[2]
    found = bus_tree(y_bus.detach().cpu().numpy())
    forest = None
    if found is not None:
        bfs, parent = found
        depth = np.zeros(len(parent), dtype=np.int64)
        for i in bfs:  # breadth-first: a parent's depth is known before its children's
            depth[i] = 0 if parent[i] < 0 else depth[parent[i]] + 1
        dev = y_bus.device
        levels = tuple(torch.as_tensor(np.flatnonzero(depth == d), device=dev) for d in range(int(depth.max()) + 1))
        forest = BusForest(torch.as_tensor(parent, dtype=torch.long, device=dev), levels)
    key = id(y_bus)
    _FORESTS[key] = (weakref.ref(y_bus, lambda _, key=key: _FORESTS.pop(key, None)), y_bus._version, forest)
    return forest


def use_tree(y_bus: torch.Tensor, rows: int) -> BusForest | None:
    """The forest to solve a batch of ``rows`` Newton steps on, if ``y_bus`` (n, n) is radial and the dense work
    ``rows · (2n − 2)³`` reaches :data:`TREE_WORK` per unit of the tree's depth; else None (dense LU). Below
    :data:`BANDED_MIN_BUS` buses always None, as the numba kernel (ANM6-Easy stays bit-identical)."""
    k = y_bus.shape[0] - 1
    if k + 1 < BANDED_MIN_BUS or rows * (2 * k) ** 3 < TREE_WORK:  # small: dense (and the forest not looked up)
        return None
    forest = bus_forest(y_bus)
    return forest if forest is not None and rows * (2 * k) ** 3 >= TREE_WORK * len(forest.levels) else None


def jacobian_blocks(v: torch.Tensor, s_inj: torch.Tensor, y_bus: torch.Tensor, forest: BusForest
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The blocks of :func:`anm_torchrl.grid.powerflow._jacobian` on the tree, each (N, k, 2, 2) float:
    ``D[:, i]`` the diagonal block of bus i, ``L[:, i]`` the block (row parent(i), column i) and ``U[:, i]`` the
    block (row i, column parent(i)); zero for roots. Rows [ΔP, ΔQ], columns [θ, |V|] (p.u., rad).

    Args:
        v: (N, n) complex bus voltages; s_inj: (N, n) complex injections at ``v``; y_bus: (n, n) complex.
    """
    vs, s = v[:, 1:], s_inj[:, 1:]
    vm = vs.abs()
    k = vs.shape[1]
    y = y_bus[1:, 1:]

    def block(a: torch.Tensor, vm_col: torch.Tensor) -> torch.Tensor:
        """[[Im a, Re b], [−Re a, Im b]] with b = a / |V_col| (the off-diagonal form of ``_jacobian``)."""
        b = a / vm_col
        return torch.stack([torch.stack([a.imag, b.real], -1), torch.stack([-a.real, b.imag], -1)], -2)

    a_ii = vs * (y.diagonal().conj() * vs.conj())
    d = block(a_ii, vm)
    sr, si = s.real, s.imag
    d = d + torch.stack([torch.stack([-si, sr / vm], -1), torch.stack([sr, si / vm], -1)], -2)
    child = torch.arange(k, device=v.device)
    has = forest.parent >= 0
    par = torch.where(has, forest.parent, child)  # roots: any index, zeroed below
    mask = has.to(vm.dtype)[None, :, None, None]
    v_c, v_p = vs, vs[:, par]
    low = block(v_p * (y[par, child].conj() * v_c.conj()), vm) * mask  # row parent, column child
    up = block(v_c * (y[child, par].conj() * v_p.conj()), vm[:, par]) * mask  # row child, column parent
    return d, low, up


def _inv2(m: torch.Tensor) -> torch.Tensor:
    """Inverse of (..., 2, 2) blocks in closed form (non-finite where singular)."""
    a, b, c, d = m[..., 0, 0], m[..., 0, 1], m[..., 1, 0], m[..., 1, 1]
    det = a * d - b * c
    return torch.stack([torch.stack([d, -b], -1), torch.stack([-c, a], -1)], -2) / det[..., None, None]


def block_tree_solve(d: torch.Tensor, low: torch.Tensor, up: torch.Tensor, rhs: torch.Tensor,
                     forest: BusForest) -> torch.Tensor:
    """``x`` (N, k, 2) with ``J x = rhs`` for the block-tree matrix of :func:`jacobian_blocks` (``rhs`` (N, k, 2)):
    leaves-first block elimination, then back-substitution roots first, one depth at a time."""
    d, rhs = d.clone(), rhs.clone()
    parent = forest.parent
    dinv = torch.empty_like(d)
    for nodes in reversed(forest.levels[1:]):  # every non-root bus, deepest first
        p = parent[nodes]
        inv = _inv2(d[:, nodes])
        dinv[:, nodes] = inv
        m = low[:, nodes] @ inv  # L D⁻¹
        d.index_add_(1, p, -(m @ up[:, nodes]))
        rhs.index_add_(1, p, -(m @ rhs[:, nodes].unsqueeze(-1)).squeeze(-1))
    roots = forest.levels[0]
    dinv[:, roots] = _inv2(d[:, roots])
    x = torch.empty_like(rhs)
    x[:, roots] = (dinv[:, roots] @ rhs[:, roots].unsqueeze(-1)).squeeze(-1)
    for nodes in forest.levels[1:]:
        r = rhs[:, nodes] - (up[:, nodes] @ x[:, parent[nodes]].unsqueeze(-1)).squeeze(-1)
        x[:, nodes] = (dinv[:, nodes] @ r.unsqueeze(-1)).squeeze(-1)
    return x


def tree_newton_step(v: torch.Tensor, s_inj: torch.Tensor, y_bus: torch.Tensor, rhs: torch.Tensor,
                     forest: BusForest, transpose: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """``J(v)⁻¹ rhs`` (or ``J(v)⁻ᵀ rhs``) for ``rhs`` (N, 2k) in the dense layout ([ΔP, ΔQ] rows, [θ, |V|]
    columns), and ``info`` (N,) int32: 1 where the step is not finite (a singular block), as ``solve_ex``'s."""
    d, low, up = jacobian_blocks(v, s_inj, y_bus, forest)
    if transpose:  # Jᵀ: the same tree with each block transposed and the two off-diagonal sets swapped
        d, low, up = d.transpose(-1, -2), up.transpose(-1, -2), low.transpose(-1, -2)
    k = rhs.shape[1] // 2
    x = block_tree_solve(d, low, up, torch.stack([rhs[:, :k], rhs[:, k:]], -1), forest)
    x = torch.cat([x[..., 0], x[..., 1]], 1)
    return x, (~torch.isfinite(x).all(1)).to(torch.int32)
