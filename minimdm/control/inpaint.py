"""Spatial inpainting and keyframe inbetweening (A-MDM §4.3), frame after frame.

Both run the one auto-regressive loop, :func:`~minimdm.amdm.sampling.autoregress`; they differ
from random sampling only in what they hand the sampler of each frame:

* :func:`inpaint` passes the hook of A-MDM eq. 4 (:func:`~minimdm.control.hooks.inpaint_hook`),
  which overwrites the user's features with their noised targets after every reverse step;
* :func:`inbetween` starts frame f's chain from the keyframe noised to level
  :math:`t_0 = (1 - f/N)\\,t_{max}` (eq. 5, :func:`~minimdm.control.hooks.inbetween_t_start`).

:func:`lerp_inbetween` is the baseline: linear interpolation in feature space.
"""

from __future__ import annotations

import os
from typing import Any

import torch
from torch import Tensor, nn

from minimdm.amdm.sampling import Sampler, autoregress
from minimdm.checkpoint import Checkpoint
from minimdm.diffusion import q_sample
from minimdm.motion.features import StartPose
from minimdm.validate import (
    InputError,
    InputTypeError,
    check_frames,
    check_int,
    check_mask,
    describe,
)

from .core import Motion, as_start, check_count
from .hooks import inbetween_t_start, inpaint_hook

__all__ = ["inpaint", "inbetween", "lerp_inbetween", "check_targets"]

ModelLike = Checkpoint | Sampler | nn.Module | str | os.PathLike


def check_targets(targets: Any, mask: Any, D: int, B: int) -> tuple[Tensor, Tensor]:
    """Validate targets ([B,] F, D) and mask ([B,] [F,] D): -> (B, F, D) float, bool.

    Entries where the mask is 0 are ignored and may be NaN; masked ones must be finite.
    """
    x = check_frames(
        "targets", targets, D, ndim=(2, 3), shape_words=f"(F, {D}) or (B, F, {D})", allow_nan=True
    )
    if x.dim() == 3 and x.shape[0] not in (1, B):
        raise InputError(f"targets must have batch size {B} or 1, got {tuple(x.shape)}")
    x = x.reshape(-1, *x.shape[-2:]).expand(B, -1, -1)  # (B, F, D)
    F = x.shape[1]
    m = check_mask("mask", mask)
    if m.dim() == 0 or m.shape[-1] != D:
        raise ValueError(
            f"mask must have last dim D={D} (the feature dimension), got shape {tuple(m.shape)}"
        )
    if m.dim() >= 2 and m.shape[-2] not in (1, F):
        raise ValueError(
            f"mask must have {F} frames (one per target frame) or 1, got shape {tuple(m.shape)}"
        )
    if m.dim() == 3 and m.shape[0] not in (1, B):
        raise ValueError(f"mask must have batch size {B} or 1, got shape {tuple(m.shape)}")
    if m.dim() > 3:
        raise ValueError(f"mask must have shape (D,), (F, D) or (B, F, D), got {tuple(m.shape)}")
    m = m.to(torch.bool).reshape((1,) * (3 - m.dim()) + tuple(m.shape)).expand(B, F, D)
    bad = m & ~torch.isfinite(x)
    if bad.any():
        b, f, d = bad.nonzero()[0].tolist()
        raise ValueError(
            f"targets hold NaN/Inf where the mask is set: character {b}, frame {f + 1}, feature {d}"
        )
    return torch.where(m, x, torch.zeros(())), m


@torch.no_grad()
def inpaint(
    model: ModelLike,
    start: Tensor,
    targets: Tensor,
    mask: Tensor,
    generator: torch.Generator | None = None,
    *,
    start_pose: StartPose | dict | None = None,
    t_stop: int | Tensor = -1,
    progress: bool = False,
) -> Motion:
    """Spatial inpainting (A-MDM §4.3, eq. 4): sample F frames that keep the masked features.

    Args:
        model: a loaded Checkpoint (normalizer, schedule, predicts, clip_x0 come from it), a
            path, a :class:`Sampler` or a bare denoiser.
        start: (D,) or (B, D) start state x_0, feature units.
        targets: (F, D) or (B, F, D) desired features :math:`\\tilde x_1..\\tilde x_F` in
            feature units (e.g. from :func:`~minimdm.control.targets.root_path_targets`).
            Entries outside the mask are ignored (NaN allowed there).
        mask: (D,), (F, D) or (B, F, D), 1/True where a feature is specified.
        generator: randomness of the chains and of the noised targets.
        start_pose: root ground position and heading of the start (a path's constraint
            carries its own).
        t_stop: the lowest diffusion level at which targets are imposed (-1: every step, an
            exact constraint), one for all frames or one per frame (F,): the buffer frames of
            A-MDM Fig. 4 stop early.

    Returns:
        A :class:`Motion` of F frames; its masked features equal the targets when
        ``t_stop = -1``.
    """
    cm = Sampler.load(model)
    if not cm.is_diffusion:
        raise ValueError(f"inpainting needs a diffusion model, got {type(cm.net).__name__}")
    x0, batched, sp = as_start(cm, start, start_pose, generator)
    B, D = x0.shape
    tgt, m = check_targets(targets, mask, D, B)  # (B, F, D)
    F = tgt.shape[1]
    stops = _t_stops(t_stop, F, cm.schedule.T)
    tgt_n = cm.normalize(tgt).to(cm.device)  # (B, F, D)
    m = m.to(cm.device)

    def step(f: int, cond: Tensor) -> Tensor:  # frame f (B, D) under eq. 4's hook
        target = cm.chain_target(tgt_n[:, f - 1], cond)  # what the chain denoises (B, D)
        hook = inpaint_hook(cm.schedule, target, m[:, f - 1], generator, int(stops[f - 1]))
        return cm.frame(cond, generator, hook=hook)

    out = autoregress(step, cm.normalize(x0), F, who=_character, desc="inpaint", progress=progress)
    feats = cm.denormalize(out)
    exact = (stops == -1)[None, :, None] & m.cpu()
    feats = torch.where(exact, tgt, feats)  # undo the normalize/denormalize rounding
    return Motion.from_normalized(cm, out, sp, batched, {"t_stop": stops}, features=feats)


def _t_stops(t_stop: Any, F: int, T: int) -> Tensor:
    """``t_stop`` (an int or F of them, each in [-1, T - 1]) as an (F,) long tensor."""
    expected = f"an integer in [-1, {T - 1}] (-1: every step) or F={F} of them"
    if isinstance(t_stop, (bool, float, str)) or t_stop is None:
        raise InputTypeError(f"t_stop must be {expected}, got {describe(t_stop)}")
    try:
        stops = torch.as_tensor(t_stop)
    except (TypeError, ValueError, RuntimeError):
        raise InputTypeError(f"t_stop must be {expected}, got {describe(t_stop)}") from None
    if stops.dtype.is_floating_point or stops.dtype == torch.bool or stops.is_complex():
        raise InputTypeError(f"t_stop must be {expected}, got a tensor of {stops.dtype}")
    stops = stops.to(torch.long).reshape(-1)
    if stops.numel() not in (1, F):
        raise InputError(f"t_stop must be {expected}, got {stops.numel()} values")
    if ((stops < -1) | (stops >= T)).any():
        bad = int(stops[(stops < -1) | (stops >= T)][0])
        raise InputError(f"t_stop must be {expected}, got {bad}")
    return stops.expand(F)


def _character(b: int) -> str:
    return f"character {b}"


def _keyframes(keyframe: Any, at: Any, n_frames: int, D: int, B: int) -> tuple[Tensor, list[int]]:
    """-> keyframes (B, K, D) and their frames [a_1 < ... < a_K <= n_frames]."""
    words = f"({D},), (K, {D}) or (B, K, {D}) (frames of this model's skeleton and layout)"
    k = check_frames("keyframe", keyframe, D, ndim=(1, 2, 3), shape_words=words)
    if k.dim() == 1:
        k = k[None]
    if k.dim() == 3 and k.shape[0] not in (1, B):
        raise ValueError(f"keyframe must have batch size {B} or 1, got {tuple(k.shape)}")
    k = k.reshape(-1, *k.shape[-2:]).expand(B, -1, -1)
    K = k.shape[1]
    ats = [n_frames] if at is None and K == 1 else at
    if ats is None:
        raise InputError(f"at must give the frame of each of the K={K} keyframes, got None")
    if isinstance(ats, Tensor):
        ats = ats.reshape(-1).tolist()
    elif not isinstance(ats, (list, tuple)):
        ats = [ats]
    ats = [check_int(f"at[{i}]" if K > 1 else "at", a, low=1) for i, a in enumerate(ats)]
    if len(ats) != K:
        raise ValueError(f"at must hold one frame per keyframe (K={K}), got {len(ats)}")
    prev = 0
    for a in ats:
        if a <= prev:
            raise ValueError(f"keyframe frames must be increasing and >= 1, got {ats}")
        if a > n_frames:
            raise ValueError(
                f"keyframe at frame {a} lies beyond the horizon: frames run 1..n_frames={n_frames}"
            )
        prev = a
    return k, ats


@torch.no_grad()
def inbetween(
    model: ModelLike,
    start: Tensor,
    keyframe: Tensor,
    n_frames: int,
    generator: torch.Generator | None = None,
    *,
    at: int | list[int] | None = None,
    start_pose: StartPose | dict | None = None,
    progress: bool = False,
) -> Motion:
    """Keyframe inbetweening (A-MDM §4.3, eq. 5, Fig. 5).

    Frame f between the previous keyframe (or the start, at frame 0) and the next keyframe
    :math:`\\tilde x_N`, N frames apart, starts its denoising chain from :math:`\\tilde x_N`
    noised to the level :math:`t_0 = (1 - f/N)\\,t_{max}` (:func:`inbetween_t_start`): early
    frames run almost the whole chain and may leave the keyframe; the last ones run few steps
    and land on it. Frames after the last keyframe are sampled freely.

    Args:
        model: a loaded Checkpoint or anything :meth:`Sampler.load` takes; a diffusion
            model, sampled with DDPM (all T steps) or with DDIM (``steps`` < T): a chain
            that starts at level :math:`t_0` follows the DDIM grid below it.
        start: (D,) or (B, D) start state x_0, feature units.
        keyframe: (D,), (K, D) or (B, K, D) keyframes in feature units, e.g. a frame of another
            clip (:func:`~minimdm.control.targets.clip_frame`).
        n_frames: frames to generate, >= 1.
        at: frame of each keyframe, increasing, in 1..n_frames (default: ``n_frames``).
        start_pose: root ground position and heading of the start.

    Returns:
        A :class:`Motion`; ``info["t_start"]`` is each frame's starting level (-1: free),
        ``info["at"]`` the keyframes' frames.
    """
    cm = Sampler.load(model)
    if not cm.is_diffusion:
        raise ValueError(f"inbetweening needs a diffusion model, got {type(cm.net).__name__}")
    n_frames = check_count("n_frames", n_frames)
    x0, batched, sp = as_start(cm, start, start_pose, generator)
    B, D = x0.shape
    keys, ats = _keyframes(keyframe, at, n_frames, D, B)
    keys_n = cm.normalize(keys).to(cm.device)  # (B, K, D)
    T = cm.schedule.T
    t_starts: list[int] = []
    key = {"k": 0, "prev": 0}  # the next keyframe and the frame of the previous one

    def step(f: int, cond: Tensor) -> Tensor:  # frame f (B, D), its chain started by eq. 5
        k, prev = key["k"], key["prev"]
        if k < len(ats):
            t0 = inbetween_t_start(f - prev, ats[k] - prev, T)
            key_t = cm.chain_target(keys_n[:, k], cond)  # the keyframe as the chain sees it
            x_start = q_sample(cm.schedule, key_t, t0, generator=generator)  # (B, D)
            x = cm.frame(cond, generator, t_start=t0, x_start=x_start)
            if f == ats[k]:
                key["k"], key["prev"] = k + 1, f
        else:
            t0 = -1
            x = cm.frame(cond, generator)
        t_starts.append(t0)
        return x

    out = autoregress(
        step, cm.normalize(x0), n_frames, who=_character, desc="inbetween", progress=progress
    )
    info = {"t_start": t_starts, "at": ats, "keyframes": keys if batched else keys[0]}
    return Motion.from_normalized(cm, out, sp, batched, info)


def lerp_inbetween(
    model: ModelLike,
    start: Tensor,
    keyframe: Tensor,
    n_frames: int,
    *,
    start_pose: StartPose | dict | None = None,
) -> Motion:
    """The baseline: linear interpolation in feature space, :math:`x_f = x_0 + \\frac fN
    (\\tilde x_N - x_0)`, f = 1..N, decoded like a model's frames (no model is run)."""
    cm = Sampler.load(model)
    n_frames = check_count("n_frames", n_frames)
    x0, batched, sp = as_start(cm, start, start_pose)
    B, D = x0.shape
    keys, _ = _keyframes(keyframe, None, n_frames, D, B)
    w = torch.arange(1, n_frames + 1, dtype=torch.float32)[None, :, None] / n_frames  # (1, N, 1)
    feats = x0.cpu()[:, None] + w * (keys[:, 0:1] - x0.cpu()[:, None])  # (B, N, D)
    return Motion.from_normalized(cm, cm.normalize(feats), sp, batched, {}, features=feats)
