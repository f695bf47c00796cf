"""Bus positions for drawing a network from its branches: a tree for radial feeders, springs for meshed ones.

Graph work by ``networkx`` (a dependency of torch): a radial feeder is laid out as a one-line diagram grown from
the slack bus (depth along x, subtrees stacked along y, each parent at the mean height of its children); a
meshed network gets networkx's Fruchterman–Reingold springs from a spectral start (seeded: the same picture
every time).
"""

from __future__ import annotations

import networkx as nx
import numpy as np


def _graph(n_bus: int, f_bus: np.ndarray, t_bus: np.ndarray) -> nx.Graph:
    """Buses 0 … n_bus − 1 joined by the branches (parallel branches and self-loops collapse)."""
    graph = nx.Graph()
    graph.add_nodes_from(range(n_bus))
    # sorted edges give every bus its neighbours in ascending order: traversals visit children by bus id
    graph.add_edges_from(sorted({tuple(sorted(e)) for e in zip(f_bus.tolist(), t_bus.tolist()) if e[0] != e[1]}))
    return graph


def is_radial(n_bus: int, f_bus: np.ndarray, t_bus: np.ndarray) -> bool:
    """True if the branches form a tree (connected, n_bus − 1 distinct edges)."""
    return nx.is_tree(_graph(n_bus, f_bus, t_bus))


def tree_layout(n_bus: int, f_bus: np.ndarray, t_bus: np.ndarray, root: int = 0) -> np.ndarray:
    """(n_bus, 2) positions of a radial network: x = hops from ``root``, y spreads the leaves evenly.

    Each parent sits at the mean height of its children, so a feeder reads as a one-line diagram.
    """
    tree = nx.bfs_tree(_graph(n_bus, f_bus, t_bus), root)  # children in ascending bus order
    depth = nx.shortest_path_length(tree, root)
    pos = np.zeros((n_bus, 2))
    next_leaf = 0.0
    for u in reversed(list(nx.dfs_preorder_nodes(tree, root))):  # children before parents; last subtree on top
        children = list(tree.successors(u))
        if children:
            pos[u, 1] = np.mean([pos[c, 1] for c in children])
        else:
            pos[u, 1] = next_leaf
            next_leaf -= 1.0
        pos[u, 0] = depth[u]
    return pos


def spring_layout(n_bus: int, f_bus: np.ndarray, t_bus: np.ndarray, iterations: int = 200) -> np.ndarray:
    """(n_bus, 2) positions of a meshed network: networkx's springs from its spectral layout, seed 0."""
    graph = _graph(n_bus, f_bus, t_bus)
    start = nx.spectral_layout(graph) if n_bus > 2 else {b: (float(b), 0.0) for b in range(n_bus)}
    pos = nx.spring_layout(graph, pos=start, iterations=iterations, seed=0)
    return np.array([pos[b] for b in range(n_bus)], dtype=float)


def network_layout(n_bus: int, f_bus: np.ndarray, t_bus: np.ndarray) -> np.ndarray:
    """(n_bus, 2) positions: :func:`tree_layout` from the slack (bus 0) if radial, else :func:`spring_layout`."""
    if is_radial(n_bus, f_bus, t_bus):
        return tree_layout(n_bus, f_bus, t_bus)
    return spring_layout(n_bus, f_bus, t_bus)
