"""Denoisers and baselines.

:class:`MLPDenoiser` is the A-MDM network (Shi et al. 2024, §3.2.1): the previous frame
:math:`x_{f-1}`, the noisy frame :math:`x_f^t` and a time embedding :math:`e^t` go through
fully connected layers, each followed by SiLU and LayerNorm; the output is the noise
:math:`\\hat\\epsilon` (eq. 3) or, optionally, the clean frame :math:`\\hat x_f^0`.
The same class, at a tiny size, is the denoiser of the Squ-9 toy.

:class:`MLPRegressor` is the deterministic baseline: one frame in, the next frame out, trained
with MSE. It is the one-to-one mapping that collapses multimodal futures to their mean.

:class:`MVAE` is the MVAE-style conditional VAE baseline (Ling et al. 2020): a latent z drawn
from a Gaussian prior, decoded with the previous frame into the next one.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

from minimdm.checkpoint import register_model_kind
from minimdm.diffusion.schedule import PREDICTS
from minimdm.nn import MLP

__all__ = [
    "DenoiserConfig",
    "MLPDenoiser",
    "MLPRegressor",
    "MVAEConfig",
    "MVAE",
    "timestep_embedding",
    "skip_weights",
]


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
    """Dimension of the condition: the previous frame x_{f-1}, or the ``history`` frames
    before x_f, oldest first (then ``history * x_dim``); 0 for none."""
    width: int = 1024
    """Hidden units per layer (A-MDM: 1024)."""
    depth: int = 10
    """Number of fully connected layers including the output layer (A-MDM: 10)."""
    time_dim: int = 128
    """Size of the sinusoidal time embedding e^t before its MLP."""
    predicts: str = "eps"
    """What the network outputs: 'eps' (A-MDM eq. 3), 'x0' or 'v' (Salimans & Ho 2022)."""
    skip: list[float] | None = None
    """x0-prediction only: the weight :math:`c_{skip}(t)` of the noisy input added to the
    network's output at each level t (:func:`skip_weights`), or None (no skip)."""
    skip_mask: list[float] | None = None
    """The features the skip applies to: one 0/1 per feature of x (D), or None (all)."""
    skip_root: list[float] | None = None
    """x0-prediction only: :math:`c_{skip}(t)` of the root's three velocity features (d_x, d_y,
    d_r, the first three of x) when they spread differently from the joints; None: ``skip``."""
    skip_yaw: list[float] | None = None
    """x0-prediction only: :math:`c_{skip}(t)` of the yaw rate d_r alone (the third feature of
    x), after ``skip_root``; None: as the other root features."""
    delta_scale: list[float] | None = None
    """None: the chain denoises the next frame :math:`x_f` itself. Else one scale :math:`k`
    per feature (D): the chain denoises the change from the previous frame,
    :math:`z_f = (x_f - x_{f-1}) / k`, with :math:`k` the spread of that change in the
    training frames (:meth:`MLPDenoiser.to_delta`)."""
    delta_mask: list[float] | None = None
    """With ``delta_scale``: one 0/1 per feature, 1 where the chain denoises the change (the
    others are denoised as they are, :math:`k` ignored); None: all features."""
    history: int = 1
    """How many previous frames the condition holds: 1, the paper's :math:`x_{f-1}`; H > 1,
    :math:`[x_{f-H}, \\dots, x_{f-1}]` flattened, oldest first (``cond_dim = H x_dim``). A
    delta model's change is still measured from :math:`x_{f-1}`, the last of them."""
    cond_level: float | None = None
    """None: the network is not told how noisy its condition is. A level s in [0, 1]: the
    network takes one more input, the size of its condition's noise as a fraction of the
    largest trained (conditioning augmentation told to the model, as in Ho et al. 2022's
    cascaded diffusion models and Chen et al. 2024's diffusion forcing). Training tells it each
    condition's own drawn size; at run time it is told s, the noise it assumes of its own
    frames: 0, that they are recorded; 1, that they are as far off as the most noised."""


def skip_weights(alphas_cumprod: Tensor, sigma: float) -> list[float]:
    """The skip weights of an x0-denoiser whose next frame spreads by ``sigma`` around its mean.

    If :math:`x_f^0 \\sim \\mathcal N(\\mu, \\sigma^2)` given the previous frame, the best
    estimate of it from :math:`x_f^t = \\sqrt{\\bar\\alpha_t} x_f^0 +
    \\sqrt{1-\\bar\\alpha_t}\\,\\epsilon` is :math:`c(t)\\, x_f^t + (1 -
    c(t)\\sqrt{\\bar\\alpha_t})\\,\\mu` with

    .. math::
        c(t) = \\frac{\\sigma^2 \\sqrt{\\bar\\alpha_t}}
                    {\\bar\\alpha_t \\sigma^2 + 1 - \\bar\\alpha_t}.

    Adding :math:`c(t)\\,x_f^t` to the network's output (the skip connection of Karras et al.
    2022, eq. 7, with :math:`\\sigma_{data}` the spread of the *next frame*, not of all frames)
    makes the nearly clean levels pass the noisy frame on, and with it the sample's own
    variation, while the noisy levels still predict the frame from the condition. Without it,
    an x0-network learns to ignore :math:`x_f^t` and every sample of a frame is the same.
    """
    ac = torch.as_tensor(alphas_cumprod, dtype=torch.float64)
    s2 = float(sigma) ** 2
    return (s2 * ac.sqrt() / (ac * s2 + 1 - ac)).tolist()


class MLPDenoiser(MLP):
    """The A-MDM denoiser :math:`p_\\theta(x_{f-1}, x_f^t, e^t)`.

    ``forward(x_t, t, cond)`` takes ``x_t`` (B, D), integer steps ``t`` (B,) and the previous
    frame ``cond`` (B, C); it returns (B, D). The body is an :class:`~minimdm.nn.MLP` on
    ``[x_t, cond]``; the time embedding is added to every hidden layer so that the step is seen
    throughout the network.
    """

    def __init__(self, config: DenoiserConfig) -> None:
        if config.depth < 2:
            raise ValueError(
                f"depth must be >= 2 (one hidden and one output layer), got {config.depth}"
            )
        if config.predicts not in PREDICTS:
            raise ValueError(f"predicts must be one of {PREDICTS}, got {config.predicts!r}")
        w, w0 = config.width, config.x_dim
        time_mlp = MLP(config.time_dim, w, w, depth=2, norm=False).sequential()  # e^t -> (B, W)
        level = 0 if config.cond_level is None else 1  # the level's one input
        if config.cond_level is not None and not 0 <= config.cond_level <= 1:
            raise ValueError(f"cond_level must be in [0, 1] or None, got {config.cond_level}")
        super().__init__(config.x_dim + config.cond_dim + level, config.x_dim, w, config.depth)
        self.time_mlp = time_mlp
        self.config = config
        self.predicts = config.predicts
        if config.history < 1 or (config.history > 1 and config.cond_dim != config.history * w0):
            raise ValueError(
                f"a history of {config.history} frames needs cond_dim = {config.history} * "
                f"{w0}, got {config.cond_dim}"
            )
        if config.skip is not None and config.predicts != "x0":
            raise ValueError(f"skip needs predicts='x0', got {config.predicts!r}")
        for name in ("skip_root", "skip_yaw"):
            if getattr(config, name) is not None and config.predicts != "x0":
                raise ValueError(f"{name} needs predicts='x0', got {config.predicts!r}")
        mask = config.skip_mask if config.skip_mask is not None else [1.0] * config.x_dim
        if len(mask) != config.x_dim or any(m not in (0, 1) for m in mask):
            raise ValueError(f"skip_mask must hold {config.x_dim} zeros and ones")
        skip = torch.empty(0, config.x_dim)  # c_skip(t) of each feature, (T, D) or empty
        if config.skip is not None:
            skip = torch.tensor(config.skip, dtype=torch.float32)[:, None] * torch.tensor(mask)
        for name, cols in (("skip_root", slice(0, 3)), ("skip_yaw", slice(2, 3))):
            if getattr(config, name) is None:
                continue
            w = torch.tensor(getattr(config, name), dtype=torch.float32)
            if skip.numel() == 0:
                skip = torch.zeros(len(w), config.x_dim)
            if len(w) != len(skip):
                raise ValueError(f"{name} must hold {len(skip)} weights, got {len(w)}")
            skip[:, cols] = w[:, None]
        self.register_buffer("skip", skip, persistent=False)
        k = m = torch.empty(0)  # the delta scale k (D,) and mask (D,), or empty
        if config.delta_scale is not None:
            k = torch.tensor(config.delta_scale, dtype=torch.float32)
            if k.shape != (config.x_dim,) or not (k > 0).all():
                raise ValueError(f"delta_scale must hold {config.x_dim} positive values")
            m = torch.ones(config.x_dim)
            if config.delta_mask is not None:
                m = torch.tensor(config.delta_mask, dtype=torch.float32)
                if m.shape != (config.x_dim,) or not ((m == 0) | (m == 1)).all():
                    raise ValueError(f"delta_mask must hold {config.x_dim} zeros and ones")
        self.register_buffer("delta_spread", k, persistent=False)  # every feature's change
        if k.numel():
            k = torch.where(m > 0, k, torch.ones_like(k))
        self.register_buffer("delta_k", k, persistent=False)
        self.register_buffer("delta_m", m, persistent=False)

    @property
    def is_delta(self) -> bool:
        """Whether the chain denoises the change from the previous frame (``delta_scale``)."""
        return self.delta_k.numel() > 0

    def to_delta(self, x: Tensor, cond: Tensor) -> Tensor:
        """What the chain denoises for a next frame ``x`` (B, D) after ``cond`` (B, D): ``x``
        itself, or :math:`(x - x_{f-1}) / k` for a delta model. With features normalized by
        their spread over all frames, the joint positions of a next frame given the previous one
        vary by about a tenth of that spread, little more than the least noisy level of a
        20-level cosine schedule leaves. The change, scaled by its own spread, varies on the
        scale the noise schedule is made for."""
        return (x - self.delta_m * self.last(cond)) / self.delta_k if self.is_delta else x

    def from_delta(self, z: Tensor, cond: Tensor) -> Tensor:
        """The next frame of a chain's sample ``z`` (B, D) after ``cond``: the inverse of
        :meth:`to_delta`."""
        return self.delta_m * self.last(cond) + self.delta_k * z if self.is_delta else z

    def last(self, cond: Tensor) -> Tensor:
        """The previous frame :math:`x_{f-1}` (B, D) of a condition (B, history D)."""
        return cond if self.config.history == 1 else cond[..., -self.config.x_dim :]

    def forward(
        self, x_t: Tensor, t: Tensor, cond: Tensor | None = None, level: Tensor | None = None
    ) -> Tensor:
        """The output for ``x_t`` (B, D) at steps ``t`` (B,) after ``cond`` (B, C). A model
        told its condition's noise (:attr:`DenoiserConfig.cond_level`) reads ``level`` (B,),
        each condition's size of noise in [0, 1]; None: the configured ``cond_level``."""
        c = self.config
        if x_t.dim() != 2 or x_t.shape[1] != c.x_dim:
            raise ValueError(f"x_t must have shape (B, {c.x_dim}), got {tuple(x_t.shape)}")
        if c.cond_dim:
            if cond is None or cond.shape != (x_t.shape[0], c.cond_dim):
                got = None if cond is None else tuple(cond.shape)
                raise ValueError(f"cond must have shape ({x_t.shape[0]}, {c.cond_dim}), got {got}")
            h = torch.cat([x_t, cond], dim=-1)  # (B, D + C)
        else:
            h = x_t
        if c.cond_level is not None:  # the condition's noise level, one more input
            if level is None:
                level = h.new_full((h.shape[0],), c.cond_level)
            h = torch.cat([h, level.to(h.dtype).reshape(-1, 1)], dim=-1)
        elif level is not None:
            raise ValueError("level needs a model told its condition's noise (cond_level)")
        e = self.time_mlp(timestep_embedding(t, c.time_dim))  # (B, W)
        out = super().forward(h, add=e)  # (B, D)
        if self.skip.numel():
            out = out + self.skip[t] * x_t  # c_skip(t) x_f^t
        return out

    def config_dict(self) -> dict:
        return asdict(self.config)


class MLPRegressor(nn.Module):
    """Deterministic next-frame regressor ``x_{f-1} -> x_f`` (the MSE baseline).

    Same body as :class:`MLPDenoiser` (SiLU then LayerNorm), no noise input and no time step.
    """

    def __init__(self, x_dim: int, cond_dim: int, width: int = 256, depth: int = 4) -> None:
        super().__init__()
        self.net = MLP(cond_dim, x_dim, width, depth).sequential()
        self.x_dim, self.cond_dim = x_dim, cond_dim

    def forward(self, cond: Tensor) -> Tensor:
        if cond.dim() != 2 or cond.shape[1] != self.cond_dim:
            raise ValueError(f"cond must have shape (B, {self.cond_dim}), got {tuple(cond.shape)}")
        return self.net(cond)


@dataclass
class MVAEConfig:
    """Size of an :class:`MVAE`."""

    x_dim: int
    """Dimension D of one frame."""
    cond_dim: int
    """Dimension of the condition, the previous frame x_{f-1}."""
    latent_dim: int = 32
    """Size of the latent z (MVAE: 32)."""
    width: int = 256
    """Hidden units per layer of the encoder and the decoder."""
    depth: int = 4
    """Fully connected layers of the decoder including its output layer (the encoder has 3)."""


class MVAE(nn.Module):
    """An MVAE-style conditional VAE baseline (Ling et al. 2020), for next-frame prediction.

    The encoder :math:`q_\\phi(z | x_f, x_{f-1})` gives the mean and log-variance of a small
    Gaussian latent; the decoder :math:`p_\\theta(x_f | z, x_{f-1})` maps a latent and the previous
    frame to the next frame, with z concatenated to the input of every layer (as in MVAE) so that
    it cannot be ignored. Trained with reconstruction + β-KL and scheduled sampling; sampled by
    drawing :math:`z \\sim \\mathcal N(0, I)`. Same body as the other networks (SiLU then
    LayerNorm).

    The parameters are ``encoder.*`` (an ``nn.Sequential``: ``encoder.0``, ``encoder.2``, ...)
    and ``decoder.*`` (an :class:`~minimdm.nn.MLP`: ``decoder.input``, ``decoder.hidden.i``,
    ``decoder.norms.i``, ``decoder.output``).
    """

    def __init__(self, config: MVAEConfig) -> None:
        super().__init__()
        if config.depth < 2:
            raise ValueError(f"depth must be >= 2, got {config.depth}")
        self.config = config
        c, w = config, config.width
        # q_phi(z | x_f, x_{f-1}): (B, D + C) -> (B, 2 Z), mean and log-variance
        self.encoder = MLP(c.x_dim + c.cond_dim, 2 * c.latent_dim, w, depth=3).sequential()
        # p_theta(x_f | z, x_{f-1}): (B, C) -> (B, D), z concatenated to every layer's input
        self.decoder = MLP(c.cond_dim, c.x_dim, w, c.depth, concat_dim=c.latent_dim)

    def _check(self, name: str, x: Tensor, dim: int) -> None:
        if x.dim() != 2 or x.shape[1] != dim:
            raise ValueError(f"{name} must have shape (B, {dim}), got {tuple(x.shape)}")

    def encode(self, x: Tensor, cond: Tensor) -> tuple[Tensor, Tensor]:
        """Posterior parameters ``(mu, logvar)``, each (B, latent_dim)."""
        self._check("x", x, self.config.x_dim)
        self._check("cond", cond, self.config.cond_dim)
        mu, logvar = self.encoder(torch.cat([x, cond], dim=-1)).chunk(2, dim=-1)
        return mu, logvar.clamp(-20.0, 10.0)

    def decode(self, z: Tensor, cond: Tensor) -> Tensor:
        """The next frame (B, D) from a latent ``z`` (B, latent_dim) and the previous frame."""
        self._check("z", z, self.config.latent_dim)
        self._check("cond", cond, self.config.cond_dim)
        return self.decoder(cond, concat=z)  # (B, D)

    def forward(
        self, x: Tensor, cond: Tensor, generator: torch.Generator | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Reconstruct ``x`` through the posterior: returns ``(x_hat, mu, logvar)``."""
        mu, logvar = self.encode(x, cond)
        eps = torch.randn(mu.shape, generator=generator, device=mu.device, dtype=mu.dtype)
        z = mu + (0.5 * logvar).exp() * eps  # reparameterisation
        return self.decode(z, cond), mu, logvar

    @torch.no_grad()
    def sample(self, cond: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Draw the next frame from the prior, :math:`z \\sim \\mathcal N(0, I)`: (B, D)."""
        self._check("cond", cond, self.config.cond_dim)
        z = torch.randn(
            (cond.shape[0], self.config.latent_dim),
            generator=generator,
            device=cond.device,
            dtype=cond.dtype,
        )
        return self.decode(z, cond)

    def config_dict(self) -> dict:
        return asdict(self.config)


def _regressor_spec(m: MLPRegressor) -> dict:
    linears = [layer for layer in m.net if isinstance(layer, nn.Linear)]
    width = linears[0].out_features if len(linears) > 1 else 0
    return {"x_dim": m.x_dim, "cond_dim": m.cond_dim, "width": width, "depth": len(linears)}


register_model_kind(
    "amdm", MLPDenoiser, lambda c: MLPDenoiser(DenoiserConfig(**c)), lambda m: m.config_dict()
)
register_model_kind("mse", MLPRegressor, lambda c: MLPRegressor(**c), _regressor_spec)
register_model_kind("mvae", MVAE, lambda c: MVAE(MVAEConfig(**c)), lambda m: m.config_dict())
