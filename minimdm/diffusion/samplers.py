"""DDPM and DDIM sampling as thin calls of the one reverse chain.

:class:`StepSettings` says which chain a frame runs (DDPM, or DDIM over fewer steps; what the
denoiser predicts; the clamp), :func:`start_chain` draws what it starts from, and
:func:`~minimdm.diffusion.reverse_chain` runs it: the samplers below and
:meth:`minimdm.amdm.sampling.Sampler.frame` are calls of these three.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .chain import DDIMStep, DDPMStep, StepRule, chain_step, predict_x0, reverse_chain
from .clamp import clamp_hook
from .schedule import (
    ClipX0,
    Denoiser,
    Hook,
    NoiseSchedule,
    X0Hook,
    check_finite,
    gaussian,
    q_posterior,
)


def hook_list(hook: Hook | None) -> list[Hook]:
    """The chain's hook list for one optional hook."""
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


@dataclass(frozen=True)
class StepSettings:
    """How a frame's reverse chain runs: the step rule, its levels and the clamp.

    ``steps`` None (or T): ancestral DDPM over all T levels (Ho et al. Algorithm 2); fewer:
    DDIM (Song et al. 2021, eq. 12) over ``steps`` evenly spaced levels with stochasticity
    ``eta`` (1: as stochastic as DDPM, 0: deterministic given the start noise). ``predicts``
    names the denoiser's output (``"eps"``, A-MDM eq. 3; ``"x0"``; ``"v"``) and ``clip_x0`` the
    clamp of its clean estimate (:func:`clip_bounds`).
    """

    steps: int | None = None
    eta: float = 1.0
    predicts: str = "eps"
    clip_x0: ClipX0 = None

    def is_ddpm(self, T: int) -> bool:
        """Whether a chain takes all ``T`` levels one at a time (DDPM) rather than DDIM's."""
        return self.steps is None or self.steps == T

    def levels(self, T: int, t_start: int | None = None) -> list[int]:
        """The levels of one chain of a ``T``-level schedule, started at ``t_start`` (default
        T - 1): every level below it for DDPM, the DDIM grid (:func:`ddim_timesteps`)."""
        if self.is_ddpm(T):
            return list(range(_check_t_start(t_start, T), -1, -1))
        return ddim_timesteps(T, self.steps, t_start)

    def chain(
        self, model: Denoiser, schedule: NoiseSchedule, t_start: int | None = None
    ) -> tuple[StepRule, list[int]]:
        """The step rule and the levels of one chain, started at ``t_start`` (default T - 1)."""
        if self.is_ddpm(schedule.T):
            rule = DDPMStep(model, schedule, self.predicts)
        else:
            rule = DDIMStep(model, schedule, self.predicts, self.eta)
        return rule, self.levels(schedule.T, t_start)


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


def _check_t_start(t_start: int | None, T: int) -> int:
    t_start = T - 1 if t_start is None else int(t_start)
    if not 0 <= t_start < T:
        raise ValueError(f"t_start must lie in [0, {T - 1}], got {t_start}")
    return t_start


def start_chain(
    shape: tuple[int, ...],
    schedule: NoiseSchedule,
    *,
    cond: Tensor | None = None,
    generator: torch.Generator | None = None,
    x_start: Tensor | None = None,
    clip_x0: ClipX0 = None,
    cond_dim: int | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> tuple[Tensor, list[X0Hook]]:
    r"""What a chain starts from: ``(x, x0_hooks)``, the sample at its first level (``x_start``,
    or standard normal noise) and the clamp ``clip_x0`` of :math:`\hat x_0` as a hook list for
    :func:`reverse_chain`, after checking ``cond`` and ``x_start`` against ``shape``. What
    :func:`ddpm_sample`, :func:`ddim_sample` and :meth:`minimdm.amdm.sampling.Sampler.frame`
    share before the chain runs."""
    device = device or (cond.device if cond is not None else schedule.device)
    _check_inputs(shape, cond, cond_dim, x_start)
    clamp = _x0_hooks(clip_x0, shape[-1], device, dtype)
    if x_start is not None:
        return x_start.to(device=device, dtype=dtype), clamp
    return gaussian(shape, generator, device, dtype), clamp


def ddpm_sample(
    model: Denoiser,
    schedule: NoiseSchedule,
    shape: tuple[int, ...],
    *,
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
    r"""Ancestral DDPM sampling (Ho et al. Algorithm 2), conditioned on ``cond``.

    Args:
        shape: ``(B, D)`` of the samples.
        cond: context tensor ``(B, C)``, e.g. the previous frame :math:`x_{f-1}` in A-MDM.
        hook: ``hook(t, x_t, x0_hat) -> x_t``, called after every step (see module docstring).
        t_start: start the chain at level ``t_start`` (default ``T - 1``); with ``x_start`` this
            runs the partial chains of keyframe inbetweening (A-MDM eq. 5).
        x_start: the sample at level ``t_start`` (default: standard normal noise).
        clip_x0: clamp :math:`\hat x_0` at every step: None, a float ``c`` (``[-c, c]``) or a
            per-feature pair ``(lo, hi)`` (:func:`clip_bounds`).
        cond_dim: if given, ``cond`` must have this last dimension.

    Returns:
        The clean samples, shape ``shape``.
    """
    rule, levels = StepSettings(steps=None, predicts=predicts).chain(model, schedule, t_start)
    x, clamp = start_chain(
        shape,
        schedule,
        cond=cond,
        generator=generator,
        x_start=x_start,
        clip_x0=clip_x0,
        cond_dim=cond_dim,
        device=device,
        dtype=dtype,
    )
    return reverse_chain(rule, x, levels, cond, generator, hook_list(hook), clamp)


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
    *,
    cond: Tensor | None = None,
    steps: int | None = None,
    eta: float = 0.0,
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
    """DDIM sampling (Song et al. 2021, eq. 12) over ``steps`` of the schedule's ``T`` levels.

    ``eta = 0`` is deterministic given the starting noise; ``eta = 1`` matches DDPM's variance.
    The hook receives the level the chain moves to next (``-1`` after the last step).
    ``t_start`` and ``x_start`` start the chain at that level from that sample, then follow
    :func:`ddim_timesteps` below it (keyframe inbetweening, A-MDM eq. 5). Unlike
    :class:`StepSettings`, ``steps = T`` still takes DDIM steps.
    """
    rule = DDIMStep(model, schedule, predicts, eta)
    levels = ddim_timesteps(schedule.T, steps or schedule.T, t_start)
    x, clamp = start_chain(
        shape,
        schedule,
        cond=cond,
        generator=generator,
        x_start=x_start,
        clip_x0=clip_x0,
        cond_dim=cond_dim,
        device=device,
        dtype=dtype,
    )
    return reverse_chain(rule, x, levels, cond, generator, hook_list(hook), clamp)
