"""DDPM and DDIM: noise schedules, the forward process, the posterior and two samplers.

Notation follows Ho et al. (2020) and the A-MDM paper (Shi et al. 2024, §3.1):

* ``t`` is a 0-based step index, ``0 <= t < T``. Index ``t`` is the paper's step ``t + 1``:
  ``x_t`` below is the paper's :math:`x^{t+1}`. We extend it by one value, ``t = -1``, which
  denotes clean data (the paper's :math:`x^0`), so that every sample in the reverse chain has a
  level: noise enters at ``T - 1`` and the last step leaves at ``-1``.
* Every function is batched over the leading dimension, works on any device, and draws its
  randomness from an explicit :class:`torch.Generator`.

The samplers take a *denoiser*: any callable ``model(x_t, t, cond) -> prediction`` with
``x_t`` of shape ``(B, D)``, ``t`` a ``(B,)`` long tensor and ``cond`` a ``(B, C)`` context
tensor (or ``None``). The prediction is the noise ``eps`` (A-MDM eq. 3) or the clean sample
``x0``, as named by ``predicts``.

Per-step hook. After each reverse step both samplers call ``hook(t, x_t, x0_hat) -> x_t``,
where ``x_t`` is the new sample at level ``t`` (``t = -1``: the final clean sample) and
``x0_hat`` the model's estimate of the clean sample at that step. Inpainting (A-MDM eq. 4),
inbetweening, RL residuals (A-MDM eq. 7) and guidance are all such hooks; none copies the loop.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Literal

import torch
from torch import Tensor

Hook = Callable[[int, Tensor, Tensor], Tensor]
Denoiser = Callable[[Tensor, Tensor, Tensor | None], Tensor]

__all__ = [
    "NoiseSchedule",
    "q_sample",
    "q_posterior",
    "predict_x0_from_eps",
    "predict_eps_from_x0",
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


def _model_x0_eps(
    model: Denoiser,
    schedule: NoiseSchedule,
    x_t: Tensor,
    t: int,
    cond: Tensor | None,
    predicts: str,
    clip_x0: float | None,
) -> tuple[Tensor, Tensor]:
    """Run the denoiser at step ``t`` and return ``(x0_hat, eps_hat)``."""
    tt = torch.full((x_t.shape[0],), t, device=x_t.device, dtype=torch.long)
    out = model(x_t, tt, cond)
    if out.shape != x_t.shape:
        raise ValueError(f"denoiser returned shape {tuple(out.shape)}, expected {tuple(x_t.shape)}")
    if predicts == "eps":
        eps = out
        x0 = predict_x0_from_eps(schedule, x_t, t, eps)
    elif predicts == "x0":
        x0 = out
        eps = None
    else:
        raise ValueError(f"predicts must be 'eps' or 'x0', got {predicts!r}")
    if clip_x0 is not None:
        x0 = x0.clamp(-clip_x0, clip_x0)
    if eps is None or clip_x0 is not None:
        eps = predict_eps_from_x0(schedule, x_t, t, x0)
    return x0, eps


def p_mean_variance(
    model: Denoiser,
    schedule: NoiseSchedule,
    x_t: Tensor,
    t: int,
    cond: Tensor | None = None,
    predicts: str = "eps",
    clip_x0: float | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """The learned reverse step :math:`p_\\theta(x_{t-1}|x_t)`: ``(mean, variance, x0_hat)``.

    The mean is the posterior mean with the model's :math:`\\hat x_0` plugged in; the variance is
    the posterior variance :math:`\\tilde\\beta_t` (Ho et al. §3.2).
    """
    x0_hat, _ = _model_x0_eps(model, schedule, x_t, t, cond, predicts, clip_x0)
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
    clip_x0: float | None = None,
) -> tuple[Tensor, Tensor]:
    """One ancestral step :math:`x_{t-1} \\sim p_\\theta(x_{t-1}|x_t)`: ``(x_{t-1}, x0_hat)``.

    At ``t = 0`` it returns the mean, without noise.
    """
    mean, var, x0_hat = p_mean_variance(model, schedule, x_t, t, cond, predicts, clip_x0)
    if t == 0:
        return mean, x0_hat
    noise = torch.randn(x_t.shape, generator=generator, device=x_t.device, dtype=x_t.dtype)
    return mean + var.sqrt() * noise, x0_hat


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


def _start(shape, schedule, x_start, generator, device, dtype):
    if x_start is not None:
        return x_start.to(device=device, dtype=dtype)
    return torch.randn(shape, generator=generator, device=device, dtype=dtype)


@torch.no_grad()
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
    clip_x0: float | None = None,
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
        clip_x0: clamp :math:`\\hat x_0` to ``[-clip_x0, clip_x0]`` at every step.
        cond_dim: if given, ``cond`` must have this last dimension.

    Returns:
        The clean samples, shape ``shape``.
    """
    device = device or (cond.device if cond is not None else schedule.device)
    _check_inputs(shape, cond, cond_dim, x_start)
    t_start = schedule.T - 1 if t_start is None else int(t_start)
    if not 0 <= t_start < schedule.T:
        raise ValueError(f"t_start must lie in [0, {schedule.T - 1}], got {t_start}")
    x = _start(shape, schedule, x_start, generator, device, dtype)
    for t in range(t_start, -1, -1):
        x, x0_hat = p_sample(model, schedule, x, t, cond, generator, predicts, clip_x0)
        if hook is not None:
            x = hook(t - 1, x, x0_hat)
    return x


def ddim_timesteps(T: int, steps: int) -> list[int]:
    """An evenly spaced, strictly decreasing subsequence of ``steps`` indices of ``0..T-1``."""
    if not 1 <= steps <= T:
        raise ValueError(f"steps must lie in [1, T={T}], got {steps}")
    ts = torch.linspace(T - 1, 0, steps).round().long().tolist()
    return list(dict.fromkeys(ts))


@torch.no_grad()
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
    clip_x0: float | None = None,
    cond_dim: int | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """DDIM sampling (Song et al. 2021, eq. 12) over ``steps`` of the schedule's ``T`` levels.

    ``eta = 0`` is deterministic given the starting noise; ``eta = 1`` matches DDPM's variance.
    The hook receives the level the chain moves to next (``-1`` after the last step).
    """
    if eta < 0:
        raise ValueError(f"eta must be >= 0, got {eta}")
    device = device or (cond.device if cond is not None else schedule.device)
    _check_inputs(shape, cond, cond_dim, x_start)
    ts = ddim_timesteps(schedule.T, steps or schedule.T)
    x = _start(shape, schedule, x_start, generator, device, dtype)
    ac = schedule.alphas_cumprod
    for i, t in enumerate(ts):
        t_next = ts[i + 1] if i + 1 < len(ts) else -1
        x0_hat, eps = _model_x0_eps(model, schedule, x, t, cond, predicts, clip_x0)
        a_t = ac[t]
        a_next = ac[t_next] if t_next >= 0 else torch.ones_like(a_t)
        # \sigma = \eta \sqrt{(1-\bar\alpha_{next})/(1-\bar\alpha_t)}
        #          \sqrt{1-\bar\alpha_t/\bar\alpha_{next}}
        sigma = eta * ((1 - a_next) / (1 - a_t)).sqrt() * (1 - a_t / a_next).clamp(min=0).sqrt()
        x = a_next.sqrt() * x0_hat + (1 - a_next - sigma**2).clamp(min=0).sqrt() * eps
        if t_next >= 0 and eta > 0:
            x = x + sigma * torch.randn(
                x.shape, generator=generator, device=x.device, dtype=x.dtype
            )
        if hook is not None:
            x = hook(t_next, x, x0_hat)
    return x


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
