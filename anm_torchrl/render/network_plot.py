"""Draw a network at one instant: buses coloured by |V| against their limits, branches by loading."""

from __future__ import annotations

import matplotlib
import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.colors import Normalize, TwoSlopeNorm
from matplotlib.lines import Line2D

from anm_torchrl.grid.network import CLASSICAL_GEN, LOAD, RENEWABLE, SLACK, STORAGE
from anm_torchrl.render.tables import NetworkTables

V_CMAP, LOAD_CMAP = "RdBu_r", "YlOrRd"
LOADING_MAX = 120.0  # % of the rating at which the loading colour saturates
MARKERS = {SLACK: ("H", "slack"), STORAGE: ("s", "storage"), RENEWABLE: ("^", "renewable"),
           CLASSICAL_GEN: ("D", "generator"), LOAD: ("o", "load"), LOAD - 1: (".", "no device")}


V_TOL = 1e-6  # p.u.: |V| this far past a limit counts as a violation (the slack's limits are [1, 1])


def voltage_limits(tables: NetworkTables) -> tuple[float, float]:
    """The widest (lower, upper) |V| limits of the non-slack buses, p.u."""
    lo, hi = (tables.v_min[1:], tables.v_max[1:]) if tables.n_bus > 1 else (tables.v_min, tables.v_max)
    return float(lo.min()), float(hi.max())


def voltage_norm(tables: NetworkTables) -> TwoSlopeNorm:
    """|V| colour scale: white at 1 p.u., fully blue / red at the lower / upper limit of the non-slack buses."""
    lo, hi = voltage_limits(tables)
    return TwoSlopeNorm(vmin=min(lo, 1.0 - 1e-3), vcenter=1.0, vmax=max(hi, 1.0 + 1e-3))


def loading_norm() -> Normalize:
    """Branch loading colour scale, 0 to :data:`LOADING_MAX` %."""
    return Normalize(0.0, LOADING_MAX)


def branch_loading(tables: NetworkTables, branch_s: np.ndarray) -> np.ndarray:
    """Loading |S| / rating in % (..., n_branch) from signed flows ``branch_s`` MVA; NaN where unrated."""
    with np.errstate(divide="ignore", invalid="ignore"):
        pct = 100.0 * np.abs(branch_s) / tables.rate_mva
    return np.where(np.isfinite(tables.rate_mva), pct, np.nan)


class NetworkArtist:
    """The network drawn once on ``ax`` at ``pos`` (n_bus, 2); :meth:`update` recolours it for another step.

    Buses are coloured by |V| against their limits (a thick black ring outside them), branches by |S| / rating
    (thicker above 100 %, grey when unrated); the marker of a bus is its most notable device (:data:`MARKERS`).
    Bus ids and loadings are written on networks of at most 40 buses (``labels``), |V| too up to 12 buses.
    """

    def __init__(self, ax: Axes, tables: NetworkTables, pos: np.ndarray, labels: bool | None = None):
        self.ax, self.tables, self.pos = ax, tables, pos
        self.labels = tables.n_bus <= 40 if labels is None else labels
        cmap = matplotlib.colormaps[LOAD_CMAP].with_extremes(bad="0.7")  # unrated branches grey
        self.lines = LineCollection(np.stack([pos[tables.f_bus], pos[tables.t_bus]], 1), cmap=cmap,
                                    norm=loading_norm(), zorder=1)
        ax.add_collection(self.lines)
        size = 260 if tables.n_bus <= 12 else 110 if tables.n_bus <= 40 else max(15, 4000 / tables.n_bus)
        self.values = tables.n_bus <= 12  # room to print |V| under each bus
        kind = tables.bus_kind()
        self.groups = [(np.flatnonzero(kind == k), m) for k, (m, _) in MARKERS.items() if (kind == k).any()]
        self.buses = [ax.scatter(pos[idx, 0], pos[idx, 1], c=np.ones(idx.size), cmap=V_CMAP,
                                 norm=voltage_norm(tables), s=size, marker=m, zorder=2) for idx, m in self.groups]
        self.bus_text, self.branch_text = [], []
        if self.labels:
            offset = -18 if self.values else -10
            self.bus_text = [ax.annotate("", pos[b], xytext=(0, offset), textcoords="offset points", ha="center",
                                         va="top", fontsize=7, zorder=3) for b in range(tables.n_bus)]
            self.branch_text = [ax.annotate("", (pos[f] + pos[t]) / 2, xytext=(0, 6), textcoords="offset points",
                                            ha="center", fontsize=7, color="0.2", zorder=3)
                                for f, t in zip(tables.f_bus, tables.t_bus)]
        pad = 0.6
        ax.set_xlim(pos[:, 0].min() - pad, pos[:, 0].max() + pad)
        ax.set_ylim(pos[:, 1].min() - pad - 0.3, pos[:, 1].max() + pad)
        ax.set_xticks([])
        ax.set_yticks([])

    def update(self, v_magn: np.ndarray, branch_s: np.ndarray, title: str = "") -> None:
        """Recolour for bus |V| ``v_magn`` (n_bus,) p.u. and signed branch flows ``branch_s`` (n_branch,) MVA."""
        tb = self.tables
        loading = branch_loading(tb, branch_s)
        self.lines.set_array(np.ma.masked_invalid(loading))
        self.lines.set_linewidths(np.where(np.nan_to_num(loading) > 100.0, 6.0, 3.5))
        bad_v = (v_magn < tb.v_min - V_TOL) | (v_magn > tb.v_max + V_TOL)
        for (idx, _), sc in zip(self.groups, self.buses):
            sc.set_array(v_magn[idx])
            sc.set_edgecolors(np.where(bad_v[idx], "black", "0.35"))
            sc.set_linewidths(np.where(bad_v[idx], 3.0, 0.8))
        for b, txt in enumerate(self.bus_text):
            txt.set_text(f"{b}\n{v_magn[b]:.3f}" if self.values and np.isfinite(v_magn[b]) else str(b))
        for j, txt in enumerate(self.branch_text):
            txt.set_text(f"{loading[j]:.0f}%" if np.isfinite(loading[j]) else "")
        self.ax.set_title(title, fontsize=10)


def marker_legend(ax: Axes, tables: NetworkTables) -> None:
    """A legend of the bus markers present in ``tables`` and of the limit-violation ring."""
    present = set(tables.bus_kind().tolist())
    handles = [Line2D([], [], ls="", marker=m, color="0.6", markeredgecolor="0.35", markersize=9, label=name)
               for k, (m, name) in MARKERS.items() if k in present]
    handles.append(Line2D([], [], ls="", marker="o", color="white", markeredgecolor="black", markeredgewidth=2.5,
                          markersize=9, label="|V| outside limits"))
    ax.legend(handles=handles, loc="lower left", fontsize=7, framealpha=0.8)
