"""Diffusion: noise schedules, the forward process, the posterior and the one reverse chain.

Notation follows Ho et al. (2020) and the A-MDM paper (Shi et al. 2024, §3.1):

* ``t`` is a 0-based step index, ``0 <= t < T``. Index ``t`` is the paper's step ``t + 1``:
  ``x_t`` below is the paper's :math:`x^{t+1}`. We extend it by one value, ``t = -1``, which
  denotes clean data (the paper's :math:`x^0`), so that every sample in the reverse chain has a
  level: noise enters at ``T - 1`` and the last step leaves at ``-1``.
* Every function is batched over the leading dimension, works on any device, and draws its
  randomness from an explicit :class:`torch.Generator`.

**The reverse chain.** :func:`reverse_chain` is the library's only loop over denoising levels.
At each level a *step rule* (:class:`StepRule`) asks its network for the clean estimate
:math:`\\hat x_0` and draws the sample at the next level from it. The rule changes, the loop
does not:

* :class:`DDPMStep`: the ancestral step of Ho et al. Algorithm 2, one level at a time;
* :class:`DDIMStep`: Song et al. (2021) eq. 12 with stochasticity ``eta``, over any decreasing
  subsequence of levels (:func:`ddim_timesteps`, which may start at ``t_start``);
* :class:`DDGANStep`: the DD-GAN generation step (Xiao et al. 2022; AAMDM §3.3): a generator
  with a latent ``r`` predicts :math:`\\hat x_0`, then the posterior is sampled;
* :class:`PolishStep`: the AAMDM polishing step (§3.2): an x0-predicting polisher, then the
  Gaussian posterior step;
* :class:`Handover` joins two rules in one chain (AAMDM's GAN levels, then polishing levels).

Denoisers are callables ``model(x_t, t, cond) -> prediction`` with ``x_t`` of shape ``(B, D)``,
``t`` a ``(B,)`` long tensor and ``cond`` a ``(B, C)`` context tensor (or ``None``); the
prediction is the noise ``eps`` (A-MDM eq. 3) or the clean sample ``x0``, as named by
``predicts``.

**Hooks.** The chain calls two kinds of hooks, so that control never copies the loop:

* *hooks on* :math:`\\hat x_0`, ``hook(t, x_t, x0_hat) -> x0_hat``, change the network's clean
  estimate before the step uses it: the guidance of AAMDM eq. 13 (a hook with
  ``needs_grad = True`` gets an ``x_t`` it can differentiate through the network) and the clamp
  to the training data's per-feature range (:func:`clip_bounds`, :func:`data_range`);
* *hooks on* :math:`x_t`, ``hook(t, x_t, x0_hat) -> x_t``, run after each step, where ``x_t`` is
  the new sample at level ``t`` (``t = -1``: the final clean sample) and ``x0_hat`` the estimate
  that step used: inpainting (A-MDM eq. 4, :mod:`minimdm.control.hooks`); the RL residuals
  of A-MDM eq. 7 take the same form.

:func:`ddpm_sample`, :func:`ddim_sample`, :func:`p_sample` and
:func:`minimdm.aamdm.model.aamdm_sample` are thin calls of the chain.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
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

__all__ = [
    "NoiseSchedule",
    "q_sample",
    "q_posterior",
    "q_posterior_sample",
    "predict_x0_from_eps",
    "predict_eps_from_x0",
    "clip_bounds",
    "clamp_x0",
    "clamp_hook",
    "data_range",
    "clamp_share",
    "StepRule",
    "DDPMStep",
    "DDIMStep",
    "DDGANStep",
    "PolishStep",
    "Handover",
    "StepCount",
    "predict_x0",
    "chain_step",
    "reverse_chain",
    "p_mean_variance",
    "p_sample",
    "ddpm_sample",
    "ddim_sample",
    "ddim_timesteps",
    "diffusion_loss",
    "check_finite",
]


def check_finite(name: str, x: Tensor) -> None:
    """Raise ``ValueError`` naming ``name`` if ``x`` holds NaN or Inf."""
    if not torch.isfinite(x).all():
        bad = (~torch.isfinite(x)).nonzero()[0].tolist()
        raise ValueError(f"{name} must be finite, but it holds NaN/Inf (first at index {bad})")


class NoiseSchedule:
    """The variance schedule :math:`\\beta_1..\\beta_T` and every buffer derived from it.

    Args:
        kind: ``"linear"`` (Ho et al. 2020, betas from 1e-4 to 0.02 rescaled to T steps) or
            ``"cosine"`` (Nichol & Dhariwal 2021, clipped at 0.999).
        T: number of diffusion steps, 1 to 1000 (more is allowed; no step is hard-coded).
        betas: explicit betas, overriding ``kind``; each must lie in (0, 1).
        device: where the buffers live.

    All buffers are float32 tensors of length ``T``, indexed by the 0-based step ``t``.
    """

    def __init__(
        self,
        kind: Literal["linear", "cosine"] = "cosine",
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
        raise ValueError(f"kind must be 'linear' or 'cosine', got {kind!r}")

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
        noise = torch.randn(x0.shape, generator=generator, device=x0.device, dtype=x0.dtype)
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
    noise = torch.randn(x_t.shape, generator=generator, device=x_t.device, dtype=x_t.dtype)
    return mean + var.sqrt() * noise


# --------------------------------------------------------------------------------------------
# The x0 clamp: the training data's per-feature range


def clip_bounds(
    clip_x0: ClipX0,
    dim: int,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> float | tuple[Tensor, Tensor] | None:
    """Check a ``clip_x0`` setting and return it as ``None``, a float or ``(lo, hi)`` tensors.

    ``clip_x0`` is one of

    * ``None``: no clamp;
    * a float ``c > 0``: the symmetric box ``[-c, c]`` (explicit or legacy);
    * a pair ``(lo, hi)`` of length-``dim`` sequences or tensors, ``lo <= hi``: a per-feature
      box in normalized units, normally the training data's range (:func:`data_range`). A
      nested list ``[[lo...], [hi...]]`` (a checkpoint's JSON) or a ``(2, dim)`` tensor is such
      a pair.

    The tensors come back with ``dtype`` on ``device``, shape ``(dim,)`` each.
    """
    if clip_x0 is None:
        return None
    if isinstance(clip_x0, Tensor) and clip_x0.dim() == 0:
        clip_x0 = float(clip_x0)
    if isinstance(clip_x0, (int, float)) and not isinstance(clip_x0, bool):
        c = float(clip_x0)
        if not math.isfinite(c) or c <= 0:
            raise ValueError(f"clip_x0 must be a finite float > 0, got {clip_x0!r}")
        return c
    expected = f"None, a float > 0 or a pair (lo, hi) of {dim} values each"
    if isinstance(clip_x0, (str, bytes, bool)):
        hint = " ('data' is resolved by training from its frames)" if clip_x0 == "data" else ""
        raise ValueError(f"clip_x0 must be {expected}, got {clip_x0!r}{hint}")
    try:
        lo, hi = clip_x0
        lo = torch.as_tensor(lo, dtype=dtype, device=device)
        hi = torch.as_tensor(hi, dtype=dtype, device=device)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"clip_x0 must be {expected}, got a {type(clip_x0).__name__}") from None
    if lo.shape != (dim,) or hi.shape != (dim,):
        raise ValueError(
            f"clip_x0 must be a pair (lo, hi) of {dim} values each (one per feature), got shapes "
            f"{tuple(lo.shape)} and {tuple(hi.shape)}"
        )
    if not (torch.isfinite(lo).all() and torch.isfinite(hi).all()):
        raise ValueError("clip_x0 must hold finite bounds, but (lo, hi) holds NaN/Inf")
    if (lo > hi).any():
        i = int((lo > hi).nonzero()[0])
        raise ValueError(f"clip_x0 must have lo <= hi, but feature {i} has {lo[i]} > {hi[i]}")
    return lo, hi


def clamp_x0(x0: Tensor, bounds: float | tuple[Tensor, Tensor] | None) -> Tensor:
    """Clamp a clean estimate (B, D) to the bounds of :func:`clip_bounds`."""
    if bounds is None:
        return x0
    if isinstance(bounds, float):
        return x0.clamp(-bounds, bounds)
    return x0.clamp(bounds[0], bounds[1])


def data_range(frames: Tensor | Sequence[Tensor]) -> tuple[Tensor, Tensor]:
    """The per-feature range ``(lo, hi)`` of ``frames`` (N, D) or a list of (F_i, D) arrays.

    Returned as float32 (D,) tensors, rounded outwards, so that clamping any of the frames to it
    changes nothing: :func:`clamp_share` of the same frames is 0.
    """
    x = _stack_frames(frames)
    lo, hi = x.amin(0), x.amax(0)  # (D,)
    lo32, hi32 = lo.float(), hi.float()
    inf = torch.tensor(math.inf)
    lo32 = torch.where(lo32.double() > lo.double(), torch.nextafter(lo32, -inf), lo32)
    hi32 = torch.where(hi32.double() < hi.double(), torch.nextafter(hi32, inf), hi32)
    return lo32, hi32


def clamp_share(clip_x0: ClipX0, frames: Tensor | Sequence[Tensor]) -> float:
    """The share of ``frames`` (N, D) with at least one feature outside the clamp ``clip_x0``.

    These frames cannot come out of a sampler that clamps its :math:`\\hat x_0` so; for the
    training frames it should be 0.
    """
    x = _stack_frames(frames).double()
    bounds = clip_bounds(clip_x0, x.shape[-1], x.device, torch.float64)
    if bounds is None:
        return 0.0
    outside = (clamp_x0(x, bounds) != x).any(-1)  # (N,)
    return float(outside.double().mean())


def _stack_frames(frames: Tensor | Sequence[Tensor]) -> Tensor:
    if isinstance(frames, (list, tuple)):
        frames = torch.cat([torch.as_tensor(a) for a in frames])
    x = torch.as_tensor(frames)
    if x.dim() < 2 or x.shape[0] == 0:
        raise ValueError(f"frames must have shape (N >= 1, D), got {tuple(x.shape)}")
    x = x.reshape(-1, x.shape[-1])
    check_finite("frames", x)
    return x


def clamp_hook(
    clip_x0: ClipX0, dim: int, device: torch.device | str | None = None, dtype=torch.float32
) -> X0Hook | None:
    """The clamp as a hook on :math:`\\hat x_0` (None when ``clip_x0`` is None)."""
    bounds = clip_bounds(clip_x0, dim, device, dtype)
    if bounds is None:
        return None
    return lambda t, x_t, x0_hat: clamp_x0(x0_hat, bounds)


# --------------------------------------------------------------------------------------------
# Step rules: how one reverse step uses the clean estimate


class StepRule:
    """One kind of reverse step :math:`x_t \\to x_{t_{next}}` (see the module docstring).

    ``predict`` runs the network and returns :math:`(\\hat x_0, \\hat\\epsilon)` (``eps`` may be
    None); ``step`` draws the next sample from them. A rule may hand some levels to another
    rule: ``at(t)`` returns the rule that makes the step from level ``t``.
    """

    name = "step"
    """What :class:`StepCount` records for a step of this rule."""

    def at(self, t: int) -> StepRule:
        return self

    def predict(
        self, x_t: Tensor, t: int, cond: Tensor | None, generator: torch.Generator | None
    ) -> tuple[Tensor, Tensor | None]:
        raise NotImplementedError

    def step(
        self,
        x_t: Tensor,
        t: int,
        t_next: int,
        x0_hat: Tensor,
        eps: Tensor | None,
        generator: torch.Generator | None,
    ) -> Tensor:
        raise NotImplementedError


def _levels(t: int, x: Tensor) -> Tensor:
    return torch.full((x.shape[0],), t, device=x.device, dtype=torch.long)


def _check_out(name: str, out: Tensor, x_t: Tensor) -> None:
    if out.shape != x_t.shape:
        raise ValueError(f"{name} returned shape {tuple(out.shape)}, expected {tuple(x_t.shape)}")


class _DenoiserRule(StepRule):
    """A denoiser ``model(x_t, t, cond)`` predicting ``eps`` (A-MDM eq. 3) or ``x0``."""

    def __init__(self, model: Denoiser, schedule: NoiseSchedule, predicts: str = "eps") -> None:
        if predicts not in ("eps", "x0"):
            raise ValueError(f"predicts must be 'eps' or 'x0', got {predicts!r}")
        self.model, self.schedule, self.predicts = model, schedule, predicts

    def predict(self, x_t, t, cond, generator):
        out = self.model(x_t, _levels(t, x_t), cond)
        _check_out("denoiser", out, x_t)
        if self.predicts == "eps":
            return predict_x0_from_eps(self.schedule, x_t, t, out), out
        return out, None


class DDPMStep(_DenoiserRule):
    """Ancestral step (Ho et al. Algorithm 2): :math:`x_{t-1} \\sim \\mathcal N(\\tilde\\mu_t(x_t,
    \\hat x_0), \\tilde\\beta_t I)`; the last step (``t = 0``) returns the mean, without noise."""

    name = "ddpm"

    def step(self, x_t, t, t_next, x0_hat, eps, generator):
        if t_next != t - 1:
            raise ValueError(f"a DDPM step goes one level down, from {t} to {t - 1}, not {t_next}")
        mean, var = q_posterior(self.schedule, x0_hat, x_t, t)
        if t == 0:
            return mean
        noise = torch.randn(x_t.shape, generator=generator, device=x_t.device, dtype=x_t.dtype)
        return mean + var.sqrt() * noise


class DDIMStep(_DenoiserRule):
    """DDIM step (Song et al. 2021, eq. 12) from level ``t`` to any lower ``t_next``.

    :math:`x_{next} = \\sqrt{\\bar\\alpha_{next}}\\hat x_0 + \\sqrt{1-\\bar\\alpha_{next}-
    \\sigma^2}\\,\\hat\\epsilon + \\sigma z`; ``eta = 0`` is deterministic, ``eta = 1`` has
    DDPM's variance.
    """

    name = "ddim"

    def __init__(
        self, model: Denoiser, schedule: NoiseSchedule, predicts: str = "eps", eta: float = 0.0
    ) -> None:
        super().__init__(model, schedule, predicts)
        if eta < 0:
            raise ValueError(f"eta must be >= 0, got {eta}")
        self.eta = eta

    def step(self, x_t, t, t_next, x0_hat, eps, generator):
        if eps is None:  # x0-prediction, or an x0 hook changed the estimate
            eps = predict_eps_from_x0(self.schedule, x_t, t, x0_hat)
        ac = self.schedule.alphas_cumprod
        a_t = ac[t]
        a_next = ac[t_next] if t_next >= 0 else torch.ones_like(a_t)
        # \sigma = \eta \sqrt{(1-\bar\alpha_{next})/(1-\bar\alpha_t)}
        #          \sqrt{1-\bar\alpha_t/\bar\alpha_{next}}
        sigma = (
            self.eta * ((1 - a_next) / (1 - a_t)).sqrt() * (1 - a_t / a_next).clamp(min=0).sqrt()
        )
        x = a_next.sqrt() * x0_hat + (1 - a_next - sigma**2).clamp(min=0).sqrt() * eps
        if t_next >= 0 and self.eta > 0:
            x = x + sigma * torch.randn(
                x.shape, generator=generator, device=x.device, dtype=x.dtype
            )
        return x


class _PosteriorRule(StepRule):
    """Draw :math:`x_{t-1} \\sim q(x_{t-1} | x_t, \\hat x_0)`; the last step returns
    :math:`\\hat x_0` (the posterior at ``t = 0`` is a point mass there)."""

    def step(self, x_t, t, t_next, x0_hat, eps, generator):
        if t_next == -1:
            return x0_hat
        if t_next != t - 1:
            raise ValueError(f"a {self.name} step goes from {t} to {t - 1} or -1, not {t_next}")
        return q_posterior_sample(self.schedule, x0_hat, x_t, t, generator)


class DDGANStep(_PosteriorRule):
    """DD-GAN generation step (Xiao et al. 2022; AAMDM §3.3, eq. 10).

    A latent :math:`r \\sim \\mathcal N(0, I)` per sample makes the step multimodal:
    :math:`\\hat x_0 = G(x_t, t - t_{offset}, cond, r)`, then the posterior sample. The
    generator sees the level within its own chain, ``t - t_offset``.
    """

    name = "gan"

    def __init__(
        self, gan: Callable, schedule: NoiseSchedule, latent_dim: int, t_offset: int = 0
    ) -> None:
        self.gan, self.schedule, self.latent_dim, self.t_offset = (
            gan,
            schedule,
            latent_dim,
            t_offset,
        )

    def predict(self, x_t, t, cond, generator):
        B = x_t.shape[0]
        r = torch.randn((B, self.latent_dim), generator=generator, device=x_t.device)  # (B, R)
        out = self.gan(x_t, _levels(t, x_t) - self.t_offset, cond, r)
        _check_out(self.name, out, x_t)
        return out, None


class PolishStep(_PosteriorRule):
    """AAMDM polishing step (§3.2, eq. 6): an x0-predicting polisher, a Gaussian posterior step."""

    name = "adm"

    def __init__(self, polisher: Denoiser, schedule: NoiseSchedule) -> None:
        self.polisher, self.schedule = polisher, schedule

    def predict(self, x_t, t, cond, generator):
        out = self.polisher(x_t, _levels(t, x_t), cond)
        _check_out(self.name, out, x_t)
        return out, None


class Handover(StepRule):
    """``high`` makes the steps from levels ``>= t_low``, ``low`` the others (AAMDM §3.4)."""

    def __init__(self, high: StepRule, low: StepRule | None, t_low: int) -> None:
        self.high, self.low, self.t_low = high, low, t_low

    def at(self, t: int) -> StepRule:
        rule = self.high if t >= self.t_low else self.low
        if rule is None:
            raise ValueError(f"no step rule for level {t} (below the hand-over {self.t_low})")
        return rule.at(t)


# --------------------------------------------------------------------------------------------
# The reverse chain


@dataclass
class StepCount:
    """What a reverse chain did: one entry per step, noisiest first."""

    levels: list[int] = field(default_factory=list)
    """The level t of x_t each step started from."""
    modules: list[str] = field(default_factory=list)
    """The step rule's name, e.g. 'gan' or 'adm' (AAMDM), 'ddpm', 'ddim'."""

    @property
    def gan_steps(self) -> int:
        return self.modules.count("gan")

    @property
    def adm_steps(self) -> int:
        return self.modules.count("adm")

    @property
    def network_calls(self) -> int:
        return len(self.modules)


def predict_x0(
    rule: StepRule,
    x_t: Tensor,
    t: int,
    cond: Tensor | None = None,
    generator: torch.Generator | None = None,
    x0_hooks: Sequence[X0Hook] = (),
) -> tuple[Tensor, Tensor | None]:
    """The rule's clean estimate at level ``t`` after the hooks on :math:`\\hat x_0`.

    Returns ``(x0_hat, eps_hat)``; ``eps_hat`` is None when a hook ran (the step rule then
    derives it from the changed :math:`\\hat x_0`). When a hook has ``needs_grad = True``
    (guidance, AAMDM eq. 13) the network runs with gradients on a copy of ``x_t`` that
    requires them, which the hooks receive as ``x_t``.
    """
    rule = rule.at(t)
    if not any(getattr(h, "needs_grad", False) for h in x0_hooks):
        x0_hat, eps = rule.predict(x_t, t, cond, generator)
        for h in x0_hooks:
            x0_hat = h(t, x_t, x0_hat)
        return x0_hat, (None if x0_hooks else eps)
    with torch.enable_grad():
        x = x_t.detach().requires_grad_(True)
        x0_hat, _ = rule.predict(x, t, cond, generator)
        for h in x0_hooks:
            x0_hat = h(t, x, x0_hat)
    return x0_hat.detach(), None


def chain_step(
    rule: StepRule,
    x_t: Tensor,
    t: int,
    t_next: int,
    cond: Tensor | None = None,
    generator: torch.Generator | None = None,
    x0_hooks: Sequence[X0Hook] = (),
    count: StepCount | None = None,
) -> tuple[Tensor, Tensor]:
    """One step of the reverse chain from level ``t`` to ``t_next``: ``(x_{t_next}, x0_hat)``."""
    x0_hat, eps = predict_x0(rule, x_t, t, cond, generator, x0_hooks)
    rule = rule.at(t)
    if count is not None:
        count.levels.append(t)
        count.modules.append(rule.name)
    return rule.step(x_t, t, t_next, x0_hat, eps, generator), x0_hat


@torch.no_grad()
def reverse_chain(
    rule: StepRule,
    x: Tensor,
    levels: Sequence[int],
    cond: Tensor | None = None,
    generator: torch.Generator | None = None,
    hooks: Sequence[Hook] = (),
    x0_hooks: Sequence[X0Hook] = (),
    count: StepCount | None = None,
) -> Tensor:
    """The reverse diffusion chain: the one loop over denoising levels of the library.

    Args:
        rule: the :class:`StepRule` (DDPM, DDIM, DD-GAN, polishing, or a :class:`Handover`).
        x: (B, D) the sample at level ``levels[0]``.
        levels: strictly decreasing levels in ``[0, T)``; step ``i`` goes from ``levels[i]`` to
            ``levels[i + 1]``, the last one to ``-1`` (clean data).
        cond: (B, C) context, e.g. the previous frame.
        hooks: ``hook(t_next, x, x0_hat) -> x``, in order, after every step (module docstring).
        x0_hooks: ``hook(t, x_t, x0_hat) -> x0_hat``, in order, before every step uses
            :math:`\\hat x_0`: guidance, then the clamp.
        count: a :class:`StepCount` to fill with the steps taken.

    Returns:
        The sample at level -1, (B, D).
    """
    levels = [int(t) for t in levels]
    decreasing = all(a > b for a, b in zip(levels[:-1], levels[1:], strict=True))
    if not levels or not decreasing or levels[-1] < 0:
        raise ValueError(f"levels must be a non-empty, strictly decreasing list >= 0, got {levels}")
    for i, t in enumerate(levels):
        t_next = levels[i + 1] if i + 1 < len(levels) else -1
        x, x0_hat = chain_step(rule, x, t, t_next, cond, generator, x0_hooks, count)
        for hook in hooks:
            x = hook(t_next, x, x0_hat)
    return x


# --------------------------------------------------------------------------------------------
# The samplers: thin calls of the chain


def _hooks(hook: Hook | None) -> list[Hook]:
    return [] if hook is None else [hook]


def _x0_hooks(clip_x0: ClipX0, dim: int, device, dtype) -> list[X0Hook]:
    h = clamp_hook(clip_x0, dim, device, dtype)
    return [] if h is None else [h]


def p_mean_variance(
    model: Denoiser,
    schedule: NoiseSchedule,
    x_t: Tensor,
    t: int,
    cond: Tensor | None = None,
    predicts: str = "eps",
    clip_x0: ClipX0 = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """The learned reverse step :math:`p_\\theta(x_{t-1}|x_t)`: ``(mean, variance, x0_hat)``.

    The mean is the posterior mean with the model's :math:`\\hat x_0` plugged in; the variance is
    the posterior variance :math:`\\tilde\\beta_t` (Ho et al. §3.2).
    """
    rule = DDPMStep(model, schedule, predicts)
    clamp = _x0_hooks(clip_x0, x_t.shape[-1], x_t.device, x_t.dtype)
    x0_hat, _ = predict_x0(rule, x_t, t, cond, None, clamp)
    mean, var = q_posterior(schedule, x0_hat, x_t, t)
    return mean, var, x0_hat


def p_sample(
    model: Denoiser,
    schedule: NoiseSchedule,
    x_t: Tensor,
    t: int,
    cond: Tensor | None = None,
    generator: torch.Generator | None = None,
    predicts: str = "eps",
    clip_x0: ClipX0 = None,
) -> tuple[Tensor, Tensor]:
    """One ancestral step :math:`x_{t-1} \\sim p_\\theta(x_{t-1}|x_t)`: ``(x_{t-1}, x0_hat)``.

    At ``t = 0`` it returns the mean, without noise. One :func:`chain_step` of :class:`DDPMStep`.
    """
    clamp = _x0_hooks(clip_x0, x_t.shape[-1], x_t.device, x_t.dtype)
    return chain_step(DDPMStep(model, schedule, predicts), x_t, t, t - 1, cond, generator, clamp)


def _check_inputs(
    shape: tuple[int, ...], cond: Tensor | None, cond_dim: int | None, x_start: Tensor | None
) -> None:
    if cond is not None:
        check_finite("cond", cond)
        if cond.shape[0] != shape[0]:
            raise ValueError(f"cond must have batch size {shape[0]}, got shape {tuple(cond.shape)}")
        if cond_dim is not None and cond.shape[-1] != cond_dim:
            raise ValueError(
                f"cond must have shape ({shape[0]}, {cond_dim}), got {tuple(cond.shape)}"
            )
    if x_start is not None:
        check_finite("x_start", x_start)
        if tuple(x_start.shape) != tuple(shape):
            raise ValueError(f"x_start must have shape {tuple(shape)}, got {tuple(x_start.shape)}")


def _start(shape, x_start, generator, device, dtype):
    if x_start is not None:
        return x_start.to(device=device, dtype=dtype)
    return torch.randn(shape, generator=generator, device=device, dtype=dtype)


def _check_t_start(t_start: int | None, T: int) -> int:
    t_start = T - 1 if t_start is None else int(t_start)
    if not 0 <= t_start < T:
        raise ValueError(f"t_start must lie in [0, {T - 1}], got {t_start}")
    return t_start


def ddpm_sample(
    model: Denoiser,
    schedule: NoiseSchedule,
    shape: tuple[int, ...],
    cond: Tensor | None = None,
    generator: torch.Generator | None = None,
    hook: Hook | None = None,
    predicts: str = "eps",
    t_start: int | None = None,
    x_start: Tensor | None = None,
    clip_x0: ClipX0 = None,
    cond_dim: int | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """Ancestral DDPM sampling (Ho et al. Algorithm 2), conditioned on ``cond``.

    Args:
        shape: ``(B, D)`` of the samples.
        cond: context tensor ``(B, C)``, e.g. the previous frame :math:`x_{f-1}` in A-MDM.
        hook: ``hook(t, x_t, x0_hat) -> x_t``, called after every step (see module docstring).
        t_start: start the chain at level ``t_start`` (default ``T - 1``); with ``x_start`` this
            runs the partial chains of keyframe inbetweening (A-MDM eq. 5).
        x_start: the sample at level ``t_start`` (default: standard normal noise).
        clip_x0: clamp :math:`\\hat x_0` at every step: None, a float ``c`` (``[-c, c]``) or a
            per-feature pair ``(lo, hi)`` (:func:`clip_bounds`).
        cond_dim: if given, ``cond`` must have this last dimension.

    Returns:
        The clean samples, shape ``shape``.
    """
    device = device or (cond.device if cond is not None else schedule.device)
    _check_inputs(shape, cond, cond_dim, x_start)
    t_start = _check_t_start(t_start, schedule.T)
    rule = DDPMStep(model, schedule, predicts)
    clamp = _x0_hooks(clip_x0, shape[-1], device, dtype)
    x = _start(shape, x_start, generator, device, dtype)
    return reverse_chain(rule, x, range(t_start, -1, -1), cond, generator, _hooks(hook), clamp)


def ddim_timesteps(T: int, steps: int, t_start: int | None = None) -> list[int]:
    """An evenly spaced, strictly decreasing subsequence of ``steps`` indices of ``0..T-1``.

    With ``t_start`` the chain starts at that level and continues on the same grid below it,
    so a chain started lower takes proportionally fewer steps.
    """
    if not 1 <= steps <= T:
        raise ValueError(f"steps must lie in [1, T={T}], got {steps}")
    ts = torch.linspace(T - 1, 0, steps).round().long().tolist()
    ts = list(dict.fromkeys(ts))
    if t_start is None:
        return ts
    t_start = _check_t_start(t_start, T)
    return [t_start] + [t for t in ts if t < t_start]


def ddim_sample(
    model: Denoiser,
    schedule: NoiseSchedule,
    shape: tuple[int, ...],
    cond: Tensor | None = None,
    steps: int | None = None,
    eta: float = 0.0,
    generator: torch.Generator | None = None,
    hook: Hook | None = None,
    predicts: str = "eps",
    x_start: Tensor | None = None,
    clip_x0: ClipX0 = None,
    cond_dim: int | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
    t_start: int | None = None,
) -> Tensor:
    """DDIM sampling (Song et al. 2021, eq. 12) over ``steps`` of the schedule's ``T`` levels.

    ``eta = 0`` is deterministic given the starting noise; ``eta = 1`` matches DDPM's variance.
    The hook receives the level the chain moves to next (``-1`` after the last step).
    ``t_start`` and ``x_start`` start the chain at that level from that sample, then follow
    :func:`ddim_timesteps` below it (keyframe inbetweening, A-MDM eq. 5).
    """
    device = device or (cond.device if cond is not None else schedule.device)
    rule = DDIMStep(model, schedule, predicts, eta)
    _check_inputs(shape, cond, cond_dim, x_start)
    ts = ddim_timesteps(schedule.T, steps or schedule.T, t_start)
    clamp = _x0_hooks(clip_x0, shape[-1], device, dtype)
    x = _start(shape, x_start, generator, device, dtype)
    return reverse_chain(rule, x, ts, cond, generator, _hooks(hook), clamp)


def diffusion_loss(
    model: Denoiser,
    schedule: NoiseSchedule,
    x0: Tensor,
    cond: Tensor | None = None,
    generator: torch.Generator | None = None,
    predicts: str = "eps",
    reduce: bool = True,
) -> tuple[Tensor, Tensor]:
    """The simple DDPM loss (A-MDM eq. 3) at a uniformly drawn step per sample.

    With ``predicts="eps"``: :math:`\\|\\epsilon - p_\\theta(x_{f-1}, x_f^t, e^t)\\|^2`; with
    ``"x0"`` the target is the clean sample. Returns ``(loss, x0_hat)``; ``x0_hat`` is the
    model's reconstruction, which scheduled sampling feeds forward as the next condition
    (A-MDM §3.2). ``reduce=False`` returns the per-sample loss.
    """
    B = x0.shape[0]
    t = torch.randint(0, schedule.T, (B,), generator=generator, device=x0.device)
    noise = torch.randn(x0.shape, generator=generator, device=x0.device, dtype=x0.dtype)
    x_t = q_sample(schedule, x0, t, noise)
    out = model(x_t, t, cond)
    if predicts == "eps":
        target, x0_hat = noise, predict_x0_from_eps(schedule, x_t, t, out)
    elif predicts == "x0":
        target, x0_hat = x0, out
    else:
        raise ValueError(f"predicts must be 'eps' or 'x0', got {predicts!r}")
    loss = ((out - target) ** 2).flatten(1).mean(1)
    return (loss.mean() if reduce else loss), x0_hat
