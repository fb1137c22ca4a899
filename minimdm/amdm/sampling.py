"""Auto-regressive rollouts: sample frame after frame from a trained model (A-MDM §3.1).

Given initial states :math:`x_0` (one per character), :func:`rollout` draws ``n_samples``
futures per character, all in one batch: each new frame :math:`x_f` is sampled conditioned on
the previous one, :math:`x_f \\sim p_\\theta(x_f | x_{f-1})`, by the reverse diffusion chain for
A-MDM (DDPM over all T steps, or DDIM over fewer), by the prior of the MVAE-style baseline, or
by the deterministic regressor. Frames are normalized before they enter the model and
denormalized after; decoded global joint positions come with them.

A rollout never returns NaN: a non-finite frame raises :class:`NonFiniteFrameError` naming the
frame and the first character and sample it appeared in.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from minimdm.amdm.models import MVAE, MLPDenoiser, MLPRegressor
from minimdm.checkpoint import Checkpoint, load_checkpoint
from minimdm.diffusion import Hook, NoiseSchedule, ddim_sample, ddpm_sample
from minimdm.motion.features import Normalizer, StartPose, decode

__all__ = ["NonFiniteFrameError", "Rollout", "rollout", "next_frame"]


class NonFiniteFrameError(FloatingPointError):
    """A rollout produced a frame holding NaN or Inf."""


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


@contextlib.contextmanager
def _threads(n: int | None) -> Iterator[None]:
    """Run torch with ``n`` CPU threads inside the block (None: leave as is)."""
    old = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


SMALL_BATCH = 256
"""On the CPU, batches below this size roll out on one thread (see :func:`rollout`)."""


def _resolve(model_or_checkpoint: Any, device) -> tuple[nn.Module, Checkpoint | None]:
    if isinstance(model_or_checkpoint, (str, os.PathLike)):
        model_or_checkpoint = load_checkpoint(model_or_checkpoint, device=device or "cpu")
    if isinstance(model_or_checkpoint, Checkpoint):
        return model_or_checkpoint.model, model_or_checkpoint
    if isinstance(model_or_checkpoint, nn.Module):
        return model_or_checkpoint, None
    raise ValueError(
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
    clip_x0: float | None = None,
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
    that level from that sample (keyframe inbetweening, A-MDM eq. 5); DDPM only.
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


def _sample_frames(
    model: nn.Module,
    x0: Tensor,
    n_frames: int,
    K: int,
    normalizer: Normalizer | None,
    generator: torch.Generator | None,
    schedule: NoiseSchedule | None,
    steps: int | None,
    eta: float,
    predicts: str,
    clip_x0: float | None,
    progress: bool,
) -> Tensor:
    """The auto-regressive loop in normalized space: (C, K, F, D) on the CPU."""
    C = x0.shape[0]
    cond = normalizer.normalize(x0) if normalizer is not None else x0
    cond = cond.repeat_interleave(K, dim=0)  # (C K, D), character-major
    out = torch.empty(C * K, n_frames, cond.shape[1], dtype=torch.float32)  # (C K, F, D) on CPU
    for f in tqdm(range(n_frames), disable=not progress, desc="rollout", unit="frame"):
        x = next_frame(model, cond, generator, schedule, steps, eta, predicts, clip_x0)
        finite = torch.isfinite(x).all(1)
        if not finite.all():
            b = int((~finite).nonzero()[0])
            raise NonFiniteFrameError(
                f"rollout produced a non-finite frame {f + 1} (of {n_frames}; frame 0 is the "
                f"initial state) for character {b // K}, sample {b % K}"
            )
        out[:, f] = x.float().cpu()
        cond = x
    return out.reshape(C, K, n_frames, -1)


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
    clip_x0: float | None | str = "checkpoint",
    normalizer: Normalizer | None = None,
    schedule: NoiseSchedule | None = None,
    decode_positions: bool = True,
    device: torch.device | str | None = None,
    progress: bool = False,
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
        clip_x0: clamp the denoiser's clean estimate to [-clip_x0, clip_x0] (normalized units)
            at every step; ``"checkpoint"``: the value the model was trained with (None for a
            bare network). With eps-prediction and few steps, the first reverse step divides by
            :math:`\\sqrt{\\bar\\alpha_T}` (tiny), so an unclamped estimate can blow up.
        decode_positions: also decode global joint positions.
        progress: show a tqdm bar over frames.

    On the CPU, batches smaller than ``SMALL_BATCH`` run on one thread: they are bound by
    per-operation overhead, which more threads only increase.

    Returns:
        A :class:`Rollout` with features (C, K, F, D), positions (C, K, F, J, 3), normalized.

    Raises:
        ValueError: bad ``init_states`` (shape, non-finite), ``n_frames`` or ``n_samples``.
        NonFiniteFrameError: a generated frame holds NaN/Inf; names the frame.
    """
    model, ckpt = _resolve(model_or_checkpoint, device)
    dev = torch.device(device) if device is not None else next(model.parameters()).device
    model = model.to(dev).eval()
    predicts = "eps"
    if ckpt is not None:
        if normalizer is None and ckpt.normalizer is not None:
            normalizer = Normalizer.from_dict(ckpt.normalizer)
        if schedule is None and ckpt.metadata.get("diffusion"):
            schedule = ckpt.schedule(dev)
        predicts = (ckpt.metadata.get("diffusion") or {}).get("predicts", "eps")
        if clip_x0 == "checkpoint":
            clip_x0 = (ckpt.metadata.get("diffusion") or {}).get("clip_x0")
    elif isinstance(model, MLPDenoiser):
        predicts = model.predicts
    if clip_x0 == "checkpoint":
        clip_x0 = None
    if schedule is not None:
        schedule = schedule.to(dev)
    D = getattr(getattr(model, "config", None), "x_dim", None) or getattr(model, "x_dim", None)

    x0 = torch.as_tensor(init_states, dtype=torch.float32)
    if x0.dim() == 1:
        x0 = x0[None]
    if x0.dim() != 2 or (D is not None and x0.shape[1] != D):
        raise ValueError(f"init_states must have shape (C, {D}) or ({D},), got {tuple(x0.shape)}")
    if not torch.isfinite(x0).all():
        bad = (~torch.isfinite(x0)).any(1).nonzero()[0].item()
        raise ValueError(f"init_states must be finite, but character {bad} holds NaN/Inf")
    if not isinstance(n_frames, int) or n_frames < 1:
        raise ValueError(f"n_frames must be an integer >= 1, got {n_frames!r}")
    if not isinstance(n_samples, int) or n_samples < 1:
        raise ValueError(f"n_samples must be an integer >= 1, got {n_samples!r}")
    if steps is not None and schedule is not None and not 1 <= steps <= schedule.T:
        raise ValueError(f"steps must lie in [1, T={schedule.T}], got {steps}")
    C, K = x0.shape[0], n_samples
    # Small batches are launch-bound: extra threads only add synchronisation, and on a shared
    # 2-core machine they made batch-1 sampling 10x slower.
    n_threads = 1 if dev.type == "cpu" and C * K < SMALL_BATCH else None
    with _threads(n_threads):
        args = (normalizer, generator, schedule, steps, eta, predicts, clip_x0, progress)
        normalized = _sample_frames(model, x0.to(dev), n_frames, K, *args)
    feats = normalizer.denormalize(normalized) if normalizer is not None else normalized.clone()
    positions = None
    if decode_positions:
        sp = StartPose.broadcast(start_pose, C)
        sp = StartPose(sp.xy[:, None].expand(C, K, 2), sp.heading[:, None].expand(C, K))
        positions = decode(feats.double(), sp).float()  # (C, K, F, J, 3)
    return Rollout(features=feats, positions=positions, normalized=normalized)
