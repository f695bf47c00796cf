"""Building blocks shared by the PINN modules: the residual MLP and input normalisation by a known box."""

from __future__ import annotations

import torch
from torch import nn

from anm_torchrl.surrogates.pinn.presets import ACTIVATIONS


def make_activation(name: str, negative_slope: float = 0.01) -> nn.Module:
    """``leaky_relu`` (slope ``negative_slope``, the paper's 0.01), ``silu``, ``tanh``, ``gelu`` or ``relu``."""
    if name == "leaky_relu":
        return nn.LeakyReLU(negative_slope)
    if name == "silu":
        return nn.SiLU()
    if name == "tanh":
        return nn.Tanh()
    if name == "gelu":
        return nn.GELU()
    if name == "relu":
        return nn.ReLU()
    raise ValueError(f"activation must be one of {ACTIVATIONS}, got {name!r}")


class ResidualMLP(nn.Module):
    """``y = skip(x) + MLP(x)``: an MLP of ``depth`` hidden layers of width ``hidden`` plus a linear input→output
    connection (the paper's "residual connection between the inputs and outputs", §5.1).

    Args:
        in_dim, out_dim: feature sizes.
        hidden: hidden width (paper: 512).
        depth: number of hidden layers (paper: 3).
        activation: see :func:`make_activation` (paper: ``leaky_relu`` with slope 0.01).
        out_scale: the last layer's initial weights are multiplied by this (small outputs at initialisation,
            so a module starts close to its skip path).
    """

    def __init__(self, in_dim: int, out_dim: int, hidden: int = 512, depth: int = 3, activation: str = "leaky_relu",
                 out_scale: float = 1.0):
        super().__init__()
        layers: list[nn.Module] = []
        d = in_dim
        for _ in range(depth):
            layers += [nn.Linear(d, hidden), make_activation(activation)]
            d = hidden
        layers.append(nn.Linear(d, out_dim))
        self.body = nn.Sequential(*layers)
        self.skip = nn.Linear(in_dim, out_dim)
        self.out_scale = out_scale
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """PyTorch's default initialisation, then the output layer and the skip scaled by ``out_scale``, biases 0."""
        for layer in self.modules():
            if isinstance(layer, nn.Linear):
                layer.reset_parameters()
        with torch.no_grad():
            for last in (self.body[-1], self.skip):
                last.weight.mul_(self.out_scale)
                last.bias.zero_()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.skip(x) + self.body(x)


def box_normalise(x: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """Map ``x`` from the box [low, high] to [-1, 1] (entries with ``high == low`` map to 0)."""
    width = torch.where(high > low, high - low, torch.ones_like(high))
    return torch.where(high > low, 2 * (x - low) / width - 1, torch.zeros_like(x))
