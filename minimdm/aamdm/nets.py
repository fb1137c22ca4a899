"""The networks of AAMDM's generation module (Qiao et al. 2024, §3.3; Xiao et al. 2022).

:class:`DDGANGenerator` is :math:`G^{GAN}(x^t, x_{n-1}, r, t) \\to \\hat x^0` (AAMDM eq. 10) and
:class:`DDGANDiscriminator` is :math:`D^{GAN}(x^{t-1}, x^t, x_{n-1}, t)` (eq. 12), both MLPs, with
optional random Fourier features of their inputs. :mod:`minimdm.aamdm.model` assembles them with the
polisher into the AAMDM sampler; :mod:`minimdm.aamdm.train` trains them.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

from minimdm.amdm.models import timestep_embedding
from minimdm.checkpoint import register_model_kind
from minimdm.nn import MLP

__all__ = [
    "FourierFeatures",
    "GeneratorConfig",
    "DDGANGenerator",
    "DiscriminatorConfig",
    "DDGANDiscriminator",
]


class FourierFeatures(nn.Module):
    """Random Fourier features :math:`[v, \\sin 2\\pi Bv, \\cos 2\\pi Bv]` (Tancik et al. 2020).

    ``B`` (in_dim, n) is drawn once from :math:`\\mathcal N(0, s^2)` with a fixed seed and
    stored as a buffer. An MLP fed raw coordinates learns smooth functions first (spectral
    bias); the sines let the discriminator resolve small, sharp modes and the generator map
    its noise onto them.
    """

    def __init__(self, in_dim: int, n: int, scale: float = 1.0, seed: int = 0) -> None:
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.register_buffer("B", torch.randn(in_dim, n, generator=g) * scale)
        self.out_dim = in_dim + 2 * n

    def forward(self, v: Tensor) -> Tensor:
        p = 2 * math.pi * v @ self.B  # (B, n)
        return torch.cat([v, p.sin(), p.cos()], dim=-1)


@dataclass
class GeneratorConfig:
    """Size of a :class:`DDGANGenerator`."""

    x_dim: int
    """Dimension of the sample (the embedded vector xz in AAMDM)."""
    cond_dim: int
    """Dimension of the condition, the previous sample x_{n-1}."""
    latent_dim: int = 8
    """Size of the latent noise r that makes each reverse step multimodal (eq. 10)."""
    width: int = 256
    """Hidden units per layer."""
    depth: int = 4
    """Fully connected layers including the output layer."""
    time_dim: int = 64
    """Size of the sinusoidal level embedding."""
    fourier: int = 0
    """Random Fourier features of x_t and of cond, each, fed beside them (0: none)."""
    fourier_scale: float = 1.0
    """Standard deviation of the Fourier frequencies, in cycles per unit of the input."""
    activation: str = "silu"
    """'silu' or 'mish' (AAMDM Figure 4 uses Mish for every network); in every MLP of the net."""


class DDGANGenerator(MLP):
    """:math:`G^{GAN}(x^t, x_{n-1}, r, t) \\to \\hat x^0` (AAMDM eq. 10).

    The A-MDM body (an :class:`~minimdm.nn.MLP`, SiLU by default). The latent ``r`` enters with
    the input and, like the level embedding, as a bias on every hidden layer, so that it cannot
    be ignored (the style-modulation of DD-GAN's generator, reduced to an MLP).
    """

    def __init__(self, config: GeneratorConfig) -> None:
        if config.depth < 2 or config.latent_dim < 1:
            raise ValueError(
                f"depth must be >= 2 and latent_dim >= 1, got {config.depth}, {config.latent_dim}"
            )
        c, w = config, config.width
        act = _check_activation(c.activation, ("silu", "mish"))
        time_mlp = MLP(c.time_dim, w, w, depth=2, activation=act, norm=False).sequential()
        latent_mlp = MLP(c.latent_dim, w, w, depth=2, activation=act, norm=False).sequential()
        x_features = FourierFeatures(c.x_dim, c.fourier, c.fourier_scale, 1)
        c_features = FourierFeatures(c.cond_dim, c.fourier if c.cond_dim else 0, c.fourier_scale, 2)
        in_dim = x_features.out_dim + (c_features.out_dim if c.cond_dim else 0)
        super().__init__(in_dim + c.latent_dim, c.x_dim, w, c.depth, activation=act)
        self.config = config
        self.time_mlp, self.latent_mlp = time_mlp, latent_mlp
        self.x_features, self.c_features = x_features, c_features

    def forward(self, x_t: Tensor, t: Tensor, cond: Tensor | None, r: Tensor) -> Tensor:
        c = self.config
        B = x_t.shape[0]
        _check_shape("x_t", x_t, (B, c.x_dim))
        _check_shape("r", r, (B, c.latent_dim))
        parts = [self.x_features(x_t), r]
        if c.cond_dim:
            _check_shape("cond", cond, (B, c.cond_dim))
            parts.insert(1, self.c_features(cond))
        v = torch.cat(parts, dim=-1)  # (B, x + c + 4F + latent)
        e = self.time_mlp(timestep_embedding(t, c.time_dim)) + self.latent_mlp(r)  # (B, W)
        return super().forward(v, add=e)  # (B, D)


@dataclass
class DiscriminatorConfig:
    """Size of a :class:`DDGANDiscriminator`."""

    x_dim: int
    """Dimension of the sample."""
    cond_dim: int
    """Dimension of the condition x_{n-1}."""
    width: int = 256
    """Hidden units per layer."""
    depth: int = 3
    """Fully connected layers including the output layer."""
    time_dim: int = 64
    """Size of the sinusoidal level embedding."""
    fourier: int = 0
    """Random Fourier features of x_{t-1}, x_t and cond, each, fed beside them (0: none)."""
    fourier_scale: float = 1.0
    """Standard deviation of the Fourier frequencies, in cycles per unit of the input."""
    activation: str = "leaky_relu"
    """Hidden layers: 'leaky_relu' (slope 0.2, the GAN habit; level MLP SiLU), 'silu' or 'mish'
    (AAMDM Figure 4: Mish for every network, the level MLP included)."""


class DDGANDiscriminator(MLP):
    """:math:`D^{GAN}(x^{t-1}, x^t, x_{n-1}, t)`: a logit, real pair vs generated pair (eq. 12).

    An :class:`~minimdm.nn.MLP` with LeakyReLU(0.2) by default and no normalisation (the usual GAN
    discriminator), the level embedding added to every hidden layer.
    """

    def __init__(self, config: DiscriminatorConfig) -> None:
        if config.depth < 2:
            raise ValueError(f"depth must be >= 2, got {config.depth}")
        c, w = config, config.width
        act = _check_activation(c.activation, ("leaky_relu", "silu", "mish"))
        time_act = (
            "silu" if act == "leaky_relu" else act
        )  # the level MLP: SiLU, or the paper's Mish
        time_mlp = MLP(c.time_dim, w, w, depth=2, activation=time_act, norm=False).sequential()
        # one set of frequencies for x_{t-1} and x_t (the same space), one for the condition
        x_features = FourierFeatures(c.x_dim, c.fourier, c.fourier_scale, 3)
        c_features = FourierFeatures(c.cond_dim, c.fourier if c.cond_dim else 0, c.fourier_scale, 4)
        in_dim = 2 * x_features.out_dim + (c_features.out_dim if c.cond_dim else 0)
        super().__init__(in_dim, 1, w, c.depth, activation=act, norm=False)
        self.config = config
        self.time_mlp = time_mlp
        self.x_features, self.c_features = x_features, c_features

    def forward(self, x_prev: Tensor, x_t: Tensor, cond: Tensor | None, t: Tensor) -> Tensor:
        c = self.config
        parts = [self.x_features(x_prev), self.x_features(x_t)]
        if c.cond_dim:
            parts.append(self.c_features(cond))
        e = self.time_mlp(timestep_embedding(t, c.time_dim))  # (B, W)
        return super().forward(torch.cat(parts, -1), add=e)[:, 0]  # (B,)


def _check_activation(value: str, allowed: tuple[str, ...]) -> str:
    """``value`` if it names an allowed activation, else a clear error."""
    if value not in allowed:
        raise ValueError(f"activation must be one of {allowed}, got {value!r}")
    return value


def _check_shape(name: str, x: Tensor | None, shape: tuple[int, ...]) -> None:
    if x is None or tuple(x.shape) != tuple(shape):
        got = None if x is None else tuple(x.shape)
        raise ValueError(f"{name} must have shape {tuple(shape)}, got {got}")


register_model_kind(
    "ddgan_generator",
    DDGANGenerator,
    lambda c: DDGANGenerator(GeneratorConfig(**c)),
    lambda m: asdict(m.config),
)
