"""What every control technique shares: the model it steers, one sampled frame, the result.

:class:`ControlModel` gathers what sampling a frame needs (network, normalizer, noise schedule,
``predicts``, ``clip_x0``), read from a loaded :class:`~minimdm.checkpoint.Checkpoint` by
:func:`minimdm.amdm.sampling.sampler_settings`, as :func:`~minimdm.amdm.sampling.rollout` reads
it. :func:`sample_frame` draws one frame through :func:`minimdm.amdm.sampling.next_frame`, i.e.
through the one sampler loop of :mod:`minimdm.diffusion`; the techniques run it frame after
frame on the one rollout loop, :func:`minimdm.amdm.sampling.autoregress`, and differ only in the
hook and the start of the chain they hand it. :class:`Motion` is what they return.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from minimdm.amdm.models import MVAE, MLPDenoiser, MLPRegressor
from minimdm.amdm.sampling import check_finite, next_frame, sampler_settings
from minimdm.checkpoint import Checkpoint, load_checkpoint
from minimdm.diffusion import ClipX0, Hook, NoiseSchedule, clip_bounds
from minimdm.motion.features import (
    FeatureLayout,
    Normalizer,
    StartPose,
    decode,
    decode_root,
    start_state,
)
from minimdm.motion.skeleton import Skeleton
from minimdm.validate import (
    InputError,
    InputTypeError,
    check_device,
    check_frames,
    check_generator,
    check_int,
    check_number,
)

__all__ = ["ControlModel", "as_control_model", "regressor_noise", "sample_frame", "Motion"]


@dataclass
class ControlModel:
    """A trained next-frame model and everything needed to sample from it."""

    net: nn.Module
    """The network: an MLPDenoiser (A-MDM), an MVAE or an MLPRegressor."""
    normalizer: Normalizer | None = None
    """Feature standardisation; None if the network works in feature units."""
    schedule: NoiseSchedule | None = None
    """The denoiser's noise schedule (None for the baselines)."""
    predicts: str = "eps"
    """What the denoiser outputs: 'eps' or 'x0'."""
    clip_x0: ClipX0 = None
    """Clamp of the clean estimate at every step (normalized units)."""
    steps: int | None = None
    """Denoising steps per frame (None: all T, DDPM; fewer: DDIM)."""
    eta: float = 1.0
    """DDIM stochasticity when ``steps`` < T."""
    noise: float | Tensor = 0.0
    """Std (normalized units, scalar or (D,)) of Gaussian noise added to a regressor's output."""
    layout: FeatureLayout | None = None
    """The feature layout (joint names, fps), from the checkpoint."""
    skeleton: Skeleton | None = None
    """The skeleton, from the checkpoint."""

    @property
    def is_diffusion(self) -> bool:
        return isinstance(self.net, MLPDenoiser)

    @property
    def dim(self) -> int:
        """D, the frame dimension."""
        cfg = getattr(self.net, "config", None)
        return int(getattr(cfg, "x_dim", None) or self.net.x_dim)

    @property
    def fps(self) -> float:
        return self.layout.fps if self.layout is not None else 30.0

    @property
    def device(self) -> torch.device:
        return next(self.net.parameters()).device

    def normalize(self, x: Tensor) -> Tensor:
        return self.normalizer.normalize(x) if self.normalizer is not None else x

    def denormalize(self, x: Tensor) -> Tensor:
        return self.normalizer.denormalize(x) if self.normalizer is not None else x


def as_control_model(
    model: Checkpoint | ControlModel | nn.Module | str | os.PathLike,
    *,
    normalizer: Normalizer | None = None,
    schedule: NoiseSchedule | None = None,
    predicts: str | None = None,
    clip_x0: ClipX0 | str = "checkpoint",
    steps: int | None = None,
    eta: float = 1.0,
    noise: float | Tensor = 0.0,
    device: torch.device | str | None = None,
) -> ControlModel:
    """Resolve a Checkpoint, a checkpoint path, a bare network or a ControlModel.

    From a checkpoint the normalizer, schedule, ``predicts``, ``clip_x0``, layout and skeleton
    come from its metadata (explicit arguments win). A bare denoiser needs ``schedule``.
    ``noise`` (regressors only) turns the deterministic MSE baseline into a Gaussian
    :math:`\\mathcal N(f(x_{f-1}), \\sigma^2 I)`, the likelihood that MSE training fits, so that
    a pool of its candidates can differ.
    """
    if isinstance(model, ControlModel):
        return model
    device = check_device("device", device)
    if steps is not None:
        steps = check_int("steps", steps, low=1)
    eta = check_number("eta", eta, low=0.0)
    if isinstance(model, (str, os.PathLike)):
        model = load_checkpoint(model, device=device or "cpu")
    layout = skeleton = None
    if isinstance(model, Checkpoint):
        settings = sampler_settings(model, device or "cpu")
        normalizer = normalizer if normalizer is not None else settings.normalizer
        schedule = schedule if schedule is not None else settings.schedule
        predicts = predicts or settings.predicts
        if isinstance(clip_x0, str) and clip_x0 == "checkpoint":
            clip_x0 = settings.clip_x0
        layout, skeleton = settings.layout, settings.skeleton
        net = model.model
    elif isinstance(model, nn.Module):
        net = model
    else:
        raise InputTypeError(
            "model must be a Checkpoint, a checkpoint path, an nn.Module or a ControlModel, "
            f"got {type(model).__name__}"
        )
    if not isinstance(net, (MLPDenoiser, MVAE, MLPRegressor)):
        held = f" (checkpoint kind {model.kind!r})" if isinstance(model, Checkpoint) else ""
        raise InputError(
            f"model must be an MLPDenoiser, MVAE or MLPRegressor, got {type(net).__name__}{held}"
        )
    if isinstance(clip_x0, str) and clip_x0 == "checkpoint":
        clip_x0 = None
    if clip_x0 is not None:
        x_dim = getattr(getattr(net, "config", None), "x_dim", None) or net.x_dim
        clip_bounds(clip_x0, int(x_dim))  # checked before any frame is sampled
    if isinstance(net, MLPDenoiser):
        predicts = predicts or net.predicts
        if schedule is None:
            raise InputError("schedule is required to sample from a bare denoiser, got None")
    if device is not None:
        net = net.to(device)
    net.eval()
    if schedule is not None:
        schedule = schedule.to(next(net.parameters()).device)
        if steps is not None and not 1 <= steps <= schedule.T:
            raise InputError(f"steps must lie in [1, T={schedule.T}], got {steps}")
    if isinstance(noise, Tensor) and noise.numel() > 1:
        noise = noise.to(next(net.parameters()).device)
    return ControlModel(
        net, normalizer, schedule, predicts or "eps", clip_x0, steps, eta, noise, layout, skeleton
    )


@torch.no_grad()
def regressor_noise(checkpoint: Checkpoint, clips: Any) -> Tensor:
    """Per-dimension residual std (D,) of a regressor on ``clips``, in normalized units.

    MSE training fits :math:`\\mathcal N(f(x_{f-1}), \\sigma^2 I)`; this is the maximum
    likelihood :math:`\\sigma` per dimension, to pass as ``as_control_model(..., noise=...)`` so
    that the deterministic baseline proposes distinct candidates (A-MDM §7.3.3 compares models
    under the same search).
    """
    from minimdm.motion.features import encode

    if not isinstance(checkpoint.model, MLPRegressor) or checkpoint.normalizer is None:
        raise ValueError("checkpoint must hold an MLPRegressor and its normalizer")
    norm = Normalizer.from_dict(checkpoint.normalizer)
    net = checkpoint.model
    res = []
    for c in clips:
        x = norm.normalize(encode(c)).to(next(net.parameters()).device)  # (F, D)
        res.append((net(x[:-1]) - x[1:]).cpu())
    return torch.cat(res).std(dim=0)


def sample_frame(
    cm: ControlModel,
    cond: Tensor,
    generator: torch.Generator | None = None,
    hook: Hook | None = None,
    t_start: int | None = None,
    x_start: Tensor | None = None,
    frame: int | None = None,
) -> Tensor:
    """One frame :math:`x_f` (B, D) from :math:`x_{f-1}` (B, D), in normalized space.

    Calls :func:`minimdm.amdm.sampling.next_frame` (the sampler of :mod:`minimdm.diffusion`) with
    the technique's ``hook`` and chain start. With ``frame`` (1-based) given, the result is
    checked by :func:`~minimdm.amdm.sampling.check_finite` (:class:`NonFiniteFrameError` naming
    the frame); the rollout loop :func:`~minimdm.amdm.sampling.autoregress` checks every frame
    it makes, so the techniques leave it out.
    """
    x = next_frame(
        cm.net,
        cond,
        generator,
        cm.schedule,
        cm.steps,
        cm.eta,
        cm.predicts,
        cm.clip_x0,
        hook,
        t_start=t_start,
        x_start=x_start,
    )
    if isinstance(cm.net, MLPRegressor) and (torch.as_tensor(cm.noise) != 0).any():
        eps = torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype)
        x = x + torch.as_tensor(cm.noise, device=x.device, dtype=x.dtype) * eps
    if frame is not None:
        check_finite(x, frame, lambda b: f"character {b}", "sampling")
    return x


def as_start(
    cm: ControlModel, start: Any, start_pose: Any = None, generator: Any = None
) -> tuple[Tensor, bool, StartPose]:
    """Check what a technique starts from: ``start`` (D,) or (B, D) in feature units, or a
    :class:`~minimdm.motion.data.Clip` to continue (:func:`~minimdm.motion.features.start_state`,
    which compares the skeleton and frame rate it came from with the model's), its
    ``start_pose`` and the ``generator``.

    Returns:
        ``(x, batched, start_pose)``: x (B, D) float32 on the model's device, whether ``start``
        was batched, and a :class:`StartPose` with xy (B, 2) and heading (B,) float64.
    """
    check_generator("generator", generator, cm.device)
    start, start_pose = start_state(
        start, start_pose, skeleton=cm.skeleton, layout=cm.layout, name="start"
    )
    D = cm.dim
    joints = cm.layout.joint_names if cm.layout is not None else None
    x = check_frames("start", start, D, joints=joints)
    batched = x.dim() == 2
    if x.dim() == 1:
        x = x[None]
    return x.to(cm.device), batched, StartPose.broadcast(start_pose, x.shape[0])


def check_count(name: str, value: Any, minimum: int = 1) -> int:
    """:func:`minimdm.validate.check_int` with a lower bound: an integer >= ``minimum``."""
    return check_int(name, value, low=minimum)


@dataclass
class Motion:
    """A controlled motion of F frames x_1..x_F (x_0 is the start state).

    Leading dimensions mirror ``start``: with one start state (D,) the fields are per frame,
    e.g. ``positions`` is (F, J, 3); with a batch (B, D) they gain a leading B.
    """

    features: Tensor
    """([B,] F, D) frames in feature units (``minimdm.motion.features.encode``)."""
    normalized: Tensor
    """([B,] F, D) the same frames in the model's normalized space."""
    positions: Tensor
    """([B,] F, J, 3) global joint positions in metres, z-up."""
    root_xy: Tensor
    """([B,] F, 2) root ground positions in metres."""
    heading: Tensor
    """([B,] F) root headings in radians."""
    start_pose: StartPose
    """Root ground position and heading at the start state, where decoding starts."""
    info: dict[str, Any] = field(default_factory=dict)
    """Technique-specific extras (scores, frames done, t_start per frame...)."""

    @property
    def n_frames(self) -> int:
        return self.features.shape[-2]

    def numpy(self) -> np.ndarray:
        """The global joint positions as a numpy array, ([B,] F, J, 3)."""
        return self.positions.numpy()

    @classmethod
    def from_normalized(
        cls,
        cm: ControlModel,
        normalized: Tensor,
        start_pose: StartPose,
        batched: bool,
        info: dict[str, Any] | None = None,
        features: Tensor | None = None,
    ) -> Motion:
        """Denormalize ``normalized`` (B, F, D), decode it from ``start_pose`` (B), squeeze."""
        normalized = normalized.detach().float().cpu()
        if features is None:
            features = cm.denormalize(normalized)
        f64 = features.double()
        sp = StartPose(start_pose.xy.cpu(), start_pose.heading.cpu())
        positions = decode(f64, sp).float()  # (B, F, J, 3)
        xy, heading = decode_root(f64, sp)  # (B, F, 2), (B, F)
        out = [normalized, features.float(), positions, xy.float(), heading.float()]
        if not batched:
            out = [t[0] for t in out]
            sp = StartPose(sp.xy[0], sp.heading[0])
        return cls(out[1], out[0], out[2], out[3], out[4], sp, dict(info or {}))
