"""``NetworkFrame``: the network at one step as an RGB image, for ``render_mode="rgb_array"`` and videos."""

from __future__ import annotations

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.figure import Figure

from anm_torchrl.render.layout import network_layout
from anm_torchrl.render.network_plot import LOAD_CMAP, V_CMAP, NetworkArtist, loading_norm, marker_legend, \
    voltage_norm
from anm_torchrl.render.tables import NetworkTables

FRAME_SIZE = (640, 480)  # px (width, height): even and a multiple of 16, as video encoders want


class NetworkFrame:
    """One figure drawn once (layout, colour bars, legend) and recoloured per step; :meth:`draw` returns pixels.

    Args:
        tables: the network (:func:`~anm_torchrl.render.tables.network_tables`).
        size: (width, height) in px.
    """

    def __init__(self, tables: NetworkTables, size: tuple[int, int] = FRAME_SIZE):
        dpi = 80
        self.fig = Figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi, layout="constrained")
        FigureCanvasAgg(self.fig)
        ax = self.fig.add_subplot()
        self.artist = NetworkArtist(ax, tables, network_layout(tables.n_bus, tables.f_bus, tables.t_bus))
        marker_legend(ax, tables)
        self.fig.colorbar(ScalarMappable(voltage_norm(tables), V_CMAP), ax=ax, label="bus |V| (p.u.)", shrink=0.8,
                          extend="both")
        self.fig.colorbar(ScalarMappable(loading_norm(), LOAD_CMAP), ax=ax, label="branch loading (%)", shrink=0.8,
                          extend="max")
        self.artist.update(np.ones(tables.n_bus), np.zeros(tables.f_bus.shape[0]), "\n")  # two title lines
        self.fig.canvas.draw()
        self.fig.set_layout_engine("none")  # freeze the layout: each frame only recolours the artists

    def draw(self, v_magn: np.ndarray, branch_s: np.ndarray, title: str = "") -> np.ndarray:
        """(H, W, 3) uint8 image of the network with bus |V| ``v_magn`` (n_bus,) p.u. and signed branch flows
        ``branch_s`` (n_branch,) MVA; ``title`` may hold two lines."""
        self.artist.update(np.asarray(v_magn, dtype=float), np.asarray(branch_s, dtype=float), title)
        self.fig.canvas.draw()
        return np.asarray(self.fig.canvas.buffer_rgba())[..., :3].copy()
