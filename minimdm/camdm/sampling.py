"""Sampling CAMDM on the one reverse chain, with classifier-free guidance (Chen et al. 2024, eq. 5).

:class:`GuidedStep` is a step rule of :func:`minimdm.diffusion.reverse_chain`: the ancestral
DDPM step with an x0-predicting network (CAMDM trains and samples with the same 8 steps), whose
clean estimate is the classifier-free combination of eq. 5,

.. math:: \\hat x_0 = G(x_t, t; \\varnothing, c) + \\gamma\\,\\bigl(G(x_t, t; p, c) -
          G(x_t, t; \\varnothing, c)\\bigr),

on the past motion p (CFG-PM, ``guide="past"``) or, the paper's rejected alternative, on the
style label (CFG-S, ``guide="style"``), or, per sample, on either (``guide`` a (B,) bool tensor,
True where the sample guides on its style: the controller guides on the style at steady state
and on the past right after a style change). Both halves run in **one** forward pass: the batch is
doubled, conditional rows first. At ``gamma = 1`` the combination is the conditional model
itself, so the rule calls the conditional model alone (as the paper does, to save the second
half): the sample is then bit for bit that of the conditional model. ``gamma`` may differ per
sample (a controller switches style for some characters only). A traced chain (the fast path,
:mod:`minimdm.fast`, where ``gamma`` is an input of the graph) always runs both halves;
``gamma=None`` (no guidance) traces the conditional model alone, the fast path's graph for the
plans at ``gamma = 1``.

:func:`sample_future` draws F future frames for a batch of conditions.
"""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from minimdm.diffusion import DDPMStep, NoiseSchedule, NoiseTape, StepCount, gaussian, reverse_chain
from minimdm.validate import InputError, check_number

from .model import CAMDM, Conditions

__all__ = ["GuidedStep", "check_guide", "guided_x0", "gamma_per_sample", "sample_future"]


def gamma_per_sample(gamma: float | Tensor, B: int, device: torch.device | str) -> Tensor:
    """(B,) float32 CFG scales from one number or one per sample; refuses other shapes, NaN."""
    g = torch.as_tensor(gamma, dtype=torch.float32, device=device)
    if g.dim() == 0:
        g = g.expand(B)
    if g.shape != (B,) or not torch.isfinite(g).all():
        raise InputError(f"gamma must be a finite number or a ({B},) tensor, got {tuple(g.shape)}")
    return g


def check_guide(guide: str | Tensor, B: int) -> str | Tensor:
    """``guide`` as :func:`guided_x0` takes it: 'past', 'style', or a (B,) bool tensor (True:
    that sample guides on its style, False: on its past motion)."""
    if isinstance(guide, Tensor):
        if guide.dtype != torch.bool or guide.shape != (B,):
            raise InputError(
                f"guide must be 'past', 'style' or a ({B},) bool tensor (True: on the style), got "
                f"a {guide.dtype} tensor of shape {tuple(guide.shape)}"
            )
        return guide
    if guide not in ("past", "style"):
        raise InputError(f"guide must be 'past' (CFG-PM) or 'style' (CFG-S), got {guide!r}")
    return guide


def drop_guided(cond: Conditions, guide: str | Tensor) -> Conditions:
    """``cond`` without what each sample guides on (the second half of eq. 5)."""
    if isinstance(guide, str):
        return cond.without(guide)
    on_style = guide.to(cond.past.device)
    return replace(cond, keep_past=on_style, keep_style=~on_style)


def guided_x0(
    model: CAMDM,
    x_t: Tensor,
    t: Tensor,
    cond: Conditions,
    gamma: float | Tensor | None,
    guide: str | Tensor,
) -> Tensor:
    """The clean estimate of eq. 5 for ``x_t`` (B, F, D) at levels ``t`` (B,).

    When every row has ``gamma = 1`` the model runs once on the B rows: the conditional model
    exactly. Otherwise it runs once on 2 B rows (``cond``, then ``cond`` without ``guide``) and
    combines the halves; rows with ``gamma = 1`` take the conditional half as it is (equal to a
    call on B rows up to the float rounding of the larger batch). Under tracing
    (:mod:`minimdm.fast`) ``gamma`` is an input of the graph, which keeps the 2 B rows for every
    ``gamma``. ``gamma=None`` is no guidance: the conditional model on the B rows, traced too.
    ``guide``: 'past', 'style', or per sample a (B,) bool tensor, True where the sample guides on
    its style.
    """
    guide = check_guide(guide, x_t.shape[0])
    if gamma is None:
        return model(x_t, t, cond)
    g = gamma_per_sample(gamma, x_t.shape[0], x_t.device)
    if not torch.jit.is_tracing() and bool((g == 1).all()):
        return model(x_t, t, cond)
    both = model(torch.cat([x_t, x_t]), torch.cat([t, t]), cond.cat(drop_guided(cond, guide)))
    full, dropped = both.chunk(2)  # G(x_t; p, c), G(x_t; ∅, c)
    w = g.view(-1, *([1] * (x_t.dim() - 1)))
    return torch.where(w == 1, full, dropped + w * (full - dropped))


class GuidedStep(DDPMStep):
    """The DDPM step with the classifier-free clean estimate of eq. 5 (module docstring)."""

    name = "cfg"

    def __init__(
        self,
        model: CAMDM,
        schedule: NoiseSchedule,
        gamma: float | Tensor | None = 1.0,
        guide: str | Tensor = "past",
    ) -> None:
        super().__init__(model, schedule, predicts="x0")
        if isinstance(guide, str):
            guide = check_guide(guide, 0)
        self.gamma, self.guide = gamma, guide

    def predict(self, x_t, t, cond, generator):
        levels = torch.full((x_t.shape[0],), t, device=x_t.device, dtype=torch.long)
        return guided_x0(self.model, x_t, levels, cond, self.gamma, self.guide), None


@torch.no_grad()
def sample_future(
    model: CAMDM,
    schedule: NoiseSchedule,
    cond: Conditions,
    generator: torch.Generator | NoiseTape | None = None,
    *,
    gamma: float | Tensor | None = 1.0,
    guide: str | Tensor = "past",
    count: StepCount | None = None,
) -> Tensor:
    """Draw the clean future ``(B, F, D)`` (normalized units) for conditions of B windows: the
    ancestral chain over the schedule's T levels (CAMDM: T = 8) with :class:`GuidedStep`.

    ``generator`` may be a :class:`~minimdm.diffusion.NoiseTape` (the fast path): its draws are
    x_T, then one (F D) block per step but the last. ``gamma=None``: no guidance (the
    conditional model, as at ``gamma = 1``, also when traced). ``guide``: as
    :func:`guided_x0`."""
    if gamma is not None and not isinstance(gamma, Tensor):
        gamma = check_number("gamma", gamma)
    c = model.config
    shape = (cond.batch, c.future, c.dim)
    device = cond.past.device
    x = gaussian(shape, generator, device)  # x_T (B, F, D)
    rule = GuidedStep(model, schedule, gamma, guide)
    return reverse_chain(rule, x, range(schedule.T - 1, -1, -1), cond, generator, count=count)
