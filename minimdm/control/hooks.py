"""The two pieces of control that act inside the denoising chain of one frame.

* :func:`inpaint_hook` is a hook on :math:`x_t` of the reverse chain
  (:func:`minimdm.diffusion.reverse_chain`, through any sampler's ``hook=``): after every
  reverse step it overwrites the user-specified features with the targets noised to the
  chain's current level (A-MDM eq. 4).
* :func:`inbetween_t_start` is the level a frame's chain starts from when it is initialised
  with a noised keyframe (A-MDM eq. 5); it is passed to the sampler as ``t_start`` (DDPM, or
  DDIM, which then follows its grid of levels below ``t_start``).

Levels follow :mod:`minimdm.diffusion`: 0-based, ``T - 1`` is the noisiest, ``-1`` clean data.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from minimdm.diffusion import Hook, NoiseSchedule, q_sample

__all__ = ["inpaint_hook", "inbetween_t_start"]


def inpaint_hook(
    schedule: NoiseSchedule,
    target: Tensor,
    mask: Tensor,
    generator: torch.Generator | None = None,
    t_stop: int = -1,
) -> Hook:
    """Spatial inpainting as a sampler hook (A-MDM eq. 4).

    .. math:: \\hat x_f^t = (1 - m_f) \\odot x_f^t + m_f \\odot \\tilde x_f^t,
              \\qquad \\tilde x_f^t \\sim q(x^t | \\tilde x_f)

    After the reverse step that leaves the chain at level ``t``, the masked entries are
    replaced by the target noised to level ``t`` with :func:`~minimdm.diffusion.q_sample`
    (fresh noise from ``generator``); at ``t = -1`` (the clean output) by the target itself, so
    a fully masked frame comes out equal to its target.

    Args:
        schedule: the denoiser's schedule.
        target: (B, D) or (D,) desired features :math:`\\tilde x_f` in normalized space.
        mask: (B, D) or (D,) bool, True where the user specified the feature (:math:`m_f = 1`).
        generator: randomness of the noised targets.
        t_stop: the lowest level at which the targets are imposed (-1: every level, the output
            included). A higher value stops inpainting early and leaves the last steps free:
            the buffer frames of A-MDM Fig. 4, a soft constraint.
    """
    mask = torch.as_tensor(mask, dtype=torch.bool, device=target.device)
    if mask.shape[-1] != target.shape[-1]:
        raise ValueError(
            f"mask must have last dim D={target.shape[-1]} (the feature dimension), "
            f"got shape {tuple(mask.shape)}"
        )
    if not -1 <= t_stop < schedule.T:
        raise ValueError(f"t_stop must lie in [-1, {schedule.T - 1}], got {t_stop}")

    def hook(t: int, x_t: Tensor, x0_hat: Tensor) -> Tensor:
        if t < t_stop:
            return x_t
        known = q_sample(schedule, target.expand_as(x_t), t, generator=generator)  # (B, D)
        return torch.where(mask, known, x_t)

    return hook


def inbetween_t_start(f: int, n: int, T: int) -> int:
    """The level frame ``f`` of ``n`` starts denoising from the keyframe (A-MDM eq. 5).

    .. math:: t_0 = \\left(1 - \\frac{f}{N}\\right) t_{max}

    In the paper's 1-based levels the chain of frame f runs the :math:`t_0` steps
    :math:`t_0, \\dots, 1`; as a 0-based index of :mod:`minimdm.diffusion` that is
    :math:`\\lceil t_0 \\rceil - 1`. Frame ``f = n`` would get :math:`t_0 = 0` (no step at all,
    the keyframe pasted); we keep one step, the least noisy, so every frame is the model's
    output. Frame 1 of a long transition starts from (almost) pure noise, level ``T - 1``.

    Args:
        f: the frame, 1..n (frames after the previous keyframe or the start).
        n: frames from the previous keyframe (or the start) to the keyframe, N >= 1.
        T: the schedule's number of steps.
    """
    if not 1 <= f <= n:
        raise ValueError(f"f must lie in [1, n={n}], got {f}")
    return min(max(math.ceil((1 - f / n) * T) - 1, 0), T - 1)
