"""The one reverse chain: step rules, the loop over levels, its hooks (:mod:`minimdm.diffusion`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from .schedule import (
    PREDICTS,
    Denoiser,
    Hook,
    NoiseSchedule,
    X0Hook,
    gaussian,
    predict_eps_from_v,
    predict_eps_from_x0,
    predict_x0_from_eps,
    predict_x0_from_v,
    q_posterior,
    q_posterior_sample,
)


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
    """A denoiser ``model(x_t, t, cond)`` predicting ``eps`` (A-MDM eq. 3), ``x0`` or ``v``."""

    def __init__(self, model: Denoiser, schedule: NoiseSchedule, predicts: str = "eps") -> None:
        if predicts not in PREDICTS:
            raise ValueError(f"predicts must be one of {PREDICTS}, got {predicts!r}")
        self.model, self.schedule, self.predicts = model, schedule, predicts

    def predict(self, x_t, t, cond, generator):
        out = self.model(x_t, _levels(t, x_t), cond)
        _check_out("denoiser", out, x_t)
        if self.predicts == "eps":
            return predict_x0_from_eps(self.schedule, x_t, t, out), out
        if self.predicts == "v":
            s = self.schedule
            return predict_x0_from_v(s, x_t, t, out), predict_eps_from_v(s, x_t, t, out)
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
        noise = gaussian(x_t.shape, generator, x_t.device, x_t.dtype)
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
            x = x + sigma * gaussian(x.shape, generator, x.device, x.dtype)
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
        r = gaussian((B, self.latent_dim), generator, x_t.device)  # (B, R)
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
    """One step of the reverse chain from level ``t`` to ``t_next``: ``(x_{t_next}, x0_hat)``.

    The same step as one pass of :func:`reverse_chain`'s loop, for callers that step by hand.
    """
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
        x0_hat, eps = predict_x0(rule, x, t, cond, generator, x0_hooks)  # the network
        step = rule.at(t)
        if count is not None:
            count.levels.append(t)
            count.modules.append(step.name)
        x = step.step(x, t, t_next, x0_hat, eps, generator)  # e.g. DDPM: the posterior
        for hook in hooks:
            x = hook(t_next, x, x0_hat)
    return x


# --------------------------------------------------------------------------------------------
# The samplers: thin calls of the chain
