"""The losses of scheduled-sampling training (A-MDM eq. 3, §3.2), for A-MDM and its baselines.

:func:`frame_loss` is one frame's loss for each model kind; :func:`window_loss` rolls it over
windows of consecutive frames, feeding each sample's own prediction back with a probability
(scheduled sampling); :func:`make_windows` cuts the windows. :mod:`minimdm.amdm.train` runs
them in its loop.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from minimdm.diffusion import (
    NoiseSchedule,
    StepSettings,
    clamp_x0,
    clip_bounds,
    diffusion_loss,
)
from minimdm.motion.skeleton import bone_pairs, rotate_about_z

__all__ = ["MODEL_KINDS", "FrameGeometry", "frame_loss", "window_loss", "make_windows"]

MODEL_KINDS = ("amdm", "mse", "mvae")
"""The three models one trainer serves: the A-MDM denoiser, the MSE regressor, the MVAE."""


class FrameGeometry:
    """Losses on what a predicted frame means as a body, for the A-MDM frame layout (§3.1).

    A frame holds the body three times over: joint positions ``j_p`` (relative to the root's
    ground projection), joint displacements ``j_v`` and rotations ``j_o``. Nothing in the
    DDPM loss makes a prediction's parts agree, and the rollout only shows ``j_p`` placed along
    the integrated root (:func:`~minimdm.motion.features.decode`). Given the previous frame, the
    displacement that the root and ``j_p`` imply is, in the heading frame of frame f,

    .. math:: \\Delta_f = (d_x, d_y, 0) + j_{p,f} - R_z(-d_r)\\, j_{p,f-1},

    and two losses read it (in the units of the normalized ``j_v``, so that their size compares
    with the DDPM loss's):

    * **consistency**: :math:`\\|\\Delta_f - j_{v,f}\\|^2`, the three parts agree (as in the
      official A-MDM code's consistency term and the velocity losses of MDM and CAMDM);
    * **foot contact**: :math:`w(h_f)\\,\\|\\Delta_f^{xy}\\|^2` for the foot joints, with
      :math:`w` the contact weight of the foot-sliding metric
      (:func:`~minimdm.motion.metrics.contact_weight`) at the *recorded* foot height: a foot that
      the recording plants must not slide in the prediction;
    * **bones**: :math:`\\big((\\hat L_b - L_b) / 1\\,\\mathrm{cm}\\big)^2` averaged over the
      bones, with :math:`\\hat L_b` the length of bone b in the predicted ``j_p`` and :math:`L_b`
      in the recorded frame (each actor has its own bones): the bone error of A-MDM eq. 11,
      squared. A centimetre is about one standard deviation of a joint's displacement per frame,
      so it weighs as the other two do.

    Both are weighted by :math:`\\bar\\alpha_t`, so that the blurred reconstructions of the noisiest
    levels are not pushed around. On recorded frames the consistency loss is zero up to float
    rounding, and the contact loss is the recording's own small slide.
    """

    def __init__(
        self,
        mean: Tensor,
        std: Tensor,
        n_joints: int,
        foot_joints: Sequence[int],
        foot_offset: Sequence[float],
        height_threshold: float = 0.025,
        consistency: float = 1.0,
        contact: float = 1.0,
        parents: Sequence[int] | None = None,
        bones: float = 0.0,
    ) -> None:
        self.mean, self.std = torch.as_tensor(mean).float(), torch.as_tensor(std).float()
        self.J = int(n_joints)
        if self.mean.shape != (3 + 12 * self.J,) or self.std.shape != self.mean.shape:
            raise ValueError(
                f"mean and std must be ({3 + 12 * self.J},) for {self.J} joints, got "
                f"{tuple(self.mean.shape)} and {tuple(self.std.shape)}"
            )
        self.feet = list(foot_joints)
        self.foot_offset = torch.as_tensor(list(foot_offset), dtype=torch.float32)
        self.height_threshold = float(height_threshold)
        self.consistency, self.contact = float(consistency), float(contact)
        self.bones = float(bones)
        if self.bones > 0 and (parents is None or len(parents) != self.J):
            raise ValueError(f"the bone loss needs the parents of the {self.J} joints")
        self.child, self.parent = bone_pairs(parents or [])  # the bones, as metrics.bone_lengths
        J = self.J
        self.vel_std = self.std[3 + 3 * J : 3 + 6 * J].reshape(J, 3)  # (J, 3)

    def _parts(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Denormalized root_vel (B, 2), yaw_rate (B,), j_p (B, J, 3), j_v (B, J, 3)."""
        x = x * self.std.to(x) + self.mean.to(x)
        J = self.J
        pos = x[:, 3 : 3 + 3 * J].unflatten(-1, (J, 3))
        vel = x[:, 3 + 3 * J : 3 + 6 * J].unflatten(-1, (J, 3))
        return x[:, 0:2], x[:, 2], pos, vel

    def bone_lengths(self, x: Tensor) -> Tensor:
        """The length (B, J-1), metres, of every bone of the joint positions of frame ``x``."""
        pos = self._parts(x)[2]
        return (pos[:, self.child] - pos[:, self.parent]).norm(dim=-1)

    def displacement(self, x: Tensor, cond: Tensor) -> Tensor:
        """:math:`\\Delta_f` (B, J, 3), metres, of frame ``x`` after ``cond`` (both normalized)."""
        root_vel, yaw, pos, _ = self._parts(x)
        _, _, prev, _ = self._parts(cond)
        prev = rotate_about_z(prev, -yaw)  # (B, J, 3) R_z(-d_r) j_{p,f-1}: heading frame of f
        root = torch.cat([root_vel, torch.zeros_like(root_vel[:, :1])], -1)[:, None]  # (B, 1, 3)
        return root + pos - prev

    def __call__(self, x0_hat: Tensor, cond: Tensor, target: Tensor, weight: Tensor) -> Tensor:
        """The weighted losses (B,) of a reconstruction ``x0_hat`` of ``target`` after ``cond``;
        ``weight`` (B,) is :math:`\\bar\\alpha_t`."""
        disp = self.displacement(x0_hat, cond)  # (B, J, 3)
        vs = self.vel_std.to(disp)
        out = torch.zeros_like(weight)
        if self.consistency > 0:
            _, _, _, vel = self._parts(x0_hat)
            out = out + self.consistency * (((disp - vel) / vs) ** 2).flatten(1).mean(1)
        if self.contact > 0:
            _, _, pos_gt, _ = self._parts(target)
            h = pos_gt[:, self.feet, 2] - self.foot_offset.to(pos_gt)  # (B, N) recorded height
            w = 2 - 2 ** (h / self.height_threshold).clamp(0, 1)  # the FS metric's weight
            slide = ((disp[:, self.feet, :2] / vs[self.feet, :2]) ** 2).sum(-1)  # (B, N)
            out = out + self.contact * (w * slide).mean(1)
        if self.bones > 0:
            error = (self.bone_lengths(x0_hat) - self.bone_lengths(target)) / 0.01  # (B, J-1)
            out = out + self.bones * (error**2).mean(1)
        return weight * out


def frame_loss(
    model: nn.Module,
    x: Tensor,
    cond: Tensor,
    generator: torch.Generator | None,
    kind: str = "amdm",
    schedule: NoiseSchedule | None = None,
    predicts: str = "eps",
    kl_beta: float = 0.2,
    norm: str = "l2",
    geometry: FrameGeometry | None = None,
    snr_gamma: float | None = None,
    snr_floor: float = 0.0,
    cond_noise: float | Tensor = 0.0,
    cond_noise_draw: str = "fixed",
    delta_from: str = "seen",
    cond_noise_history: str = "each",
) -> tuple[Tensor, Tensor]:
    """Per-sample loss of predicting ``x`` (B, D) from ``cond`` (B, D), and the prediction.

    A model with a history of H frames takes ``cond`` (B, H D), the frames before ``x``
    oldest first; the delta and the geometry read the last of them, :math:`x_{f-1}`.

    * amdm: the DDPM loss (A-MDM eq. 3), squared (``norm="l2"``) or absolute (``"l1"``), plus
      the ``geometry`` losses of the reconstruction if given, each level weighted by Min-SNR-γ
      when ``snr_gamma`` is given (:func:`~minimdm.diffusion.diffusion_loss`); the prediction is
      :math:`\\hat x_0` at the drawn step. A delta model's chain denoises the change from
      ``cond`` (:meth:`~minimdm.amdm.models.MLPDenoiser.to_delta`); its prediction is still
      the frame.
    * mse: :math:`\\|f(x_{f-1}) - x_f\\|^2 / D`; the prediction is :math:`f(x_{f-1})`.
    * mvae: :math:`\\|\\hat x_f - x_f\\|^2 / D + \\beta\\,\\mathrm{KL}(q \\| \\mathcal N(0, I)) / D`
      with :math:`q = q(z | x_f, x_{f-1})`, the β-ELBO; the prediction is the reconstruction
      through the posterior.

    ``cond_noise > 0`` (amdm only) adds Gaussian noise of that spread (normalized units; for a
    delta model, times each feature's :math:`k`) to the condition the network sees, the target
    staying the recorded frame: at run time the model conditions on its own imperfect frames,
    and this teaches it to lead them back to the data. A tensor (D,) gives each feature's own
    spread, in normalized frame units for every model (:func:`~minimdm.amdm.train` builds it
    from ``TrainConfig.cond_noise`` and ``cond_noise_motion``). ``cond_noise_draw="uniform"``
    scales each sample's noise by a factor drawn uniformly in [0, 1], which a network with a
    ``cond_level`` is told. The ``geometry`` losses read the displacement from the recorded
    ``cond``, not the noised one: the noise is what the network sees, not how the body moved. A
    delta model's change is measured from the noised condition (``delta_from="seen"``: the
    change also undoes the noise), or from the recorded one (``"recorded"``: the change alone;
    the prediction is then the recorded frame plus it). With a history of H frames, each frame
    gets its own draw of the noise (``cond_noise_history="each"``) or all H the same
    (``"shared"``: the whole past offset alike, as a rollout's slow drift moves it, the changes
    between its frames left clean).

    Returns ``(loss (B,), prediction (B, D))``.
    """
    if kind == "amdm":
        if schedule is None:
            raise ValueError("schedule is required for kind='amdm'")
        net = getattr(model, "module", model)  # the network inside a DDP wrapper
        delta = getattr(net, "is_delta", False)  # DenoiserConfig.delta_scale
        recorded = cond  # the geometry measures the motion from the recorded previous frame
        history = cond.shape[1] // x.shape[1]  # frames in the condition
        if isinstance(cond_noise, Tensor) or cond_noise > 0:
            spread = cond_noise  # a float is, for a delta model, in units of each feature's change
            if delta and not isinstance(spread, Tensor):
                spread = net.delta_spread * cond_noise
            if isinstance(spread, Tensor) and spread.numel() == x.shape[1] < cond.shape[1]:
                spread = spread.repeat(history)  # each frame of the history alike
            if cond_noise_history not in ("each", "shared"):
                raise ValueError(
                    f"cond_noise_history must be 'each' or 'shared', got {cond_noise_history!r}"
                )
            shape = (cond.shape[0], x.shape[1]) if cond_noise_history == "shared" else cond.shape
            eps = torch.randn(shape, generator=generator, device=cond.device, dtype=cond.dtype)
            noise = spread * eps.repeat(1, cond.shape[1] // shape[1])  # (B, H D)
            if cond_noise_draw == "uniform":  # each condition's own size, in [0, 1] of it
                size = torch.rand(cond.shape[0], 1, generator=generator, device=cond.device)
                noise = noise * size.to(cond.dtype)
                told = getattr(getattr(net, "config", None), "cond_level", None) is not None
                if told:  # the network reads each condition's size (DenoiserConfig.cond_level)
                    model = functools.partial(model, level=size[:, 0])
            cond = cond + noise

        if delta_from not in ("seen", "recorded"):
            raise ValueError(f"delta_from must be 'seen' or 'recorded', got {delta_from!r}")
        start = recorded if delta_from == "recorded" else cond  # the change's origin
        previous = recorded[:, -x.shape[1] :]  # x_{f-1} as recorded (B, D)

        def frame_of(z: Tensor) -> Tensor:  # the frame of the chain's sample z
            return net.from_delta(z, start) if delta else z

        x0_loss = None
        if geometry is not None:
            ac = schedule.alphas_cumprod

            def x0_loss(z0_hat: Tensor, t: Tensor) -> Tensor:
                x0_hat = frame_of(z0_hat)
                return geometry(x0_hat, previous, x, ac.to(x0_hat.device)[t])

        loss_kw = dict(norm=norm, x0_loss=x0_loss, snr_gamma=snr_gamma, snr_floor=snr_floor)
        z = net.to_delta(x, start) if delta else x  # the frame, or its change
        loss, z0_hat = diffusion_loss(
            model, schedule, z, cond, generator, predicts, reduce=False, **loss_kw
        )
        return loss, frame_of(z0_hat)
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
    norm: str = "l2",
    geometry: FrameGeometry | None = None,
    student_steps: int = 0,
    snr_gamma: float | None = None,
    snr_floor: float = 0.0,
    cond_noise: float | Tensor = 0.0,
    cond_noise_draw: str = "fixed",
    delta_from: str = "seen",
    history: int = 1,
    cond_noise_history: str = "each",
) -> tuple[Tensor, dict[str, float]]:
    """Scheduled-sampling loss over windows (B, N_r + 1, D) (A-MDM §3.2).

    Frame 0 of each window is the ground-truth start. Frame ``f >= 1`` costs the loss of eq. 3
    (:func:`frame_loss`) given the condition ``c_f``: ``c_1 = x_0``; for ``f > 1`` each sample
    takes its own previous prediction ``\\hat x_{f-1}`` (detached) with probability
    ``p_student``, else the ground truth ``x_{f-1}``; a fed-back prediction is clamped to
    ``clip_x0``: None, a float ``c`` (``[-c, c]``) or a per-feature range ``(lo, hi)``
    (:func:`~minimdm.diffusion.clip_bounds`).

    For A-MDM the prediction fed back is the reconstruction :math:`\\hat x_0` at the noise level
    drawn for the loss, as in the paper. With eps-prediction it divides by
    :math:`\\sqrt{\\bar\\alpha_t}`, which is tiny at the noisiest levels: the clamp keeps it
    bounded, and x0-prediction avoids the division. ``student_steps = k >= 1`` feeds back a
    real draw from the model instead, what the sampler will feed it at run time: the reverse
    chain from the same condition (:meth:`~minimdm.amdm.sampling.Sampler.frame`, no gradient), over
    all T steps (DDPM) when ``k = T``, else DDIM over ``k`` steps with :math:`\\eta = 1`. It
    costs ``k`` extra network calls per fed-back frame.

    ``teacher_weight > 0`` adds, while ``p_student > 0``, that weight times the teacher-forced
    loss of the same windows, as the official A-MDM trainer does at every student step: the
    fit to ground-truth conditions is kept while the model learns to recover from its own.

    A model with a ``history`` of H frames takes windows (B, H - 1 + N_r + 1, D): the first H
    frames are the recorded condition of the first predicted frame, and each later condition
    drops its oldest frame for the one just fed back (recorded or the student's own).

    Returns the mean loss over frames and samples, and the fraction of student conditions
    used. With ``p_student = 0`` all frames run as one batch.
    """
    bounds = _check_window_loss(windows, clip_x0, teacher_weight, history)
    B, n1, D = windows.shape
    H = history
    model_kw = dict(kind=kind, schedule=schedule, predicts=predicts, kl_beta=kl_beta)
    loss_kw = dict(norm=norm, geometry=geometry, snr_gamma=snr_gamma, snr_floor=snr_floor)
    loss_kw.update(cond_noise=cond_noise, cond_noise_draw=cond_noise_draw, delta_from=delta_from)
    loss_kw.update(cond_noise_history=cond_noise_history)

    def loss_of(x: Tensor, cond: Tensor) -> tuple[Tensor, Tensor]:
        """Eq. 3 (or the baseline's loss) per sample of frames x after ``cond``, and the
        prediction."""
        return frame_loss(model, x, cond, generator, **model_kw, **loss_kw)

    def draw(c: Tensor) -> Tensor:
        """x_f ~ p(x_f | c_f): the reverse chain, as the sampler feeds the model at run time."""
        return _draw(model, c, generator, schedule, predicts, student_steps, bounds)

    if p_student <= 0:  # teacher forcing
        return loss_of(*_teacher_forced(windows, H))[0].mean(), {"student_frac": 0.0}
    if student_steps and kind != "amdm":
        raise ValueError(f"student_steps needs kind='amdm', got {kind!r}")
    cond = windows[:, :H].reshape(B, H * D)  # c_1 = x_0 (and the frames before it), (B, H D)
    losses, n_student = [], 0
    for f in range(H, n1):  # roll out over the N_r frames
        loss_f, pred = loss_of(windows[:, f], cond)  # eq. 3 at frame f
        losses.append(loss_f)
        if f + 1 < n1:  # c_{f+1}: the student's own \hat x_f w.p. p_student, else x_f
            pred = pred.detach()
            coin = torch.rand(B, generator=generator, device=windows.device) < p_student  # (B,)
            if student_steps and coin.any():
                pred = pred.clone()
                pred[coin] = draw(cond[coin])
            pred = clamp_x0(pred, bounds)
            n_student += int(coin.sum())
            fed = torch.where(coin[:, None], pred, windows[:, f])  # (B, D)
            cond = torch.cat([cond[:, D:], fed], dim=1)  # the oldest frame out, x_f in
    frac = n_student / (B * max(n1 - H - 1, 1))
    loss = torch.stack(losses).mean()
    if teacher_weight > 0:  # the official A-MDM trainer's teacher-forced term
        loss = loss + teacher_weight * loss_of(*_teacher_forced(windows, H))[0].mean()
    return loss, {"student_frac": frac}


def _check_window_loss(windows: Tensor, clip_x0: Any, teacher_weight: float, history: int) -> Any:
    """Refuse windows that are not (B, history - 1 + N_r + 1, D) with N_r >= 1, a history below
    1 and a negative ``teacher_weight``; return the clamp's bounds
    (:func:`~minimdm.diffusion.clip_bounds`)."""
    if not isinstance(history, int) or history < 1:
        raise ValueError(f"history must be an int >= 1, got {history!r}")
    if windows.dim() != 3 or windows.shape[1] < history + 1:
        raise ValueError(
            f"windows must have shape (B, {history - 1} + N_r + 1 >= {history + 1}, D) for a "
            f"history of {history}, got {tuple(windows.shape)}"
        )
    bounds = clip_bounds(clip_x0, windows.shape[2], windows.device, windows.dtype)
    if teacher_weight < 0:
        raise ValueError(f"teacher_weight must be >= 0, got {teacher_weight}")
    return bounds


def _teacher_forced(windows: Tensor, history: int = 1) -> tuple[Tensor, Tensor]:
    """Teacher forcing: every frame (B N_r, D) of windows (B, H - 1 + N_r + 1, D) after the
    first H, and its H recorded predecessors as its condition (B N_r, H D), as one batch."""
    B, n1, D = windows.shape
    n = n1 - history  # N_r
    x = windows[:, history:].reshape(B * n, D)  # (B N_r, D)
    cond = torch.stack([windows[:, i : i + n] for i in range(history)], dim=2)  # (B, N_r, H, D)
    return x, cond.reshape(B * n, history * D)


@torch.no_grad()
def _draw(
    model: nn.Module,
    cond: Tensor,
    generator: torch.Generator | None,
    schedule: NoiseSchedule | None,
    predicts: str,
    steps: int,
    bounds: Any,
) -> Tensor:
    """A frame drawn from the model by the sampler's own reverse chain (no gradient)."""
    from minimdm.amdm.sampling import Sampler

    if schedule is None:
        raise ValueError("schedule is required to draw from a denoiser")
    net = getattr(model, "module", model)  # the network inside a DDP wrapper
    was_training = net.training
    net.eval()
    try:
        settings = StepSettings(steps=min(steps, schedule.T), predicts=predicts, clip_x0=bounds)
        return Sampler(net, schedule=schedule, settings=settings).frame(cond, generator)
    finally:
        net.train(was_training)


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
