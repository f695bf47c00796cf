"""Bus positions for drawing a network from its branches: a tree for radial feeders, springs for meshed ones.

numpy only (no graph library): a radial feeder is laid out as a tree grown from the slack bus (depth along x,
subtrees stacked along y); a meshed network gets a spectral embedding refined by a few spring iterations.
"""

from __future__ import annotations

from collections import deque

import numpy as np


def _adjacency(n_bus: int, f_bus: np.ndarray, t_bus: np.ndarray) -> list[list[int]]:
    adj: list[set[int]] = [set() for _ in range(n_bus)]
    for f, t in zip(f_bus.tolist(), t_bus.tolist()):
        if f != t:
            adj[f].add(t)
            adj[t].add(f)
    return [sorted(a) for a in adj]


def is_radial(n_bus: int, f_bus: np.ndarray, t_bus: np.ndarray) -> bool:
    """True if the branches form a tree (connected, n_bus − 1 distinct edges)."""
    edges = {tuple(sorted(e)) for e in zip(f_bus.tolist(), t_bus.tolist()) if e[0] != e[1]}
    return len(edges) == n_bus - 1 and len(_bfs_order(_adjacency(n_bus, f_bus, t_bus), 0)[0]) == n_bus


def _bfs_order(adj: list[list[int]], root: int) -> tuple[list[int], dict[int, int]]:
    order, parent, queue = [root], {root: -1}, deque([root])
    while queue:
        u = queue.popleft()
        for v in adj[u]:
            if v not in parent:
                parent[v] = u
                order.append(v)
                queue.append(v)
    return order, parent


def tree_layout(n_bus: int, f_bus: np.ndarray, t_bus: np.ndarray, root: int = 0) -> np.ndarray:
    """(n_bus, 2) positions of a radial network: x = hops from ``root``, y spreads the leaves evenly.

    Each parent sits at the mean height of its children, so a feeder reads as a one-line diagram.
    """
    adj = _adjacency(n_bus, f_bus, t_bus)
    order, parent = _bfs_order(adj, root)
    children: dict[int, list[int]] = {u: [] for u in order}
    for v in order[1:]:
        children[parent[v]].append(v)
    pos = np.zeros((n_bus, 2))
    depth = {root: 0}
    for v in order[1:]:
        depth[v] = depth[parent[v]] + 1
    next_leaf = 0.0
    for u in reversed(_dfs_order(children, root)):  # children before parents
        if children[u]:
            pos[u, 1] = np.mean([pos[c, 1] for c in children[u]])
        else:
            pos[u, 1] = next_leaf
            next_leaf -= 1.0
        pos[u, 0] = depth[u]
    return pos


def _dfs_order(children: dict[int, list[int]], root: int) -> list[int]:
    out, stack = [], [root]
    while stack:
        u = stack.pop()
        out.append(u)
        stack.extend(reversed(children[u]))
    return out


def spring_layout(n_bus: int, f_bus: np.ndarray, t_bus: np.ndarray, iterations: int = 200) -> np.ndarray:
    """(n_bus, 2) positions of a meshed network: spectral start, then Fruchterman–Reingold springs."""
    adj = np.zeros((n_bus, n_bus))
    for f, t in zip(f_bus.tolist(), t_bus.tolist()):
        if f != t:
            adj[f, t] = adj[t, f] = 1.0
    lap = np.diag(adj.sum(1)) - adj
    _, vecs = np.linalg.eigh(lap)
    pos = vecs[:, 1:3] if n_bus > 2 else np.c_[np.arange(n_bus), np.zeros(n_bus)]
    pos = (pos - pos.mean(0)) / (np.abs(pos).max() + 1e-12)
    k = 1.0 / np.sqrt(n_bus)
    temp = 0.1
    for _ in range(iterations):
        delta = pos[:, None, :] - pos[None, :, :]
        dist = np.maximum(np.linalg.norm(delta, axis=-1), 1e-3)
        force = (k * k / dist ** 2 - adj * dist / k)[..., None] * delta  # repulsion − attraction along edges
        disp = force.sum(1)
        length = np.maximum(np.linalg.norm(disp, axis=1, keepdims=True), 1e-9)
        pos += disp / length * np.minimum(length, temp)
        temp *= 0.98
    return pos


def network_layout(n_bus: int, f_bus: np.ndarray, t_bus: np.ndarray) -> np.ndarray:
    """(n_bus, 2) positions: :func:`tree_layout` from the slack (bus 0) if radial, else :func:`spring_layout`."""
    if is_radial(n_bus, f_bus, t_bus):
        return tree_layout(n_bus, f_bus, t_bus)
    return spring_layout(n_bus, f_bus, t_bus)
