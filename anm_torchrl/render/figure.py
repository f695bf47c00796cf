"""``episode_figure``: one episode on one page — the network at chosen steps and every quantity over time."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
from matplotlib import rc_context
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from tensordict import TensorDictBase

from anm_torchrl.grid.network import RENEWABLE
from anm_torchrl.render.layout import network_layout
from anm_torchrl.render.network_plot import NetworkArtist, branch_loading, marker_legend, voltage_limits
from anm_torchrl.render.tables import NetworkTables

MAX_LINES = 8  # above this many devices / buses / branches a panel shows totals or envelopes instead
LETTERS = "ABCD"  # snapshot labels, on the network panels and on every time series
WINDOW_HOURS = 24.0  # the time series of a longer episode show this much of it (96 steps of 15 min: readable)
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

    def window(self, start: int, stop: int) -> "Episode":
        """Steps ``start`` … ``stop - 1`` as an episode of their own (states s_start … s_stop)."""
        if not 0 <= start < stop <= self.steps:
            raise ValueError(f"window must satisfy 0 <= start < stop <= {self.steps}, got [{start}, {stop})")
        cut = {f.name: getattr(self, f.name)[start:stop] for f in dataclasses.fields(self) if f.name != "state"}
        return Episode(state=self.state[start:stop + 1], **cut)


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
    terminated = get("next", "terminated")[:, 0].astype(bool)
    # a diverged power flow's voltages and flows are the solver's last iterate, not the grid's: drawn as missing
    v_magn, branch_s = get("next", "grid", "v_magn"), get("next", "grid", "branch_s")
    v_magn[terminated], branch_s[terminated] = np.nan, np.nan
    return Episode(
        state=np.concatenate([get("state")[:1], get("next", "state")]), action=get("action"),
        reward=get("next", "reward")[:, 0], terminated=terminated, v_magn=v_magn, branch_s=branch_s,
        e_loss=get("next", "grid", "e_loss")[:, 0] * base_mva, penalty=get("next", "grid", "penalty")[:, 0],
        curtailment=get("next", "grid", "curtailment")[:, 0])


def minutes_from_midnight(ep: Episode, tables: NetworkTables) -> np.ndarray:
    """(T + 1,) minutes since the first midnight before s_0, at states s_0 … s_T (the time index advances one
    step per step; only its value in s_0 is read)."""
    start = ep.state[0, tables.state_slices()["aux"]][0] * tables.delta_t * 60
    return start % 1440 + np.arange(ep.steps + 1) * tables.delta_t * 60


def day_of_step(ep: Episode, tables: NetworkTables) -> np.ndarray:
    """(T,) calendar day of each step, 1-based (day 1 runs from the episode's start to its first midnight)."""
    return (minutes_from_midnight(ep, tables)[:-1] // 1440).astype(int) + 1


def clock(ep: Episode, tables: NetworkTables, step: int) -> str:
    """Time of day ``hh:mm`` after ``step`` (from s_0's time index: a diverged step's state is zeroed)."""
    minutes = int(round(minutes_from_midnight(ep, tables)[step + 1]))
    return f"{minutes // 60 % 24:02d}:{minutes % 60:02d}"


def snapshot_title(ep: Episode, tables: NetworkTables, t: int) -> str:
    """``step k (day d, hh:mm): reward r, curtailment c MW`` for step index ``t``."""
    return (f"step {t + 1} (day {day_of_step(ep, tables)[t]}, {clock(ep, tables, t)}): reward {ep.reward[t]:.2f}, "
            f"curtailment {ep.curtailment[t]:.1f} MW")


def choose_window(ep: Episode, tables: NetworkTables, hours: float = WINDOW_HOURS) -> tuple[int, int, str]:
    """The steps ``[start, stop)`` the time series show, and why: the whole episode if it fits in ``hours``,
    else ``hours`` centred on the first diverged power flow, or else on the costliest step (lowest reward)."""
    width = max(1, int(round(hours / tables.delta_t)))
    if ep.steps <= width:
        return 0, ep.steps, "the whole episode"
    diverged = np.flatnonzero(ep.terminated)
    if diverged.size:
        centre, why = int(diverged[0]), f"the first diverged power flow (step {diverged[0] + 1})"
    else:
        centre = int(np.argmin(ep.reward))
        why = f"the costliest step (step {centre + 1}, reward {ep.reward[centre]:.2f})"
    start = min(max(0, centre - width // 2), ep.steps - width)
    return start, start + width, f"{hours:g} h around {why}"


def default_times(ep: Episode, tables: NetworkTables, start: int = 0, stop: int | None = None
                  ) -> list[tuple[int, str]]:
    """Up to three converged steps of ``[start, stop)`` worth a look, each with its reason: the largest penalty
    (else the highest branch loading), the peak load and the most curtailment (else the peak renewable
    potential). A step chosen for several reasons is drawn once with all of them; with no converged step, the
    first step ("diverged")."""
    stop = ep.steps if stop is None else stop
    ok = np.flatnonzero(~ep.terminated[start:stop]) + start
    if ok.size == 0:
        return [(start, "diverged")]
    sl = tables.state_slices()
    p_next = ep.state[1:, sl["dev_p"]]
    with np.errstate(all="ignore"):
        loading = np.nan_to_num(branch_loading(tables, ep.branch_s)).max(1)
    load = -p_next[:, tables.load_ids].sum(1)
    potential = ep.state[1:, sl["gen_p_max"]].sum(1)
    # gen_p_max also holds classical generators' caps: "renewable" only where a renewable is among them
    renewable = bool(np.isin(tables.dev_type[tables.gen_ids], [RENEWABLE]).any())
    picks: dict[int, list[str]] = {}
    for scores in (((ep.penalty, "largest penalty"), (loading, "highest branch loading")),
                   ((load, "peak load"),),
                   ((ep.curtailment, "most curtailment"),
                    (potential, "peak renewable potential" if renewable else "peak generation potential"))):
        for score, why in scores:
            if score[ok].max() > 0:
                picks.setdefault(int(ok[np.argmax(score[ok])]), []).append(why)
                break
    if not picks:
        picks[int(ok[0])] = ["first converged step"]
    return [(t, " & ".join(whys)) for t, whys in sorted(picks.items())]


def episode_figure(ep: Episode, tables: NetworkTables, times: list[int] | None = None, title: str = "",
                   window_hours: float = WINDOW_HOURS) -> Figure:
    """One page: the network at a few labelled steps, a readable window of the time series, and — for an
    episode longer than a day — the whole episode as per-day bars.

    The window is :func:`choose_window` (the whole episode if it fits in ``window_hours``); the snapshot steps
    are ``times`` or :func:`default_times` inside the window, each titled with why it was chosen and marked by
    its letter on every time series. The figure says both choices.

    Args:
        ep: the episode (:func:`episode_from_rollout`).
        tables: its network (:func:`~anm_torchrl.render.tables.network_tables`).
        times: steps whose post-step grid is drawn (at most 4; the window is then the one holding them all, if
            ``window_hours`` allows, else the whole episode).
        title: figure title.
        window_hours: length of the time-series window, hours.

    Raises:
        ValueError: a time outside [0, T), more than 4 times, or ``window_hours`` <= 0.
    """
    if window_hours <= 0:
        raise ValueError(f"window_hours must be > 0, got {window_hours}")
    if times is None:
        start, stop, why_window = choose_window(ep, tables, window_hours)
        picks = default_times(ep, tables, start, stop)
    else:
        chosen = sorted(set(int(t) for t in times))
        if not chosen or len(chosen) > 4 or min(chosen) < 0 or max(chosen) >= ep.steps:
            raise ValueError(f"times must be 1 to 4 step indices in [0, {ep.steps}), got {times}")
        picks = [(t, "chosen") for t in chosen]
        start, stop, why_window = choose_window(ep, tables, window_hours)
        width = stop - start
        if chosen[-1] - chosen[0] >= width:
            start, stop, why_window = 0, ep.steps, "the whole episode (the chosen steps span more than the window)"
        elif chosen[0] < start or chosen[-1] >= stop:  # the window must show the chosen steps
            start = min(chosen[0], ep.steps - width)
            stop, why_window = start + width, f"{window_hours:g} h from the first chosen step"
    days = day_of_step(ep, tables)
    summary = stop - start < ep.steps  # the window shows part of the episode: per-day bars of all of it
    fig = Figure(figsize=(18, 20.5 if summary else 17), layout="constrained")
    outer = fig.add_gridspec(3 if summary else 2, 1, height_ratios=[1.05, 2.6, 0.62][:3 if summary else 2])
    top = outer[0].subgridspec(1, len(picks))
    pos = network_layout(tables.n_bus, tables.f_bus, tables.t_bus)
    net_axes = [fig.add_subplot(top[i]) for i in range(len(picks))]
    for k, (ax, (t, why)) in enumerate(zip(net_axes, picks)):
        art = NetworkArtist(ax, tables, pos)
        art.update(ep.v_magn[t], ep.branch_s[t], f"{LETTERS[k]}: {why}\n{snapshot_title(ep, tables, t)}")
    marker_legend(net_axes[0], tables)
    v_lo, v_hi = voltage_limits(tables)
    fig.colorbar(art.buses[0], ax=net_axes, label=f"bus |V| (p.u.), limits [{v_lo:.2f}, {v_hi:.2f}]", shrink=0.9,
                 pad=0.01, extend="both")
    fig.colorbar(art.lines, ax=net_axes, label="branch loading |S| / rating (%)", shrink=0.9, pad=0.01, extend="max")
    grid = outer[1].subgridspec(4, 2)
    axes = [fig.add_subplot(grid[i, j]) for i in range(4) for j in range(2)]
    for ax in axes[1:]:
        ax.sharex(axes[0])
    # a line through one or two points is invisible or bare: mark the points of so short a window
    with rc_context({"lines.marker": "o", "lines.markersize": 4} if stop - start <= 2 else {}):
        _time_series(axes, ep.window(start, stop), tables, offset=start)
    ticks, labels = _clock_ticks(ep, tables, start, stop)
    for ax in axes:
        ax.set_xlim(start + 0.5, stop + 0.5)
        for k, (t, _) in enumerate(picks):
            if start <= t < stop:
                ax.axvline(t + 1, color="0.45", lw=0.9, ls=":")
                ax.annotate(LETTERS[k], (t + 1, 1.0), xycoords=("data", "axes fraction"), xytext=(0, -2),
                            textcoords="offset points", ha="center", va="top", fontsize=9, fontweight="bold",
                            color="0.25", bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="0.6", lw=0.6),
                            zorder=10)  # above the legends
        for t in np.flatnonzero(ep.terminated[start:stop]) + start:
            ax.axvline(t + 1, color="red", lw=1.5)
        ax.set_xticks(ticks, labels)
    for ax in axes[-2:]:
        ax.set_xlabel(f"time of day (steps {start + 1}–{stop} of {ep.steps}, Δt = {tables.delta_t * 60:.0f} min; "
                      "dotted, lettered: the network snapshots"
                      + ("; red: power flow diverged" if ep.terminated[start:stop].any() else "") + ")")
    if summary:
        _daily_summary(outer[2].subgridspec(1, 4), fig, ep, tables, days, (days[start], days[stop - 1]))
    head = f"{title}  ({ep.steps} steps from {clock(ep, tables, -1)}, return {ep.reward.sum():.2f})".strip()
    fig.suptitle(f"{head}\ntime series: {why_window}; snapshots: " + ", ".join(
        f"{LETTERS[k]} {why}" for k, (_, why) in enumerate(picks)), fontsize=13)
    return fig


def _clock_ticks(ep: Episode, tables: NetworkTables, start: int, stop: int) -> tuple[list[float], list[str]]:
    """x ticks (step numbers) every few hours of ``[start, stop)``, labelled ``hh:mm`` and the day at midnight."""
    minutes = minutes_from_midnight(ep, tables)[start + 1:stop + 1]  # after each step of the window
    span_h = (stop - start) * tables.delta_t
    every = next(h for h in (1, 2, 3, 4, 6, 12, 24, 48, 96, 168, 10 ** 9) if span_h / h <= 12) * 60
    ticks, labels = [], []
    for i, m in enumerate(minutes):
        if abs(m / every - round(m / every)) * every < tables.delta_t * 30:  # the step ending nearest the hour
            if ticks and start + i + 1 - ticks[-1] < every / (tables.delta_t * 60) / 2:
                continue
            hh = int(round(m)) // 60 % 24
            day = int(round(m)) // 1440 + 1
            ticks.append(start + i + 1)
            labels.append(f"{hh:02d}:00" + (f"\nday {day}" if hh == 0 or not labels else ""))
    return ticks, labels


def _daily_summary(grid, fig: Figure, ep: Episode, tb: NetworkTables, days: np.ndarray,
                   shown: tuple[int, int]) -> None:
    """Per calendar day of the whole episode: energy loss, curtailed energy, penalty and return, as bars."""
    ok = ~ep.terminated
    day_ids = np.arange(days[0], days[-1] + 1)
    steps_per_day = 24 / tb.delta_t
    count = np.array([(days == d).sum() for d in day_ids])
    per_day = lambda v: np.array([v[(days == d) & ok].sum() for d in day_ids])  # noqa: E731
    panels = [(per_day(ep.e_loss), "C0", "energy loss ΔE per day (MWh, incl. curtailment)"),
              (per_day(ep.curtailment * tb.delta_t), "C1", "curtailed energy per day (MWh)"),
              (per_day(ep.penalty), "C3", "penalty per day (Σ λΦ)"),
              (np.array([ep.reward[days == d].sum() for d in day_ids]), "0.3", "return per day (Σ reward)")]
    partial = count < steps_per_day - 1e-9
    diverged = [d for d in day_ids if ep.terminated[days == d].any()]
    axes = [fig.add_subplot(grid[0, i]) for i in range(4)]
    for ax, (values, colour, what) in zip(axes, panels):
        ax.bar(day_ids, values, color=colour, alpha=0.85, width=0.8)
        ax.bar(day_ids[partial], values[partial], color="white", alpha=0.55, width=0.8, hatch="//",
               edgecolor=colour, lw=0)
        ax.axvspan(shown[0] - 0.5, shown[1] + 0.5, color="0.85", zorder=0)
        for d in diverged:
            ax.axvline(d, color="red", lw=1.5)
        ax.set_title(what, fontsize=10)
        ax.set_xlabel("day")
        ax.set_xlim(day_ids[0] - 0.6, day_ids[-1] + 0.6)
        ax.set_xticks(day_ids[::max(1, int(np.ceil(day_ids.size / 16)))])
        if values.min() >= 0:
            ax.set_ylim(bottom=0, top=max(ax.get_ylim()[1], 1e-3))
        ax.grid(alpha=0.3, axis="y")
    axes[0].annotate("grey band: the days of the time series above; hatched: partial day"
                     + ("; red: power flow diverged" if diverged else ""), (0, 1.18),
                     xycoords="axes fraction", fontsize=8, color="0.3")


def _series(ax: Axes, x: np.ndarray, ys: np.ndarray, names: list[str], total: str, **kw) -> list:
    """Plot columns of ``ys`` (T, k) named ``names``, or their sum labelled ``total`` if k > MAX_LINES."""
    if ys.shape[1] > MAX_LINES:
        return ax.plot(x, ys.sum(1), label=total, **kw)
    return [ax.plot(x, ys[:, i], label=n, color=f"C{i}", **kw)[0] for i, n in enumerate(names)]


def _time_series(axes: list[Axes], ep: Episode, tb: NetworkTables, offset: int = 0) -> None:
    """The eight time-series panels of ``ep``, steps numbered from ``offset + 1`` (a window of a longer one)."""
    sl = tb.state_slices()
    nxt = ep.state[1:].copy()
    nxt[ep.terminated] = np.nan  # gym-anm zeroes the state after a diverged power flow: not a real value
    x = np.arange(1, ep.steps + 1) + offset
    ng, nd = len(tb.gen_ids), len(tb.des_ids)
    p, q = nxt[:, sl["dev_p"]], nxt[:, sl["dev_q"]]
    gen_names = [f"gen {tb.dev_id[d]} (bus {tb.dev_bus[d]})" for d in tb.gen_ids]
    des_names = [f"DES {tb.dev_id[d]} (bus {tb.dev_bus[d]})" for d in tb.des_ids]

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
    ax.set_title("generator active power: applied, potential, set-point" if ng else
                 "no generator but the slack in this network")

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
    _series(ax, x, -p[:, tb.load_ids], [f"load {tb.dev_id[d]} (bus {tb.dev_bus[d]})" for d in tb.load_ids],
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
    so_far = "return so far" if offset == 0 else f"return from step {offset + 1}"
    twin.plot(x, np.cumsum(ep.reward), color="C2", lw=1.2, label=so_far)
    twin.set_ylabel(so_far, color="C2")
    if ax.get_yscale() == "linear":
        _align_zero(ax, twin)
    ax.set_title("reward")
    ax.legend(handles=ax.get_lines() + twin.get_lines(), fontsize=7, loc="lower left")
    for a in axes[:4]:
        if a.get_legend_handles_labels()[0]:  # a network without generators or storage leaves a panel empty
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
