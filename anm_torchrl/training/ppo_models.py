"""PPO networks for any env of the package: a bounded ``TanhNormal`` actor, a value network, fixed observation
normalisation.

Everything is built from the env's specs only (``observation`` bounds and ``action`` box), so the same factory
serves the true simulator, gym-anm and every surrogate.

Observation normalisation uses *fixed* statistics from the ``observation`` ``Bounded`` spec (no running
statistics: nothing to synchronise between collector workers, nothing that drifts between training on a surrogate
and evaluating on the true simulator): ``loc`` = centre of the box, ``scale`` = its half-width, capped at
``max_scale``. The cap matters for ANM6-Easy: the slack generator's P/Q bounds are a loose ±200 MW/MVAr, while
in practice they stay within about ±100 (−Σ of the other devices' ranges); an uncapped scale of 200 would squash
the slack, which carries the grid's net balance, into ±0.5. With ``max_scale=50`` it spans about ±2. Normalised
values are clipped to ±``clip``.
"""

from __future__ import annotations

import torch
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from torch import nn
from torchrl.data import Bounded
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator

ACTIVATIONS = {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU, "leaky_relu": nn.LeakyReLU, "silu": nn.SiLU}


class ObservationNormalizer(nn.Module):
    """``clamp((x - loc) / scale, -clip, clip)`` with fixed buffers ``loc``, ``scale`` (obs_dim,).

    The buffers travel in the actor's and critic's ``state_dict``, so a saved policy normalises by itself.
    """

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor, clip: float = 5.0):
        super().__init__()
        loc, scale = torch.as_tensor(loc, dtype=torch.float32), torch.as_tensor(scale, dtype=torch.float32)
        if loc.shape != scale.shape or loc.ndim != 1:
            raise ValueError(f"loc and scale must be 1-D of equal shape, got {tuple(loc.shape)}, {tuple(scale.shape)}")
        if not (torch.isfinite(loc).all() and torch.isfinite(scale).all() and (scale > 0).all()):
            raise ValueError(f"normalisation statistics must be finite with scale > 0; got loc {loc.tolist()}, "
                             f"scale {scale.tolist()}")
        self.register_buffer("loc", loc)
        self.register_buffer("scale", scale)
        self.clip = float(clip)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return ((x - self.loc) / self.scale).clamp(-self.clip, self.clip)

    def stats(self) -> dict[str, torch.Tensor]:
        """``{"loc", "scale"}`` copies (for checkpoints)."""
        return {"loc": self.loc.detach().clone(), "scale": self.scale.detach().clone()}


def observation_stats(spec: Bounded, max_scale: float | None = 50.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Centre and half-width (capped at ``max_scale``) of an unbatched ``Bounded`` observation spec (obs_dim,).

    Entries with a non-finite bound or zero width get loc 0 (or the finite centre) and scale 1.
    """
    low, high = spec.space.low.to(torch.float64), spec.space.high.to(torch.float64)
    while low.ndim > 1:  # a batched spec: every row has the same bounds
        low, high = low[0], high[0]
    finite = torch.isfinite(low) & torch.isfinite(high)
    loc = torch.where(finite, (low + high) / 2, torch.zeros_like(low))
    scale = torch.where(finite, (high - low) / 2, torch.ones_like(low))
    if max_scale is not None:
        scale = scale.clamp(max=float(max_scale))
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    return loc.float(), scale.float()


def initial_mean_bias(action: torch.Tensor, low: torch.Tensor, high: torch.Tensor, clip: float) -> torch.Tensor:
    """Pre-tanh bias (A,) that makes the actor's deterministic action (its ``TanhNormal`` mean mapped into the box,
    ``low + (high - low)(1 + tanh(b)) / 2``) equal ``action`` (A,), with ``|tanh(b)|`` capped at ``clip`` < 1
    (a target on the box's edge would need an infinite bias; ``clip`` = 0.98 puts it 1 % of the width inside).

    Raises:
        ValueError: shapes differ, ``clip`` is not in (0, 1), or ``action`` lies outside [low, high].
    """
    action, low, high = (torch.as_tensor(x, dtype=torch.float64) for x in (action, low, high))
    if not action.shape == low.shape == high.shape or action.ndim != 1:
        raise ValueError(f"action, low and high must be 1-D of equal shape, got {tuple(action.shape)}, "
                         f"{tuple(low.shape)}, {tuple(high.shape)}")
    if not 0.0 < float(clip) < 1.0:
        raise ValueError(f"clip must be in (0, 1), got {clip}")
    if ((action < low) | (action > high)).any():
        raise ValueError(f"initial action {action.tolist()} lies outside the action box [{low.tolist()}, "
                         f"{high.tolist()}]")
    u = (2 * (action - low) / (high - low) - 1).clamp(-float(clip), float(clip))
    return torch.atanh(u).float()


def _initial_action(env: EnvBase, init_action: torch.Tensor | str | None) -> torch.Tensor | None:
    """``make_ppo_models``' ``init_action`` as an action tensor (A,) MW/MVAr, or None for the box centre."""
    if init_action is None or isinstance(init_action, torch.Tensor):
        return init_action
    if init_action == "center":
        return None
    if init_action != "do_nothing":
        raise ValueError(f"init_action must be 'center', 'do_nothing', an action tensor or None; got {init_action!r}")
    from torchrl.envs import TransformedEnv

    from anm_torchrl.baselines.simple import DoNothingPolicy

    sim = getattr(env.base_env if isinstance(env, TransformedEnv) else env, "sim", None)
    if sim is None:
        raise ValueError(f"init_action='do_nothing' needs an env with a simulator (.sim), got {type(env).__name__}")
    return DoNothingPolicy(sim).action_value


def _unbatched(spec, key: str):
    spec = spec[key] if key in spec.keys() else spec
    return spec[(0,) * (spec.ndim - 1)] if spec.ndim > 1 else spec


def make_ppo_models(env: EnvBase, actor_cells=(64, 64), critic_cells=(64, 64), activation: str = "tanh",
                    max_obs_scale: float | None = 50.0, obs_clip: float = 5.0, init_log_std: float = -2.0,
                    obs_stats: dict[str, torch.Tensor] | None = None, obs_key: str = "observation",
                    init_action: torch.Tensor | str | None = None, init_action_clip: float = 0.98,
                    ) -> tuple[ProbabilisticActor, ValueOperator, ObservationNormalizer]:
    """Actor, critic and observation normaliser for ``env``.

    Args:
        env: any env of the package (only its ``observation`` / ``action`` specs are read).
        actor_cells, critic_cells: hidden layer widths of the two MLPs (separate networks, as SB3's MlpPolicy).
        activation: one of :data:`ACTIVATIONS`.
        max_obs_scale: cap on the normalisation half-width (see the module docstring); None for no cap.
        obs_clip: clip of the normalised observation.
        init_log_std: initial state-independent log standard deviation of the pre-tanh Gaussian.
        obs_stats: ``{"loc", "scale"}`` to use instead of the spec's (e.g. from a checkpoint).
        obs_key: observation key read by both networks.
        init_action: the untrained policy's deterministic action: None or ``"center"`` (bias 0, the centre of the
            box), ``"do_nothing"`` (the do-nothing action of ``env``'s simulator ``env.sim``: renewables at their
            maximum, no reactive power, storage idle) or an (A,) action in MW/MVAr; the last layer's bias is set by
            :func:`initial_mean_bias` (the weights are drawn identically either way).
        init_action_clip: ``clip`` of :func:`initial_mean_bias`.

    Returns:
        ``actor``: ``ProbabilisticActor`` writing ``"action"`` (…, A) within the action box (a ``TanhNormal``
        scaled to [low, high]; deterministic mode = its mean) and ``"action_log_prob"``;
        ``critic``: ``ValueOperator`` writing ``"state_value"``; ``normalizer``: the shared normaliser module.
    """
    init_action = _initial_action(env, init_action)
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
    obs_spec = _unbatched(env.observation_spec, obs_key)
    act_spec = _unbatched(env.full_action_spec, "action")
    if obs_stats is None:
        if not isinstance(obs_spec, Bounded):
            raise ValueError(f"observation spec {obs_key!r} must be Bounded to derive normalisation statistics, got "
                             f"{type(obs_spec).__name__}; pass obs_stats")
        loc, scale = observation_stats(obs_spec, max_obs_scale)
    else:
        loc, scale = obs_stats["loc"], obs_stats["scale"]
    normalizer = ObservationNormalizer(loc, scale, obs_clip)
    obs_dim, act_dim = int(obs_spec.shape[-1]), int(act_spec.shape[-1])
    act = ACTIVATIONS[activation]

    actor_mlp = MLP(in_features=obs_dim, out_features=act_dim, num_cells=list(actor_cells), activation_class=act)
    critic_mlp = MLP(in_features=obs_dim, out_features=1, num_cells=list(critic_cells), activation_class=act)
    for mlp, last_gain in ((actor_mlp, 0.01), (critic_mlp, 1.0)):  # orthogonal init, small last actor layer
        layers = [m for m in mlp.modules() if isinstance(m, nn.Linear)]
        for i, layer in enumerate(layers):
            nn.init.orthogonal_(layer.weight, last_gain if i == len(layers) - 1 else 2 ** 0.5)
            nn.init.zeros_(layer.bias)
    low, high = act_spec.space.low.float(), act_spec.space.high.float()
    if init_action is not None:
        last = [m for m in actor_mlp.modules() if isinstance(m, nn.Linear)][-1]
        with torch.no_grad():
            last.bias.copy_(initial_mean_bias(init_action, low, high, init_action_clip))

    policy_net = nn.Sequential(normalizer, actor_mlp,
                               AddStateIndependentNormalScale(act_dim, scale_lb=1e-4, init_value=float(init_log_std)))
    actor = ProbabilisticActor(
        TensorDictModule(policy_net, in_keys=[obs_key], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        spec=act_spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": low, "high": high, "tanh_loc": False},
        return_log_prob=True,
        default_interaction_type=ExplorationType.RANDOM,
    )
    critic = ValueOperator(nn.Sequential(normalizer, critic_mlp), in_keys=[obs_key])
    return actor, critic, normalizer
