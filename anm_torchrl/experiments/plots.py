"""Figures of the experiments (matplotlib, Agg), drawn from the result records only.

Every ``fig_*`` takes one result record (``io.load_results(dir)[name]``) and a PNG path, and returns the path,
or None when the record has no data for it. :func:`make_all` draws every figure the results allow.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from anm_torchrl.experiments.io import load_results  # noqa: E402


def _ok(rec: dict | None) -> bool:
    return bool(rec) and rec.get("status") in ("ok", "partial") and bool(rec.get("data"))


def _save(fig, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def fig_pinn_losses(rec: dict, path) -> Path | None:
    """Fig. 5: PINN loss components (log scale) against training step, one panel per module."""
    if not _ok(rec):
        return None
    sc = rec["data"]["scalars"]
    modules = sorted({t.split("/")[1] for t in sc if t.count("/") >= 2})
    fig, axes = plt.subplots(1, max(len(modules), 1), figsize=(4.5 * max(len(modules), 1), 3.5), squeeze=False)
    for ax, m in zip(axes[0], modules):
        for tag, pts in sorted(sc.items()):
            term = tag.split("/")[-1]
            if tag.split("/")[1] != m or term in ("lr",) or term.startswith("val_"):
                continue
            s, v = zip(*pts)
            v = np.abs(np.asarray(v, float))
            ax.plot(s, np.where(v > 0, v, np.nan), label=term)
        ax.set_yscale("log")
        ax.set_title(m)
        ax.set_xlabel("step")
        ax.legend(fontsize=7)
    return _save(fig, path)


def fig_speed(rec: dict, path) -> Path | None:
    """Fig. 6: median seconds per transition, batch 1 and batched, per implementation (log scale)."""
    if not _ok(rec):
        return None
    rows = rec["data"]["table"]
    impls = list(dict.fromkeys(r["impl"] for r in rows))
    fig, ax = plt.subplots(figsize=(1.2 * len(impls) + 3, 3.8))
    x = np.arange(len(impls))
    for k, mode in enumerate(("batch 1", "batched")):
        vals = [next((r["s_per_transition"] for r in rows if r["impl"] == i and r["mode"] == mode), np.nan)
                for i in impls]
        lo = [next((r["s_per_transition"] - r["q25"] for r in rows if r["impl"] == i and r["mode"] == mode), 0)
              for i in impls]
        hi = [next((r["q75"] - r["s_per_transition"] for r in rows if r["impl"] == i and r["mode"] == mode), 0)
              for i in impls]
        ax.bar(x + (k - 0.5) * 0.4, vals, 0.4, yerr=[lo, hi],
               label=mode if mode == "batch 1" else f"batched ({rec['data'].get('n_transitions')})")
    ax.set_xticks(x, impls, rotation=20)
    ax.set_yscale("log")
    ax.set_ylabel("s per transition (median, IQR)")
    ax.legend()
    return _save(fig, path)


def fig_speed_scaling(rec: dict, path) -> Path | None:
    """Seconds per transition against the batch size, per implementation (log–log)."""
    if not _ok(rec) or not rec["data"].get("scaling"):
        return None
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    rows = rec["data"]["scaling"]
    for impl in dict.fromkeys(r["impl"] for r in rows):
        pts = sorted((r["batch"], r["s_per_transition"]) for r in rows if r["impl"] == impl)
        ax.plot(*zip(*pts), marker="o", label=impl)
    gym = [r for r in rec["data"]["table"] if r["impl"] == "gym_anm"]
    if gym:
        ax.axhline(gym[0]["s_per_transition"], color="k", ls="--", label="gym_anm (batch 1)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("batch size")
    ax.set_ylabel("s per transition")
    ax.legend(fontsize=7)
    return _save(fig, path)


def fig_accuracy(rec: dict, path) -> Path | None:
    """Fig. 7: R² (linear) and MAE (log) per model × train dataset, in- and cross-dataset."""
    if not _ok(rec):
        return None
    rows = [r for r in rec["data"]["rows"] if "test" in r["split"] or r["cross"]] or rec["data"]["rows"]
    keys = list(dict.fromkeys((r["model"], r["train_dataset"], r["eval_dataset"]) for r in rows))
    fig, axes = plt.subplots(1, 2, figsize=(max(6, 0.6 * len(keys) + 4), 3.8))
    x = np.arange(len(keys))
    for ax, metric in zip(axes, ("r2", "mae")):
        vals = [np.mean([r[metric] for r in rows if (r["model"], r["train_dataset"], r["eval_dataset"]) == k])
                for k in keys]
        colors = ["tab:orange" if k[1] != k[2] else "tab:blue" for k in keys]
        ax.bar(x, vals, color=colors)
        ax.set_xticks(x, [f"{m}\n{t}→{e}" for m, t, e in keys], rotation=60, fontsize=7)
        ax.set_title(metric.upper() + (" (log)" if metric == "mae" else "") + "  blue: in-dataset, orange: cross")
        if metric == "mae":
            ax.set_yscale("log")
    return _save(fig, path)


def fig_rollout_mae(rec: dict, path, mode: str = "one_step") -> Path | None:
    """Fig. 8: MAE per surrogate and agent (one-step teacher-forced or free-running)."""
    if not _ok(rec) or not rec["data"].get("agents"):
        return None
    agents = rec["data"]["agents"]
    labs = list(dict.fromkeys(l for a in agents.values() for l in a["surrogates"]))
    fig, ax = plt.subplots(figsize=(1.0 * len(labs) + 3, 3.8))
    x = np.arange(len(labs))
    w = 0.8 / max(len(agents), 1)
    for k, (name, a) in enumerate(agents.items()):
        vals = [(a["surrogates"].get(l, {}).get(mode) or {}).get("mae", np.nan) for l in labs]
        ax.bar(x + (k - (len(agents) - 1) / 2) * w, vals, w, label=f"{name} ({a['policy'].split(' (')[0]})")
    ax.set_xticks(x, labs, rotation=20)
    ax.set_yscale("symlog", linthresh=1e-6)
    ax.set_ylabel(f"{mode.replace('_', '-')} MAE (state units)")
    ax.legend(fontsize=7)
    return _save(fig, path)


def fig_episode_mae(rec: dict, path, surrogate: str = "pinn", mode: str = "one_step") -> Path | None:
    """Fig. 9 (one-step) / free-running curve: MAE against the step for one surrogate (the PINN by default; the
    first available one otherwise), one line per agent."""
    if not _ok(rec) or not rec["data"].get("agents"):
        return None
    agents = rec["data"]["agents"]
    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    drawn = False
    for name, a in agents.items():
        labs = [surrogate] if surrogate in a["surrogates"] else [l for l in a["surrogates"] if l != "none"][:1]
        for lab in labs if mode == "one_step" else [l for l in a["surrogates"] if l != "none"]:
            ys = (a["surrogates"][lab].get(mode) or {}).get("mae_per_step")
            if ys:
                ax.plot([np.nan if y is None else y for y in ys], label=f"{lab} / {name}", lw=1)
                drawn = True
    if not drawn:
        plt.close(fig)
        return None
    ax.set_xlabel("step (15 min)")
    ax.set_ylabel(f"{mode.replace('_', '-')} MAE")
    ax.set_yscale("symlog", linthresh=1e-6)
    ax.legend(fontsize=7)
    return _save(fig, path)


def fig_sweep(rec: dict, path) -> Path | None:
    """Figs. 10–11: mean return and training time per (n_envs, buffer), and the correlation matrix."""
    if not _ok(rec):
        return None
    grid = rec["data"]["grid"]
    ns = sorted({r["n_envs"] for r in grid})
    bs = sorted({r["buffer"] for r in grid})
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for ax, key, title in ((axes[0], "mean_return", "mean eval return (last evals)"),
                           (axes[1], "train_time_s", "training time (s)")):
        m = np.full((len(ns), len(bs)), np.nan)
        for r in grid:
            if r[key] is not None:
                m[ns.index(r["n_envs"]), bs.index(r["buffer"])] = r[key]
        im = ax.imshow(m, cmap="viridis", aspect="auto")
        for i in range(len(ns)):
            for j in range(len(bs)):
                if not math.isnan(m[i, j]):
                    ax.text(j, i, f"{m[i, j]:.3g}", ha="center", va="center", color="w", fontsize=8)
        ax.set_xticks(range(len(bs)), bs)
        ax.set_yticks(range(len(ns)), ns)
        ax.set_xlabel("buffer (steps per env)")
        ax.set_ylabel("n_envs")
        ax.set_title(title)
        fig.colorbar(im, ax=ax)
    corr = rec["data"]["correlation"]
    names = list(corr)
    c = np.array([[np.nan if corr[a][b] is None else corr[a][b] for b in names] for a in names])
    im = axes[2].imshow(c, cmap="coolwarm", vmin=-1, vmax=1)
    axes[2].set_xticks(range(len(names)), names, rotation=30, fontsize=7)
    axes[2].set_yticks(range(len(names)), names, fontsize=7)
    for i in range(len(names)):
        for j in range(len(names)):
            if not math.isnan(c[i, j]):
                axes[2].text(j, i, f"{c[i, j]:.2f}", ha="center", va="center", fontsize=7)
    axes[2].set_title("Pearson correlation")
    fig.colorbar(im, ax=axes[2])
    return _save(fig, path)


def _band(runs: list[dict], x: str, n: int = 50):
    curves = [r["curve"] for r in runs if r.get("curve")]
    if not curves:
        return None
    hi = min(c[-1][x] for c in curves)
    lo = max(c[0][x] for c in curves)
    if len(curves) == 1 or hi <= lo:
        c = curves[0]
        return np.array([p[x] for p in c]), np.array([p["return"] for p in c]), None
    grid = np.linspace(lo, hi, n)
    ys = np.stack([np.interp(grid, [p[x] for p in c], [p["return"] for p in c]) for c in curves])
    mean = ys.mean(0)
    half = 1.96 * ys.std(0, ddof=1) / math.sqrt(len(curves))
    return grid, mean, half


def fig_ppo_curves(rec: dict, path) -> Path | None:
    """PPO evaluation loss (−return) on the true simulator against frames and wall time, log scales (returns span
    three decades); mean over seeds with its 95 % CI, one colour per training env, baselines dotted."""
    if not _ok(rec) or not rec["data"].get("runs"):
        return None
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.5))
    colours = plt.cm.tab20(np.linspace(0, 1, 20))
    for ax, x, xlabel in ((axes[0], "frames", "training frames"), (axes[1], "wall_s", "wall time (s), log scale")):
        for k, (lab, runs) in enumerate(rec["data"]["runs"].items()):
            b = _band(runs, x)
            if b is None:
                continue
            loss = -b[1]
            ax.plot(b[0], loss, color=colours[k % 20], lw=2 if lab in ("pinn", "none", "gym_anm") else 1,
                    label=f"{lab} ({len([r for r in runs if r.get('curve')])} seeds)")
            if b[2] is not None:  # a band that would cross zero is cut at a tenth of the mean (log axis)
                ax.fill_between(b[0], np.maximum(loss - b[2], 0.1 * np.abs(loss)), loss + b[2],
                                color=colours[k % 20], alpha=0.15)
        for k, (name, m) in enumerate(rec["data"].get("baselines", {}).items()):
            if m.get("available") and m["return"] < 0:
                ax.axhline(-m["return"], ls=":", color=str(0.2 + 0.25 * k), label=f"{name} (baseline)")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("eval loss = −return (true simulator)")
        ax.set_yscale("log")
        if x == "wall_s":
            ax.set_xscale("log")
    axes[1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    return _save(fig, path)


def fig_adaptability(rec: dict, path) -> Path | None:
    """One-step MAE per surrogate under each demand/generation scenario."""
    if not _ok(rec):
        return None
    rows = rec["data"]["rows"]
    scen = list(dict.fromkeys(r["scenario"] for r in rows))
    labs = list(dict.fromkeys(r["surrogate"] for r in rows))
    fig, ax = plt.subplots(figsize=(1.0 * len(labs) + 4, 3.8))
    x = np.arange(len(labs))
    w = 0.8 / len(scen)
    for k, s in enumerate(scen):
        vals = [np.nanmean([r["one_step_mae"] for r in rows if r["scenario"] == s and r["surrogate"] == l] or [np.nan])
                for l in labs]
        ax.bar(x + (k - (len(scen) - 1) / 2) * w, vals, w, label=s)
    ax.set_xticks(x, labs)
    ax.set_yscale("symlog", linthresh=1e-6)
    ax.set_ylabel("one-step MAE")
    ax.legend(fontsize=7)
    return _save(fig, path)


FIGURES = {
    "fig5_pinn_losses": ("pinn_losses", fig_pinn_losses),
    "fig6_speed": ("speed", fig_speed),
    "fig6b_speed_scaling": ("speed", fig_speed_scaling),
    "fig7_accuracy": ("accuracy", fig_accuracy),
    "fig8_one_step_mae": ("rollout_error", fig_rollout_mae),
    "fig9_episode_mae": ("rollout_error", fig_episode_mae),
    "fig8b_free_running_mae": ("rollout_error", lambda r, p: fig_rollout_mae(r, p, "free_running")),
    "fig9b_free_running_curve": ("rollout_error", lambda r, p: fig_episode_mae(r, p, mode="free_running")),
    "fig10_11_sweep": ("sweep", fig_sweep),
    "fig12_ppo_curves": ("ppo_curves", fig_ppo_curves),
    "adaptability": ("adaptability", fig_adaptability),
}


def make_all(results: dict[str, dict] | str | Path, fig_dir: str | Path) -> dict[str, str | None]:
    """Draw every figure the results allow into ``fig_dir``; returns figure name -> path (None: no data)."""
    if not isinstance(results, dict):
        results = load_results(results)
    out = {}
    for name, (key, fn) in FIGURES.items():
        try:
            p = fn(results.get(key), Path(fig_dir) / f"{name}.png")
        except Exception:  # noqa: BLE001 - a figure never breaks the run; it is reported missing
            plt.close("all")
            p = None
        out[name] = None if p is None else str(p)
    return out
