"""Auto-regressive rollouts: sample frame after frame from a trained model (A-MDM §3.1).

Given initial states :math:`x_0` (one per character), :func:`rollout` draws ``n_samples``
futures per character, all in one batch: each new frame :math:`x_f` is sampled conditioned on
the previous one, :math:`x_f \\sim p_\\theta(x_f | x_{f-1})`, by the reverse diffusion chain for
A-MDM (DDPM over all T steps, or DDIM over fewer), by the prior of the MVAE-style baseline, or
by the deterministic regressor. Frames are normalized before they enter the model and
denormalized after; decoded global joint positions come with them.

:func:`autoregress` is the one frame-after-frame loop of the library: random rollouts, beam
search (:mod:`minimdm.control.beam`), inpainting and inbetweening (:mod:`minimdm.control.inpaint`),
AAMDM rollouts (:mod:`minimdm.aamdm.eval`) and the Squ-9 chains of the studies all run on it and
differ only in the per-frame step they hand it. It never returns NaN: a non-finite frame raises
:class:`NonFiniteFrameError` naming the frame and the first bad batch row (which the caller
names as a character and sample).

:func:`sampler_settings` is the one reader of a checkpoint's sampler settings (normalizer,
schedule, ``predicts``, ``clip_x0``, layout, skeleton).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from minimdm.amdm.models import MVAE, MLPDenoiser, MLPRegressor
from minimdm.checkpoint import Checkpoint, check_same_model, load_checkpoint, model_spec
from minimdm.diffusion import ClipX0, Hook, NoiseSchedule, clip_bounds, ddim_sample, ddpm_sample
from minimdm.motion.features import FeatureLayout, Normalizer, StartPose, decode, start_state
from minimdm.motion.skeleton import Skeleton
from minimdm.utils import num_threads
from minimdm.validate import (
    InputError,
    InputTypeError,
    check_device,
    check_frames,
    check_generator,
    check_int,
    check_number,
)

__all__ = [
    "NonFiniteFrameError",
    "Rollout",
    "FrameStep",
    "check_finite",
    "autoregress",
    "SamplerSettings",
    "sampler_settings",
    "rollout",
    "next_frame",
]


class NonFiniteFrameError(FloatingPointError):
    """A rollout produced a frame holding NaN or Inf.

    ``frame`` is the frame (1-based: frame 0 is the initial state) and ``row`` the first batch
    row that held NaN/Inf (None when raised without them).
    """

    def __init__(self, message: str, frame: int | None = None, row: int | None = None) -> None:
        super().__init__(message)
        self.frame = frame
        self.row = row


@dataclass
class Rollout:
    """The result of :func:`rollout` for C characters, K samples each and F frames."""

    features: Tensor
    """(C, K, F, D) generated frames x_1..x_F, denormalized (the units of ``features.encode``)."""
    positions: Tensor | None
    """(C, K, F, J, 3) global joint positions in metres, z-up (None if ``decode=False``)."""
    normalized: Tensor
    """(C, K, F, D) the same frames in the model's normalized space."""

    @property
    def n_frames(self) -> int:
        return self.features.shape[2]


SMALL_BATCH = 256
"""On the CPU, batches below this size roll out on one thread (see :func:`rollout`)."""


def _resolve(model_or_checkpoint: Any, device) -> tuple[nn.Module, Checkpoint | None]:
    if isinstance(model_or_checkpoint, (str, os.PathLike)):
        model_or_checkpoint = load_checkpoint(model_or_checkpoint, device=device or "cpu")
    if isinstance(model_or_checkpoint, Checkpoint):
        return model_or_checkpoint.model, model_or_checkpoint
    if isinstance(model_or_checkpoint, nn.Module):
        return model_or_checkpoint, None
    raise InputTypeError(
        "model_or_checkpoint must be a Checkpoint, a checkpoint path or an nn.Module, "
        f"got {type(model_or_checkpoint).__name__}"
    )


@torch.no_grad()
def next_frame(
    model: nn.Module,
    cond: Tensor,
    generator: torch.Generator | None = None,
    schedule: NoiseSchedule | None = None,
    steps: int | None = None,
    eta: float = 1.0,
    predicts: str = "eps",
    clip_x0: ClipX0 = None,
    hook: Hook | None = None,
    *,
    t_start: int | None = None,
    x_start: Tensor | None = None,
) -> Tensor:
    """One auto-regressive step in normalized space: :math:`x_f` (B, D) from :math:`x_{f-1}`.

    For an :class:`~minimdm.amdm.models.MLPDenoiser` this runs the reverse chain: DDPM over all T
    steps when ``steps`` is None or T, else DDIM over ``steps`` of them with ``eta``
    (1: as stochastic as DDPM, 0: deterministic given the start noise). ``hook`` is passed to
    the sampler (inpainting, guidance...). ``t_start`` and ``x_start`` start the DDPM chain at
    that level from that sample (keyframe inbetweening, A-MDM eq. 5), with DDPM or DDIM.
    """
    if isinstance(model, MLPDenoiser):
        if schedule is None:
            raise ValueError("schedule is required to sample from a denoiser")
        shape = tuple(cond.shape)
        if steps is None or steps == schedule.T:
            return ddpm_sample(
                model,
                schedule,
                shape,
                cond,
                generator,
                hook,
                predicts,
                t_start=t_start,
                x_start=x_start,
                clip_x0=clip_x0,
            )
        return ddim_sample(
            model,
            schedule,
            shape,
            cond,
            steps,
            eta,
            generator,
            hook,
            predicts,
            x_start=x_start,
            clip_x0=clip_x0,
            t_start=t_start,
        )
    if hook is not None or t_start is not None or x_start is not None:
        raise ValueError(
            f"hook, t_start and x_start need a diffusion model, got {type(model).__name__}"
        )
    if isinstance(model, MVAE):
        return model.sample(cond, generator)
    if isinstance(model, MLPRegressor):
        return model(cond)
    raise ValueError(f"cannot sample from a {type(model).__name__}")


FrameStep = Callable[[int, Tensor], Tensor]
"""``step(f, x_prev) -> x_f``: frame ``f`` (1-based) of a batch (B, ...) from frame ``f - 1``."""


def check_finite(
    x: Tensor, frame: int, who: Callable[[int], str] | None = None, what: str = "rollout"
) -> Tensor:
    """Return ``x`` (B, ...), or raise :class:`NonFiniteFrameError` if a row holds NaN/Inf.

    The message names ``frame`` and the first bad row, ``who(row)`` (e.g. "character 1,
    sample 0"; default "batch row {row}"); ``what`` names the technique.
    """
    finite = torch.isfinite(x.reshape(x.shape[0], -1)).all(1)  # (B,)
    if not finite.all():
        b = int((~finite).nonzero()[0])
        name = who(b) if who is not None else f"batch row {b}"
        raise NonFiniteFrameError(
            f"{what} produced a non-finite frame {frame} (frame 0 is the initial state) for {name}",
            frame,
            b,
        )
    return x


def autoregress(
    step: FrameStep,
    x0: Tensor,
    n_frames: int,
    *,
    first: int = 1,
    stop: Callable[[int], bool] | None = None,
    who: Callable[[int], str] | None = None,
    desc: str = "rollout",
    progress: bool = False,
) -> Tensor:
    """The auto-regressive loop (A-MDM §3.1): :math:`x_f = \\mathrm{step}(f, x_{f-1})`.

    Starting from ``x0`` (B, ...), it calls ``step`` for the frames ``f = first, ...,
    first + n_frames - 1`` and feeds each result back as the next condition, so that
    :math:`x_f \\sim p_\\theta(x_f | x_{f-1})` when ``step`` samples the model (one reverse
    diffusion chain per frame, :func:`next_frame`). Every technique is a step: random sampling,
    inpainting (a hook), inbetweening (a chain started from a noised keyframe), beam search (a
    search, then the best plan's frames), AAMDM (GAN draft + polishing + decoding). The loop
    owns what they share: the tqdm bar, the output buffer and the non-finite check
    (:func:`check_finite`, with ``who`` naming a batch row and ``desc`` the technique).

    Args:
        step: ``step(f, x_prev) -> x_f``, (B, ...) -> (B, ...); all randomness comes from the
            generator it closes over, consumed in frame order.
        x0: (B, ...) the condition of the first frame (frame ``first - 1``).
        n_frames: frames to generate, >= 1.
        first: the number of the first generated frame (a beam search's candidates start
            after the frames already committed).
        stop: ``stop(f) -> bool`` after frame f: True ends the loop early (beam search when
            every character has completed its task); the result then holds frames up to f.
        who: names batch row ``b`` in the error (default "batch row b").
        desc: the bar's label and the error's subject.
        progress: show a tqdm bar over frames.

    Returns:
        (B, F, ...) the generated frames :math:`x_{first}..`, float32 on the CPU (the steps'
        own outputs, which stay on the device, are what is fed back).

    Raises:
        NonFiniteFrameError: a frame holds NaN/Inf; names the frame and the row.
    """
    n_frames = check_int("n_frames", n_frames, low=1)
    out: Tensor | None = None  # (B, F, ...) float32, CPU
    x = x0
    n = 0
    for i in tqdm(range(n_frames), disable=not progress, desc=desc, unit="frame"):
        f = first + i
        x = check_finite(step(f, x), f, who, desc)
        if out is None:
            out = torch.empty(x.shape[0], n_frames, *x.shape[1:], dtype=torch.float32)
        out[:, i] = x.float().cpu()
        n = i + 1
        if stop is not None and stop(f):
            break
    return out if n == n_frames else out[:, :n]


@dataclass
class SamplerSettings:
    """What sampling from a checkpoint needs besides the network, as its metadata says."""

    normalizer: Normalizer | None
    """Feature standardisation (None if the checkpoint stores none)."""
    schedule: NoiseSchedule | None
    """The denoiser's noise schedule (None for the baselines)."""
    predicts: str
    """What the denoiser outputs: 'eps' or 'x0'."""
    clip_x0: Any
    """The training-time clamp of the clean estimate, exactly as stored (None, a number or a
    per-feature range); the samplers of :mod:`minimdm.diffusion` interpret it."""
    layout: FeatureLayout | None
    """The feature layout (joint names, fps)."""
    skeleton: Skeleton | None
    """The skeleton."""


def sampler_settings(ckpt: Checkpoint, device: torch.device | str = "cpu") -> SamplerSettings:
    """Read a checkpoint's sampler settings (the one place that reads them).

    ``predicts`` falls back to the network's own (a denoiser) or ``"eps"``; the schedule is
    built on ``device``; ``clip_x0`` is passed through unchanged.
    """
    meta = ckpt.metadata
    diff = meta.get("diffusion") or {}
    norm = Normalizer.from_dict(ckpt.normalizer) if ckpt.normalizer is not None else None
    layout = ckpt.feature_layout
    skeleton = ckpt.skeleton
    return SamplerSettings(
        normalizer=norm,
        schedule=ckpt.schedule(device) if diff else None,
        predicts=diff.get("predicts") or getattr(ckpt.model, "predicts", None) or "eps",
        clip_x0=diff.get("clip_x0"),
        layout=FeatureLayout.from_dict(layout) if layout is not None else None,
        skeleton=Skeleton.from_dict(skeleton) if skeleton is not None else None,
    )


@torch.no_grad()
def rollout(
    model_or_checkpoint: Checkpoint | str | os.PathLike | nn.Module,
    init_states: Tensor,
    n_frames: int,
    n_samples: int = 1,
    steps: int | None = None,
    generator: torch.Generator | None = None,
    *,
    start_pose: StartPose | dict | None = None,
    eta: float = 1.0,
    clip_x0: ClipX0 | str = "checkpoint",
    normalizer: Normalizer | None = None,
    schedule: NoiseSchedule | None = None,
    decode_positions: bool = True,
    device: torch.device | str | None = None,
    progress: bool = False,
    sampler: Callable[[Tensor, torch.Generator | None], Tensor] | None = None,
) -> Rollout:
    """Sample ``n_samples`` futures of ``n_frames`` frames from each initial state.

    Args:
        model_or_checkpoint: a loaded :class:`~minimdm.checkpoint.Checkpoint`, a checkpoint
            path, or a bare network (then pass ``schedule`` for a denoiser and ``normalizer``
            unless ``init_states`` are already normalized).
        init_states: (C, D) or (D,) initial frames x_0, in feature units (``features.encode``).
        n_frames: frames to generate after each initial state, >= 1.
        n_samples: futures per character; the batch is C * n_samples.
        steps: denoising steps per frame (None: the model's T; fewer: DDIM).
        generator: the source of randomness (seed it for reproducible rollouts).
        start_pose: root ground position ``xy`` (C, 2) and ``heading`` (C,) at the initial
            frame, where decoding starts (default: the origin, heading 0).
        eta: DDIM stochasticity when ``steps`` < T.
        clip_x0: clamp the denoiser's clean estimate (normalized units): None, a float c for
            [-c, c], or a per-feature range ``(lo, hi)`` (:func:`minimdm.diffusion.clip_bounds`)
            at every step; ``"checkpoint"``: the value the model was trained with (None for a
            bare network). With eps-prediction and few steps, the first reverse step divides by
            :math:`\\sqrt{\\bar\\alpha_T}` (tiny), so an unclamped estimate can blow up.
        decode_positions: also decode global joint positions.
        progress: show a tqdm bar over frames.
        sampler: ``sampler(x_prev, generator) -> x_f`` (normalized, (B, D)) replaces the eager
            per-frame step :func:`next_frame`, e.g. a :class:`minimdm.fast.FastFrame` of the same
            checkpoint: the same chain as one graph, with its own steps, eta and clamp.

    On the CPU, batches smaller than ``SMALL_BATCH`` run on one thread: they are bound by
    per-operation overhead, which more threads only increase.

    Returns:
        A :class:`Rollout` with features (C, K, F, D), positions (C, K, F, J, 3), normalized.

    Raises:
        ValueError: bad ``init_states`` (shape, non-finite), ``n_frames`` or ``n_samples``.
        NonFiniteFrameError: a generated frame holds NaN/Inf; names the frame.
    """
    device = check_device("device", device)
    n_frames = check_int("n_frames", n_frames, low=1)
    n_samples = check_int("n_samples", n_samples, low=1)
    if steps is not None:
        steps = check_int("steps", steps, low=1)
    eta = check_number("eta", eta, low=0.0)
    if sampler is not None and steps is not None:
        raise InputError("steps belong to the sampler when one is given: pass steps=None")
    model, ckpt = _resolve(model_or_checkpoint, device)
    if not isinstance(model, (MLPDenoiser, MVAE, MLPRegressor)):
        where = f"checkpoint {ckpt.paths.weights} holds" if ckpt is not None else "got"
        raise InputError(
            f"model_or_checkpoint must be an A-MDM denoiser, an MVAE or an MSE regressor "
            f"(kinds amdm, mvae, mse); {where} a {type(model).__name__}"
            + (f" (kind {ckpt.kind!r})" if ckpt is not None else "")
        )
    dev = device if device is not None else next(model.parameters()).device
    check_generator("generator", generator, dev)
    if sampler is not None:  # a graph exported from another checkpoint is refused
        where = str(ckpt.paths.weights) if ckpt is not None else f"a {type(model).__name__}"
        kind = ckpt.kind if ckpt is not None else model_spec(model)["kind"]
        check_same_model("sampler", sampler, model, kind, where)
    model = model.to(dev).eval()
    predicts = model.predicts if isinstance(model, MLPDenoiser) else "eps"
    layout = skeleton = None
    if ckpt is not None:
        settings = sampler_settings(ckpt, dev)
        normalizer = normalizer if normalizer is not None else settings.normalizer
        schedule = schedule if schedule is not None else settings.schedule
        predicts = settings.predicts
        layout, skeleton = settings.layout, settings.skeleton
        if isinstance(clip_x0, str) and clip_x0 == "checkpoint":
            clip_x0 = settings.clip_x0
    if isinstance(clip_x0, str) and clip_x0 == "checkpoint":
        clip_x0 = None
    if isinstance(model, MLPDenoiser) and schedule is None:
        raise InputError("schedule is required to sample from a bare denoiser, got None")
    if schedule is not None:
        schedule = schedule.to(dev)
    D = getattr(getattr(model, "config", None), "x_dim", None) or getattr(model, "x_dim", None)
    if clip_x0 is not None and D is not None:
        clip_bounds(clip_x0, D)  # checked here, before any frame is sampled

    init_states, start_pose = start_state(
        init_states, start_pose, skeleton=skeleton, layout=layout, name="init_states"
    )
    x0 = check_frames(
        "init_states",
        init_states,
        D,
        joints=layout.joint_names if layout is not None else None,
        shape_words=f"(C, {D}) or ({D},)",
    )
    if x0.dim() == 1:
        x0 = x0[None]
    if steps is not None and schedule is not None and not 1 <= steps <= schedule.T:
        raise InputError(f"steps must lie in [1, T={schedule.T}], got {steps}")
    C, K = x0.shape[0], n_samples
    # Small batches are launch-bound: extra threads only add synchronisation, and on a shared
    # 2-core machine they made batch-1 sampling 10x slower.
    n_threads = 1 if dev.type == "cpu" and C * K < SMALL_BATCH else None
    cond = x0.to(dev)
    cond = normalizer.normalize(cond) if normalizer is not None else cond
    cond = cond.repeat_interleave(K, dim=0)  # (C K, D), character-major

    def step(f: int, x_prev: Tensor) -> Tensor:  # x_f (C K, D) from x_{f-1}
        if sampler is not None:
            return sampler(x_prev, generator)
        return next_frame(model, x_prev, generator, schedule, steps, eta, predicts, clip_x0)

    with num_threads(n_threads):
        normalized = autoregress(
            step, cond, n_frames, who=lambda b: f"character {b // K}, sample {b % K}",
            progress=progress,
        )  # fmt: skip
    normalized = normalized.reshape(C, K, n_frames, -1)  # (C, K, F, D)
    feats = normalizer.denormalize(normalized) if normalizer is not None else normalized.clone()
    positions = None
    if decode_positions:
        sp = StartPose.broadcast(start_pose, C)
        sp = StartPose(sp.xy[:, None].expand(C, K, 2), sp.heading[:, None].expand(C, K))
        positions = decode(feats.double(), sp).float()  # (C, K, F, J, 3)
    return Rollout(features=feats, positions=positions, normalized=normalized)
