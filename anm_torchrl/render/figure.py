"""``episode_figure``: one episode on one page — the network at chosen steps and every quantity over time."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from tensordict import TensorDictBase

from anm_torchrl.render.layout import network_layout
from anm_torchrl.render.network_plot import NetworkArtist, branch_loading, marker_legend, voltage_limits
from anm_torchrl.render.tables import NetworkTables

MAX_LINES = 8  # above this many devices / buses / branches a panel shows totals or envelopes instead
REQUIRED = ("state", "action", ("next", "state"), ("next", "reward"), ("next", "terminated"),
            *(("next", "grid", k) for k in ("v_magn", "branch_s", "e_loss", "penalty", "curtailment")))


@dataclasses.dataclass
class Episode:
    """One recorded episode of T steps, as float64 numpy arrays (gym-anm units).

    Attributes:
        state: (T + 1, D) states s_0 … s_T (MW, MVAr, MWh, time index).
        action: (T, A) set-points (MW / MVAr).   reward: (T,).   terminated: (T,) bool.
        v_magn: (T, n_bus) p.u. and branch_s: (T, n_branch) MVA after each step.
        e_loss: (T,) MWh.   penalty: (T,) λΦ.   curtailment: (T,) MW.
    """

    state: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    terminated: np.ndarray
    v_magn: np.ndarray
    branch_s: np.ndarray
    e_loss: np.ndarray
    penalty: np.ndarray
    curtailment: np.ndarray

    @property
    def steps(self) -> int:
        return int(self.action.shape[0])


def episode_from_rollout(rollout: TensorDictBase, base_mva: float) -> Episode:
    """An :class:`Episode` from ``env.rollout(...)`` of one env (batch (T,) or (1, T)).

    Raises:
        ValueError: a required key is missing or the rollout holds more than one env.
    """
    if rollout.batch_dims == 2:
        if rollout.batch_size[0] != 1:
            raise ValueError(f"rollout must hold one env, got batch size {tuple(rollout.batch_size)}")
        rollout = rollout[0]
    if rollout.batch_dims != 1:
        raise ValueError(f"rollout must have batch size (T,) or (1, T), got {tuple(rollout.batch_size)}")
    keys = set(rollout.keys(True, True))
    missing = [k for k in REQUIRED if k not in keys]
    if missing:
        raise ValueError(f"rollout lacks keys {missing} (expected an env rollout with ('grid', ...) entries)")
    get = lambda *k: rollout.get(k if len(k) > 1 else k[0]).detach().cpu().double().numpy()  # noqa: E731
    return Episode(
        state=np.concatenate([get("state")[:1], get("next", "state")]), action=get("action"),
        reward=get("next", "reward")[:, 0], terminated=get("next", "terminated")[:, 0].astype(bool),
        v_magn=get("next", "grid", "v_magn"), branch_s=get("next", "grid", "branch_s"),
        e_loss=get("next", "grid", "e_loss")[:, 0] * base_mva, penalty=get("next", "grid", "penalty")[:, 0],
        curtailment=get("next", "grid", "curtailment")[:, 0])


def default_times(ep: Episode, tables: NetworkTables) -> list[int]:
    """First and last converged steps and, between them, the most stressed one: the largest penalty, else the
    highest branch loading, else the largest curtailment, else the middle step."""
    ok = np.flatnonzero(~ep.terminated)
    if ok.size == 0:
        return [0]
    first, last = int(ok[0]), int(ok[-1])
    inner = ok[(ok != first) & (ok != last)]
    if inner.size == 0:
        return sorted({first, last})
    with np.errstate(all="ignore"):
        loading = np.nan_to_num(branch_loading(tables, ep.branch_s[inner])).max(1)
    for score in (ep.penalty[inner], loading, ep.curtailment[inner]):
        if score.max() > 0:
            return [first, int(inner[np.argmax(score)]), last]
    return [first, int(inner[inner.size // 2]), last]


def clock(ep: Episode, tables: NetworkTables, step: int) -> str:
    """Time of day ``hh:mm`` after ``step`` (from the state's time index)."""
    minutes = int(round(ep.state[step + 1, tables.state_slices()["aux"]][0] * tables.delta_t * 60))
    return f"{minutes // 60 % 24:02d}:{minutes % 60:02d}"


def snapshot_title(ep: Episode, tables: NetworkTables, t: int) -> str:
    """``step k (hh:mm): reward r, curtailment c MW`` for step index ``t``."""
    return (f"step {t + 1} ({clock(ep, tables, t)}): reward {ep.reward[t]:.2f}, "
            f"curtailment {ep.curtailment[t]:.1f} MW")


def episode_figure(ep: Episode, tables: NetworkTables, times: list[int] | None = None,
                   title: str = "") -> Figure:
    """The network at ``times`` (step indices, default :func:`default_times`) over the episode's time series.

    Args:
        ep: the episode (:func:`episode_from_rollout`).
        tables: its network (:func:`~anm_torchrl.render.tables.network_tables`).
        times: steps whose post-step grid is drawn (at most 4).
        title: figure title.

    Raises:
        ValueError: a time outside [0, T) or more than 4 times.
    """
    times = default_times(ep, tables) if times is None else sorted(set(int(t) for t in times))
    if not times or len(times) > 4 or min(times) < 0 or max(times) >= ep.steps:
        raise ValueError(f"times must be 1 to 4 step indices in [0, {ep.steps}), got {times}")
    fig = Figure(figsize=(18, 17), layout="constrained")
    outer = fig.add_gridspec(2, 1, height_ratios=[1.05, 2.6])
    top = outer[0].subgridspec(1, len(times))
    pos = network_layout(tables.n_bus, tables.f_bus, tables.t_bus)
    net_axes = [fig.add_subplot(top[i]) for i in range(len(times))]
    for ax, t in zip(net_axes, times):
        art = NetworkArtist(ax, tables, pos)
        art.update(ep.v_magn[t], ep.branch_s[t], snapshot_title(ep, tables, t))
    marker_legend(net_axes[0], tables)
    v_lo, v_hi = voltage_limits(tables)
    fig.colorbar(art.buses[0], ax=net_axes, label=f"bus |V| (p.u.), limits [{v_lo:.2f}, {v_hi:.2f}]", shrink=0.9,
                 pad=0.01, extend="both")
    fig.colorbar(art.lines, ax=net_axes, label="branch loading |S| / rating (%)", shrink=0.9, pad=0.01, extend="max")
    grid = outer[1].subgridspec(4, 2)
    axes = [fig.add_subplot(grid[i, j]) for i in range(4) for j in range(2)]
    for ax in axes[1:]:
        ax.sharex(axes[0])
    _time_series(axes, ep, tables)
    for ax in axes:
        for t in times:
            ax.axvline(t + 1, color="0.6", lw=0.8, ls=":")
        for t in np.flatnonzero(ep.terminated):
            ax.axvline(t + 1, color="red", lw=1.5)
    for ax in axes[-2:]:
        ax.set_xlabel(f"step (Δt = {tables.delta_t * 60:.0f} min; dotted: the network snapshots"
                      + ("; red: power flow diverged" if ep.terminated.any() else "") + ")")
    start = clock(ep, tables, -1)
    fig.suptitle(f"{title}  ({ep.steps} steps from {start}, return {ep.reward.sum():.2f})".strip(), fontsize=13)
    return fig


def _series(ax: Axes, x: np.ndarray, ys: np.ndarray, names: list[str], total: str, **kw) -> list:
    """Plot columns of ``ys`` (T, k) named ``names``, or their sum labelled ``total`` if k > MAX_LINES."""
    if ys.shape[1] > MAX_LINES:
        return ax.plot(x, ys.sum(1), label=total, **kw)
    return [ax.plot(x, ys[:, i], label=n, color=f"C{i}", **kw)[0] for i, n in enumerate(names)]


def _time_series(axes: list[Axes], ep: Episode, tb: NetworkTables) -> None:
    sl = tb.state_slices()
    nxt = ep.state[1:].copy()
    nxt[ep.terminated] = np.nan  # gym-anm zeroes the state after a diverged power flow: not a real value
    x = np.arange(1, ep.steps + 1)
    ng, nd = len(tb.gen_ids), len(tb.des_ids)
    p, q = nxt[:, sl["dev_p"]], nxt[:, sl["dev_q"]]
    gen_names = [f"gen {d} (bus {tb.dev_bus[d]})" for d in tb.gen_ids]
    des_names = [f"DES {d} (bus {tb.dev_bus[d]})" for d in tb.des_ids]

    ax = axes[0]
    pot, applied = nxt[:, sl["gen_p_max"]], p[:, tb.gen_ids]
    _series(ax, x, applied, [f"{n}: P" for n in gen_names], "all generators: P", lw=1.8)
    _series(ax, x, pot, [f"{n}: potential" for n in gen_names], "all generators: potential", lw=1, ls="--")
    _series(ax, x, ep.action[:, :ng], [f"{n}: set-point" for n in gen_names], "all: set-point", lw=0.8, ls=":")
    if ng > MAX_LINES:
        applied, pot = applied.sum(1, keepdims=True), pot.sum(1, keepdims=True)
    for i in range(applied.shape[1]):  # the curtailed energy: between what was available and what was used
        ax.fill_between(x, applied[:, i], pot[:, i], color=f"C{i}", alpha=0.15, lw=0,
                        label="curtailed" if i == 0 else None)
    ax.set_ylabel("MW")
    ax.set_title("generator active power: applied, potential, set-point")

    ax = axes[1]
    _series(ax, x, np.c_[q[:, tb.gen_ids], q[:, tb.des_ids]], gen_names + des_names, "all devices", lw=1.5)
    _series(ax, x, ep.action[:, ng:2 * ng], [f"{n}: set-point" for n in gen_names], "set-points", lw=0.8, ls=":")
    ax.axhline(0, color="0.5", lw=0.5)
    ax.set_ylabel("MVAr")
    ax.set_title("reactive power (solid: applied, dotted: generator set-points)")

    ax = axes[2]
    if nd:
        _series(ax, x, nxt[:, sl["des_soc"]], [f"{n}: SoC" for n in des_names], "total SoC", lw=1.8)
        for cap in np.unique(tb.soc_max):
            ax.axhline(cap, color="0.4", lw=0.8, ls="--")
        ax.set_ylabel("MWh (dashed: capacity)")
        twin = ax.twinx()
        _series(twin, x, p[:, tb.des_ids], [f"{n}: P" for n in des_names], "total P", lw=0.9, ls="-.",
                alpha=0.8)
        twin.set_ylabel("P (MW, dash-dot; > 0 discharging)")
        ax.set_title("storage state of charge and active power")
    else:
        ax.set_title("no storage in this network")

    ax = axes[3]
    _series(ax, x, -p[:, tb.load_ids], [f"load {d} (bus {tb.dev_bus[d]})" for d in tb.load_ids],
            "total load", lw=1.5)
    ax.set_ylabel("MW consumed")
    ax.set_title("loads")

    ax = axes[4]
    v = ep.v_magn.copy()
    v[ep.terminated] = np.nan
    _envelope(ax, x, v, [f"bus {b}" for b in range(tb.n_bus)], "bus |V|")
    for limit in voltage_limits(tb):
        ax.axhline(limit, color="red", lw=1, ls="--")
    ax.set_ylabel("p.u. (dashed: limits)")
    ax.set_title("bus voltage magnitudes")

    ax = axes[5]
    load = branch_loading(tb, ep.branch_s)
    load[ep.terminated] = np.nan
    _envelope(ax, x, load, [f"branch {f}-{t}" for f, t in zip(tb.f_bus, tb.t_bus)], "loading")
    ax.axhline(100, color="red", lw=1, ls="--")
    ax.set_ylabel("% of rating")
    rated = np.isfinite(tb.rate_mva)
    ax.set_title("branch loading |S| / rating" + ("" if rated.all() else f" ({int(rated.sum())} of "
                                                  f"{rated.size} branches rated)"))

    ax = axes[6]
    e_loss, pen = ep.e_loss.copy(), ep.penalty.copy()
    e_loss[ep.terminated] = pen[ep.terminated] = np.nan
    ax.plot(x, e_loss, color="C0", label="energy loss ΔE (MWh)")
    ax.set_ylabel("MWh")
    twin = ax.twinx()
    twin.plot(x, pen, color="C3", label="penalty λΦ")
    twin.set_ylabel("penalty λΦ", color="C3")
    _align_zero(ax, twin)
    ax.set_title("energy loss (incl. curtailment) and constraint penalty")
    ax.legend(handles=ax.get_lines() + twin.get_lines(), fontsize=7, loc="upper left")

    ax = axes[7]
    ax.plot(x, ep.reward, color="k", lw=1.2, label="reward")
    ax.set_ylabel("reward per step")
    if ep.reward.min() < -100:  # a terminal reward (−100 / (1 − γ)) would flatten everything else
        ax.set_yscale("symlog", linthresh=10)
    twin = ax.twinx()
    twin.plot(x, np.cumsum(ep.reward), color="C2", lw=1.2, label="return so far")
    twin.set_ylabel("return so far", color="C2")
    if ax.get_yscale() == "linear":
        _align_zero(ax, twin)
    ax.set_title("reward")
    ax.legend(handles=ax.get_lines() + twin.get_lines(), fontsize=7, loc="lower left")
    for a in axes[:4]:
        a.legend(fontsize=7, loc="upper left", ncol=2)
        a.grid(alpha=0.3)
    for a in axes[4:]:
        a.grid(alpha=0.3)


def _align_zero(ax: Axes, twin: Axes) -> None:
    """Put 0 at the same height on both y axes (each keeps its data in view)."""
    lims = []
    for a in (ax, twin):
        lo, hi = a.get_ylim()
        lo, hi = min(lo, 0.0), max(hi, 0.0)
        lims.append((lo, hi, -lo / (hi - lo) if hi > lo else 0.5))
    frac = max(lims[0][2], lims[1][2])  # fraction of the height below zero
    for a, (lo, hi, _) in zip((ax, twin), lims):
        if frac >= 1.0:
            a.set_ylim(lo, 0.0 + 1e-12)
        else:
            top = max(hi, -lo * (1 - frac) / frac if frac > 0 else hi)
            a.set_ylim(-top * frac / (1 - frac), top)


def _envelope(ax: Axes, x: np.ndarray, ys: np.ndarray, names: list[str], what: str) -> None:
    """One line per column of ``ys`` (T, k) if k <= MAX_LINES, else min / mean / max over the columns."""
    if ys.shape[1] <= MAX_LINES:
        for i, n in enumerate(names):
            ax.plot(x, ys[:, i], color=f"C{i}", lw=1.2, label=n)
        ax.legend(fontsize=7, loc="upper left", ncol=2)
        return
    with warnings.catch_warnings():  # an all-NaN row (no value at that step) plots as a gap, as intended
        warnings.simplefilter("ignore", RuntimeWarning)
        lo, mid, hi = np.nanmin(ys, 1), np.nanmean(ys, 1), np.nanmax(ys, 1)
    ax.fill_between(x, lo, hi, color="C0", alpha=0.25, label=f"{what}: min–max over {ys.shape[1]}")
    ax.plot(x, mid, color="C0", lw=1.2, label=f"{what}: mean")
    ax.legend(fontsize=7, loc="upper left")
