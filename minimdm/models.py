"""Denoisers and baselines.

:class:`MLPDenoiser` is the A-MDM network (Shi et al. 2024, §3.2.1): the previous frame
:math:`x_{f-1}`, the noisy frame :math:`x_f^t` and a time embedding :math:`e^t` go through
fully connected layers, each followed by SiLU and LayerNorm; the output is the noise
:math:`\\hat\\epsilon` (eq. 3) or, optionally, the clean frame :math:`\\hat x_f^0`.
The same class, at a tiny size, is the denoiser of the Squ-9 toy.

:class:`MLPRegressor` is the deterministic baseline: one frame in, the next frame out, trained
with MSE. It is the one-to-one mapping that collapses multimodal futures to their mean.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

__all__ = ["DenoiserConfig", "MLPDenoiser", "MLPRegressor", "timestep_embedding"]


def timestep_embedding(t: Tensor, dim: int, max_period: float = 10_000.0) -> Tensor:
    """Sinusoidal embedding of integer steps ``t`` (B,) -> (B, dim) (Vaswani et al. 2017)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device) / half)
    args = t.float()[:, None] * freqs[None]  # (B, half)
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    if dim % 2:
        emb = torch.cat([emb, torch.zeros_like(emb[:, :1])], dim=-1)
    return emb


@dataclass
class DenoiserConfig:
    """Size and output of an :class:`MLPDenoiser`."""

    x_dim: int
    """Dimension D of one frame (the noisy input and the output)."""
    cond_dim: int
    """Dimension of the condition, the previous frame x_{f-1} (0 for none)."""
    width: int = 1024
    """Hidden units per layer (A-MDM: 1024)."""
    depth: int = 10
    """Number of fully connected layers including the output layer (A-MDM: 10)."""
    time_dim: int = 128
    """Size of the sinusoidal time embedding e^t before its MLP."""
    predicts: str = "eps"
    """What the network outputs: 'eps' (A-MDM eq. 3) or 'x0'."""


class MLPDenoiser(nn.Module):
    """The A-MDM denoiser :math:`p_\\theta(x_{f-1}, x_f^t, e^t)`.

    ``forward(x_t, t, cond)`` takes ``x_t`` (B, D), integer steps ``t`` (B,) and the previous
    frame ``cond`` (B, C); it returns (B, D). The time embedding is added to every hidden layer
    so that the step is seen throughout the network.
    """

    def __init__(self, config: DenoiserConfig) -> None:
        super().__init__()
        if config.depth < 2:
            raise ValueError(f"depth must be >= 2 (one hidden and one output layer), got {config.depth}")
        if config.predicts not in ("eps", "x0"):
            raise ValueError(f"predicts must be 'eps' or 'x0', got {config.predicts!r}")
        self.config = config
        self.predicts = config.predicts
        w = config.width
        self.time_mlp = nn.Sequential(
            nn.Linear(config.time_dim, w), nn.SiLU(), nn.Linear(w, w)
        )
        self.input = nn.Linear(config.x_dim + config.cond_dim, w)
        self.hidden = nn.ModuleList(nn.Linear(w, w) for _ in range(config.depth - 2))
        self.norms = nn.ModuleList(nn.LayerNorm(w) for _ in range(config.depth - 1))
        self.output = nn.Linear(w, config.x_dim)

    def forward(self, x_t: Tensor, t: Tensor, cond: Tensor | None = None) -> Tensor:
        c = self.config
        if x_t.dim() != 2 or x_t.shape[1] != c.x_dim:
            raise ValueError(f"x_t must have shape (B, {c.x_dim}), got {tuple(x_t.shape)}")
        if c.cond_dim:
            if cond is None or cond.shape != (x_t.shape[0], c.cond_dim):
                got = None if cond is None else tuple(cond.shape)
                raise ValueError(f"cond must have shape ({x_t.shape[0]}, {c.cond_dim}), got {got}")
            h = torch.cat([x_t, cond], dim=-1)
        else:
            h = x_t
        e = self.time_mlp(timestep_embedding(t, c.time_dim))  # (B, W)
        h = self.norms[0](nn.functional.silu(self.input(h) + e))  # (B, W)
        for layer, norm in zip(self.hidden, self.norms[1:], strict=True):
            h = norm(nn.functional.silu(layer(h) + e))
        return self.output(h)  # (B, D)

    def config_dict(self) -> dict:
        return asdict(self.config)


class MLPRegressor(nn.Module):
    """Deterministic next-frame regressor ``x_{f-1} -> x_f`` (the MSE baseline).

    Same body as :class:`MLPDenoiser` (SiLU then LayerNorm), no noise input and no time step.
    """

    def __init__(self, x_dim: int, cond_dim: int, width: int = 256, depth: int = 4) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        d = cond_dim
        for _ in range(depth - 1):
            layers += [nn.Linear(d, width), nn.SiLU(), nn.LayerNorm(width)]
            d = width
        layers.append(nn.Linear(d, x_dim))
        self.net = nn.Sequential(*layers)
        self.x_dim, self.cond_dim = x_dim, cond_dim

    def forward(self, cond: Tensor) -> Tensor:
        if cond.dim() != 2 or cond.shape[1] != self.cond_dim:
            raise ValueError(f"cond must have shape (B, {self.cond_dim}), got {tuple(cond.shape)}")
        return self.net(cond)
