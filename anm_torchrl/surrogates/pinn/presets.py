"""PINN training configuration: :class:`ModuleTrainConfig`, :class:`PINNTrainConfig` and the named presets.

What simulator data touched the PINN's design (its weights never see any: ``tests/test_pinn.py::
test_physics_alone`` trains with every exact reference replaced by garbage and gets bit-identical weights):

* the ``default`` preset was chosen by comparing candidate settings' validation errors against the *exact*
  projection and Newton–Raphson solutions on held-out Sobol points (tables in docs/PINN.md) — exact solvers, not
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
  after training (``refine_steps: auto``: case33bw 1, CIGRE MV 2, the 115-bus SimBench feeder 3); tables in docs/PINN.md;
* ``quick``: ``default`` with a third of the steps and the box unit (the first feeder measurements);
* ``smoke``: tiny networks and a few steps, for tests.

The measurements that chose ``default`` and ``feeder`` (validation errors, times, the rule's box quantiles) are in
``docs/PINN.md``, section "How the presets were chosen".
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from importlib import resources
from collections.abc import Iterable
from typing import Any

import yaml

from anm_torchrl.overrides import parse_override

log = logging.getLogger(__name__)

MODULES = ("generator", "storage", "power_balance")
# the loss terms of each module (losses.py computes them): what a preset's ``weights`` may name
KKT_TERMS = ("stationarity", "primal", "complementarity")
PB_TERMS = ("residual_p", "residual_q")
NOT_OPTIONS = ("name", "preset", "base")  # a composed preset's name, and a YAML file's base preset: not options
PRESET_PACKAGE = "anm_torchrl.surrogates.conf"
#: the preset that ``default`` stands for on every network other than ANM6-Easy (:func:`network_preset_name`)
FEEDER_DEFAULT = "feeder"
#: ``refine_steps`` value asking for the refinement-step count to be chosen after training (:mod:`.refine`)
REFINE_AUTO = "auto"
#: the most refinement steps a power balance may take (``refine_steps``, fixed or chosen by :mod:`.refine`)
REFINE_MAX = 8
#: the hidden activations of the modules' networks (:func:`.nets.make_activation`)
ACTIVATIONS = ("leaky_relu", "silu", "tanh", "gelu", "relu")
#: what keeps a KKT-NN's dual variables >= 0 (:mod:`.kkt`)
DUAL_ACTIVATIONS = ("softplus", "relu")


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
        refine_steps: power balance only: refinement steps after the network (damped Newton, rules v2 and v3), at
            inference and in the validation errors, not in the training loss
            (:class:`.power_balance.PowerBalanceNet`; 0: none);
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
            high = REFINE_MAX if k == "refine_steps" else math.inf
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= high:
                expected = f"in 0..{REFINE_MAX} or 'auto'" if k == "refine_steps" else ">= 0"
                raise ValueError(f"PINN training option {k!r} must be an integer {expected}, got {v!r}")
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
        if self.max_time_s is not None and not (isinstance(self.max_time_s, (int, float))
                                                and not isinstance(self.max_time_s, bool) and self.max_time_s > 0):
            raise ValueError(f"PINN training option 'max_time_s' must be > 0 or null, got {self.max_time_s!r}")
        for k, allowed in (("schedule", ("constant", "cosine")), ("norm", ("squared", "l2")),
                           ("residual_unit", ("pu", "box")),
                           ("robust", ("squared", "pseudo_huber", "cauchy"))):
            if getattr(self, k) not in allowed:
                raise ValueError(f"PINN training option {k!r} must be one of {allowed}, got {getattr(self, k)!r}")
        for k, allowed in (("activation", ACTIVATIONS), ("dual_activation", DUAL_ACTIVATIONS)):
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

    def __post_init__(self):
        """Reject a ``weights`` entry that names no loss term of its module (it was ignored) or is not finite >= 0,
        and an ``acceptance`` bar that names no module or is not a number (it was read only after training)."""
        if self.acceptance is not None:
            if not isinstance(self.acceptance, dict):
                raise ValueError(f"PINN training option 'acceptance' must map modules to {{metric: bound}}, "
                                 f"got {self.acceptance!r}")
            for module, bars in self.acceptance.items():
                if module not in MODULES or not isinstance(bars, dict):
                    raise ValueError(f"PINN training option acceptance.{module}: must be one of {list(MODULES)} "
                                     f"mapping metrics to bounds, got {bars!r}")
                for metric, bound in bars.items():
                    if isinstance(bound, bool) or not isinstance(bound, (int, float)) or math.isnan(bound):
                        raise ValueError(f"PINN training option acceptance.{module}.{metric} must be a number, "
                                         f"got {bound!r}")
        for name in MODULES:
            terms = PB_TERMS if name == "power_balance" else KKT_TERMS
            weights = getattr(self, name).weights if isinstance(getattr(self, name), ModuleTrainConfig) else {}
            for term, w in (weights or {}).items():
                if term not in terms:
                    raise ValueError(f"PINN training option {name}.weights names {term!r}, not a loss term of the "
                                     f"{name} module; its terms: {list(terms)}")
                if isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w) or w < 0:
                    raise ValueError(f"PINN training option {name}.weights.{term} must be a finite number >= 0, "
                                     f"got {w!r}")

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


def network_preset_name(name: str, sim=None, *, anm6: bool | None = None) -> str:
    """The preset ``name`` stands for on ``sim``'s network (a :class:`GridSimulator`; or say ``anm6``, whether
    it is ANM6-Easy's, without building it): ``default`` is the ANM6-Easy design on ANM6-Easy (unchanged) and
    :data:`FEEDER_DEFAULT` on any other network; every other name is itself."""
    if anm6 is None:
        from anm_torchrl.networks.resolve import is_anm6

        anm6 = is_anm6(sim)
    return FEEDER_DEFAULT if name == "default" and not anm6 else name


def preset_for(name: str, sim, **overrides: Any) -> PINNTrainConfig:
    """:func:`preset` of :func:`network_preset_name` ``(name, sim)``: what ``load_pinn``/``make_env`` train."""
    return preset(network_preset_name(name, sim), **overrides)


def overrides_of(d: dict[str, Any], name: str) -> dict[str, Any]:
    """The entries of a (nested) preset dict ``d`` that differ from preset ``name``, as :func:`preset` overrides
    (``preset`` key excluded): what a command line changed in a composed Hydra preset."""
    base = preset(name).to_dict()
    out: dict[str, Any] = {}
    for k, v in d.items():
        if k in NOT_OPTIONS:
            continue
        if k in MODULES and isinstance(v, dict):
            sub = {m: x for m, x in v.items() if base.get(k, {}).get(m) != x}
            if sub:
                out[k] = sub
        elif base.get(k) != v:
            out[k] = v
    return out


def preset_keys(task_overrides: Iterable[str]) -> list[str]:
    """The ``pinn_preset`` keys a Hydra command line sets (``pinn_preset.power_balance.lr=1e-3`` ->
    ``power_balance.lr``; ``+``/``++``/``~`` prefixes dropped): :func:`from_composed`'s ``explicit``."""
    keys = (parse_override(o).key for o in task_overrides)
    return [k.removeprefix("pinn_preset.") for k in keys if k.startswith("pinn_preset.")]


def from_composed(composed: dict[str, Any], sim=None, *, anm6: bool | None = None,
                  explicit: Iterable[str] = (), **overrides: Any) -> PINNTrainConfig:
    """The training configuration a recipe's composed ``pinn_preset`` group (a dict with its ``name``) stands for
    on ``sim``'s network (or on ANM6-Easy's or a feeder's, ``anm6``): the preset it names (``default`` resolved by
    :func:`network_preset_name`) with the entries the command line changed (:func:`overrides_of`), the entries it
    set (``explicit``: dotted keys under ``pinn_preset``, e.g. ``power_balance.refine_steps``; a value equal to the
    named preset's is kept too, as ``default`` stands for another preset off ANM6-Easy) and ``overrides`` (e.g.
    ``seed``).

    Raises:
        ValueError: a value out of range, naming the option."""
    d = dict(composed)
    given = d.pop("name")
    changed = overrides_of(d, given)
    for key in explicit:
        top, _, sub = key.partition(".")
        if top in MODULES and sub and isinstance(d.get(top), dict) and sub in d[top]:
            changed.setdefault(top, {})[sub] = d[top][sub]
        elif not sub and top in d and top not in NOT_OPTIONS:
            changed[top] = d[top]
    return preset(network_preset_name(given, sim, anm6=anm6), **{**changed, **overrides})


def check_default_target(cfg: PINNTrainConfig, target: str, overwrite_cache: bool) -> None:
    """Raise ``ValueError`` if ``cfg`` has no acceptance bar, aims at the default cache (``target`` names it) and
    ``overwrite_cache`` is off: such a model never replaces the default PINN."""
    if not cfg.acceptance and not overwrite_cache:
        raise ValueError(f"preset {cfg.preset!r} has no acceptance bar, so it never replaces the default PINN cache "
                         f"{target}; give another path (path=...) or overwrite_cache=true")


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
        bar = refine.get("bar_pu")  # rules v3, v4; v1/v2 records: margin x threshold
        if bar is None:
            bar = f"{refine.get('margin')} x {refine.get('threshold_pu')} p.u."
        elif bar < refine["margin"] * refine["threshold_pu"]:
            bar = (f"{bar:.3g} p.u. ({refine.get('loss_fraction')} x the network's median losses "
                   f"{refine.get('loss_median_pu'):.3g} p.u.)")
        else:
            bar = f"{bar:.3g} p.u."
        env = ""  # rule v4: the bar is met on the env-like injections too
        if refine.get("env_residual_q_pu") is not None:
            env = (f"; on env-like injections to {refine.get('env_bar_pu'):.3g} p.u. (after {refine.get('k')}: "
                   f"{refine['env_residual_q_pu']})")
        failed.append(f"power_balance.refine: no k <= {refine.get('k_max')} {kind} steps brings the "
                      f"{refine.get('quantile')} quantile of the power-flow residual to {bar} on the injection "
                      f"box (after {refine.get('k')}: {refine.get('residual_q_pu')}){env}; "
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
