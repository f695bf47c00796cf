"""Do-nothing and uniform-random ANM6-Easy policies, and :func:`make_baseline`.

Every baseline is a :class:`tensordict.nn.TensorDictModuleBase` reading ``in_key`` (default ``"state"``,
(..., state_dim)) and writing ``"action"`` (..., action_dim) float32 in MW/MVAr, action order
(P gen…, Q gen…, P DES…, Q DES…) — for ANM6-Easy [P PV, P wind, Q PV, Q wind, P DES, Q DES]. Any batch
shape works, so each can be passed directly as the policy of ``env.rollout(T, policy)``.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from anm_torchrl.baselines.names import BASELINES
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.networks.resolve import unbounded_actions


def _box(sim: GridSimulator | None) -> tuple[GridSimulator, torch.Tensor, torch.Tensor]:
    sim = network_simulator(ANM6_EASY) if sim is None else sim
    lo, hi = sim.action_bounds()
    return sim, lo.detach().cpu(), hi.detach().cpu()


class DoNothingPolicy(TensorDictModuleBase):
    """Full renewable output, no reactive power, idle storage: a = [PMAX gen…, 0…, 0…, 0…] MW/MVAr.

    P at PMAX makes the projection return the potential P_pot (no curtailment). For ANM6-Easy the action is
    [30, 50, 0, 0, 0, 0].
    """

    def __init__(self, sim: GridSimulator | None = None, in_key: str = "state"):
        super().__init__()
        sim, _, hi = _box(sim)
        self.in_keys, self.out_keys = [in_key], ["action"]
        a = torch.zeros(sim.action_dim, dtype=torch.float32)
        a[:sim.n_gen] = hi[:sim.n_gen].float()
        self.register_buffer("action_value", a)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        x = tensordict.get(self.in_keys[0])
        a = self.action_value.to(x.device).expand(*x.shape[:-1], self.action_value.numel()).clone()
        tensordict.set(self.out_keys[0], a)
        return tensordict


class RandomPolicy(TensorDictModuleBase):
    """Uniform actions over the action box, from its own seeded ``torch.Generator``.

    The same seed and the same sequence of calls (batch shapes) give the same actions.
    """

    def __init__(self, seed: int | None = None, sim: GridSimulator | None = None, in_key: str = "state"):
        super().__init__()
        sim, lo, hi = _box(sim)
        unbounded = unbounded_actions(sim)
        if unbounded:  # uniform draws in an infinite box are NaN
            raise ValueError(f"RandomPolicy draws uniformly in the action box, which is unbounded at "
                             f"{', '.join(unbounded)}: give those devices finite PMIN/PMAX/QMIN/QMAX")
        self.in_keys, self.out_keys = [in_key], ["action"]
        self.register_buffer("low", lo.double())
        self.register_buffer("high", hi.double())
        self.generator = torch.Generator()
        self.seed = seed
        self.reseed(seed)

    def reseed(self, seed: int | None) -> None:
        """Restart the action stream from ``seed`` (a fresh random seed when None)."""
        self.seed = seed
        if seed is None:
            self.generator.seed()
        else:
            self.generator.manual_seed(int(seed))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        x = tensordict.get(self.in_keys[0])
        u = torch.rand(*x.shape[:-1], self.low.numel(), generator=self.generator, dtype=torch.float64)
        a = (self.low + u * (self.high - self.low)).float()
        a = torch.minimum(torch.maximum(a, self.low.float()), self.high.float())
        tensordict.set(self.out_keys[0], a.to(x.device))
        return tensordict


def make_baseline(name: str, sim: GridSimulator | None = None, **kw) -> TensorDictModuleBase:
    """Build a baseline by name: ``do_nothing``, ``random`` (kw: ``seed``), ``mpc_perfect`` / ``mpc_constant``
    (kw: ``horizon``, ``safety_margin``, ``gamma``, ``backend``…, see :class:`MPCPolicy`), ``optimal`` (the
    perfect-foresight AC optimum, kw: ``horizon`` = episode length, ``warm_start``…, see
    :class:`~anm_torchrl.baselines.optimal.OptimalPolicy`) and ``acmpc`` (AC-MPC, kw: ``horizon``, ``forecast``…,
    see :class:`~anm_torchrl.baselines.acmpc.ACMPCPolicy`).

    ``sim`` defaults to the ANM6-Easy simulator; with an env, pass ``env.sim``.
    """
    if name == "do_nothing":
        return DoNothingPolicy(sim, **kw)
    if name == "random":
        return RandomPolicy(sim=sim, **kw)
    sim = network_simulator(ANM6_EASY) if sim is None else sim
    if name in ("mpc_perfect", "mpc_constant"):
        from anm_torchrl.baselines.mpc import MPCPolicy

        return MPCPolicy(sim, forecast=name.split("_")[1], **kw)
    if name == "optimal":
        from anm_torchrl.baselines.optimal import OptimalPolicy

        return OptimalPolicy(sim, **kw)
    if name == "acmpc":
        from anm_torchrl.baselines.acmpc import ACMPCPolicy

        return ACMPCPolicy(sim, **kw)
    raise ValueError(f"unknown baseline {name!r}; expected one of {BASELINES}")
