"""KKT-informed neural networks (KKT-NN, Delle Femine 2024) for the device projections of ANM6-Easy.

gym-anm maps a set-point ``t = (a_P, a_Q)`` (p.u.) of a controllable device onto its feasible set by the
projection ``x* = argmin ½‖x − t‖²  s.t.  G x ≤ h(θ)`` (spec §3.3), where ``G`` is fixed per device and only
``h`` depends on a parameter θ: the potential ``P_pot`` for a renewable generator (7 rows) and the state of
charge ``SoC`` for the storage unit (10 rows). A KKT-NN learns ``(t, θ) ↦ (x*, λ*)`` from the KKT conditions
alone (losses in :mod:`anm_torchrl.surrogates.pinn.losses`), with no solved example.

Design (both modules):

* **Units.** Every device is worked on in units of its rating ``S = max(|PMIN|, PMAX, |QMIN|, QMAX)`` (p.u.):
  a uniform scaling leaves the Euclidean projection unchanged (``x̃ = x/S``, ``h̃ = h/S``, ``λ̃ = λ/S``), so
  every device's problem lives in [−1, 1]² and the losses have the same scale for all devices.
* **Inputs** are normalised by their known boxes (Appendix A of the paper): a_P ∈ [PMIN, PMAX], a_Q ∈ [QMIN,
  QMAX], P_pot ∈ [PMIN, PMAX], SoC ∈ [SOC_MIN, SOC_MAX], each mapped to [−1, 1].
* **Primal head** with the paper's residual input→output connection: ``x̃ = t̃ + Δ(t, θ)``. Two optional
  structural facts of the projection (both on in the ``default`` preset, off in ``paper``):

  - ``gated``: ``x̃ = t̃ + v(t̃)·Δ`` with ``v`` the set-point's largest constraint violation
    ``max_j (G t̃ − h̃)_j⁺`` (a residual, not a solve): a feasible set-point maps to itself exactly (it is its
    own projection), and ``‖x* − t‖`` is at most proportional to ``v`` (Hoffman), so Δ stays bounded. This
    removes the smooth network's error at the kinks of the projection, where expert policies sit (e.g. P
    set-point = P_pot).
  - ``hard_constraints``: the losses see ``clamp_to_polygon(x̃)`` (below), so the primal is feasible by
    construction (the KKT-NN authors bound P and Q by construction with sigmoid/tanh; this is the polygon
    version) and primal feasibility is identically 0.
* **Dual head**: ``λ̃ = softplus(z − 4)`` (or ``relu``), so dual feasibility λ ≥ 0 holds by construction; the
  shift starts every multiplier near 0. ``separate_dual`` uses a second network for λ; ``dual_gate = δ``
  multiplies λ_j by ``exp(min(s_j, 0)/δ)`` with ``s_j = (G x̃ − h̃)_j`` (x̃ detached), i.e. complementary
  slackness by construction. Without the gate, a KKT-NN can sit in a spurious near-stationary point where the
  multiplier of an *inactive* row (e.g. P ≤ P_pot) explains a wrong, horizontal move onto a capability line
  (complementarity residual only ~1e-2); with it the generator MAE fell from 5e-4 to 2e-6 p.u. (train.py).
* **Exact-feasibility safeguard** at inference (``safeguard=True``, a no-op with ``hard_constraints``):
  :func:`clamp_to_polygon` clamps P to the rows that involve P only (box, P_pot, SoC rows), then Q to the
  interval the remaining rows allow at that P. For the generator and storage polygons of gym-anm this
  interval is never empty, so the output is feasible to round-off; where the raw output was already
  feasible the clamp is the identity, where it was not it moves the point onto the violated boundary.
  It is not the projection: where a capability line binds, the projection moves diagonally.
* Networks in float32, the device physics (``G``, ``h``, clamp, gates) in float64.

Generators: **one network shared by all renewable generators, conditioned on device parameters.** Both
generators' sets belong to the same 7-row family (box ∩ P ≤ P_pot ∩ two capability lines) and, in rating
units, differ only in their corner (P⁺, Q⁺, Q⁻): the network receives the device's normalised polygon (the
finite rows of ``h̃`` and the slopes τ₁, τ₂) next to (a_P, a_Q, P_pot). One network runs the whole
(N·n_gen) batch in one pass, has half the parameters of two, learns the part the devices share (clipping to
the box and to P_pot) once, and extends to other generators of the family without a new class.
The storage unit (10 rows, SoC-dependent) has its own network of the same design.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from anm_torchrl.grid import devices as dv
from anm_torchrl.grid.residuals import constraint_slack
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.surrogates.pinn.nets import ResidualMLP, box_normalise
from anm_torchrl.surrogates.pinn.presets import DUAL_ACTIVATIONS

DUAL_SHIFT = -4.0  # softplus(-4) ≈ 0.018: multipliers start near zero


def clamp_to_polygon(x: torch.Tensor, g: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """Move ``x`` (..., 2) = (P, Q) into ``{G x ≤ h}`` by clamping P, then Q.

    P is clamped to the interval allowed by the rows with no Q coefficient; Q to the interval the other rows
    allow at that P (``g_Q Q ≤ h − g_P P``). Exact (to round-off) whenever that Q interval is non-empty for
    every P of the P interval — true for the gym-anm generator and storage polygons, whose capability lines
    stay above Q⁺ > 0 and below Q⁻ < 0 over [PMIN, PMAX]. The identity on feasible points.

    Args:
        x: (..., 2) points.
        g: (..., m, 2) constraint normals; h: (..., m) right-hand sides (broadcast against ``x``).
    """
    gp, gq = g[..., 0], g[..., 1]
    inf = torch.full_like(h, float("inf"))
    pure = gq == 0
    bound_p = h / torch.where(pure & (gp != 0), gp, torch.ones_like(gp))
    p_hi = torch.where(pure & (gp > 0), bound_p, inf).amin(-1)
    p_lo = torch.where(pure & (gp < 0), bound_p, -inf).amax(-1)
    p = torch.minimum(torch.maximum(x[..., 0], p_lo), p_hi)
    bound_q = (h - gp * p.unsqueeze(-1)) / torch.where(pure, torch.ones_like(gq), gq)
    q_hi = torch.where(~pure & (gq > 0), bound_q, inf).amin(-1)
    q_lo = torch.where(~pure & (gq < 0), bound_q, -inf).amax(-1)
    q = torch.minimum(torch.maximum(x[..., 1], q_lo), q_hi)
    return torch.stack([p, q], -1)


def _device_features(g: torch.Tensor, h0: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Conditioning features (n, k) of each device's polygon in rating units: finite rows of h0/S, then the
    slopes of the rows that involve both P and Q. Which rows are finite is the same for every device of a kind
    (checked), so a network of that kind takes the same features on any feeder; no device: (0, 0)."""
    if h0.shape[0] == 0:
        return h0.new_zeros(0, 0)
    finite = torch.isfinite(h0[0])
    if not torch.equal(torch.isfinite(h0), finite.expand_as(h0)):
        raise ValueError(f"every device of a kind needs the same finite polygon rows (gym-anm's bounds given); "
                         f"got finite rows {torch.isfinite(h0).int().tolist()}")
    both = (g[0, :, 0] != 0) & (g[0, :, 1] != 0)
    slopes = -g[:, both, 0] / g[:, both, 1]
    return torch.cat([h0[:, finite] / scale.unsqueeze(1), slopes], 1)


class _ProjectionKKT(nn.Module):
    """Shared machinery of the generator and storage KKT-NNs (see the module docstring).

    Subclasses call :meth:`_setup` (buffers ``g`` (n, m, 2), ``h0`` (n, m), ``scale`` (n,), ``in_low``/``in_high``
    (n, 3): boxes of a_P, a_Q, θ in p.u., ``cond`` (n, k)) and :meth:`_build_net`, and implement :meth:`rhs`.
    """

    def _setup(self, dev: torch.Tensor, g: torch.Tensor, h0: torch.Tensor, theta_low: torch.Tensor,
               theta_high: torch.Tensor, safeguard: bool, hard_constraints: bool, gated: bool, dual_gate: float) -> None:
        """Buffers of the devices ``dev`` (n, 15) p.u. with polygons ``g``/``h0`` and parameter box θ ∈ [low, high]."""
        self.hard_constraints, self.gated, self.dual_gate = hard_constraints, gated, float(dual_gate)
        self.safeguard = safeguard
        scale = torch.stack([dev[:, dv.PMAX].abs(), dev[:, dv.PMIN].abs(), dev[:, dv.QMAX].abs(),
                             dev[:, dv.QMIN].abs()], 1).amax(1)
        self.register_buffer("g", g.clone(), persistent=False)
        self.register_buffer("h0", h0.clone(), persistent=False)
        self.register_buffer("scale", scale, persistent=False)
        self.register_buffer("in_low", torch.stack([dev[:, dv.PMIN], dev[:, dv.QMIN], theta_low], 1),
                             persistent=False)
        self.register_buffer("in_high", torch.stack([dev[:, dv.PMAX], dev[:, dv.QMAX], theta_high], 1),
                             persistent=False)
        self.register_buffer("cond", _device_features(g, h0, scale), persistent=False)

    def _build_net(self, hidden: int, depth: int, activation: str, dual_activation: str,
                   separate_dual: bool = False) -> None:
        if dual_activation not in DUAL_ACTIVATIONS:
            raise ValueError(f"dual_activation must be one of {DUAL_ACTIVATIONS}, got {dual_activation!r}")
        self.dual_activation = dual_activation
        m, n_in = self.g.shape[1], 3 + self.cond.shape[1]
        kw = dict(hidden=hidden, depth=depth, activation=activation, out_scale=0.1)
        if separate_dual:  # a primal network and a dual network
            self.net = ResidualMLP(n_in, 2, **kw)
            self.dual_net = ResidualMLP(n_in, m, **kw)
        else:  # one network with a primal and a dual head (the KKT-NN paper)
            self.net = ResidualMLP(n_in, 2 + m, **kw)
            self.dual_net = None

    @property
    def n_rows(self) -> int:
        return self.g.shape[1]

    def rhs(self, theta: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        """Right-hand sides h (N, n, m) p.u. for the parameter θ (N, n)."""
        raise NotImplementedError

    def predict_scaled(self, target: torch.Tensor, theta: torch.Tensor, duals: bool = True) -> dict[str, torch.Tensor]:
        """The raw network prediction in rating units, for the losses.

        Args:
            target: (N, n, 2) set-points (P, Q) p.u.; theta: (N, n) parameter (P_pot p.u. / SoC p.u.·h).
            duals: also predict the multipliers (``False`` skips the dual network: inference needs only x).

        Returns:
            ``x`` (N, n, 2) raw primal, ``lam`` (N, n, m) duals ≥ 0 (with ``duals``), ``target`` (N, n, 2), ``h``
            (N, n, m) and ``g`` (n, m, 2) — all float64, in rating units (divided by the device's ``scale``). With
            ``hard_constraints`` the primal is already clamped into the polygon.
        """
        s = self.scale.unsqueeze(-1)
        dtype = self.net.skip.weight.dtype
        feats = torch.cat([box_normalise(target, self.in_low[:, :2], self.in_high[:, :2]),
                           box_normalise(theta, self.in_low[:, 2], self.in_high[:, 2]).unsqueeze(-1),
                           self.cond.expand(*theta.shape, -1)], -1)
        feats = feats.to(dtype)
        out = self.net(feats).to(torch.float64)
        t = target / s
        h = self.rhs(theta) / s
        if self.gated:  # correction per unit of the target's largest violation: x = t exactly on the set
            viol = torch.relu(constraint_slack(t, self.g, h)).amax(-1, keepdim=True)
            x = t + viol * out[..., :2]
        else:
            x = t + out[..., :2]
        if self.hard_constraints:
            x = clamp_to_polygon(x, self.g, h)
        pred = {"x": x, "target": t, "h": h, "g": self.g}
        if duals:
            pred["lam"] = self._duals(feats, out, x, h)
        return pred

    def _duals(self, feats: torch.Tensor, out: torch.Tensor, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """Multipliers (N, n, m) ≥ 0 in rating units from the dual head (or network) and the activity gate."""
        z = (out[..., 2:] if self.dual_net is None else self.dual_net(feats).to(torch.float64)) + DUAL_SHIFT
        # the floor keeps collapsed multipliers (~1e-13) out of the float64 denormal range, which is very slow on CPU
        lam = F.softplus(z.clamp(min=-30.0)) if self.dual_activation == "softplus" else torch.relu(z)
        if self.dual_gate > 0:  # complementary slackness by construction: λ_j → 0 off the boundary of row j
            slack = constraint_slack(x.detach(), self.g, h).clamp(max=0.0)
            lam = lam * torch.exp((slack / self.dual_gate).clamp(min=-20.0))  # floor: no denormals in backward
        return lam

    def forward(self, target: torch.Tensor, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Projected (P, Q) (N, n, 2) p.u. (safeguarded if ``self.safeguard``) and duals λ (N, n, m) of
        ``min ½‖x − t‖²`` in p.u."""
        return self._project(target, theta, duals=True)

    def project(self, target: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """Projected (P, Q) (N, n, 2) p.u. alone, as :meth:`forward`'s first output, without the dual network."""
        return self._project(target, theta, duals=False)

    def _project(self, target: torch.Tensor, theta: torch.Tensor, duals: bool):
        shape = target.shape
        if shape[-2] == 0:  # a network without devices of this kind
            x = target.new_zeros(shape, dtype=torch.float64)
            return (x, target.new_zeros(*shape[:-1], self.n_rows, dtype=torch.float64)) if duals else x
        target = target.reshape(-1, *shape[-2:]).to(torch.float64)
        theta = theta.reshape(-1, shape[-2]).to(torch.float64)
        pred = self.predict_scaled(target, theta, duals=duals)
        x = pred["x"]
        if self.safeguard and not self.hard_constraints:  # with hard constraints x is in the polygon already
            x = clamp_to_polygon(x, pred["g"], pred["h"])
        s = self.scale.unsqueeze(-1)
        x = (x * s).reshape(shape)
        return (x, (pred["lam"] * s).reshape(*shape[:-1], self.n_rows)) if duals else x


class PrimalProjection(nn.Module):
    """A KKT-NN's projection alone (:meth:`_ProjectionKKT.project`): ``(target, theta) -> pq``, the inference
    chain's module when the multipliers are not asked for (the dual network is a training device)."""

    def __init__(self, kkt: _ProjectionKKT):
        super().__init__()
        self.kkt = kkt

    def forward(self, target: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        return self.kkt.project(target, theta)


class GeneratorKKT(_ProjectionKKT):
    """KKT-NN of the renewable generators' projections: (a_P, a_Q, P_pot) → (P, Q), λ ∈ R⁷₊ per generator.

    One network shared by all generators, conditioned on each device's normalised polygon (module docstring).

    Args:
        sim: the simulator (network, generator polygons).
        hidden, depth, activation: the :class:`ResidualMLP`.
        dual_activation: ``"softplus"`` (default) or ``"relu"``.
        safeguard: clamp the output into the polygon (:func:`clamp_to_polygon`) at inference.
        hard_constraints: clamp inside the network too, so the losses see the clamped primal (feasibility by
            construction; the primal-feasibility loss is then identically 0).
        gated: scale the primal correction by the target's largest constraint violation (the projection is the
            identity on the feasible set, and ‖x* − t‖ is at most proportional to the violation).
        separate_dual: a separate network for the duals (else one network with two heads).
        dual_gate: δ > 0 multiplies each λ_j by exp(min(s_j, 0)/δ), s_j = (G x − h)_j in rating units (x
            detached): a multiplier fades off its constraint's boundary (complementary slackness by construction).

    ``forward(target (N, n_gen, 2) p.u., p_pot (N, n_gen) p.u.) -> (pq (N, n_gen, 2) p.u., lam (N, n_gen, 7))``.
    """

    def __init__(self, sim: GridSimulator, hidden: int = 128, depth: int = 3, activation: str = "silu",
                 dual_activation: str = "softplus", safeguard: bool = True, hard_constraints: bool = False,
                 gated: bool = False, separate_dual: bool = False, dual_gate: float = 0.0):
        super().__init__()
        dev = sim.net.dev[sim.gen_ids]
        self._setup(dev, sim.gen_g, sim.gen_h0, dev[:, dv.PMIN], dev[:, dv.PMAX], safeguard, hard_constraints, gated,
                    dual_gate)
        self._build_net(hidden, depth, activation, dual_activation, separate_dual)

    def rhs(self, theta: torch.Tensor) -> torch.Tensor:
        return dv.generator_h(self.h0, theta)


class StorageKKT(_ProjectionKKT):
    """KKT-NN of the storage projection: (a_P, a_Q, SoC) → (P, Q), λ ∈ R¹⁰₊ per storage unit.

    Args:
        sim: the simulator (network, storage polygon, Δt, efficiency).
        hidden, depth, activation, dual_activation, safeguard, hard_constraints, gated, separate_dual,
            dual_gate: as :class:`GeneratorKKT`.

    ``forward(target (N, n_des, 2) p.u., soc (N, n_des) p.u.·h) -> (pq (N, n_des, 2) p.u., lam (N, n_des, 10))``.
    """

    def __init__(self, sim: GridSimulator, hidden: int = 128, depth: int = 3, activation: str = "silu",
                 dual_activation: str = "softplus", safeguard: bool = True, hard_constraints: bool = False,
                 gated: bool = False, separate_dual: bool = False, dual_gate: float = 0.0):
        super().__init__()
        self.sim = sim
        dev = sim.net.dev[sim.des_ids]
        self._setup(dev, sim.des_g, sim.des_h0, dev[:, dv.SOC_MIN], dev[:, dv.SOC_MAX], safeguard, hard_constraints,
                    gated, dual_gate)
        self._build_net(hidden, depth, activation, dual_activation, separate_dual)

    def rhs(self, theta: torch.Tensor) -> torch.Tensor:
        return self.sim.storage_h(theta)


def projection_net(module: nn.Module) -> _ProjectionKKT:
    """The KKT-NN of a chain's projection module (the module itself, or the one a :class:`PrimalProjection` wraps)."""
    return module.kkt if isinstance(module, PrimalProjection) else module
