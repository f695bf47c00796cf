"""How close the PINN chain's gradients are to the exact ones: d(reward)/d(action), the signal SHAC learns from.

The exact gradient is the differentiable simulator's (:func:`anm_torchrl.grid.differentiable.step`: the power flow
by the implicit function theorem, tested against finite differences in ``tests/test_gradients.py``); the PINN's is
autograd through its chain of ``TensorDictModule``s. Both are taken at the same (state, action) rows: states from
the network's reset distribution (``make_true_env(n, seed=0).reset()``), actions in two sets — ``near_do_nothing``
(do-nothing plus 5 % of the action range in Gaussian noise, clipped to the box: where an early policy acts) and
``uniform`` (uniform in the box). Rows terminal in either model carry no gradient and are left out. Per set: the
cosine similarity of the two gradient vectors (median, 10 % quantile), their relative error ‖g_pinn − g‖/‖g‖
(median, 90 % quantile), and the sign agreement of the components whose exact gradient is not negligible
(|g| > 1 % of the row's largest). Where they part (a component off by more than 10 % of its row's largest exact
|g|), the record says which actions, how many sit on the action box's bound, and both models' one-sided differences
from ``PART_STEP`` inside the box: at a kink (a cap meeting a bound or the potential) the exact model's gradient is one
branch's derivative and the PINN's smooth chain may give a value between the branches, while the two models agree
one step away from it.

Command (the record ``results/shac/pinn_gradients.{json,png}``; each network's cached default PINN is used, trained
first with ``--train`` when missing)::

    python -m anm_torchrl.cli.pinn_gradients --networks anm6_easy case33bw --rows 512 --out results/shac/pinn_gradients
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

import torch
from tensordict import TensorDict

from anm_torchrl.grid import differentiable
from anm_torchrl.provenance import machine_info, versions
from anm_torchrl.strict_json import json_text

SIGN_FLOOR = 0.01  # a component counts in the sign agreement when |g| > this share of its row's largest |g|
PART_FLOOR = 0.10  # a component "parts" when |g_pinn - g| > this share of its row's largest exact |g|
PART_STEP = 0.01  # MW/MVAr: the one-sided difference's step into the box at a parting component


def action_sets(sim, n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """The two action sets (N, action_dim) float64 MW/MVAr of the module docstring."""
    from anm_torchrl.baselines.simple import DoNothingPolicy

    lo, hi = sim.action_bounds()
    g = torch.Generator().manual_seed(seed)
    near = (DoNothingPolicy(sim).action_value.to(torch.float64)
            + 0.05 * (hi - lo) * torch.randn(n, sim.action_dim, generator=g, dtype=torch.float64))
    uniform = lo + torch.rand(n, sim.action_dim, generator=g, dtype=torch.float64) * (hi - lo)
    return {"near_do_nothing": torch.minimum(torch.maximum(near, lo), hi), "uniform": uniform}


def models(chain, sim) -> dict[str, Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]]:
    """The two models as ``(state (N, D), action (N, A)) -> (reward (N,), non-terminal (N,) bool)``: ``exact``
    (the differentiable simulator) and ``pinn`` (``chain``)."""
    def exact(state, action):
        tr = differentiable.step(sim, state, action)[1]
        return tr.reward, tr.converged

    def pinn(state, action):
        out = chain(TensorDict({"state": state, "action": action}, [state.shape[0]]))
        return out["reward"].reshape(-1), ~out["terminated"].reshape(-1)

    return {"exact": exact, "pinn": pinn}


def reward_gradients(chain, sim, state: torch.Tensor, action: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """d(reward)/d(action) (N, action_dim) of the exact model and of ``chain``, and the rows (N,) bool that are
    terminal in neither."""
    grads, ok = [], torch.ones(state.shape[0], dtype=torch.bool)
    for model in models(chain, sim).values():
        a = action.clone().requires_grad_(True)
        reward, alive = model(state, a)
        grads.append(torch.autograd.grad(reward.sum(), a)[0])
        ok = ok & alive
    return grads[0], grads[1], ok


def compare(g_exact: torch.Tensor, g_pinn: torch.Tensor) -> dict[str, float]:
    """Agreement of two gradient batches (N, A): cosine, relative error and sign agreement (module docstring)."""
    cos = torch.nn.functional.cosine_similarity(g_exact, g_pinn, dim=1)
    rel = (g_pinn - g_exact).norm(dim=1) / g_exact.norm(dim=1).clamp_min(1e-12)
    big = g_exact.abs() > SIGN_FLOOR * g_exact.abs().amax(1, keepdim=True)
    signs = (torch.sign(g_exact) == torch.sign(g_pinn))[big]
    return {"rows": int(g_exact.shape[0]), "cosine_median": float(cos.median()),
            "cosine_q10": float(cos.quantile(0.1)), "rel_error_median": float(rel.median()),
            "rel_error_q90": float(rel.quantile(0.9)),
            "sign_agreement": float(signs.double().mean()) if signs.numel() else float("nan")}


def parting(g_exact: torch.Tensor, g_pinn: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The (row, column) indices of the components where the two gradients (N, A) part (``PART_FLOOR``)."""
    scale = g_exact.abs().amax(1, keepdim=True).clamp_min(1e-12)
    return ((g_pinn - g_exact).abs() > PART_FLOOR * scale).nonzero(as_tuple=True)


def inside_differences(reward_fns: dict, state: torch.Tensor, action: torch.Tensor, rows: torch.Tensor,
                       cols: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, h: float = PART_STEP
                       ) -> dict[str, torch.Tensor]:
    """Per model of ``reward_fns`` (name -> (state, action) -> reward (N,)), the one-sided difference quotient
    (r(a) - r(a - s h e_c)) / (s h) of each component (rows[k], cols[k]), stepping down (s = 1) unless the action
    sits within ``h`` of its lower bound (then up, s = -1): a derivative taken from inside the box."""
    a0, k = action[rows], torch.arange(len(cols))
    s = torch.where(a0[k, cols] - h >= lo[cols] - 1e-12, 1.0, -1.0).to(action.dtype)
    a1 = a0.clone()
    a1[k, cols] = torch.minimum(torch.maximum(a0[k, cols] - s * h, lo[cols]), hi[cols])
    out = {}
    with torch.no_grad():
        for name, fn in reward_fns.items():
            out[name] = (fn(state[rows], a0) - fn(state[rows], a1)) / (s * h)
    return out


def parting_summary(chain, sim, state: torch.Tensor, action: torch.Tensor, g_exact: torch.Tensor,
                    g_pinn: torch.Tensor) -> dict[str, Any]:
    """Where the gradients part, per action index: how many components, the share on the box's bound, and the
    medians of both models' autograd gradients and one-sided differences from inside the box (module docstring)."""
    rows, cols = parting(g_exact, g_pinn)
    out: dict[str, Any] = {"components": int(len(rows)), "of": int(g_exact.numel()), "floor": PART_FLOOR,
                           "step": PART_STEP, "by_action": {}}
    if not len(rows):
        return out
    lo, hi = (b.to(action.dtype) for b in sim.action_bounds())
    a = action[rows, cols]
    on_bound = ((a - lo[cols]).abs() < 1e-9) | ((a - hi[cols]).abs() < 1e-9)
    rewards = {name: (lambda s, x, f=f: f(s, x)[0]) for name, f in models(chain, sim).items()}
    inside = inside_differences(rewards, state, action, rows, cols, lo, hi)
    for c in torch.unique(cols).tolist():
        m = cols == c
        out["by_action"][str(c)] = {
            "components": int(m.sum()), "on_box_bound": float(on_bound[m].double().mean()),
            "autograd_exact_median": float(g_exact[rows[m], c].median()),
            "autograd_pinn_median": float(g_pinn[rows[m], c].median()),
            "inside_exact_median": float(inside["exact"][m].median()),
            "inside_pinn_median": float(inside["pinn"][m].median())}
    return out


def measure(network: str, rows: int, train: bool = False, seed: int = 0) -> tuple[dict[str, Any], dict]:
    """One network's entry and the gradients of its ``near_do_nothing`` set (for the figure)."""
    from anm_torchrl.surrogates.pinn.cache import default_path
    from anm_torchrl.surrogates.pinn.load import load_pinn
    from anm_torchrl.training.factory import make_true_env

    env = make_true_env(rows, seed=seed, network=network)
    sim = env.sim
    t0 = time.perf_counter()
    chain = load_pinn(sim, train_if_missing=train, progress=False)
    load_s = time.perf_counter() - t0
    state = env.reset()["state"].to(torch.float64)
    entry: dict[str, Any] = {"network": network, "pinn_file": str(default_path(sim)), "pinn_load_s": load_s,
                             "sets": {}}
    kept = {}
    for name, action in action_sets(sim, rows, seed).items():
        g_exact, g_pinn, ok = reward_gradients(chain, sim, state, action)
        entry["sets"][name] = {**compare(g_exact[ok], g_pinn[ok]), "terminal_rows": int((~ok).sum()),
                               "parting": parting_summary(chain, sim, state[ok], action[ok], g_exact[ok], g_pinn[ok])}
        if name == "near_do_nothing":
            kept = {"exact": g_exact[ok], "pinn": g_pinn[ok]}
    return entry, kept


def draw(grads: dict[str, dict], path: Path) -> None:
    """Scatter of PINN against exact gradient components, one panel per network (near-do-nothing set)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.5 * len(grads), 5), layout="constrained")
    FigureCanvasAgg(fig)
    for ax, (network, g) in zip(fig.subplots(1, len(grads), squeeze=False)[0], grads.items()):
        x, y = g["exact"].flatten().numpy(), g["pinn"].flatten().numpy()
        ax.scatter(x, y, s=3, alpha=0.4)
        lim = max(abs(x).max(), abs(y).max()) * 1.05
        ax.plot([-lim, lim], [-lim, lim], "k--", lw=0.8)
        ax.set(xlim=(-lim, lim), ylim=(-lim, lim), title=f"{network}: d(reward)/d(action), near do-nothing",
               xlabel="exact (implicit-function power flow), per MW/MVAr", ylabel="PINN chain (autograd)")
    fig.savefig(path, dpi=90)


def run(networks: list[str], rows: int, out: str | Path, train: bool = False) -> dict[str, Any]:
    """Measure every network; write ``<out>.json`` and ``<out>.png``; return the record."""
    t0 = time.perf_counter()
    entries, grads = [], {}
    for network in networks:
        e, g = measure(network, rows, train)
        entries.append(e)
        grads[network] = g
    rec = {"what": "PINN chain vs exact d(reward)/d(action) on reset states", "rows": rows,
           "sign_floor": SIGN_FLOOR, "networks": entries, "wall_s": time.perf_counter() - t0,
           "machine": machine_info(), "versions": versions(),
           "command": f"python -m anm_torchrl.cli.pinn_gradients --networks {' '.join(networks)} --rows {rows} "
                      f"--out {out}"}
    stem = Path(out)
    stem.parent.mkdir(parents=True, exist_ok=True)
    stem.with_suffix(".json").write_text(json_text(rec, indent=1) + "\n")
    draw(grads, stem.with_suffix(".png"))
    return rec
