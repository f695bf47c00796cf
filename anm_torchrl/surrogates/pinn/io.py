"""The saved PINN: one safetensors file (:mod:`anm_torchrl.artifacts`: content hash, kind, finite weights).

Tensors ``<module>.<parameter>`` for the three modules; metadata ``config`` (the :class:`PINNTrainConfig`),
``report`` (training report), ``network`` (:func:`anm_torchrl.grid.identity.network_key` of the simulator it
was trained on: loading it on another network raises), ``refine_steps`` (the chord-Newton steps the power balance
runs with: the config's, or the one :mod:`.refine` chose for ``auto``, with its record in
``report.power_balance.refine``; checked at load by :func:`.refine.check_record`), ``refine_method`` (``newton``,
rule v2; absent in files written before it, which run their ``chord`` steps as before: :func:`.refine.check_method`)
and ``torch_version``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import nn

from anm_torchrl.artifacts import ArtifactError, load_tensors, save_tensors
from anm_torchrl.grid.identity import network_key
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.surrogates.pinn.model import build_modules
from anm_torchrl.surrogates.pinn.presets import (MODULES, PRESETS, REFINE_AUTO, PINNTrainConfig, check_acceptance,
                                                 module_seed, preset)
from anm_torchrl.surrogates.pinn.refine import RULE, RULE_METHODS, check_method, check_record, choose_refine_steps

KIND = "anm_torchrl.pinn"
FILE_NAME = "pinn.safetensors"


def resolve_path(path: str | Path) -> Path:
    """``path / "pinn.safetensors"`` if ``path`` is an existing folder or has no suffix, else ``path`` itself (a file).

    The folder test comes first: a folder named with a dot (``run.v2``) has a suffix too."""
    p = Path(path).expanduser()
    return p / FILE_NAME if p.is_dir() or not p.suffix else p


def plain(x: Any) -> Any:
    """JSON-ready copy (dicts, lists, str, int, float, bool, None; other numbers as float)."""
    if isinstance(x, dict):
        return {str(k): plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain(v) for v in x]
    if isinstance(x, (str, int, float, bool)) or x is None:
        return x
    return float(x)


def save_pinn(path: str | Path, modules: dict[str, nn.Module], cfg: PINNTrainConfig,
              report: dict[str, Any] | None = None, sim: GridSimulator | None = None) -> Path:
    """Write the trained modules, the config, the report and the network key of ``sim`` (the simulator they
    were trained on; None: ANM6-Easy) to ``path``.

    ``path`` is a file or a folder (then ``<folder>/pinn.safetensors``); written atomically. Returns the file.

    Raises:
        ArtifactError: a weight is NaN or inf (a diverged training is never saved).
    """
    sim = sim if sim is not None else network_simulator(ANM6_EASY)
    tensors = {f"{k}.{n}": t for k, m in modules.items() for n, t in m.state_dict().items()}
    meta = {"config": cfg.to_dict(), "report": plain(report or {}), "network": network_key(sim),
            "refine_steps": int(modules["power_balance"].refine_steps),
            "refine_method": str(modules["power_balance"].refine_method), "torch_version": str(torch.__version__)}
    return save_tensors(resolve_path(path), tensors, meta, KIND)


def read_pinn_file(path: str | Path) -> dict[str, Any]:
    """Read and check a saved PINN file: ``{"kind", "config", "report", "network", "state_dict"}``.

    Raises:
        FileNotFoundError: no file at ``path`` (or ``path/pinn.safetensors``).
        ArtifactError (a ``ValueError``): not a PINN file, corrupted (hash), or a NaN/inf weight.
    """
    file = resolve_path(path)
    if not file.is_file():
        raise FileNotFoundError(f"no trained PINN at {file}")
    tensors, meta = load_tensors(file, KIND)
    state = {k: {} for k in MODULES}
    for name, t in tensors.items():
        mod, _, param = name.partition(".")
        if mod not in state:
            raise ArtifactError(f"{file} holds tensor {name!r} of no PINN module {MODULES}")
        state[mod][param] = t
    return {"kind": KIND, "state_dict": state, **meta}


def config_of(payload: dict[str, Any], path: str | Path, sim: GridSimulator) -> PINNTrainConfig:
    """The training config of a read file (:func:`read_pinn_file`), after checking it was trained on ``sim``'s
    network.

    Raises:
        ArtifactError: trained on another network.
    """
    if payload.get("network") != network_key(sim):
        raise ArtifactError(f"{resolve_path(path)} was trained on network {payload.get('network')!r}, the simulator "
                            f"is network {network_key(sim)!r}: train a PINN for this network")
    return PINNTrainConfig.from_dict(payload["config"], strict=False)


def refine_steps_of(payload: dict[str, Any], cfg: PINNTrainConfig, path: str | Path) -> int:
    """The chord steps a read file runs with (:func:`.refine.check_record`: fields checked against each other and
    against what the file's preset does today)."""
    auto_now = cfg.preset in PRESETS and preset(cfg.preset).power_balance.refine_steps == REFINE_AUTO
    record = ((payload.get("report") or {}).get("power_balance") or {}).get("refine")
    return check_record(resolve_path(path), cfg.power_balance.refine_steps, payload.get("refine_steps"), record,
                        auto_now)


def refine_method_of(payload: dict[str, Any], path: str | Path) -> str:
    """The refinement a read file runs (:func:`.refine.check_method`)."""
    record = ((payload.get("report") or {}).get("power_balance") or {}).get("refine")
    return check_method(resolve_path(path), payload.get("refine_method"), record)


def modules_from_payload(payload: dict[str, Any], cfg: PINNTrainConfig, sim: GridSimulator, path: str | Path,
                         refine_steps: int, refine_method: str = "newton") -> dict[str, nn.Module]:
    """The modules of a read file, built for ``cfg`` on ``sim``'s device with ``refine_steps`` of
    ``refine_method``, in eval mode.

    Raises:
        ArtifactError: the weights do not fit the config.
    """
    modules = build_modules(cfg, sim, refine_steps=0)
    modules["power_balance"].set_refine_method(refine_method)
    modules["power_balance"].set_refine_steps(refine_steps)
    for k, m in modules.items():
        try:
            m.load_state_dict(payload["state_dict"][k])
        except RuntimeError as err:
            raise ArtifactError(f"{resolve_path(path)}: the {k} weights do not fit its config ({err})") from err
        m.eval()
    return modules


def load_modules(path: str | Path, sim: GridSimulator) -> tuple[dict[str, nn.Module], PINNTrainConfig, dict]:
    """Rebuild the modules saved at ``path`` for ``sim`` (on its device), the power balance with the chord steps the
    file names; returns (modules, config, report).

    Raises:
        ArtifactError: the file was trained on another network than ``sim``'s, its weights do not fit, or its
            chord-step fields are bad, disagree, or predate its preset's rule (:func:`.refine.check_record`).
    """
    payload = read_pinn_file(path)
    cfg = config_of(payload, path, sim)
    modules = modules_from_payload(payload, cfg, sim, path, refine_steps_of(payload, cfg, path),
                                   refine_method_of(payload, path))
    return modules, cfg, payload.get("report", {})


def apply_refine_rule(path: str | Path, sim: GridSimulator) -> dict[str, Any]:
    """Apply the refinement rule (:mod:`.refine`, today's :data:`.refine.RULE`) to the model saved at ``path``
    (trained on ``sim``'s network) and rewrite it with the chosen k and the rule's record (weights unchanged; the
    config's ``power_balance.refine_steps`` becomes ``auto``; the report's acceptance re-checked, the rule's verdict
    being part of the bar). Returns the record."""
    payload = read_pinn_file(path)
    cfg = config_of(payload, path, sim)
    cfg.power_balance.refine_steps = REFINE_AUTO
    modules = modules_from_payload(payload, cfg, sim, path, refine_steps=0, refine_method=RULE_METHODS[RULE])
    report = dict(payload.get("report") or {})
    record = choose_refine_steps(modules["power_balance"], sim, module_seed(cfg, "power_balance"))
    report["power_balance"] = {**report.get("power_balance", {}), "refine": {**record, "applied_after_training": True}}
    # the acceptance bar includes the rule's verdict: the file's record must say what the rewritten model meets
    report["acceptance_failures"] = check_acceptance(cfg, report)
    report["accepted"] = not report["acceptance_failures"]
    save_pinn(path, modules, cfg, report, sim)
    return record
