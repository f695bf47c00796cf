"""How many Newton steps follow a network's power-balance PINN: chosen per network from physics alone.

Rule v4 (:data:`RULE`, ``box_and_env_quantile_v4``) is rule v3 applied to two point sets, and k must meet the bar on
both: the Sobol points of the injection box (v3's) and :data:`POINTS` env-like injections (:func:`env_injections`:
time index, SoC and set-points drawn as the env's ``random_state`` draws them, projected by the devices' exact
constraints; no power flow). In a box of 2(n−1) independent coordinates the total load concentrates near its middle,
while the env's loads follow one profile and reach their peaks together: on the PINN battery's 46-bus meshed network
(seed 5) the residual quantile after v3's k = 2 was 8e-6 p.u. on the box and 2.4e-3 on the env's transitions (total
load P: median −0.057 p.u. on the box, −0.12 in the env), a reward error of 7.3 %; k = 3 brings the env's to 3e-6.
A v3 file keeps its k, like a v2 file (a warning at load names the command that re-chooses it).

Rule v3 (``sobol_box_quantile_v3``) is rule v2 with a second, unit-free bar (below): v2's bar was
absolute in p.u., so on a low-power grid (SimBench ``1-LV-semiurb4--0-sw``: ~0.3 kW of losses on a 1 MVA base) a
residual that met it (2.2e-3 p.u. = 2.2 kW after one step) was a slack-power error larger than every reward; one
more step brings it to 3e-6 p.u. A v2 file keeps its k (same method; a warning at load names the command that
re-chooses it). Rule v2 (``sobol_box_quantile_v2``): the steps are damped Newton steps with the exact Jacobian at
the current estimate (:class:`.power_balance.PowerBalanceNet`, ``refine_method="newton"``). Rule v1
(``sobol_box_quantile_v1``) used chord steps with the flat-start Jacobian, which diverge on networks whose
operating points are far from the flat start in Jacobian terms (a 132/33 kV transformer with X = 0.55 p.u. on
100 MVA and tap 1.03: the residual grew each step, no k met the bar, the model was refused). A v1 file still
loads and runs its chord steps exactly as it was chosen with (:data:`RULE_METHODS`; its ``refine_method`` field is
absent); ``python -m anm_torchrl.cli.pinn_refine`` moves it to today's rule (same weights).

A preset with ``power_balance.refine_steps: auto`` (``feeder``) gets, at the end of its power-balance training,
the smallest k in 1…:data:`K_MAX` whose power-flow residual meets :func:`rule_met` — no simulator label enters:

* points: :data:`POINTS` scrambled-Sobol points of the network's bus-injection box (the box the network is trained
  on, :func:`.power_balance.bus_injection_box`; Sobol seed = training seed + :data:`SEED_OFFSET`, apart from the
  training, held-out and L-BFGS draws);
* residual: the chain's own terminal statistic (:class:`.chain.SlackAndFlows`), the largest |ΔP|, |ΔQ| (p.u.) at
  the non-slack buses of the network's output followed by k Newton steps;
* bar: its :data:`QUANTILE` quantile ≤ :data:`MARGIN` × the terminal check's threshold
  (:data:`.chain.DEFAULT_RESIDUAL_THRESHOLD`, 0.005 p.u.) and (v3) ≤ :data:`LOSS_FRACTION` × the network's own
  active losses (the median over the same points of Σᵢ Pᵢ(V) at the k-step estimate, p.u.): the residual is, to first
  order, the error of the slack injection and so of the energy loss in the reward, and the losses are that term's
  size. The registered feeders keep v2's k: on CIGRE MV and the 115-bus SimBench feeder (median losses 0.047 and
  0.072 p.u. on 512 of these points, converged) the absolute bar is the lower one; case33bw's (0.1 × 0.0128 p.u.)
  is lower than the absolute one, and its PINN's residual after its one step is 2.6e-6 p.u.
  (``results/pinn/pinn_generic_accuracy.json``). Random networks on 100 MVA have 3e-5 to 4e-2 p.u. of losses:
  there the relative bar binds (``results/pinn_battery/``).

Why these: a transition is flagged terminal when its residual exceeds the threshold, so a k whose residual on
solvable injections reaches the threshold flags healthy transitions (the 115-bus SimBench feeder with k = 1:
residual ~0.6 p.u., 100 % flagged). A 0.99 quantile at half the threshold is the regime in which the threshold
was calibrated against the simulator's non-convergence (ANM6-Easy's default model: residual p99 ≈ 2e-3 p.u. on
reachable injections, precision 0.97–0.98, recall 0.96–1.00; :mod:`.chain`); it bounds the share of box points
above the bar at 1 %, and the factor 2 leaves room for what the box does not show (the env's injections are the
KKT-NN outputs). Measured on the feeders' validation transitions (``evaluate.random_transitions`` seed 777), the
residual at the chosen k stays below the bar there too (table in ``docs/PINN.md``). The box also holds injections
with no power-flow solution, whose residual cannot vanish: where they are more than 1 % of it no k meets the bar,
the choice records ``met: false`` at :data:`K_MAX` steps and the training fails its acceptance bar (:func:`.presets.check_acceptance`) — a clear
failure, never a silent k.

The chosen k is stored in the model file (top-level ``refine_steps`` and the training report's
``power_balance.refine`` record, :mod:`.io`), and a file is always run with the k it names; :func:`check_record`
is the format check :func:`.io.load_modules` applies. ``python -m anm_torchrl.cli.pinn_refine --network <name>
--path <file>`` (:func:`.io.apply_refine_rule`) applies the rule to a model trained before it (same weights; the
file is rewritten with its k and record).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import torch

from anm_torchrl.grid.reset import free_variables
from anm_torchrl.grid.residuals import bus_voltage, power_injection
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.surrogates.pinn.chain import DEFAULT_RESIDUAL_THRESHOLD, BusAggregation  # the threshold's one home
from anm_torchrl.surrogates.pinn.power_balance import PowerBalanceNet
from anm_torchrl.surrogates.pinn.presets import REFINE_AUTO as AUTO, REFINE_MAX, module_seed

log = logging.getLogger(__name__)

RULE = "box_and_env_quantile_v4"
#: the refinement each rule's k was chosen with (a file runs its record's method)
RULE_METHODS = {"sobol_box_quantile_v1": "chord", "sobol_box_quantile_v2": "newton",
                "sobol_box_quantile_v3": "newton", RULE: "newton"}
QUANTILE = 0.99
MARGIN = 0.5
#: the residual quantile's bar relative to the network's median active losses at the box points (rule v3)
LOSS_FRACTION = 0.1
#: losses below this fraction of the network's injection scale count as this much: a lossless network (R = 0, which
#: gym-anm allows) has round-off losses (~1e-17 p.u.) that no float64 residual (~1e-14) can be a tenth of
LOSS_FLOOR = 1e-7
POINTS = 4096
K_MAX = REFINE_MAX
SEED_OFFSET = 30_000


def bar(loss_pu: float | None = None, threshold: float | None = None) -> float:
    """The rule's bar (p.u.): ``MARGIN × threshold``, and at most ``LOSS_FRACTION × loss_pu`` where the network's
    median active losses ``loss_pu`` are given (non-finite losses: the absolute bar alone)."""
    thr = DEFAULT_RESIDUAL_THRESHOLD if threshold is None else threshold
    b = MARGIN * thr
    if loss_pu is not None and math.isfinite(loss_pu):
        b = min(b, LOSS_FRACTION * abs(loss_pu))
    return b


def rule_met(residual_q: float, loss_pu: float | None = None, threshold: float | None = None) -> bool:
    """Whether a residual quantile (p.u.) meets :func:`bar` (NaN: not met)."""
    return bool(residual_q <= bar(loss_pu, threshold))


def median_losses(pb: PowerBalanceNet, x: torch.Tensor) -> float:
    """The median over the samples of the network's active losses Σᵢ Pᵢ(V) (p.u.) at ``x`` (N, 2n−2) = [θ, |V|] of
    the non-slack buses (the slack at 1∠0), at least :data:`LOSS_FLOOR` × ``pb.injection_scale()``; non-finite
    samples ignored (NaN if none is finite)."""
    n = pb.n_bus - 1
    one, zero = torch.ones_like(x[:, :1]), torch.zeros_like(x[:, :1])
    v = bus_voltage(torch.cat([one, x[:, n:]], -1), torch.cat([zero, x[:, :n]], -1))
    loss = power_injection(v, pb.y_bus.to(v.dtype)).real.sum(-1)
    loss = loss[torch.isfinite(loss)]
    return max(float(loss.median()), LOSS_FLOOR * pb.injection_scale()) if loss.numel() else math.nan


def residual_quantiles(pb: PowerBalanceNet, p_bus: torch.Tensor, q_bus: torch.Tensor, k_max: int = K_MAX,
                       stop_when_met: bool = True) -> tuple[list[float], list[float]]:
    """The :data:`QUANTILE` quantile (p.u.) of the per-sample largest |ΔP|, |ΔQ| after k = 1, 2, … refinement
    steps (``pb``'s :attr:`~.PowerBalanceNet.refine_method`), and the network's median losses at each k.

    Args:
        pb: the trained power-balance network (its own ``refine_steps`` is not used).
        p_bus, q_bus: (N, n_bus) p.u. bus injections (column 0, the slack, ignored).
        k_max: the most steps tried.
        stop_when_met: stop at the first k that meets :func:`rule_met`.

    Returns:
        ``(quantiles, losses)`` for k = 1 … (the first k meeting the bar, or ``k_max``), p.u.; non-finite
        quantiles as ``inf``.
    """
    steps = _refinement(pb, p_bus, q_bus)
    out, losses = [], []
    for _ in range(k_max):
        q, loss = next(steps)
        out.append(q)
        losses.append(loss)
        if stop_when_met and rule_met(q, loss):
            break
    return out, losses


def _refinement(pb: PowerBalanceNet, p_bus: torch.Tensor, q_bus: torch.Tensor):
    """Generator of (residual quantile, median losses) (p.u.) after each further refinement step (no gradient)."""
    p64, q64 = p_bus.to(torch.float64), q_bus.to(torch.float64)
    with torch.no_grad():
        v_magn, v_ang = pb(p64, q64, refine=False)
        x = torch.cat([v_ang[:, 1:], v_magn[:, 1:]], -1)  # [θ, |V|] of the non-slack buses, as PowerBalanceNet
        r = pb.residual(x, p64, q64)
    while True:  # each step's residual is the next step's input
        with torch.no_grad():
            x, r = pb.refine_step(x, p64, q64, r)
            res = r.abs().amax(-1)
            res = torch.where(torch.isfinite(res), res, torch.full_like(res, math.inf))
            quantile, loss = float(torch.quantile(res, QUANTILE)), median_losses(pb, x)
        yield quantile, loss


def env_injections(sim: GridSimulator, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Bus injections (P, Q) (n, n_bus) p.u. of ``n`` env-like steps, from the network's tables alone: the free
    variables of the env's random states (:func:`anm_torchrl.grid.reset.free_variables`: time index, SoC,
    set-points), the loads and potentials of the series at that index (clipped as the simulator clips them), the
    set-points projected by the devices' exact constraints; no power flow runs. The slack column is 0. (A
    ``next_vars`` hook's exogenous process needs states to run: the network's series stands for it here.)"""
    t, soc, a = free_variables(sim, n, torch.Generator(device=sim.net.dev.device).manual_seed(seed))
    gen_target, des_target = sim.split_action(a)
    gen_pq = sim.project_generators(gen_target, sim.p_pot_at(t))
    des_pq = sim.project_storage(des_target, soc)
    _, _, p_bus, q_bus = BusAggregation(sim)(gen_pq, des_pq, *sim.loads_at(t))
    return p_bus, q_bus


def choose_refine_steps(pb: PowerBalanceNet, sim: GridSimulator, seed: int) -> dict[str, Any]:
    """Apply the rule (module docstring) to ``pb`` and set its ``refine_steps`` to the chosen k.

    Args:
        pb: a trained :class:`PowerBalanceNet` of ``sim``'s network.
        sim: its simulator (only the network's tables; no simulator step runs).
        seed: the training seed of ``pb`` (the Sobol and env-like draws use ``seed + SEED_OFFSET``).

    Returns:
        the record stored in the model file: ``rule``, ``k``, ``met``, ``quantile``, ``margin``, ``threshold_pu``,
        ``loss_fraction``, ``loss_median_pu`` (the box's losses at k steps), ``bar_pu`` (the bar they set),
        ``points``, ``k_max``, ``seed``, ``residual_q_pu`` (the box's quantile after 1 … k steps; null: not
        finite), and the same for the env-like injections: ``env_loss_median_pu``, ``env_bar_pu``,
        ``env_residual_q_pu``.
    """
    from anm_torchrl.surrogates.pinn.tasks import TASKS

    task = TASKS["power_balance"](pb, sim)
    u = torch.quasirandom.SobolEngine(task.dim, scramble=True, seed=seed + SEED_OFFSET).draw(POINTS).double()
    pb.set_refine_method(RULE_METHODS[RULE])
    sets = {"box": _refinement(pb, *task.sample(u)),
            "env": _refinement(pb, *env_injections(sim, POINTS, seed + SEED_OFFSET))}
    q: dict[str, list[float]] = {s: [] for s in sets}
    losses: dict[str, float] = {}
    for _ in range(K_MAX):
        for s, steps in sets.items():
            qk, losses[s] = next(steps)
            q[s].append(qk)
        met = all(rule_met(q[s][-1], losses[s]) for s in sets)
        if met:
            break
    k = len(q["box"])
    pb.set_refine_steps(k)
    if not met:
        log.warning("no Newton-step count <= %d brings the %.2f quantile of the power-flow residual below the bar on "
                    "both point sets (after %d steps: box %.3g p.u., bar %.2g; env %.3g p.u., bar %.2g): the model "
                    "fails its acceptance bar", K_MAX, QUANTILE, k, q["box"][-1], bar(losses["box"]),
                    q["env"][-1], bar(losses["env"]))
    return {"rule": RULE, "method": RULE_METHODS[RULE], "k": k, "met": met, "quantile": QUANTILE, "margin": MARGIN,
            "threshold_pu": DEFAULT_RESIDUAL_THRESHOLD, "loss_fraction": LOSS_FRACTION,
            "loss_median_pu": _finite(losses["box"]), "bar_pu": bar(losses["box"]),
            "points": POINTS, "k_max": K_MAX, "seed": seed + SEED_OFFSET,
            "residual_q_pu": [_finite(x) for x in q["box"]],
            "env_loss_median_pu": _finite(losses["env"]), "env_bar_pu": bar(losses["env"]),
            "env_residual_q_pu": [_finite(x) for x in q["env"]]}


def _finite(x: float) -> float | None:
    """``x``, or None where it is not finite (JSON has no inf/NaN)."""
    return x if math.isfinite(x) else None


def check_record(file: Path | str, config_k: Any, file_k: Any, record: Any, preset_is_auto: bool) -> int:
    """The refinement-step count a saved PINN runs with, after checking that its fields agree (the format check).

    Args:
        file: the model file (for messages).
        config_k: its training config's ``power_balance.refine_steps`` (an int, or ``"auto"``).
        file_k: its top-level ``refine_steps`` (None: a file written before the field existed).
        record: its report's ``power_balance.refine`` (the rule's record; None if absent).
        preset_is_auto: whether the preset the file names chooses k by the rule today.

    A record of an earlier rule is served with its k and logged as a warning naming the command that re-chooses it.

    Raises:
        ArtifactError: ``file_k`` not an integer in 0…K_MAX; a config that fixes k disagreeing with it; an ``auto``
            config without a record of this rule whose ``k`` is ``file_k``; or a file without ``refine_steps``
            whose preset now chooses k by the rule (trained before the rule: its fixed k is not the network's).
    """
    from anm_torchrl.artifacts import ArtifactError

    def bad(why: str) -> ArtifactError:
        return ArtifactError(f"{file}: {why}; retrain it, or apply the rule to it with python -m "
                             f"anm_torchrl.cli.pinn_refine --network <name> --path {file}")

    if file_k is None:
        if preset_is_auto or config_k == AUTO:
            raise bad(f"no refine_steps field, and its preset now chooses the chord steps per network (rule {RULE}): "
                      f"it was trained before the rule with a fixed {config_k!r}, which need not be this network's k")
        file_k = config_k
    if isinstance(file_k, bool) or not isinstance(file_k, int) or not 0 <= file_k <= K_MAX:
        raise bad(f"refine_steps must be an integer in 0..{K_MAX}, got {file_k!r} (corrupted or another version)")
    if config_k == AUTO:
        if not isinstance(record, dict) or record.get("rule") not in RULE_METHODS or record.get("k") != file_k:
            raise bad(f"its refinement steps were chosen by the rule but the record ({record!r}) is not one of rule "
                      f"{RULE} (or {sorted(set(RULE_METHODS) - {RULE})}) with k = refine_steps = {file_k}")
        if record["rule"] != RULE:  # it runs as chosen; an earlier rule's k may be short of today's bar
            log.warning("%s: its %d refinement steps were chosen by rule %s, not today's %s (whose bar is also "
                        "relative to the network's losses: where they are small in p.u., fewer steps leave reward "
                        "errors); python -m anm_torchrl.cli.pinn_refine --network <name> --path %s re-chooses them "
                        "(same weights)", file, file_k, record["rule"], RULE, file)
    elif config_k != file_k:
        raise bad(f"its config fixes refine_steps = {config_k!r} but the file says {file_k}")
    return file_k


def check_method(file: Path | str, file_method: Any, record: Any) -> str:
    """The refinement a saved PINN runs (``"newton"`` or ``"chord"``), after checking it against its rule's record.

    Args:
        file: the model file (for messages).
        file_method: its top-level ``refine_method`` (None: written before rule v2, whose steps were all chord
            steps: it runs them, exactly as before).
        record: its report's ``power_balance.refine`` (None: a fixed k).

    Raises:
        ArtifactError: an unknown method, or one that is not the method its record's rule chose k with.
    """
    from anm_torchrl.artifacts import ArtifactError
    from anm_torchrl.surrogates.pinn.power_balance import REFINE_METHODS

    method = "chord" if file_method is None else file_method
    if method not in REFINE_METHODS:
        raise ArtifactError(f"{file}: refine_method must be one of {REFINE_METHODS}, got {file_method!r} (corrupted "
                            f"or another version); retrain it")
    rule = record.get("rule") if isinstance(record, dict) else None
    if rule in RULE_METHODS and RULE_METHODS[rule] != method:
        raise ArtifactError(f"{file}: its steps were chosen by rule {rule} with {RULE_METHODS[rule]} steps, but it "
                            f"names refine_method {method!r}; retrain it, or apply the rule to it with python -m "
                            f"anm_torchrl.cli.pinn_refine --network <name> --path {file}")
    return method
