"""PINN training configuration: :class:`ModuleTrainConfig`, :class:`PINNTrainConfig` and the named presets.

What simulator data touched the PINN's design (its weights never see any: ``tests/test_pinn.py::
test_physics_alone`` trains with every exact reference replaced by garbage and gets bit-identical weights):

* the ``default`` preset was chosen by comparing candidate settings' validation errors against the *exact*
  projection and Newton–Raphson solutions on held-out Sobol points (tables below) — exact solvers, not
  simulator transitions, but simulator code;
* the acceptance bar of a preset (``acceptance``) is checked on the same errors; it decides only whether a
  trained model may replace the default cache, never a weight;
* the terminal check's residual threshold (0.005 p.u., :mod:`.chain`) was swept against the simulator's
  non-convergence labels on random transitions.

Presets (:data:`PRESETS`; their one home is ``anm_torchrl/surrogates/conf/pinn_preset/*.yaml``, which the
recipe ``train_pinn.py`` reads too):

* ``paper``: the paper's §5.1 — one 3×512 residual MLP per module (primal and dual heads), LeakyReLU 0.01, AdamW
  lr 1e-5, batch 64, raw outputs in the losses, early stop after 5,000 steps without progress (capped at
  300,000 steps per module; ≈9 ms per step here, so up to ≈45 min per module);
* ``default``: what measured fastest to the accuracy targets on a 2-core CPU: KKT-NNs 3×128 LeakyReLU with the
  structural options of :mod:`.kkt` (``hard_constraints``, ``gated``, ``separate_dual``, ``dual_gate``) and the
  per-device residual norm; power balance 128×5 SiLU with a pseudo-Huber residual; AdamW lr 3e-3 with cosine
  decay, batch 1024; 3,000 / 2,000 / 10,000 steps. About 2 min of training (110 s measured: 39 + 16 + 56 s);
* ``feeder``: what ``default`` stands for on every network other than ANM6-Easy (:func:`network_preset_name`;
  ANM6-Easy keeps ``default`` unchanged): ``default`` with the power-balance residual in units of the feeder's
  largest bus injection (``residual_unit: box``) and chord-Newton steps after the power-balance network
  (:class:`.power_balance.PowerBalanceNet`), as many as the physics rule of :mod:`.refine` picks for the network
  after training (``refine_steps: auto``: case33bw 1, CIGRE MV 2, the 115-bus SimBench feeder 3); tables below;
* ``quick``: ``default`` with a third of the steps and the box unit (the first feeder measurements);
* ``smoke``: tiny networks and a few steps, for tests.

Measurements behind ``feeder`` (validation only: 4,000 random transitions, ``evaluate.random_transitions`` seed
777 — the reported figures use seed 12345 —, the power-balance network fed the simulator's bus injections, |V| MAE
p.u. against its Newton–Raphson; power-balance training alone, 10,000 steps, one torch thread, CPU seconds, 2-core
machine shared at load 3–7; ``flat start``: no network, the chord steps from |V| = 1, θ = 0):

=========================================  =======  ===========  ===========  =====
case33bw (33 buses, 10 MVA base)           raw      + 1 chord    + 2 chords   CPU s
=========================================  =======  ===========  ===========  =====
``default`` (residual in p.u.)             2.3e-4   —            —            163
residual in box units (**feeder**)         2.1e-4   **1.4e-5**   1.4e-6       155
flat start, no network                     1.2e-2   6.2e-4       4.9e-5       0
cigre_mv (15 buses, 1 MVA base): box       2.0e-4   **6.2e-6**   3.6e-7       132
cigre_mv: flat start, no network           1.6e-2   1.1e-3       6.2e-5       0
=========================================  =======  ===========  ===========  =====

One chord step from the trained network is 40–180× closer to the exact power flow than one from the flat start.
Until 2026-12-01 ``feeder`` fixed one step (the second was not worth its cost with the first already ≥ 70× under
the 1e-3 p.u. |V| target); that left the 115-bus SimBench feeder (1 MVA base, stiff lines; its power-balance
network, 10,000 steps, 462 CPU s with the KKT-NNs, is worse than the flat start: validation |V| MAE 3.8e-2 vs
2.3e-2) with a power-flow residual of ~0.6 p.u., above the terminal check's 0.005 p.u.: every transition flagged
terminal although |V| was within 3.1e-4 p.u. (test). Since then the count is chosen per network from physics alone
(:mod:`.refine`: the smallest k whose 0.99 quantile of the residual on 4,096 Sobol points of the injection box is
≤ 0.0025 p.u.). The figures below were measured with rule v1's flat-start chord steps; since rule v2 (2026-12-03) the
steps are damped Newton steps at the estimate, which converge where the chord diverged (issue 23's 132/33 kV
network, X = 0.55 p.u.) and typically need fewer steps; the battery on random networks is in docs/PINN.md. Box quantiles after k = 1, 2, 3 steps (p.u., the trained models) and, on the validation transitions
above, the chain's residual p99 and the share flagged terminal at k − 1, k and k + 1:

=====================  ===========================  ====  ==============================================
network                box q0.99, k = 1 / 2 / 3      k     validation p99 (flagged) at k−1 / k / k+1
=====================  ===========================  ====  ==============================================
case33bw               3.3e-4 / — / —               1     — / 1.7e-4 (0 %) / 3.0e-5 (0 %)
cigre_mv               5.5e-3 / 7.5e-4 / —          2     2.1e-3 (0 %) / 1.9e-4 (0 %) / 1.7e-5 (0 %)
simbench_mv_semiurb    0.68 / 3.0e-2 / 1.4e-3       3     4.0e-2 (100 %) / 2.3e-3 (0 %) / 1.3e-4 (0 %)
=====================  ===========================  ====  ==============================================

On every network the validation residual at the chosen k stays below the rule's bar (largest: SimBench, p99
2.3e-3, max 2.8e-3 p.u.), so no healthy transition is flagged; CIGRE MV's box holds injections harder than its
transitions (its k = 1 flagged none of them), and the rule spends one more step there.

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

import dataclasses
import functools
import logging
import math
from importlib import resources
from typing import Any

import yaml

log = logging.getLogger(__name__)

MODULES = ("generator", "storage", "power_balance")
PRESET_PACKAGE = "anm_torchrl.surrogates.conf"
#: the preset that ``default`` stands for on every network other than ANM6-Easy (:func:`network_preset_name`)
FEEDER_DEFAULT = "feeder"
#: ``refine_steps`` value asking for the refinement-step count to be chosen after training (:mod:`.refine`)
REFINE_AUTO = "auto"


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
        refine_steps: power balance only: refinement steps after the network (damped Newton, rule v2), at inference and in the
            validation errors, not in the training loss (:class:`.power_balance.PowerBalanceNet`; 0: none);
            ``auto``: the smallest k meeting the physics rule of :mod:`.refine`, chosen after training and stored
            in the model file.
        val_size: held-out Sobol points.
        max_time_s: wall-clock cap of the Adam phase (None: none).
        residual_unit: power balance only: the unit of the residuals in its loss, ``pu`` (the network's base) or
            ``box`` (its largest bus-injection bound, :meth:`.power_balance.PowerBalanceNet.injection_scale`), so
            that one ``robust_scale`` suits feeders of any base (ANM6-Easy 100 MVA, CIGRE MV 1 MVA).
        per_device: KKT-NNs only: ``batch_size``, ``val_size`` and ``lbfgs_batch`` count device samples, not
            Sobol points: a step draws ``ceil(batch_size / n_devices)`` points of all n devices of the kind, so the
            cost of a step stays the same on a feeder with 2 or 120 generators (the network is shared by them).
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
    refine_steps: int | str = 0
    val_size: int = 4096
    max_time_s: float | None = None
    per_device: bool = False
    residual_unit: str = "pu"

    def __post_init__(self):
        """Reject bad values before any work starts (a ``ValueError`` names the option and what it got)."""
        for k in ("hidden", "depth", "batch_size", "max_steps", "patience", "eval_every", "val_size", "lbfgs_batch"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"PINN training option {k!r} must be an integer >= 1, got {v!r}")
        if not isinstance(self.per_device, bool):
            raise ValueError(f"PINN training option 'per_device' must be true or false, got {self.per_device!r}")
        for k in ("warmup_steps", "lbfgs_iters", "refine_steps"):
            v = getattr(self, k)
            if k == "refine_steps" and v == REFINE_AUTO:
                continue
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                extra = " or 'auto'" if k == "refine_steps" else ""
                raise ValueError(f"PINN training option {k!r} must be an integer >= 0{extra}, got {v!r}")
        for k in ("lr", "robust_scale", "v_scale", "ang_scale"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"PINN training option {k!r} must be a finite number > 0, got {v!r}")
        for k in ("weight_decay", "dual_gate"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"PINN training option {k!r} must be a finite number >= 0, got {v!r}")
        if not 0 <= self.min_lr_ratio <= 1:
            raise ValueError(f"PINN training option 'min_lr_ratio' must lie in [0, 1], got {self.min_lr_ratio!r}")
        if self.max_time_s is not None and not self.max_time_s > 0:
            raise ValueError(f"PINN training option 'max_time_s' must be > 0 or null, got {self.max_time_s!r}")
        for k, allowed in (("schedule", ("constant", "cosine")), ("norm", ("squared", "l2")),
                           ("residual_unit", ("pu", "box")),
                           ("robust", ("squared", "pseudo_huber", "cauchy"))):
            if getattr(self, k) not in allowed:
                raise ValueError(f"PINN training option {k!r} must be one of {allowed}, got {getattr(self, k)!r}")


@dataclasses.dataclass
class PINNTrainConfig:
    """Training of the whole chain: one :class:`ModuleTrainConfig` per module, a seed, the preset's name and
    its acceptance bar (``{module: {validation metric: largest accepted value}}``; None: never accepted into the
    default cache)."""

    generator: ModuleTrainConfig = dataclasses.field(default_factory=ModuleTrainConfig)
    storage: ModuleTrainConfig = dataclasses.field(default_factory=ModuleTrainConfig)
    power_balance: ModuleTrainConfig = dataclasses.field(default_factory=ModuleTrainConfig)
    seed: int = 0
    preset: str = "custom"
    acceptance: dict[str, dict[str, float]] | None = None

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


def preset_names() -> list[str]:
    """Names of the presets (the YAML files of ``anm_torchrl/surrogates/conf/pinn_preset``)."""
    folder = resources.files(PRESET_PACKAGE) / "pinn_preset"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))


def _load_preset(name: str) -> PINNTrainConfig:
    """Preset ``name`` from its YAML file; a ``base: <preset>`` entry makes the file a set of changes to that
    preset (module entries merged key by key)."""
    data = yaml.safe_load((resources.files(PRESET_PACKAGE) / "pinn_preset" / f"{name}.yaml").read_text())
    if data.pop("name", name) != name:
        raise ValueError(f"pinn_preset/{name}.yaml names another preset")
    base = data.pop("base", None)
    if base is not None:
        if base == name or base not in preset_names():
            raise ValueError(f"pinn_preset/{name}.yaml: base must name another preset, got {base!r}")
        d = _load_preset(base).to_dict()
        for k, v in data.items():
            d[k] = {**d[k], **v} if k in MODULES and isinstance(v, dict) else v
        data = d
    return PINNTrainConfig.from_dict({**data, "preset": name})


#: ``PRESETS[name]()`` builds the preset, read from its YAML file on each call.
PRESETS = {n: functools.partial(_load_preset, n) for n in preset_names()}


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


def network_preset_name(name: str, sim) -> str:
    """The preset ``name`` stands for on ``sim``'s network (a :class:`GridSimulator`):
    ``default`` is the ANM6-Easy design on ANM6-Easy (unchanged) and :data:`FEEDER_DEFAULT` on any other
    network; every other name is itself."""
    from anm_torchrl.data.generic import is_anm6

    return FEEDER_DEFAULT if name == "default" and not is_anm6(sim) else name


def preset_for(name: str, sim, **overrides: Any) -> PINNTrainConfig:
    """:func:`preset` of :func:`network_preset_name` ``(name, sim)``: what ``load_pinn``/``make_env`` train."""
    return preset(network_preset_name(name, sim), **overrides)


def overrides_of(d: dict[str, Any], name: str) -> dict[str, Any]:
    """The entries of a (nested) preset dict ``d`` that differ from preset ``name``, as :func:`preset` overrides
    (``preset`` key excluded): what a command line changed in a composed Hydra preset."""
    base = preset(name).to_dict()
    out: dict[str, Any] = {}
    for k, v in d.items():
        if k in ("name", "preset", "base"):  # the name, and a YAML file's base preset, are not options
            continue
        if k in MODULES and isinstance(v, dict):
            sub = {m: x for m, x in v.items() if base.get(k, {}).get(m) != x}
            if sub:
                out[k] = sub
        elif base.get(k) != v:
            out[k] = v
    return out


def from_composed(composed: dict[str, Any], sim, **overrides: Any) -> PINNTrainConfig:
    """The training configuration a recipe's composed ``pinn_preset`` group (a dict with its ``name``) stands for
    on ``sim``'s network: the preset it names (``default`` resolved by :func:`network_preset_name`) with the
    entries the command line changed (:func:`overrides_of`) and ``overrides`` (e.g. ``seed``)."""
    d = dict(composed)
    given = d.pop("name")
    return preset(network_preset_name(given, sim), **{**overrides_of(d, given), **overrides})


def module_seed(cfg: PINNTrainConfig, name: str) -> int:
    """The seed module ``name`` is trained with (its Sobol draws; :func:`.loop.train_module`'s ``seed``)."""
    return cfg.seed + 1000 * MODULES.index(name)


def check_acceptance(cfg: PINNTrainConfig, report: dict[str, Any]) -> list[str]:
    """The failed acceptance criteria of a training ``report`` (empty: accepted). No bar: one failure. A refinement-step
    count chosen by :mod:`.refine` that does not meet its rule is a failure too."""
    if not cfg.acceptance:
        return [f"preset {cfg.preset!r} has no acceptance bar"]
    failed = []
    refine = report.get("power_balance", {}).get("refine")
    if refine is not None and not refine.get("met"):
        kind = "Newton" if refine.get("method") == "newton" else "chord"
        failed.append(f"power_balance.refine: no k <= {refine.get('k_max')} {kind} steps brings the "
                      f"{refine.get('quantile')} quantile of the power-flow residual to {refine.get('margin')} x "
                      f"{refine.get('threshold_pu')} p.u. (after {refine.get('k')}: {refine.get('residual_q_pu')}); "
                      "more than 1 % of the devices' injection box may have no power flow (lower the device "
                      "ratings, or strengthen the lines/transformer), or train the power balance longer "
                      "(power_balance.max_steps)")
    for module, bars in cfg.acceptance.items():
        if report.get(module, {}).get("devices") == 0:  # no device of this kind on the network: nothing to check
            continue
        for metric, bound in bars.items():
            got = report.get(module, {}).get(metric)
            if got is None or not got <= float(bound):
                failed.append(f"{module}.{metric} = {got} > {bound}")
    return failed
