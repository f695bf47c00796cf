"""What each PINN module is trained on: its Sobol input box, its physics losses, and (for validation only) its
errors against the exact solver.

``reference`` (the exact projection or Newton–Raphson) feeds ``errors`` only, which are logged and checked
against the preset's acceptance bar; no training decision reads them (guarded by ``test_physics_alone``).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from anm_torchrl.grid.powerflow import newton_raphson
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.surrogates.pinn.kkt import clamp_to_polygon
from anm_torchrl.surrogates.pinn.losses import kkt_losses, power_balance_losses, power_balance_residuals
from anm_torchrl.surrogates.pinn.presets import KKT_TERMS, PB_TERMS, ModuleTrainConfig


class _Task:
    """What a module is trained on: its Sobol dimension, how a unit-cube point maps into its input box, its
    physics losses, and its validation errors against the exact solver."""

    name: str
    terms: tuple[str, ...]
    dim: int
    units: int = 1  # samples one Sobol point holds (devices of a KKT-NN), for ``per_device`` batch sizes

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
        self.n = self.units = module.g.shape[0]
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
        v_magn, v_ang = self.module(*inputs, refine=False)  # the network is trained on its raw output
        unit = self.module.injection_scale() if cfg.residual_unit == "box" else 1.0
        return power_balance_losses(v_magn, v_ang, *inputs, self.module.y_bus, cfg.robust, cfg.robust_scale, unit)

    def reference(self, inputs):
        pf = newton_raphson(self.sim.net.y_bus, torch.complex(*inputs), tol=1e-10)
        return pf

    def errors(self, inputs, ref):
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
