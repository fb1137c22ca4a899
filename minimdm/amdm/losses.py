"""The losses of scheduled-sampling training (A-MDM eq. 3, §3.2), for A-MDM and its baselines.

:func:`frame_loss` is one frame's loss for each model kind; :func:`window_loss` rolls it over
windows of consecutive frames, feeding each sample's own prediction back with a probability
(scheduled sampling); :func:`make_windows` cuts the windows. :mod:`minimdm.amdm.train` runs
them in its loop.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from minimdm.diffusion import (
    NoiseSchedule,
    clamp_x0,
    clip_bounds,
    diffusion_loss,
)

__all__ = ["MODEL_KINDS", "frame_loss", "window_loss", "make_windows"]

MODEL_KINDS = ("amdm", "mse", "mvae")
"""The three models one trainer serves: the A-MDM denoiser, the MSE regressor, the MVAE."""


def frame_loss(
    model: nn.Module,
    x: Tensor,
    cond: Tensor,
    generator: torch.Generator | None,
    kind: str = "amdm",
    schedule: NoiseSchedule | None = None,
    predicts: str = "eps",
    kl_beta: float = 0.2,
) -> tuple[Tensor, Tensor]:
    """Per-sample loss of predicting ``x`` (B, D) from ``cond`` (B, D), and the prediction.

    * amdm: the DDPM loss (A-MDM eq. 3); the prediction is :math:`\\hat x_0` at the drawn step.
    * mse: :math:`\\|f(x_{f-1}) - x_f\\|^2 / D`; the prediction is :math:`f(x_{f-1})`.
    * mvae: :math:`\\|\\hat x_f - x_f\\|^2 / D + \\beta\\,\\mathrm{KL}(q \\| \\mathcal N(0, I)) / D`
      with :math:`q = q(z | x_f, x_{f-1})`, the β-ELBO; the prediction is the reconstruction
      through the posterior.

    Returns ``(loss (B,), prediction (B, D))``.
    """
    if kind == "amdm":
        if schedule is None:
            raise ValueError("schedule is required for kind='amdm'")
        return diffusion_loss(model, schedule, x, cond, generator, predicts, reduce=False)
    if kind == "mse":
        pred = model(cond)
        return ((pred - x) ** 2).mean(1), pred
    if kind == "mvae":
        pred, mu, logvar = model(x, cond, generator)
        rec = ((pred - x) ** 2).mean(1)
        kl = -0.5 * (1 + logvar - mu**2 - logvar.exp()).sum(1)  # (B,)
        return rec + kl_beta * kl / x.shape[1], pred
    raise ValueError(f"kind must be one of {MODEL_KINDS}, got {kind!r}")


def window_loss(
    model: nn.Module,
    windows: Tensor,
    p_student: float,
    generator: torch.Generator | None,
    kind: str = "amdm",
    schedule: NoiseSchedule | None = None,
    predicts: str = "eps",
    kl_beta: float = 0.2,
    clip_x0: Any = None,
    teacher_weight: float = 0.0,
) -> tuple[Tensor, dict[str, float]]:
    """Scheduled-sampling loss over windows (B, N_r + 1, D) (A-MDM §3.2).

    Frame 0 of each window is the ground-truth start. Frame ``f >= 1`` is predicted from the
    condition ``c_f``: ``c_1 = x_0``; for ``f > 1`` each sample takes its own previous
    prediction ``\\hat x_{f-1}`` (detached) with probability ``p_student``, else the ground truth
    ``x_{f-1}``; a fed-back prediction is clamped to ``clip_x0``: None, a float ``c``
    (``[-c, c]``) or a per-feature range ``(lo, hi)`` (:func:`~minimdm.diffusion.clip_bounds`).

    For A-MDM the prediction fed back is the reconstruction :math:`\\hat x_0` at the noise level
    drawn for the loss, as in the paper. With eps-prediction it divides by
    :math:`\\sqrt{\\bar\\alpha_t}`, which is tiny at the noisiest levels: the clamp keeps it
    bounded, and x0-prediction avoids the division.

    ``teacher_weight > 0`` adds, while ``p_student > 0``, that weight times the teacher-forced
    loss of the same windows, as the official A-MDM trainer does at every student step: the
    fit to ground-truth conditions is kept while the model learns to recover from its own.

    Returns the mean loss over frames and samples, and the fraction of student conditions
    used. With ``p_student = 0`` all frames run as one batch.
    """
    if windows.dim() != 3 or windows.shape[1] < 2:
        raise ValueError(
            f"windows must have shape (B, N_r + 1 >= 2, D), got {tuple(windows.shape)}"
        )
    B, n1, D = windows.shape
    bounds = clip_bounds(clip_x0, D, windows.device, windows.dtype)
    if teacher_weight < 0:
        raise ValueError(f"teacher_weight must be >= 0, got {teacher_weight}")
    kw = dict(kind=kind, schedule=schedule, predicts=predicts, kl_beta=kl_beta)

    def teacher_loss() -> Tensor:  # every frame from its ground-truth predecessor, one batch
        x = windows[:, 1:].reshape(B * (n1 - 1), D)  # (B N_r, D)
        cond = windows[:, :-1].reshape(B * (n1 - 1), D)
        return frame_loss(model, x, cond, generator, **kw)[0].mean()

    if p_student <= 0:
        return teacher_loss(), {"student_frac": 0.0}
    cond = windows[:, 0]  # (B, D)
    losses, n_student = [], 0
    for f in range(1, n1):
        loss_f, pred = frame_loss(model, windows[:, f], cond, generator, **kw)
        losses.append(loss_f)
        if f + 1 < n1:
            pred = pred.detach()
            coin = torch.rand(B, generator=generator, device=windows.device) < p_student  # (B,)
            pred = clamp_x0(pred, bounds)
            n_student += int(coin.sum())
            cond = torch.where(coin[:, None], pred, windows[:, f])
    frac = n_student / (B * max(n1 - 2, 1))
    loss = torch.stack(losses).mean()
    if teacher_weight > 0:
        loss = loss + teacher_weight * teacher_loss()
    return loss, {"student_frac": frac}


def make_windows(features: Sequence[Tensor | np.ndarray], n: int) -> Tensor:
    """Every window of ``n + 1`` consecutive frames of every clip, stacked: (W, n + 1, D).

    Windows never cross clips (:class:`~minimdm.motion.features.WindowDataset`); clips shorter than
    ``n + 1`` frames contribute none.
    """
    from minimdm.motion.features import WindowDataset

    for i, a in enumerate(features):
        a = torch.as_tensor(a)
        if a.dim() != 2:
            raise ValueError(f"features[{i}] must have shape (F, D), got {tuple(a.shape)}")
        if not torch.isfinite(a).all():
            raise ValueError(f"features[{i}] must be finite, but it holds NaN/Inf")
    ds = WindowDataset(features, n)
    return torch.stack([ds[i] for i in range(len(ds))])  # (W, n + 1, D)
