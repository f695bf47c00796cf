"""``RegressorSurrogate``: a fitted regressor and the terminal classifier as a ``SurrogateEnv`` transition model."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.grid.identity import transition_key
from anm_torchrl.surrogates.features import Featurizer, target_layout
from anm_torchrl.surrogates.regressors.backends import Backend
from anm_torchrl.surrogates.regressors.defaults import KINDS, train_command
from anm_torchrl.surrogates.terminal import TerminalClassifier


class RegressorSurrogate(TensorDictModuleBase):
    """A trained regressor + terminal classifier as a ``SurrogateEnv`` transition model.

    Reads ``"state"`` (N, state_dim) and ``"action"`` (N, action_dim) (any float dtype, MW/MVAr), writes
    ``"next_state"`` (N, state_dim) float64 (predicted physics entries; the other entries are copied from
    ``state`` and overwritten by the env), ``"reward"`` (N, 1) float64 and ``"terminated"`` (N, 1) bool. With
    ``clip`` the predicted entries are clamped to the state's observation bounds (the slack excepted, whose
    bounds gym-anm does not enforce) and the reward to gym-anm's clipping range [−(c₁ + c₂), c₁].

    Build one with :func:`fit_regressor` or :meth:`load`.
    """

    in_keys = ["state", "action"]
    out_keys = ["next_state", "reward", "terminated"]

    def __init__(self, kind: str, backend: Backend, sim: GridSimulator, featurizer: Featurizer,
                 x_mean: torch.Tensor, x_std: torch.Tensor, y_mean: torch.Tensor, y_std: torch.Tensor,
                 classifier: TerminalClassifier | None = None, clip: bool = True, meta: dict | None = None):
        super().__init__()
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
        self.kind, self.backend, self.sim, self.featurizer = kind, backend, sim, featurizer
        self.transition_key = transition_key(sim)  # SurrogateEnv refuses to run it on another network or other profiles
        self.classifier, self.clip, self.meta = classifier, bool(clip), dict(meta or {})
        idx, names = target_layout(sim)
        self.target_names = names
        self.register_buffer("target_index", torch.tensor(idx, dtype=torch.long))
        for name, t in (("x_mean", x_mean), ("x_std", x_std), ("y_mean", y_mean), ("y_std", y_std)):
            self.register_buffer(name, torch.as_tensor(t, dtype=torch.float64).clone())
        low, high = sim.state_bounds()
        low, high = low[idx].clone().to(torch.float64), high[idx].clone().to(torch.float64)
        slack = [k for k, i in enumerate(idx) if i - sim.state_slices()["dev_p"].start in sim.slack_ids
                 or i - sim.state_slices()["dev_q"].start in sim.slack_ids]
        low[slack], high[slack] = -torch.inf, torch.inf
        c1, c2 = sim.costs_clipping
        self.register_buffer("y_low", torch.cat([low, low.new_tensor([-(c1 + c2)])]))
        self.register_buffer("y_high", torch.cat([high, high.new_tensor([c1])]))
        soc = sim.state_slices()["des_soc"]
        self.soc_columns = [k for k, i in enumerate(idx) if soc.start <= i < soc.stop]  # predicted SoC entries

    # ---------------------------------------------------------------------------------------------- predict
    def features(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Standardised inputs (N, F) float64."""
        x = self.featurizer(state.to(torch.float64).cpu(), action.to(torch.float64).cpu()).to(self.x_mean.device)
        return (x - self.x_mean) / self.x_std

    def predict_targets(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Predicted targets (N, T) float64 in their units (``target_names``: MW, MVAr, MWh, then reward)."""
        y = self.backend.predict(self.features(state, action)) * self.y_std + self.y_mean
        if self.clip:
            y = torch.maximum(torch.minimum(y, self.y_high), self.y_low)
        else:  # the SoC within its bounds, always: the simulator never leaves them, and the next step checks them
            soc = self.soc_columns
            y[:, soc] = torch.maximum(torch.minimum(y[:, soc], self.y_high[soc]), self.y_low[soc])
        return y

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        state = tensordict.get("state").to(torch.float64)
        action = tensordict.get("action").to(torch.float64)
        y = self.predict_targets(state, action).to(state.device)
        next_state = state.clone()
        next_state[:, self.target_index.to(state.device)] = y[:, :-1]
        if self.classifier is None:
            raise RuntimeError(f"{self.kind} surrogate has no terminal classifier; retrain it "
                               f"({train_command(self.kind, self.meta.get('dataset', 'generative'), self.sim)})")
        terminated = self.classifier.predict_terminated(state, action).reshape(-1, 1).to(state.device)
        tensordict.set("next_state", next_state)
        tensordict.set("reward", y[:, -1:])
        tensordict.set("terminated", terminated)
        return tensordict

    # ------------------------------------------------------------------------------------------- save/load
    def layout(self) -> dict[str, Any]:
        """The state/action layout this surrogate was trained for (checked on load)."""
        return {"state_dim": self.sim.state_dim, "action_dim": self.sim.action_dim, "n_time": self.sim.n_time,
                "features": list(self.featurizer.names), "targets": list(self.target_names),
                "target_index": self.target_index.tolist()}
