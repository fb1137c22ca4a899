"""The forward process: noise schedules, q_sample, the posterior, the DDPM loss.

Levels are 0-based (:mod:`minimdm.diffusion`): ``t = T - 1`` is the noisiest, ``t = -1`` clean data.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Literal

import torch
from torch import Tensor

Hook = Callable[[int, Tensor, Tensor], Tensor]
"""A hook on x_t: ``hook(t, x_t, x0_hat) -> x_t``, after each step."""
X0Hook = Callable[[int, Tensor, Tensor], Tensor]
"""A hook on the clean estimate: ``hook(t, x_t, x0_hat) -> x0_hat``, before each step."""
Denoiser = Callable[[Tensor, Tensor, Tensor | None], Tensor]
ClipX0 = float | Sequence | Tensor | None
"""None, a float c (clamp to [-c, c]) or a per-feature pair (lo, hi): see clip_bounds."""


class NoiseTape:
    """Gaussian noise drawn in advance, handed to the reverse chain in place of a generator.

    The step rules draw their noise through :func:`gaussian`; given a tape instead of a
    :class:`torch.Generator`, each draw of shape ``(B, *s)`` takes the next ``prod(s)`` columns
    of ``noise`` (B, N). A whole frame's chain then has its noise as an input, which is what lets
    it be traced into one graph (:mod:`minimdm.fast`). :meth:`draw` fills a tape from a generator
    with exactly the draws the chain would have made, in the same order, so that the chain gives
    the same sample with the tape as with the generator.
    """

    def __init__(self, noise: Tensor) -> None:
        if noise.dim() != 2:
            raise ValueError(f"noise must have shape (B, N), got {tuple(noise.shape)}")
        self.noise = noise  # (B, N)
        self.used = 0
        self.widths: list[int] = []
        """The width of every draw taken so far, in order."""

    def take(self, shape: tuple[int, ...], dtype: torch.dtype | None = None) -> Tensor:
        """The next draw of ``shape`` (B, ...): ``prod(shape[1:])`` columns, reshaped."""
        B, n = shape[0], math.prod(shape[1:])
        if B != self.noise.shape[0] or self.used + n > self.noise.shape[1]:
            raise ValueError(
                f"the noise tape {tuple(self.noise.shape)} has no draw of shape {tuple(shape)} "
                f"left after {self.used} columns"
            )
        out = self.noise[:, self.used : self.used + n].reshape(shape)
        self.used += n
        self.widths.append(n)
        return out if dtype is None else out.to(dtype)

    @staticmethod
    def draw(
        widths: Sequence[int],
        batch: int,
        generator: torch.Generator | None = None,
        device: torch.device | str | None = None,
    ) -> Tensor:
        """(batch, sum(widths)) float32: one ``randn((batch, w))`` per width, in order."""
        parts = [torch.randn((batch, int(w)), generator=generator, device=device) for w in widths]
        return torch.cat(parts, dim=1)


def gaussian(
    shape: tuple[int, ...],
    generator: torch.Generator | NoiseTape | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> Tensor:
    """Standard normal noise of ``shape``: the one way the reverse chain draws its noise.

    From ``generator`` (a :class:`torch.Generator` or None: ``torch.randn``), or the next
    columns of a :class:`NoiseTape`.
    """
    if isinstance(generator, NoiseTape):
        return generator.take(tuple(shape), dtype)
    at = _draw_device(generator, device)
    return torch.randn(shape, generator=generator, device=at, dtype=dtype).to(device)


def _draw_device(generator: torch.Generator | None, device) -> torch.device | str | None:
    """Where a draw happens: on the generator's own device. A seeded CPU generator then feeds a
    GPU run with the same numbers as a CPU run (the draws are moved, not re-seeded)."""
    return generator.device if isinstance(generator, torch.Generator) else device


def check_finite(name: str, x: Tensor) -> None:
    """Raise ``ValueError`` naming ``name`` if ``x`` holds NaN or Inf."""
    if not torch.isfinite(x).all():
        bad = (~torch.isfinite(x)).nonzero()[0].tolist()
        raise ValueError(f"{name} must be finite, but it holds NaN/Inf (first at index {bad})")


KARRAS_SIGMAS = (0.01, 10.0)
"""The ``"karras"`` schedule's least and most noisy levels, as noise-to-signal ratios
:math:`\\sigma = \\sqrt{1 - \\bar\\alpha} / \\sqrt{\\bar\\alpha}` of normalized features."""
KARRAS_RHO = 7.0
"""How strongly the ``"karras"`` levels crowd towards the clean end (Karras et al. 2022: 7)."""


class NoiseSchedule:
    """The variance schedule :math:`\\beta_1..\\beta_T` and every buffer derived from it.

    Args:
        kind: ``"linear"`` (Ho et al. 2020, betas from 1e-4 to 0.02 rescaled to T steps),
            ``"cosine"`` (Nichol & Dhariwal 2021, clipped at 0.999), or ``"karras"``: the noise
            levels of Karras et al. 2022 eq. 5 (:math:`\\rho = 7`) from :data:`KARRAS_SIGMAS`
            ``[0]`` to ``[1]`` as variance-preserving levels,
            :math:`\\bar\\alpha_t = 1 / (1 + \\sigma_t^2)`. It packs more levels near the
            clean end: at T = 20 the least noisy level keeps 0.01 of a feature's spread, where
            the cosine schedule's keeps 0.09.
        T: number of diffusion steps, 1 to 1000 (more is allowed; no step is hard-coded).
        betas: explicit betas, overriding ``kind``; each must lie in (0, 1).
        device: where the buffers live.

    All buffers are float32 tensors of length ``T``, indexed by the 0-based step ``t``.
    """

    def __init__(
        self,
        kind: Literal["linear", "cosine", "karras"] = "cosine",
        T: int = 40,
        betas: Tensor | None = None,
        device: torch.device | str = "cpu",
    ) -> None:
        if betas is None:
            if not isinstance(T, int) or T < 1:
                raise ValueError(f"T must be an integer >= 1, got {T!r}")
            betas = self._make_betas(kind, T)
        else:
            betas = torch.as_tensor(betas, dtype=torch.float64).flatten()
            if betas.numel() < 1:
                raise ValueError("betas must hold at least one value (T >= 1)")
            kind = "custom"
        if not torch.isfinite(betas).all() or (betas <= 0).any() or (betas >= 1).any():
            raise ValueError(
                f"betas must lie in the open interval (0, 1); got min {betas.min().item():.3g}, "
                f"max {betas.max().item():.3g}"
            )
        self.kind = kind
        self.T = int(betas.numel())
        b = betas.double()
        alphas = 1.0 - b
        ac = torch.cumprod(alphas, 0)
        ac_prev = torch.cat([torch.ones(1, dtype=torch.float64), ac[:-1]])
        f32 = dict(dtype=torch.float32, device=device)
        self.betas = b.to(**f32)  # \beta_t
        self.alphas = alphas.to(**f32)  # \alpha_t = 1 - \beta_t
        self.alphas_cumprod = ac.to(**f32)  # \bar\alpha_t
        self.alphas_cumprod_prev = ac_prev.to(**f32)  # \bar\alpha_{t-1}
        self.sqrt_alphas_cumprod = ac.sqrt().to(**f32)  # \sqrt{\bar\alpha_t}
        self.sqrt_one_minus_alphas_cumprod = (1 - ac).sqrt().to(**f32)  # \sqrt{1-\bar\alpha_t}
        self.sqrt_recip_alphas_cumprod = (1 / ac).sqrt().to(**f32)  # 1/\sqrt{\bar\alpha_t}
        self.sqrt_recipm1_alphas_cumprod = (1 / ac - 1).sqrt().to(**f32)  # \sqrt{1/\bar\alpha_t-1}
        # \tilde\beta_t = \beta_t (1-\bar\alpha_{t-1}) / (1-\bar\alpha_t)   (Ho et al. eq. 7)
        post_var = b * (1 - ac_prev) / (1 - ac)
        self.posterior_variance = post_var.to(**f32)
        # log \tilde\beta_t, clipped: \tilde\beta_1 = 0
        self.posterior_log_variance_clipped = torch.log(
            torch.cat([post_var[1:2], post_var[1:]]) if self.T > 1 else b
        ).to(**f32)
        # \tilde\mu_t = c_1 x_0 + c_2 x_t, c_1 = \sqrt{\bar\alpha_{t-1}}\beta_t/(1-\bar\alpha_t)
        self.posterior_mean_coef1 = (ac_prev.sqrt() * b / (1 - ac)).to(**f32)
        # c_2 = \sqrt{\alpha_t}(1-\bar\alpha_{t-1})/(1-\bar\alpha_t)
        self.posterior_mean_coef2 = (alphas.sqrt() * (1 - ac_prev) / (1 - ac)).to(**f32)

    @staticmethod
    def _make_betas(kind: str, T: int) -> Tensor:
        if kind == "linear":
            scale = 1000.0 / T
            lo, hi = scale * 1e-4, min(scale * 0.02, 0.999)
            if T == 1:
                return torch.tensor([0.999], dtype=torch.float64)
            return torch.linspace(min(lo, hi), hi, T, dtype=torch.float64)
        if kind == "cosine":
            s = 0.008
            steps = torch.arange(T + 1, dtype=torch.float64) / T
            f = torch.cos((steps + s) / (1 + s) * math.pi / 2) ** 2
            betas = 1 - f[1:] / f[:-1]
            return betas.clamp(1e-5, 0.999)
        if kind == "karras":  # Karras et al. 2022 eq. 5, least noisy level first
            lo, hi = (x ** (1 / KARRAS_RHO) for x in KARRAS_SIGMAS)
            i = torch.arange(T, dtype=torch.float64) / (T - 1) if T > 1 else torch.ones(1)
            sigma = (lo + i * (hi - lo)) ** KARRAS_RHO
            ac = 1 / (1 + sigma**2)
            betas = 1 - ac / torch.cat([torch.ones(1, dtype=torch.float64), ac[:-1]])
            return betas.clamp(1e-5, 0.999)
        raise ValueError(f"kind must be 'linear', 'cosine' or 'karras', got {kind!r}")

    @property
    def device(self) -> torch.device:
        return self.betas.device

    def to(self, device: torch.device | str) -> NoiseSchedule:
        """Return a copy of the schedule with every buffer on ``device``."""
        out = object.__new__(NoiseSchedule)
        for k, v in vars(self).items():
            setattr(out, k, v.to(device) if isinstance(v, Tensor) else v)
        return out

    def __repr__(self) -> str:
        return f"NoiseSchedule(kind={self.kind!r}, T={self.T})"


def _index(buf: Tensor, t: Tensor | int, x: Tensor, clean_value: float) -> Tensor:
    """Gather ``buf[t]`` for a batch and shape it to broadcast against ``x``.

    ``t = -1`` (clean data) takes ``clean_value``.
    """
    t = torch.as_tensor(t, device=buf.device, dtype=torch.long)
    if t.dim() == 0:
        t = t.expand(x.shape[0])
    if t.shape != (x.shape[0],):
        raise ValueError(
            f"t must be an int or a ({x.shape[0]},) tensor, got shape {tuple(t.shape)}"
        )
    if (t < -1).any() or (t >= buf.numel()).any():
        raise ValueError(f"t must lie in [-1, {buf.numel() - 1}], got {t.min()}..{t.max()}")
    vals = torch.where(t >= 0, buf[t.clamp(min=0)], torch.full_like(buf[:1], clean_value))
    return vals.to(x.dtype).reshape(-1, *([1] * (x.dim() - 1)))


def q_sample(
    schedule: NoiseSchedule,
    x0: Tensor,
    t: Tensor | int,
    noise: Tensor | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Sample the forward process :math:`q(x_t | x_0)` in closed form (Ho et al. eq. 4).

    :math:`x_t = \\sqrt{\\bar\\alpha_t} x_0 + \\sqrt{1-\\bar\\alpha_t}\\,\\epsilon`; the product of
    A-MDM eqs. 1-2. ``t = -1`` returns ``x0`` unchanged.
    """
    if noise is None:
        noise = gaussian(x0.shape, generator, x0.device, x0.dtype)
    return (
        _index(schedule.sqrt_alphas_cumprod, t, x0, 1.0) * x0
        + _index(schedule.sqrt_one_minus_alphas_cumprod, t, x0, 0.0) * noise
    )


def q_posterior(
    schedule: NoiseSchedule, x0: Tensor, x_t: Tensor, t: Tensor | int
) -> tuple[Tensor, Tensor]:
    """Mean and variance of the posterior :math:`q(x_{t-1} | x_t, x_0)` (Ho et al. eqs. 6-7)."""
    mean = (
        _index(schedule.posterior_mean_coef1, t, x_t, 0.0) * x0
        + _index(schedule.posterior_mean_coef2, t, x_t, 0.0) * x_t
    )
    var = _index(schedule.posterior_variance, t, x_t, 0.0).expand_as(x_t)
    return mean, var


def predict_x0_from_eps(
    schedule: NoiseSchedule, x_t: Tensor, t: Tensor | int, eps: Tensor
) -> Tensor:
    """Invert q_sample (Ho et al. eq. 4).

    :math:`x_0 = (x_t - \\sqrt{1-\\bar\\alpha_t}\\epsilon)/\\sqrt{\\bar\\alpha_t}`.
    """
    return (
        _index(schedule.sqrt_recip_alphas_cumprod, t, x_t, 1.0) * x_t
        - _index(schedule.sqrt_recipm1_alphas_cumprod, t, x_t, 0.0) * eps
    )


def predict_eps_from_x0(
    schedule: NoiseSchedule, x_t: Tensor, t: Tensor | int, x0: Tensor
) -> Tensor:
    """The noise implied by a clean estimate (Ho et al. eq. 4 solved for the noise).

    :math:`\\epsilon = (x_t - \\sqrt{\\bar\\alpha_t}x_0)/\\sqrt{1-\\bar\\alpha_t}`.
    """
    return (_index(schedule.sqrt_recip_alphas_cumprod, t, x_t, 1.0) * x_t - x0) / _index(
        schedule.sqrt_recipm1_alphas_cumprod, t, x_t, 1.0
    )


def predict_v(schedule: NoiseSchedule, x0: Tensor, t: Tensor | int, eps: Tensor) -> Tensor:
    """The velocity target of v-prediction (Salimans & Ho 2022, §4).

    :math:`v = \\sqrt{\\bar\\alpha_t}\\,\\epsilon - \\sqrt{1-\\bar\\alpha_t}\\,x_0`.
    """
    return (
        _index(schedule.sqrt_alphas_cumprod, t, x0, 1.0) * eps
        - _index(schedule.sqrt_one_minus_alphas_cumprod, t, x0, 0.0) * x0
    )


def predict_x0_from_v(schedule: NoiseSchedule, x_t: Tensor, t: Tensor | int, v: Tensor) -> Tensor:
    """The clean estimate of a v-prediction: :math:`x_0 = \\sqrt{\\bar\\alpha_t}\\,x_t -
    \\sqrt{1-\\bar\\alpha_t}\\,v`. An error in ``v`` reaches ``x0`` shrunk by
    :math:`\\sqrt{1-\\bar\\alpha_t} \\le 1`, where ``eps``-prediction multiplies it by
    :math:`\\sqrt{1/\\bar\\alpha_t - 1}`."""
    return (
        _index(schedule.sqrt_alphas_cumprod, t, x_t, 1.0) * x_t
        - _index(schedule.sqrt_one_minus_alphas_cumprod, t, x_t, 0.0) * v
    )


def predict_eps_from_v(schedule: NoiseSchedule, x_t: Tensor, t: Tensor | int, v: Tensor) -> Tensor:
    """The noise implied by a v-prediction: :math:`\\epsilon = \\sqrt{1-\\bar\\alpha_t}\\,x_t +
    \\sqrt{\\bar\\alpha_t}\\,v`."""
    return (
        _index(schedule.sqrt_one_minus_alphas_cumprod, t, x_t, 0.0) * x_t
        + _index(schedule.sqrt_alphas_cumprod, t, x_t, 1.0) * v
    )


PREDICTS = ("eps", "x0", "v")
"""What a denoiser may output: the noise (A-MDM eq. 3), the clean sample, or the velocity."""


def q_posterior_sample(
    schedule: NoiseSchedule,
    x0: Tensor,
    x_t: Tensor,
    t: Tensor | int,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Draw :math:`x_{t-1} \\sim q(x_{t-1} | x_t, x_0)` (Ho et al. eqs. 6-7).

    DD-GAN's fake pairs put the generator's :math:`\\hat x_0` here (Xiao et al. eq. 9); at level
    ``t = 0`` the posterior is a point mass on ``x0``.
    """
    mean, var = q_posterior(schedule, x0, x_t, t)
    noise = gaussian(x_t.shape, generator, x_t.device, x_t.dtype)
    return mean + var.sqrt() * noise


# --------------------------------------------------------------------------------------------
# The x0 clamp: the training data's per-feature range


def diffusion_loss(
    model: Denoiser,
    schedule: NoiseSchedule,
    x0: Tensor,
    cond: Tensor | None = None,
    generator: torch.Generator | None = None,
    predicts: str = "eps",
    reduce: bool = True,
    norm: str = "l2",
    x0_loss: Callable[[Tensor, Tensor], Tensor] | None = None,
    snr_gamma: float | None = None,
    snr_floor: float = 0.0,
) -> tuple[Tensor, Tensor]:
    """The simple DDPM loss (A-MDM eq. 3) at a uniformly drawn step per sample.

    With ``predicts="eps"``: :math:`\\|\\epsilon - p_\\theta(x_{f-1}, x_f^t, e^t)\\|^2`; with
    ``"x0"`` the target is the clean sample, with ``"v"`` the velocity :func:`predict_v`.
    ``norm="l1"`` takes the absolute error instead of the square, as the official A-MDM code
    does. ``x0_loss(x0_hat, t) -> (B,)`` adds a loss on the reconstruction, e.g. the geometric
    losses of MDM and CAMDM (:class:`minimdm.amdm.losses.FrameGeometry`). ``snr_gamma`` weights
    each level by Min-SNR-γ (Hang et al. 2023): as an error on :math:`x_0`, the loss weighs level
    t by :math:`\\min(\\mathrm{SNR}_t, \\gamma)` with :math:`\\mathrm{SNR}_t = \\bar\\alpha_t /
    (1 - \\bar\\alpha_t)` (an ε loss weighs it by :math:`\\mathrm{SNR}_t`, an x0 loss by 1, a v loss
    by :math:`\\mathrm{SNR}_t + 1`), so the nearly clean levels count more than in the x0 loss
    and less than in the ε loss. ``snr_floor`` raises the weight of the noisiest levels to at
    least that (1: as much as the x0 loss gives them; Min-SNR leaves them near 0).
    Returns ``(loss, x0_hat)``; ``x0_hat`` is the model's reconstruction, which scheduled
    sampling feeds forward as the next condition (A-MDM §3.2). ``reduce=False`` returns the
    per-sample loss.
    """
    B = x0.shape[0]
    at = _draw_device(generator, x0.device)
    t = torch.randint(0, schedule.T, (B,), generator=generator, device=at).to(x0.device)
    noise = gaussian(x0.shape, generator, x0.device, x0.dtype)
    x_t = q_sample(schedule, x0, t, noise)
    out = model(x_t, t, cond)
    if predicts == "eps":
        target, x0_hat = noise, predict_x0_from_eps(schedule, x_t, t, out)
    elif predicts == "x0":
        target, x0_hat = x0, out
    elif predicts == "v":
        target, x0_hat = predict_v(schedule, x0, t, noise), predict_x0_from_v(schedule, x_t, t, out)
    else:
        raise ValueError(f"predicts must be one of {PREDICTS}, got {predicts!r}")
    if norm not in ("l1", "l2"):
        raise ValueError(f"norm must be 'l1' or 'l2', got {norm!r}")
    err = (out - target).abs() if norm == "l1" else (out - target) ** 2
    loss = err.flatten(1).mean(1)  # (B,)
    if snr_gamma is not None:
        ac = schedule.alphas_cumprod.to(x0.device)[t]
        snr = ac / (1 - ac).clamp_min(1e-12)  # \bar\alpha_t / (1 - \bar\alpha_t)
        native = {"eps": snr, "x0": torch.ones_like(snr), "v": snr + 1}[predicts]
        loss = loss * snr.clamp(max=snr_gamma).clamp(min=snr_floor) / native
    if x0_loss is not None:
        loss = loss + x0_loss(x0_hat, t)
    return (loss.mean() if reduce else loss), x0_hat
