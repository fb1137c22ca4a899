"""AAMDM's sampler: a few DD-GAN steps draft a sample, a few diffusion steps polish it.

AAMDM (Qiao et al. 2024, §3.2-3.4) splits one reverse chain of ``T = T_GAN + T_ADM`` levels:

* the **generation module** (§3.3, DD-GAN of Xiao et al. 2022) covers the ``T_GAN`` noisy levels
  ``t = T-1 .. T_ADM``. Its generator :math:`G^{GAN}(x^t, x_{n-1}, r, t) \\to \\hat x^0` (eq. 10)
  takes a latent noise ``r``, so one reverse step :math:`x^t \\to x^{t-1}` can be **multimodal**:
  :math:`x^{t-1} \\sim q(x^{t-1} | x^t, \\hat x^0)` with a random :math:`\\hat x^0`. It is trained
  adversarially (eqs. 11-12) against a step-conditioned discriminator
  :math:`D^{GAN}(x^{t-1}, x^t, x_{n-1}, t)` that sees real pairs from the forward process and
  fake pairs drawn through the posterior;
* the **polishing module** (§3.2, eq. 6) is an auto-regressive diffusion model (ADM) that predicts
  :math:`\\hat x^0` directly and covers the ``T_ADM`` last, nearly clean levels with ordinary
  Gaussian reverse steps.

Levels use the library's 0-based index (:mod:`minimdm.diffusion`): ``t = T-1`` is the noisiest,
``t = -1`` clean data. The default schedule is the paper's (§6.2), five betas
``[3.764e-4, 1.452e-3, 0.257, 0.668, 0.999]``: two tiny polishing steps and three large GAN steps.
:func:`aamdm_schedule` builds the schedules of the ablations (other ``T_GAN``, ``T_ADM``).

The sampler :func:`aamdm_sample` runs the library's one reverse chain
(:func:`minimdm.diffusion.reverse_chain`) with two step rules joined by a
:class:`~minimdm.diffusion.Handover`: :class:`~minimdm.diffusion.DDGANStep` on the GAN's levels,
:class:`~minimdm.diffusion.PolishStep` below. It counts its network calls (:class:`StepCount`),
passes the per-step ``hook(t, x_t, x0_hat)`` on :math:`x_t` to the chain, and turns the guidance
of eq. 13 (:class:`Guide`) and the clamp into hooks on :math:`\\hat x^0`. Training lives in
:mod:`minimdm.aamdm.train`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

from minimdm.aamdm.nets import (
    DDGANDiscriminator,
    DDGANGenerator,
    DiscriminatorConfig,
    FourierFeatures,
    GeneratorConfig,
    _check_shape,
)
from minimdm.amdm.models import DenoiserConfig, MLPDenoiser
from minimdm.checkpoint import register_model_kind
from minimdm.diffusion import (
    ClipX0,
    DDGANStep,
    Handover,
    Hook,
    NoiseSchedule,
    PolishStep,
    StepCount,
    check_finite,
    clamp_hook,
    clip_bounds,
    gaussian,
    hook_list,
    q_posterior_sample,
    q_sample,
    reverse_chain,
)

__all__ = [
    "PAPER_BETAS",
    "aamdm_betas",
    "aamdm_schedule",
    "q_sample_pairs",
    "q_posterior_sample",
    "FourierFeatures",
    "GeneratorConfig",
    "DDGANGenerator",
    "DiscriminatorConfig",
    "DDGANDiscriminator",
    "AAMDMConfig",
    "AAMDM",
    "StepCount",
    "Guide",
    "aamdm_sample",
]

PAPER_BETAS = (3.764e-4, 1.452e-3, 0.257, 0.668, 0.999)
"""AAMDM §6.2: the noise schedule of the 3 + 2 model, from clean to pure noise."""


# --------------------------------------------------------------------------------------------
# Schedules


def _check_steps(T_gan: int, T_adm: int) -> None:
    if not isinstance(T_gan, int) or T_gan < 1:
        raise ValueError(f"T_gan must be an integer >= 1 (the GAN draws from noise), got {T_gan!r}")
    if not isinstance(T_adm, int) or T_adm < 0:
        raise ValueError(f"T_adm must be an integer >= 0, got {T_adm!r}")


def aamdm_betas(T_gan: int = 3, T_adm: int = 2) -> list[float]:
    """The betas of a ``T_gan + T_adm`` schedule, exactly the paper's (§6.2) for 3 + 2.

    Other step counts (the ablations of §4.3) keep the paper's two hand-over points:

    * polishing: the ``T_adm`` small steps remove the same total noise as the paper's two,
      :math:`1 - \\bar\\alpha = 1.83 \\times 10^{-3}`, split geometrically with the paper's ratio
      :math:`\\beta_2 / \\beta_1 = 3.86` (``T_adm = 0``: the GAN goes down to clean data);
    * generation: :math:`\\log \\bar\\alpha` of the GAN levels, relative to the hand-over level,
      is interpolated piecewise-linearly through the paper's three GAN levels at fractions 1/3,
      2/3 and 1 of the GAN chain, so the last level is the paper's nearly pure noise.

    Returns ``T_gan + T_adm`` betas, index 0 the least noisy.
    """
    _check_steps(T_gan, T_adm)
    b = PAPER_BETAS
    polish_total = 1.0 - (1.0 - b[0]) * (1.0 - b[1])  # 1 - abar at the hand-over level
    if T_adm == 0:
        polish: list[float] = []
    elif T_adm == 2:
        polish = list(b[:2])
    else:
        ratio = b[1] / b[0]
        w = [ratio**i for i in range(T_adm)]
        # split -log(1 - polish_total) in proportion to w, so the product matches exactly
        total = -math.log(1.0 - polish_total)
        polish = [1.0 - math.exp(-total * wi / sum(w)) for wi in w]
    if T_gan == 3:
        gan = list(b[2:])
    else:
        knots = [0.0]
        for beta in b[2:]:
            knots.append(knots[-1] + math.log(1.0 - beta))  # log abar relative to hand-over
        pos = [0.0, 1 / 3, 2 / 3, 1.0]

        def log_abar(u: float) -> float:
            for i in range(3):
                if u <= pos[i + 1] + 1e-12:
                    f = (u - pos[i]) / (pos[i + 1] - pos[i])
                    return knots[i] + f * (knots[i + 1] - knots[i])
            return knots[-1]

        la = [log_abar(k / T_gan) for k in range(T_gan + 1)]
        gan = [1.0 - math.exp(la[k + 1] - la[k]) for k in range(T_gan)]
    return polish + gan


def aamdm_schedule(
    T_gan: int = 3, T_adm: int = 2, device: torch.device | str = "cpu"
) -> NoiseSchedule:
    """The :class:`~minimdm.diffusion.NoiseSchedule` of :func:`aamdm_betas`."""
    return NoiseSchedule(betas=torch.tensor(aamdm_betas(T_gan, T_adm)), device=device)


# --------------------------------------------------------------------------------------------
# Real pairs for the discriminator (the fake ones: q_posterior_sample of minimdm.diffusion)


def _bcast(buf: Tensor, t: Tensor, x: Tensor) -> Tensor:
    return buf[t].to(x.dtype).reshape(-1, *([1] * (x.dim() - 1)))


def q_sample_pairs(
    schedule: NoiseSchedule, x0: Tensor, t: Tensor, generator: torch.Generator | None = None
) -> tuple[Tensor, Tensor]:
    """Real pairs for the discriminator: :math:`(x^{t-1}, x^t)` from the forward process.

    :math:`x^{t-1} \\sim q(x^{t-1} | x^0)`, then one forward step (AAMDM eq. 5)
    :math:`x^t \\sim \\mathcal N(\\sqrt{\\alpha_t} x^{t-1}, \\beta_t I)`; Algorithm 1 lines 20-21.
    ``t`` is a (B,) tensor of levels in [0, T); level ``t - 1 = -1`` is ``x0`` itself.
    """
    t = torch.as_tensor(t, device=x0.device, dtype=torch.long)
    if t.shape != (x0.shape[0],) or (t < 0).any() or (t >= schedule.T).any():
        raise ValueError(
            f"t must be a ({x0.shape[0]},) tensor of levels in [0, {schedule.T - 1}], "
            f"got {tuple(t.shape)}"
        )
    x_prev = q_sample(schedule, x0, t - 1, generator=generator)  # (B, D), t - 1 = -1: x0
    noise = torch.randn(x0.shape, generator=generator, device=x0.device, dtype=x0.dtype)
    alpha, beta = _bcast(schedule.alphas, t, x0), _bcast(schedule.betas, t, x0)
    return x_prev, alpha.sqrt() * x_prev + beta.sqrt() * noise


# --------------------------------------------------------------------------------------------
# The two modules together


@dataclass
class AAMDMConfig:
    """An AAMDM transition model over vectors of size ``x_dim`` (AAMDM §3.4)."""

    x_dim: int
    """Dimension of the sample (xz for motion, 2 for Squ-9)."""
    cond_dim: int
    """Dimension of the condition (the previous sample)."""
    T_gan: int = 3
    """Generation steps (DD-GAN), the noisy levels T-1 .. T_adm."""
    T_adm: int = 2
    """Polishing steps (x0-predicting diffusion), the levels T_adm-1 .. 0."""
    betas: list[float] | None = None
    """The schedule's betas (None: aamdm_betas(T_gan, T_adm)); length T_gan + T_adm."""
    latent_dim: int = 8
    """Size of the GAN latent r."""
    width: int = 256
    """Hidden units of the generator and the polisher."""
    depth: int = 4
    """Layers of the generator and the polisher."""
    time_dim: int = 64
    """Level embedding size."""
    polish_width: int | None = None
    """Hidden units of the polisher (None: width)."""
    fourier: int = 0
    """Random Fourier features in the generator's input (0: none)."""
    fourier_scale: float = 1.0
    """Their frequency scale (cycles per unit)."""
    clip_x0: float | list | None = None
    """Clamp every x0 estimate while sampling: None, a float c ([-c, c]) or [lo, hi] per feature
    (the training data's range, see minimdm.diffusion.clip_bounds)."""

    def __post_init__(self) -> None:
        _check_steps(self.T_gan, self.T_adm)
        if self.betas is None:
            self.betas = aamdm_betas(self.T_gan, self.T_adm)
        self.betas = [float(b) for b in self.betas]
        if len(self.betas) != self.T_gan + self.T_adm:
            raise ValueError(
                f"betas must hold T_gan + T_adm = {self.T_gan} + {self.T_adm} = "
                f"{self.T_gan + self.T_adm} values, got {len(self.betas)}"
            )
        bounds = clip_bounds(self.clip_x0, self.x_dim)  # raises on a bad clamp
        if isinstance(bounds, tuple):  # JSON-able, for the checkpoint
            self.clip_x0 = [bounds[0].tolist(), bounds[1].tolist()]


class AAMDM(nn.Module):
    """Generator + polisher + their schedule: one module, one checkpoint (kind ``"ddgan"``).

    ``polisher`` is an :class:`~minimdm.amdm.models.MLPDenoiser` predicting x0 (eq. 6); it is
    ``None`` when ``T_adm = 0``. Sample with :meth:`sample` (see :func:`aamdm_sample`).
    """

    def __init__(self, config: AAMDMConfig) -> None:
        super().__init__()
        self.config = c = config
        self.generator = DDGANGenerator(
            GeneratorConfig(
                c.x_dim,
                c.cond_dim,
                c.latent_dim,
                c.width,
                c.depth,
                c.time_dim,
                c.fourier,
                c.fourier_scale,
            )
        )
        self.polisher = (
            MLPDenoiser(
                DenoiserConfig(
                    c.x_dim, c.cond_dim, c.polish_width or c.width, c.depth, c.time_dim, "x0"
                )
            )
            if c.T_adm > 0
            else None
        )

    @property
    def T_gan(self) -> int:
        return self.config.T_gan

    @property
    def T_adm(self) -> int:
        return self.config.T_adm

    def schedule(self, device: torch.device | str | None = None) -> NoiseSchedule:
        dev = device or next(self.parameters()).device
        return NoiseSchedule(betas=torch.tensor(self.config.betas), device=dev)

    def sample(
        self,
        cond: Tensor,
        generator: torch.Generator | None = None,
        hook: Hook | None = None,
        guide: Guide | None = None,
        T_adm: int | None = None,
        count: StepCount | None = None,
    ) -> Tensor:
        """One sample per condition ``cond`` (B, C): :func:`aamdm_sample` with this model."""
        return aamdm_sample(
            self.generator,
            self.polisher,
            self.schedule(cond.device),
            (cond.shape[0], self.config.x_dim),
            cond,
            T_gan=self.T_gan,
            T_adm=self.T_adm if T_adm is None else T_adm,
            generator=generator,
            hook=hook,
            guide=guide,
            clip_x0=self.config.clip_x0,
            count=count,
        )

    def config_dict(self) -> dict:
        return asdict(self.config)


register_model_kind("ddgan", AAMDM, lambda c: AAMDM(AAMDMConfig(**c)), lambda m: m.config_dict())


# --------------------------------------------------------------------------------------------
# The combined sampler


@dataclass
class Guide:
    """Guided sampling, AAMDM eq. 13 (after Rempe et al. 2023).

    At every step the clean estimate is moved against the gradient, taken with respect to the
    noisy input :math:`x^t`, of a cost on it:
    :math:`\\hat x^{0,*} = \\hat x^0 - \\epsilon\\,\\alpha_t \\nabla_{x^t} J(\\hat x^0)`.
    """

    cost: Callable[[Tensor], Tensor]
    """J: maps the clean estimates (B, D) to one cost per sample (B,)."""
    scale: float = 1.0
    """The step epsilon."""

    def x0_hook(self, schedule: NoiseSchedule):
        """Eq. 13 as a hook on :math:`\\hat x^0` of the reverse chain (:mod:`minimdm.diffusion`).

        The chain runs the network with gradients on ``x_t`` for it (``needs_grad``).
        """

        def hook(t: int, x_t: Tensor, x0_hat: Tensor) -> Tensor:
            J = self.cost(x0_hat)  # (B,)
            if J.shape != (x_t.shape[0],):
                raise ValueError(
                    f"guide.cost must return shape ({x_t.shape[0]},), got {tuple(J.shape)}"
                )
            (grad,) = torch.autograd.grad(J.sum(), x_t)  # dJ/dx_t, (B, D)
            return x0_hat.detach() - self.scale * schedule.alphas[t] * grad

        hook.needs_grad = True
        return hook


def _check_sample(
    gan: nn.Module,
    polisher: nn.Module | None,
    T: int,
    shape: tuple[int, int],
    cond: Tensor | None,
    T_gan: int,
    T_adm: int,
) -> tuple[int, bool]:
    """Refuse what :func:`aamdm_sample` cannot run (its Raises); return the GAN's latent size
    and whether the chain stops after the GAN's levels (``T_adm = 0`` with ``T_gan < T``)."""
    _check_steps(T_gan, T_adm)
    gan_only = T_adm == 0 and T_gan < T  # "no polishing": stop after the GAN's levels
    if T_gan + T_adm != T and not gan_only:
        raise ValueError(
            f"T_gan + T_adm must equal the schedule's T = {T} (or T_adm = 0 with T_gan < T), "
            f"got T_gan = {T_gan}, T_adm = {T_adm}"
        )
    if T_adm > 0 and polisher is None:
        raise ValueError(f"T_adm = {T_adm} polishing steps need a polisher, got None")
    B, D = shape
    latent = getattr(getattr(gan, "config", None), "latent_dim", None)
    if latent is None:
        raise ValueError("gan must have config.latent_dim (a DDGANGenerator)")
    x_dim = getattr(gan.config, "x_dim", D)
    if x_dim != D:
        raise ValueError(f"shape must be (B, {x_dim}) for this generator, got {tuple(shape)}")
    if cond is not None:
        check_finite("cond", cond)
        if cond.shape[0] != B:
            raise ValueError(f"cond must have batch size {B}, got shape {tuple(cond.shape)}")
    return latent, gan_only


def _start(
    x_start: Tensor | None,
    shape: tuple[int, int],
    generator: torch.Generator | None,
    device: torch.device,
) -> Tensor:
    """The chain's start (B, D): ``x_start`` checked and moved to ``device``, else N(0, I)."""
    if x_start is None:
        return gaussian(shape, generator, device)
    check_finite("x_start", x_start)
    _check_shape("x_start", x_start, shape)
    return x_start.to(device)


@torch.no_grad()
def aamdm_sample(
    gan: nn.Module,
    polisher: nn.Module | None,
    schedule: NoiseSchedule,
    shape: tuple[int, int],
    cond: Tensor | None = None,
    T_gan: int = 3,
    T_adm: int = 2,
    generator: torch.Generator | None = None,
    hook: Hook | None = None,
    guide: Guide | None = None,
    x_start: Tensor | None = None,
    clip_x0: ClipX0 = None,
    count: StepCount | None = None,
) -> Tensor:
    """Draft with ``T_gan`` DD-GAN steps, polish with ``T_adm`` diffusion steps (AAMDM §3.4).

    One :func:`~minimdm.diffusion.reverse_chain` with :class:`~minimdm.diffusion.DDGANStep` on
    the levels ``T-1 .. T-T_gan`` and :class:`~minimdm.diffusion.PolishStep` below them.

    Args:
        gan: :math:`G^{GAN}(x^t, t, cond, r) \\to \\hat x^0` (:class:`DDGANGenerator`).
        polisher: :math:`G^{ADM}(x^t, t, cond) \\to \\hat x^0` (an x0-predicting denoiser);
            unused, and may be None, when ``T_adm = 0``.
        schedule: ``T_gan + T_adm`` levels, e.g. :func:`aamdm_schedule`; a polisher trained with
            more levels can still be run with fewer: ``T_adm = 0`` returns the GAN's last
            :math:`\\hat x^0`, the paper's "no polishing" ablation.
        shape: ``(B, D)``.
        cond: ``(B, C)`` the previous sample.
        hook: ``hook(t, x_t, x0_hat) -> x_t`` after every step, ``t`` the new level.
        guide: eq. 13 guidance applied to every step's :math:`\\hat x^0`.
        x_start: the start at level ``T - 1`` (default: standard normal noise).
        clip_x0: clamp every :math:`\\hat x^0` (after guidance): None, a float ``c``
            (``[-c, c]``) or a per-feature ``(lo, hi)`` (:func:`~minimdm.diffusion.clip_bounds`).
        count: a :class:`StepCount` to fill with the steps taken.

    The generator sees the index of the level within the GAN chain, ``t - (T - T_gan)``, not
    ``t`` itself: the hand-over level of :func:`aamdm_betas` does not depend on ``T_adm``, so
    one generator serves every ``T_adm`` of the ablation. Each GAN step draws ``r ~ N(0, I)``,
    predicts :math:`\\hat x^0` and samples the posterior
    :math:`q(x^{t-1} | x^t, \\hat x^0)`; each polishing step does the same with the polisher's
    :math:`\\hat x^0` (a Gaussian step, Ho et al. §3.2). The last step returns its
    :math:`\\hat x^0` (the posterior at ``t = 0`` is a point mass there).

    Raises:
        ValueError: ``T_gan + T_adm`` differs from the schedule's T, with only the GAN's levels
            kept for ``T_adm = 0``; ``T_gan < 1``; ``T_adm > 0`` without a polisher; bad shapes;
            non-finite ``cond`` or ``x_start``.
    """
    latent, gan_only = _check_sample(gan, polisher, schedule.T, shape, cond, T_gan, T_adm)
    B, D = shape
    device = cond.device if cond is not None else schedule.device
    x0_hooks = [clamp_hook(clip_x0, D, device)] if clip_x0 is not None else []
    x = _start(x_start, (B, D), generator, device)  # x^{T-1}
    schedule = schedule.to(device)
    T = schedule.T
    t_low = T - T_gan  # the first level below the GAN's
    # the GAN sees its own step index, t - T_adm
    gan_rule = DDGANStep(gan, schedule, latent, t_offset=t_low)
    rule = Handover(gan_rule, PolishStep(polisher, schedule) if polisher else None, t_low)
    if guide is not None:
        x0_hooks.insert(0, guide.x0_hook(schedule))
    levels = range(T - 1, (t_low if gan_only else 0) - 1, -1)
    return reverse_chain(rule, x, levels, cond, generator, hook_list(hook), x0_hooks, count)
