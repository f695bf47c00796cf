"""The PINN training loop: each module on its own, on Sobol batches, from its physics losses alone.

Every module is trained on scrambled-Sobol batches (``torch.quasirandom.SobolEngine(scramble=True)``) drawn
over its input box (paper Appendix A), with losses built only from the shared residual functions
(:mod:`.losses`): no simulator transition, projection or power-flow solution enters training. The exact
solvers are used for *validation errors only* (:mod:`.tasks`; logged, and checked against the preset's
acceptance bar, never used for a training decision): early stopping watches the physics loss on a fixed
held-out Sobol set.

TensorBoard tags (``surrogate/*``, paper Fig. 5): ``surrogate/<module>/<term>`` for every loss term
(``generator``/``storage``: ``stationarity``, ``primal``, ``complementarity``; ``power_balance``:
``residual_p``, ``residual_q``), ``surrogate/<module>/loss`` (weighted sum), ``surrogate/<module>/lr``,
``surrogate/<module>/val_loss`` (same physics loss on the held-out Sobol set) and the validation errors against
the exact solvers: ``surrogate/<module>/val_mae_pu`` (projection MAE, p.u.), ``val_feasible`` (fraction of raw
outputs inside the polygon), ``surrogate/power_balance/val_vmag_mae``, ``val_vang_mae`` (p.u., rad),
``val_residual_mean``/``val_residual_p99`` (per-sample max-abs residual, p.u.).
"""

from __future__ import annotations

import copy
import logging
import math
import sys
import time
from pathlib import Path
from typing import Any

import torch
from torch import nn

from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.processes import ModuleProcess
from anm_torchrl.provenance import usable_cpus
from anm_torchrl.surrogates.pinn.model import build_modules
from anm_torchrl.surrogates.pinn.presets import (MODULES, REFINE_AUTO, ModuleTrainConfig, PINNTrainConfig,
                                                 check_acceptance, module_seed, preset_for)
from anm_torchrl.surrogates.pinn.refine import choose_refine_steps
from anm_torchrl.surrogates.pinn.tasks import TASKS, _Task

log = logging.getLogger(__name__)


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


def _points(samples: int, task: _Task, cfg: ModuleTrainConfig) -> int:
    """Sobol points for ``samples`` (device samples with ``cfg.per_device``, else points)."""
    return -(-samples // task.units) if cfg.per_device else samples


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

    A power balance with ``refine_steps: auto`` gets its refinement (Newton) steps from :func:`.refine.choose_refine_steps` after
    training (report keys ``refine`` and ``refine_steps``); the final validation errors use them.
    """
    task = TASKS[name](module, sim)
    if task.dim == 0:  # a network without devices of this kind (e.g. no storage): nothing to learn
        return {"steps": 0, "best_step": 0, "adam_time_s": 0.0, "time_s": 0.0, "devices": 0}
    engine = torch.quasirandom.SobolEngine(task.dim, scramble=True, seed=seed)
    val_in = task.sample(torch.quasirandom.SobolEngine(task.dim, scramble=True, seed=seed + 10_000)
                         .draw(_points(cfg.val_size, task, cfg)).double())
    batch = _points(cfg.batch_size, task, cfg)
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
    step = n_evals = 0
    module.train()
    while step < cfg.max_steps:
        inputs = task.sample(engine.draw(batch).double())
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
        capped = cfg.max_time_s is not None and time.perf_counter() - t0 > cfg.max_time_s
        # the weights the time cap stops at are evaluated too: they may be the best, or the only trained ones
        if step % cfg.eval_every == 0 or step == cfg.max_steps or capped:
            v = log_eval(step)["val_loss"]
            n_evals += 1
            if v < best:
                best, best_step, best_state = v, step, copy.deepcopy(module.state_dict())
            if step - best_step >= cfg.patience:
                log.info("%s: early stop at step %d (best held-out loss %.3e at step %d)", name, step, best,
                         best_step)
                break
        if capped:
            log.info("%s: time cap %.0f s reached at step %d", name, cfg.max_time_s, step)
            break
    if not math.isfinite(best):  # restoring best_state would save the untrained weights as trained
        raise RuntimeError(f"PINN module {name!r} diverged: its held-out loss was not finite at any of its {n_evals} "
                           f"evaluations ({step} Adam steps at lr {cfg.lr:g}); lower {name}.lr or check the preset")
    module.load_state_dict(best_state)
    adam_time = time.perf_counter() - t0
    if cfg.lbfgs_iters > 0:
        _lbfgs_finish(task, cfg, seed)
    if writer is not None and cfg.lbfgs_iters > 0:
        log_eval(step + 1)
    module.eval()
    extra: dict[str, Any] = {}
    if name == "power_balance" and cfg.refine_steps == REFINE_AUTO:  # k from physics, before the final errors
        extra["refine"] = choose_refine_steps(module, sim, seed)
        extra["refine_steps"] = extra["refine"]["k"]
    final = {"val_loss": val_loss(), **task.errors(val_in, val_ref)}
    return {"steps": step, "best_step": best_step, "adam_time_s": adam_time,
            "time_s": time.perf_counter() - t0, **final, **extra}


def _lbfgs_finish(task: _Task, cfg: ModuleTrainConfig, seed: int) -> None:
    """L-BFGS (strong Wolfe) on a fixed Sobol batch, in float64, then back to float32."""
    module = task.module
    # only the networks: the physics buffers are float64 / complex128 already
    nets = [net for net in (module.net, getattr(module, "dual_net", None)) if net is not None]
    for net in nets:
        net.double()
    inputs = task.sample(torch.quasirandom.SobolEngine(task.dim, scramble=True, seed=seed + 20_000)
                         .draw(_points(cfg.lbfgs_batch, task, cfg)).double())
    opt = torch.optim.LBFGS(module.parameters(), lr=1.0, max_iter=cfg.lbfgs_iters, history_size=50,
                            tolerance_grad=1e-12, tolerance_change=1e-15, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad(set_to_none=True)
        loss = _total(task.losses(inputs, cfg), cfg.weights)
        loss.backward()
        return loss

    opt.step(closure)
    for net in nets:
        net.float()


STAGE_KIND = "anm_torchrl.pinn_stage"


def _stage_file(stage_dir: Path, name: str) -> Path:
    return stage_dir / f"{name}.safetensors"


def _save_stage(stage_dir: Path, name: str, module: nn.Module, cfg: PINNTrainConfig, sim: GridSimulator,
                report: dict[str, Any]) -> None:
    """Keep a finished stage (weights, its report, what it was trained for) so a killed training resumes here."""
    from anm_torchrl.artifacts import save_tensors
    from anm_torchrl.grid.identity import network_key
    from anm_torchrl.surrogates.pinn.io import plain

    stage_dir.mkdir(parents=True, exist_ok=True)
    save_tensors(_stage_file(stage_dir, name), module.state_dict(),
                 {"module": name, "config": plain(cfg.to_dict()), "network": network_key(sim),
                  "report": plain(report)}, STAGE_KIND)


def _resume_stage(stage_dir: Path, name: str, module: nn.Module, cfg: PINNTrainConfig,
                  sim: GridSimulator) -> dict[str, Any] | None:
    """The report of a stage kept by an earlier, interrupted training of the same config on the same network, its
    weights loaded into ``module``; None (the stage is trained) when there is none or it does not match."""
    from anm_torchrl.artifacts import ArtifactError, load_tensors
    from anm_torchrl.grid.identity import network_key
    from anm_torchrl.surrogates.pinn.io import plain

    file = _stage_file(stage_dir, name)
    if not file.is_file():
        return None
    try:
        tensors, meta = load_tensors(file, STAGE_KIND)
    except ArtifactError as err:
        log.warning("PINN stage %s: the kept stage %s is unusable (%s); training it again", name, file, err)
        return None
    if (meta.get("module"), meta.get("network"), meta.get("config")) != (name, network_key(sim),
                                                                         plain(cfg.to_dict())):
        log.warning("PINN stage %s: the kept stage %s was trained for another config or network; training it again",
                    name, file)
        return None
    report = dict(meta["report"])
    _load_trained(module, tensors, report)
    return {**report, "resumed_from": str(file)}


def _load_trained(module: nn.Module, state: dict[str, torch.Tensor], report: dict[str, Any]) -> None:
    """Weights of a stage trained elsewhere (kept on disk, or by the stage process) into ``module``, with the
    refinement steps its report chose (an attribute, not a weight)."""
    module.load_state_dict(state)
    module.eval()
    if report.get("refine_steps") is not None:
        module.set_refine_steps(int(report["refine_steps"]))


def _writer(log_dir: str | Path | None):
    """A TensorBoard ``SummaryWriter`` on ``log_dir`` (None: none); two processes may write in the same folder."""
    if log_dir is None:
        return None
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(str(log_dir))


def _train_in_process(name: str, state: dict[str, torch.Tensor], sim: GridSimulator, cfg: PINNTrainConfig,
                      log_dir: str | None, threads: int) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """:func:`train_module` of stage ``name`` from the initial weights ``state`` (the body of the stage process)."""
    torch.set_num_threads(threads)  # the parent's: the same kernels, so the same weights
    module = build_modules(cfg, sim)[name]
    module.load_state_dict(state)
    writer = _writer(log_dir)
    try:
        report = train_module(name, module, sim, getattr(cfg, name), seed=module_seed(cfg, name), writer=writer)
    finally:
        if writer is not None:
            writer.close()
    return module.state_dict(), report


class _StageProcess(ModuleProcess):
    """One stage trained by ``python -m anm_torchrl.surrogates.pinn.loop SETUP OUT`` (:class:`ModuleProcess`), its
    trained weights and report written to ``OUT`` in the process's temp folder."""

    def __init__(self, name: str, module: nn.Module, sim: GridSimulator, cfg: PINNTrainConfig,
                 log_dir: str | Path | None):
        setup = {"name": name, "state": module.state_dict(), "sim": sim, "cfg": cfg,
                 "threads": torch.get_num_threads(), "log_dir": None if log_dir is None else str(log_dir)}
        super().__init__(__name__, setup, prefix="anm_torchrl_pinn_stage_", args=("out.pt",))

    def result(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        """Wait for the stage: its trained weights and report; ``RuntimeError`` with its stderr if it failed."""
        if self.proc.wait() != 0:
            raise self.failure("the PINN stage process")
        return torch.load(self.folder / "out.pt", weights_only=False)  # written by that process, in its folder


#: power-balance steps from which a second process pays: it takes ~4 s to start, the default preset's 10,000 steps ~60 s
PARALLEL_MIN_STEPS = 1000


def default_jobs(cfg: PINNTrainConfig) -> int:
    """Processes of a training by default: 2 where this process may use 2 or more CPUs and the power balance trains
    at least :data:`PARALLEL_MIN_STEPS` steps, else 1."""
    return 2 if usable_cpus() >= 2 and cfg.power_balance.max_steps >= PARALLEL_MIN_STEPS else 1


def train_pinn(cfg: PINNTrainConfig | None = None, sim: GridSimulator | None = None, log_dir: str | Path | None = None,
               progress: bool = False, stage_dir: str | Path | None = None,
               jobs: int | None = None) -> tuple[dict[str, nn.Module], dict[str, Any]]:
    """Train the three PINN modules from physics alone.

    Args:
        cfg: training configuration (default: the ``default`` preset of ``sim``'s network, :func:`.presets.preset_for`).
        sim: the simulator providing the physics constants (default ANM6-Easy on CPU).
        log_dir: TensorBoard folder (None: no logging).
        progress: show a tqdm progress bar over all Adam steps.
        stage_dir: keep each finished stage there, and resume from the stages an interrupted training of the same
            config on the same network kept (every stage has its own seed, so a resumed training gives the weights
            an uninterrupted one gives); None: no stages kept.
        jobs: processes; with 2 or more the power balance (the longest stage) trains in a spawned process while
            the projections train here, to the same weights as ``jobs=1`` (each stage starts from its own initial
            weights and seed; the process runs this one's torch thread count). None: :func:`default_jobs`.

    Returns:
        the trained modules (``generator``, ``storage``, ``power_balance``) and a report (per-module steps,
        times and validation errors against the exact solvers; ``accepted`` and ``acceptance_failures``
        against the preset's bar).
    """
    sim = sim if sim is not None else network_simulator(ANM6_EASY)
    cfg = cfg if cfg is not None else preset_for("default", sim)
    devices = [] if sim.net.dev.device.type == "cpu" else [sim.net.dev.device]
    # the caller's random stream is left as it was: a run that trains its PINN first draws what a run that found
    # it cached draws (the recipes seed once, then may train the PINN on first use)
    with torch.random.fork_rng(devices=devices):
        return _train_pinn(cfg, sim, log_dir, progress, stage_dir, jobs)


def _train_pinn(cfg: PINNTrainConfig, sim: GridSimulator, log_dir: str | Path | None, progress: bool,
                stage_dir: str | Path | None, jobs: int | None) -> tuple[dict[str, nn.Module], dict[str, Any]]:
    torch.manual_seed(cfg.seed)
    modules = build_modules(cfg, sim)
    writer = _writer(log_dir)
    budget = {m: getattr(cfg, m).max_steps for m in MODULES}
    kept = {m: None if stage_dir is None else _resume_stage(Path(stage_dir), m, modules[m], cfg, sim) for m in MODULES}
    jobs = jobs if jobs is not None else default_jobs(cfg)
    aside = "power_balance" if jobs > 1 and kept["power_balance"] is None else None
    bar = None
    if progress:  # the steps trained in this process
        from tqdm.auto import tqdm

        bar = tqdm(total=sum(budget[m] for m in MODULES if m != aside), mininterval=1.0, unit="step",
                   desc="training PINN surrogate" + (f" ({aside} in a second process)" if aside else ""))
    report: dict[str, Any] = {}
    t0 = time.perf_counter()
    stage = None
    try:
        if aside is not None:
            stage = _StageProcess(aside, modules[aside], sim, cfg, log_dir)
        for i, name in enumerate(MODULES, 1):
            if bar is not None:
                bar.set_postfix_str(name)
            if kept[name] is not None:
                log.info("PINN stage %d/%d: %s resumed from %s (trained before an interruption)", i, len(MODULES),
                         name, kept[name]["resumed_from"])
                report[name] = kept[name]
                if bar is not None:
                    bar.update(budget[name])
                continue
            if name == aside:
                log.info("PINN stage %d/%d: %s, up to %d Adam steps in a second process (started with the first "
                         "stage)", i, len(MODULES), name, budget[name])
                state, report[name] = stage.result()
                _load_trained(modules[name], state, report[name])
            else:
                log.info("PINN stage %d/%d: %s, up to %d Adam steps", i, len(MODULES), name, budget[name])
                report[name] = train_module(name, modules[name], sim, getattr(cfg, name),
                                            seed=module_seed(cfg, name), writer=writer, progress=bar)
            if stage_dir is not None:
                _save_stage(Path(stage_dir), name, modules[name], cfg, sim, report[name])
            elapsed, left = time.perf_counter() - t0, sum(budget[m] for m in MODULES[i:] if m != aside)
            rate = report[name]["steps"] / max(report[name]["adam_time_s"], 1e-9)  # this stage's steps/s
            # a module without devices on this network trains no step: no rate to extrapolate the others' time from
            eta = f"; at this stage's {rate:.0f} steps/s, up to ~{left / rate:.0f} s left" if left and rate > 0 else ""
            none = ", no such device on this network" if report[name].get("devices") == 0 else ""
            log.info("PINN stage %d/%d done: %s%s, %d steps in %.0f s (%.0f s so far%s)", i, len(MODULES), name,
                     none, report[name]["steps"], report[name]["time_s"], elapsed, eta)
            log.debug("%s report: %s", name, report[name])
    finally:
        if stage is not None:
            stage.close()
        if bar is not None:
            bar.close()
        if writer is not None:
            writer.close()
    report["time_s"] = sum(report[m]["time_s"] for m in MODULES)  # the stages' own times
    report["wall_s"], report["jobs"] = time.perf_counter() - t0, 1 if aside is None else 2
    report["acceptance_failures"] = check_acceptance(cfg, report)
    report["accepted"] = not report["acceptance_failures"]
    return modules, report


if __name__ == "__main__":  # the stage process of :class:`_StageProcess`: SETUP OUT (OUT beside SETUP)
    args = torch.load(sys.argv[1], weights_only=False)  # written by the parent in its own temp folder
    torch.save(_train_in_process(**args), Path(sys.argv[1]).with_name(sys.argv[2]))
