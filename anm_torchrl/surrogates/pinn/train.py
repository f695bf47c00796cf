"""Training of the PINN modules from physics alone, presets, and the saved-file format.

Every module is trained on its own, on Sobol batches (``torch.quasirandom.SobolEngine(scramble=True)``)
drawn over its input box (paper Appendix A), with losses built only from the shared residual functions
(:mod:`.losses`): no simulator transition, projection or power-flow solution enters training. The exact
solvers (:func:`anm_torchrl.grid.devices.project`, :func:`anm_torchrl.grid.powerflow.newton_raphson`) are used
for *validation errors only* (logged, never used for a training decision): early stopping watches the
physics loss on a fixed held-out Sobol set.

TensorBoard tags (``surrogate/*``, paper Fig. 5): ``surrogate/<module>/<term>`` for every loss term
(``generator``/``storage``: ``stationarity``, ``primal``, ``complementarity``; ``power_balance``:
``residual_p``, ``residual_q``), ``surrogate/<module>/loss`` (weighted sum), ``surrogate/<module>/lr``,
``surrogate/<module>/val_loss`` (same physics loss on the held-out Sobol set) and the validation errors against
the exact solvers: ``surrogate/<module>/val_mae_pu`` (projection MAE, p.u.), ``val_feasible`` (fraction of raw
outputs inside the polygon), ``surrogate/power_balance/val_vmag_mae``, ``val_vang_mae`` (p.u., rad),
``val_residual_mean``/``val_residual_p99`` (per-sample max-abs residual, p.u.).

Presets (:data:`PRESETS`; mirrored by ``recipes/conf/pinn_preset/*.yaml``):

* ``paper``: the paper's §5.1 — one 3×512 residual MLP per module (primal and dual heads), LeakyReLU 0.01, AdamW
  lr 1e-5, batch 64, raw outputs in the losses, early stop after 5,000 steps without progress (capped at
  300,000 steps per module; ≈9 ms per step here, so up to ≈45 min per module);
* ``default``: what measured fastest to the accuracy targets on a 2-core CPU: KKT-NNs 3×128 LeakyReLU with the
  structural options of :mod:`.kkt` (``hard_constraints``, ``gated``, ``separate_dual``, ``dual_gate``) and the
  per-device residual norm; power balance 128×5 SiLU with a pseudo-Huber residual; AdamW lr 3e-3 with cosine
  decay, batch 1024; 3,000 / 2,000 / 10,000 steps. About 2 min of training (110 s measured: 39 + 16 + 56 s);
* ``smoke``: tiny networks and a few steps, for tests.

Measurements behind ``default`` (2-core shared CPU, torch 1 thread; times are wall-clock and noisy, ±30 %).
Held-out validation set: 4,096 scrambled-Sobol points of the module's input box, errors against the exact
projection / a 1e-10 Newton–Raphson (converged points). Batch 1024, lr 3e-3 cosine unless noted.

======================================================  =====  ============  ====
generator KKT-NN (3×128)                                steps  val MAE p.u.  time
======================================================  =====  ============  ====
SiLU, squared residuals, raw output (the paper's loss)  3000   2.3e-3        36 s
LeakyReLU, squared                                      3000   1.3e-3        49 s
SiLU, squared, primal and complementarity weighted ×10  3000   1.4e-3        50 s
LeakyReLU, per-device residual norm (``norm=l2``)       3000   6.3e-4        62 s
+ ``hard_constraints``                                  3000   4.9e-4        56 s
+ ``gated``                                             4000   2.6e-4        33 s
+ ``separate_dual`` + ``dual_gate=0.01`` (**default**)  3000   3.3e-6        39 s
======================================================  =====  ============  ====

Storage KKT-NN (3×128, LeakyReLU, ``norm=l2``): 1.5e-3 (3000 steps) → ``hard_constraints`` 4.7e-4 → ``gated``
1.6e-5 → + ``separate_dual``/``dual_gate`` 2.3e-6 (**default**, 2000 steps, 16 s). With the dual gate the duals are
learned too: mean |λ − λ*| 9e-5 (generator) and 8e-5 (storage), λ* the exact multipliers.

===============================================  =====  =======  ========  =======
power-balance PINN                               steps  |V| MAE  residual  time
===============================================  =====  =======  ========  =======
128×3 SiLU, squared residual (paper loss)        2000   3.0e-3   4.7e-3    16 s
128×3, squared                                   4000   2.1e-3   2.8e-3    34 s
same + L-BFGS finish, 300 iterations in float64  4000   2.1e-3   2.8e-3    +21 s
128×3, pseudo-Huber (c = 0.01)                   4000   1.3e-3   2.0e-3    31 s
128×3, Cauchy (redescending) loss                4000   5.5e-2   2.9e-1    28 s
256×3, pseudo-Huber                              6000   7.2e-4   1.1e-3    123 s
256×3, pseudo-Huber, batch 2048                  4000   9.7e-4   1.6e-3    126 s
128×4, pseudo-Huber, lr 2e-3                     12000  3.6e-4   5.5e-4    58 s
128×4, pseudo-Huber                              12000  2.7e-4   4.4e-4    76 s
128×5, pseudo-Huber (**default**)                10000  2.6e-4   4.5e-4    56–67 s
===============================================  =====  =======  ========  =======

(residual: mean per-sample max |ΔP|, |ΔQ|, p.u.) The squared residual is dominated by the ≈2 % of the box with no
power-flow solution; the pseudo-Huber penalty fixes that, while a redescending (Cauchy) one never starts
fitting. L-BFGS made little progress for the same reason. Narrow-and-deep beat wide at equal time.

The ``paper`` preset given more wall-clock than ``default`` (142 s vs 110 s: 43 / 20 / 79 s, i.e. 4,800 / 3,000 /
12,900 steps, via ``+pinn_preset.<module>.max_time_s``): validation MAE 5.3e-3 (generator), 5.2e-3 (storage), |V|
MAE 3.5e-3 and residual 9.0e-3 — 13× (power balance) to 2,000× (KKT-NNs) worse.
On held-out transitions (``evaluate.py``; random / expert): projection MAE 4.8e-3 / 9.9e-3 and 5.2e-3 / 1.8e-3,
|V| MAE 3.4e-3 / 1.4e-3, residual 8.2e-3 / 6.6e-3, next-state P/Q MAE 0.47 / 0.86 MW; its residual is too large for
the 0.005 p.u. terminal threshold (89 % flagged). The default preset on the same sets: projection MAE 7.5e-6 /
1e-14 and 2.2e-6 / 2e-16 p.u., |V| MAE 2.0e-4 / 1.1e-4, residual 3.7e-4 / 2.9e-4, next-state P/Q MAE 0.011 /
0.007 MW, feasible 100 %, terminal precision 0.97 / recall 0.99 (``python recipes/train_pinn.py``).
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import time
from pathlib import Path
from typing import Any

import torch
from torch import nn

from anm_torchrl.grid.powerflow import newton_raphson
from anm_torchrl.grid.simulator import GridSimulator, anm6_easy_simulator
from anm_torchrl.paths import atomic_torch_save
from anm_torchrl.surrogates.pinn.kkt import GeneratorKKT, StorageKKT, clamp_to_polygon
from anm_torchrl.surrogates.pinn.losses import KKT_TERMS, PB_TERMS, kkt_losses, power_balance_losses
from anm_torchrl.surrogates.pinn.power_balance import PowerBalanceNet

log = logging.getLogger(__name__)

KIND = "anm_torchrl.pinn"
FORMAT_VERSION = 1
FILE_NAME = "pinn.pt"
MODULES = ("generator", "storage", "power_balance")


@dataclasses.dataclass
class ModuleTrainConfig:
    """How one PINN module is built and trained.

    Attributes:
        hidden, depth, activation: the residual MLP (paper: 512, 3, ``leaky_relu``).
        dual_activation: KKT-NN dual head, ``softplus`` or ``relu`` (ignored by the power balance).
        hard_constraints: KKT-NNs only: train through the clamp into the polygon (feasibility by construction,
            see :class:`.kkt.GeneratorKKT`); ``False`` trains the raw output (the paper's formulation).
        gated: KKT-NNs only: the primal correction is scaled by the target's largest constraint violation, so a
            feasible set-point maps to itself exactly (:class:`.kkt.GeneratorKKT`).
        separate_dual: KKT-NNs only: separate primal and dual networks (else one network with two heads).
        dual_gate: KKT-NNs only: δ of the multipliers' activity gate (0: none), see :class:`.kkt.GeneratorKKT`.
        lr: AdamW learning rate (paper: 1e-5); weight_decay: AdamW decoupled weight decay.
        batch_size: Sobol points per step (paper: 64).
        max_steps: Adam steps at most; patience: stop after this many steps without a new best held-out
            physics loss (paper: 5,000); eval_every: steps between held-out evaluations (and TensorBoard points).
        schedule: ``constant`` or ``cosine`` (decay to ``lr·min_lr_ratio`` over ``max_steps``).
        warmup_steps: linear learning-rate warm-up.
        lbfgs_iters: L-BFGS iterations after Adam (0: none), on ``lbfgs_batch`` fixed Sobol points, in float64.
        weights: loss-term weights (missing terms weigh 1).
        norm: KKT-NNs only: ``squared`` (mean squared residual) or ``l2`` (mean residual norm per device).
        robust, robust_scale: power balance only: residual penalty (``squared``, ``pseudo_huber``, ``cauchy``) and
            its scale (p.u.), see :func:`.losses.power_balance_losses`.
        v_scale, ang_scale: power balance only: output scaling (p.u., rad per unit output).
        val_size: held-out Sobol points.
        max_time_s: wall-clock cap of the Adam phase (None: none).
    """

    hidden: int = 128
    depth: int = 3
    activation: str = "silu"
    dual_activation: str = "softplus"
    hard_constraints: bool = False
    gated: bool = False
    separate_dual: bool = False
    dual_gate: float = 0.0
    lr: float = 3e-3
    weight_decay: float = 0.0
    batch_size: int = 1024
    max_steps: int = 3000
    patience: int = 5000
    eval_every: int = 250
    schedule: str = "cosine"
    min_lr_ratio: float = 0.01
    warmup_steps: int = 0
    lbfgs_iters: int = 0
    lbfgs_batch: int = 4096
    weights: dict[str, float] = dataclasses.field(default_factory=dict)
    norm: str = "squared"
    robust: str = "squared"
    robust_scale: float = 0.01
    v_scale: float = 0.1
    ang_scale: float = 0.1
    val_size: int = 4096
    max_time_s: float | None = None


@dataclasses.dataclass
class PINNTrainConfig:
    """Training of the whole chain: one :class:`ModuleTrainConfig` per module, a seed and a thread count."""

    generator: ModuleTrainConfig = dataclasses.field(default_factory=ModuleTrainConfig)
    storage: ModuleTrainConfig = dataclasses.field(default_factory=ModuleTrainConfig)
    power_balance: ModuleTrainConfig = dataclasses.field(default_factory=ModuleTrainConfig)
    seed: int = 0
    preset: str = "custom"

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any], strict: bool = True) -> "PINNTrainConfig":
        """Build from a (possibly partial) nested dict.

        Unknown keys raise ``ValueError`` naming them, or with ``strict=False`` (reading saved files written by
        another version) are dropped with a warning.
        """
        d = dict(d)
        kw: dict[str, Any] = {}

        def check(bad: list[str], where: str, known: set[str]) -> None:
            if bad and strict:
                raise ValueError(f"unknown {where} options {bad}; known: {sorted(known)}")
            if bad:
                log.warning("ignoring unknown %s options %s", where, bad)

        known_mod = {f.name for f in dataclasses.fields(ModuleTrainConfig)}
        for name in MODULES:
            if name in d:
                sub = dict(d.pop(name) or {})
                check(sorted(set(sub) - known_mod), f"{name} training", known_mod)
                kw[name] = ModuleTrainConfig(**{k: v for k, v in sub.items() if k in known_mod})
        known_top = {f.name for f in dataclasses.fields(cls)} - set(MODULES)
        check(sorted(set(d) - known_top), "PINN training", known_top | set(MODULES))
        return cls(**kw, **{k: v for k, v in d.items() if k in known_top})


def _preset_paper() -> PINNTrainConfig:
    m = dict(hidden=512, depth=3, activation="leaky_relu", lr=1e-5, weight_decay=0.01, batch_size=64,
             max_steps=300_000, patience=5000, eval_every=500, schedule="constant", lbfgs_iters=0)
    return PINNTrainConfig(generator=ModuleTrainConfig(**m), storage=ModuleTrainConfig(**m),
                           power_balance=ModuleTrainConfig(**m), preset="paper")


def _preset_default() -> PINNTrainConfig:
    kkt = dict(hidden=128, depth=3, activation="leaky_relu", hard_constraints=True, gated=True, separate_dual=True,
               dual_gate=0.01, norm="l2", lr=3e-3, batch_size=1024, schedule="cosine", eval_every=250)
    pb = dict(hidden=128, depth=5, activation="silu", lr=3e-3, batch_size=1024, max_steps=10_000, schedule="cosine",
              eval_every=500, robust="pseudo_huber", robust_scale=0.01)
    return PINNTrainConfig(generator=ModuleTrainConfig(**kkt, max_steps=3000),
                           storage=ModuleTrainConfig(**kkt, max_steps=2000),
                           power_balance=ModuleTrainConfig(**pb), preset="default")


def _preset_smoke() -> PINNTrainConfig:
    m = dict(hidden=16, depth=2, activation="silu", lr=1e-2, batch_size=128, max_steps=40, eval_every=20,
             val_size=256, lbfgs_iters=0)
    return PINNTrainConfig(generator=ModuleTrainConfig(**m), storage=ModuleTrainConfig(**m),
                           power_balance=ModuleTrainConfig(**m), preset="smoke")


PRESETS = {"default": _preset_default, "paper": _preset_paper, "smoke": _preset_smoke}


def preset(name: str, **overrides: Any) -> PINNTrainConfig:
    """The named preset (``default``, ``paper``, ``smoke``), with nested ``overrides`` applied, e.g.
    ``preset("default", power_balance={"max_steps": 100}, seed=1)``."""
    if name not in PRESETS:
        raise ValueError(f"unknown PINN preset {name!r}; available: {sorted(PRESETS)}")
    d = PRESETS[name]().to_dict()
    for k, v in overrides.items():
        if k in MODULES and isinstance(v, dict):
            d[k] = {**d[k], **v}
        else:
            d[k] = v
    return PINNTrainConfig.from_dict(d)


# ------------------------------------------------------------------------------------------------- modules
def build_modules(cfg: PINNTrainConfig, sim: GridSimulator) -> dict[str, nn.Module]:
    """Untrained ``generator`` (:class:`GeneratorKKT`), ``storage`` (:class:`StorageKKT`) and
    ``power_balance`` (:class:`PowerBalanceNet`) networks for ``cfg``, float32, on the simulator's device."""
    g, s, p = cfg.generator, cfg.storage, cfg.power_balance
    mods = {
        "generator": GeneratorKKT(sim, g.hidden, g.depth, g.activation, g.dual_activation,
                                  hard_constraints=g.hard_constraints, gated=g.gated, separate_dual=g.separate_dual,
                                  dual_gate=g.dual_gate),
        "storage": StorageKKT(sim, s.hidden, s.depth, s.activation, s.dual_activation,
                              hard_constraints=s.hard_constraints, gated=s.gated, separate_dual=s.separate_dual,
                              dual_gate=s.dual_gate),
        "power_balance": PowerBalanceNet(sim, p.hidden, p.depth, p.activation, p.v_scale, p.ang_scale),
    }
    return {k: m.to(sim.net.dev.device) for k, m in mods.items()}


# ---------------------------------------------------------------------------------------------------- tasks
class _Task:
    """What a module is trained on: its Sobol dimension, how a unit-cube point maps into its input box, its
    physics losses, and its validation errors against the exact solver."""

    name: str
    terms: tuple[str, ...]
    dim: int

    def __init__(self, module: nn.Module, sim: GridSimulator):
        self.module, self.sim = module, sim

    def sample(self, u: torch.Tensor) -> tuple[torch.Tensor, ...]:
        raise NotImplementedError

    def losses(self, inputs: tuple[torch.Tensor, ...], cfg: ModuleTrainConfig) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    def reference(self, inputs: tuple[torch.Tensor, ...]) -> Any:
        raise NotImplementedError

    def errors(self, inputs: tuple[torch.Tensor, ...], ref: Any) -> dict[str, float]:
        raise NotImplementedError


class _KKTTask(_Task):
    terms = KKT_TERMS

    def __init__(self, module, sim):
        super().__init__(module, sim)
        self.n = module.g.shape[0]
        self.dim = 3 * self.n

    def sample(self, u):
        lo, hi = self.module.in_low, self.module.in_high  # (n, 3) p.u.
        x = lo + u.view(-1, self.n, 3).to(lo) * (hi - lo)
        return x[..., :2].contiguous(), x[..., 2].contiguous()

    def losses(self, inputs, cfg):
        pred = self.module.predict_scaled(*inputs)
        return kkt_losses(pred["x"], pred["target"], pred["lam"], pred["g"], pred["h"], cfg.norm)

    def errors(self, inputs, ref):
        with torch.no_grad():
            pred = self.module.predict_scaled(*inputs)
            s = self.module.scale.unsqueeze(-1)
            raw = pred["x"]
            safe = clamp_to_polygon(raw, pred["g"], pred["h"])
            viol = (torch.einsum("nmk,bnk->bnm", pred["g"], raw) - pred["h"]).amax(-1)
            return {"val_mae_pu": float((safe * s - ref).abs().mean()),
                    "val_mae_raw_pu": float((raw * s - ref).abs().mean()),
                    "val_max_err_pu": float((safe * s - ref).abs().max()),
                    "val_feasible": float((viol <= 1e-6).double().mean())}


class _GeneratorTask(_KKTTask):
    name = "generator"

    def reference(self, inputs):
        return self.sim.project_generators(*inputs)


class _StorageTask(_KKTTask):
    name = "storage"

    def reference(self, inputs):
        return self.sim.project_storage(*inputs)


class _PowerBalanceTask(_Task):
    name = "power_balance"
    terms = PB_TERMS

    def __init__(self, module, sim):
        super().__init__(module, sim)
        self.n_bus = sim.net.n_bus
        self.dim = 2 * (self.n_bus - 1)

    def sample(self, u):
        lo, hi = self.module.input_box()
        x = lo + u.to(lo) * (hi - lo)
        zero = x.new_zeros(x.shape[0], 1)
        n = self.n_bus - 1
        return torch.cat([zero, x[:, :n]], 1), torch.cat([zero, x[:, n:]], 1)

    def losses(self, inputs, cfg):
        v_magn, v_ang = self.module(*inputs)
        return power_balance_losses(v_magn, v_ang, *inputs, self.module.y_bus, cfg.robust, cfg.robust_scale)

    def reference(self, inputs):
        pf = newton_raphson(self.sim.net.y_bus, torch.complex(*inputs), tol=1e-10)
        return pf

    def errors(self, inputs, ref):
        from anm_torchrl.surrogates.pinn.losses import power_balance_residuals

        with torch.no_grad():
            v_magn, v_ang = self.module(*inputs)
            ok = ref.converged
            dp, dq = power_balance_residuals(v_magn, v_ang, *inputs, self.module.y_bus)
            res = torch.cat([dp, dq], 1).abs().amax(1)[ok]
            return {"val_vmag_mae": float((v_magn - ref.v.abs())[ok].abs().mean()),
                    "val_vang_mae": float((v_ang - ref.v.angle())[ok].abs().mean()),
                    "val_residual_mean": float(res.mean()),
                    "val_residual_p99": float(res.quantile(0.99))}


TASKS = {"generator": _GeneratorTask, "storage": _StorageTask, "power_balance": _PowerBalanceTask}


# ---------------------------------------------------------------------------------------------- training
def _lr_factor(cfg: ModuleTrainConfig, step: int) -> float:
    f = 1.0
    if cfg.warmup_steps > 0 and step < cfg.warmup_steps:
        f = (step + 1) / cfg.warmup_steps
    if cfg.schedule == "cosine":
        t = min(step / max(cfg.max_steps, 1), 1.0)
        f *= cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * t))
    elif cfg.schedule != "constant":
        raise ValueError(f"schedule must be 'constant' or 'cosine', got {cfg.schedule!r}")
    return f


def _total(losses: dict[str, torch.Tensor], weights: dict[str, float]) -> torch.Tensor:
    return sum(weights.get(k, 1.0) * v for k, v in losses.items())


def train_module(name: str, module: nn.Module, sim: GridSimulator, cfg: ModuleTrainConfig, seed: int = 0,
                 writer=None, progress=None) -> dict[str, Any]:
    """Train one module in place from its physics losses; returns a report (steps, time, final metrics).

    Args:
        name: ``generator``, ``storage`` or ``power_balance``.
        module: the network (its best held-out state is restored at the end).
        sim: the simulator (physics constants; the exact solvers are used only for validation errors).
        cfg: the module's training configuration.
        seed: Sobol scrambling seed (training uses ``seed``, the held-out set ``seed + 10_000``).
        writer: a TensorBoard ``SummaryWriter`` (or None).
        progress: a tqdm bar to advance by one per step (or None).
    """
    task = TASKS[name](module, sim)
    engine = torch.quasirandom.SobolEngine(task.dim, scramble=True, seed=seed)
    val_in = task.sample(torch.quasirandom.SobolEngine(task.dim, scramble=True, seed=seed + 10_000)
                         .draw(cfg.val_size).double())
    val_ref = task.reference(val_in)
    opt = torch.optim.AdamW(module.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: _lr_factor(cfg, s))
    tag = f"surrogate/{name}"

    def val_loss() -> float:
        with torch.no_grad():
            return float(_total(task.losses(val_in, cfg), cfg.weights))

    def log_eval(step: int) -> dict[str, float]:
        out = {"val_loss": val_loss(), **task.errors(val_in, val_ref)}
        if writer is not None:
            for k, v in out.items():
                writer.add_scalar(f"{tag}/{k}", v, step)
        return out

    best, best_step, best_state = float("inf"), 0, copy.deepcopy(module.state_dict())
    t0 = time.perf_counter()
    step = 0
    module.train()
    while step < cfg.max_steps:
        inputs = task.sample(engine.draw(cfg.batch_size).double())
        losses = task.losses(inputs, cfg)
        loss = _total(losses, cfg.weights)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        step += 1
        if progress is not None:
            progress.update(1)
        if writer is not None and (step % max(cfg.eval_every // 5, 1) == 0 or step == 1):
            for k, v in losses.items():
                writer.add_scalar(f"{tag}/{k}", v.item(), step)
            writer.add_scalar(f"{tag}/loss", loss.item(), step)
            writer.add_scalar(f"{tag}/lr", opt.param_groups[0]["lr"], step)
        if step % cfg.eval_every == 0 or step == cfg.max_steps:
            v = log_eval(step)["val_loss"]
            if v < best:
                best, best_step, best_state = v, step, copy.deepcopy(module.state_dict())
            if step - best_step >= cfg.patience:
                log.info("%s: early stop at step %d (best held-out loss %.3e at step %d)", name, step, best,
                         best_step)
                break
        if cfg.max_time_s is not None and time.perf_counter() - t0 > cfg.max_time_s:
            log.info("%s: time cap %.0f s reached at step %d", name, cfg.max_time_s, step)
            break
    module.load_state_dict(best_state)
    adam_time = time.perf_counter() - t0
    if cfg.lbfgs_iters > 0:
        _lbfgs_finish(task, cfg, seed)
    if writer is not None and cfg.lbfgs_iters > 0:
        log_eval(step + 1)
    module.eval()
    final = {"val_loss": val_loss(), **task.errors(val_in, val_ref)}
    return {"steps": step, "best_step": best_step, "adam_time_s": adam_time,
            "time_s": time.perf_counter() - t0, **final}


def _lbfgs_finish(task: _Task, cfg: ModuleTrainConfig, seed: int) -> None:
    """L-BFGS (strong Wolfe) on a fixed Sobol batch, in float64, then back to float32."""
    module = task.module
    module.net.double()  # only the network: the physics buffers are float64 / complex128 already
    inputs = task.sample(torch.quasirandom.SobolEngine(task.dim, scramble=True, seed=seed + 20_000)
                         .draw(cfg.lbfgs_batch).double())
    opt = torch.optim.LBFGS(module.parameters(), lr=1.0, max_iter=cfg.lbfgs_iters, history_size=50,
                            tolerance_grad=1e-12, tolerance_change=1e-15, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad(set_to_none=True)
        loss = _total(task.losses(inputs, cfg), cfg.weights)
        loss.backward()
        return loss

    opt.step(closure)
    module.net.float()


def train_pinn(cfg: PINNTrainConfig | None = None, sim: GridSimulator | None = None, log_dir: str | Path | None = None,
               progress: bool = False) -> tuple[dict[str, nn.Module], dict[str, Any]]:
    """Train the three PINN modules from physics alone.

    Args:
        cfg: training configuration (default: the ``default`` preset).
        sim: the simulator providing the physics constants (default ANM6-Easy on CPU).
        log_dir: TensorBoard folder (None: no logging).
        progress: show a tqdm progress bar over all Adam steps.

    Returns:
        the trained modules (``generator``, ``storage``, ``power_balance``) and a report (per-module steps,
        times and validation errors against the exact solvers).
    """
    cfg = cfg if cfg is not None else preset("default")
    sim = sim if sim is not None else anm6_easy_simulator()
    torch.manual_seed(cfg.seed)
    modules = build_modules(cfg, sim)
    writer = None
    if log_dir is not None:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(log_dir))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=sum(getattr(cfg, m).max_steps for m in MODULES), desc="training PINN surrogate",
                   mininterval=1.0,
                   unit="step")
    report: dict[str, Any] = {}
    try:
        for k, name in enumerate(MODULES):
            if bar is not None:
                bar.set_postfix_str(name)
            report[name] = train_module(name, modules[name], sim, getattr(cfg, name), seed=cfg.seed + 1000 * k,
                                        writer=writer, progress=bar)
            log.info("%s trained: %s", name, report[name])
    finally:
        if bar is not None:
            bar.close()
        if writer is not None:
            writer.close()
    report["time_s"] = sum(report[m]["time_s"] for m in MODULES)
    return modules, report


# ------------------------------------------------------------------------------------------------ files
def resolve_path(path: str | Path) -> Path:
    """``path`` itself if it names a file (has a suffix), else ``path / "pinn.pt"``."""
    p = Path(path).expanduser()
    return p if p.suffix else p / FILE_NAME


def save_pinn(path: str | Path, modules: dict[str, nn.Module], cfg: PINNTrainConfig,
              report: dict[str, Any] | None = None) -> Path:
    """Write the trained modules with the kind marker ``"anm_torchrl.pinn"``, the config and the report.

    ``path`` is a file or a folder (then ``<folder>/pinn.pt``); written atomically. Returns the file path.
    """
    file = resolve_path(path)
    payload = {
        "kind": KIND,
        "format_version": FORMAT_VERSION,
        "config": cfg.to_dict(),
        "state_dict": {k: {n: t.detach().cpu() for n, t in m.state_dict().items()} for k, m in modules.items()},
        "report": _plain(report or {}),
        "torch_version": str(torch.__version__),
    }
    return atomic_torch_save(payload, file)


def _plain(x: Any) -> Any:
    """Only dicts/lists/str/int/float/bool/None (for ``torch.load(weights_only=True)``)."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (str, int, float, bool)) or x is None:
        return x
    return float(x)


def read_pinn_file(path: str | Path) -> dict[str, Any]:
    """Read and check a saved PINN file.

    Raises:
        FileNotFoundError: no file at ``path`` (or ``path/pinn.pt``).
        ValueError: the file is not a PINN file (wrong or missing ``kind`` marker, unknown format version).
    """
    file = resolve_path(path)
    if not file.is_file():
        raise FileNotFoundError(f"no trained PINN at {file}")
    try:
        payload = torch.load(file, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any unreadable file is "not a PINN file"
        raise ValueError(f"{file} is not a readable anm_torchrl PINN file ({err.__class__.__name__}: {err})") from err
    kind = payload.get("kind") if isinstance(payload, dict) else None
    if kind != KIND:
        raise ValueError(f"{file} holds kind {kind!r}, expected {KIND!r} (a file written by "
                         "anm_torchrl.surrogates.pinn.train.save_pinn)")
    if payload.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{file} has PINN format version {payload.get('format_version')!r}, this code reads "
                         f"{FORMAT_VERSION}")
    return payload


def load_modules(path: str | Path, sim: GridSimulator) -> tuple[dict[str, nn.Module], PINNTrainConfig, dict]:
    """Rebuild the trained modules saved at ``path`` on the simulator's device; returns (modules, config, report)."""
    payload = read_pinn_file(path)
    cfg = PINNTrainConfig.from_dict(payload["config"], strict=False)
    modules = build_modules(cfg, sim)
    for k, m in modules.items():
        m.load_state_dict(payload["state_dict"][k])
        m.eval()
    return modules, cfg, payload.get("report", {})


__all__ = ["KIND", "MODULES", "ModuleTrainConfig", "PINNTrainConfig", "PRESETS", "build_modules", "load_modules",
           "preset", "read_pinn_file", "resolve_path", "save_pinn", "train_module", "train_pinn"]
