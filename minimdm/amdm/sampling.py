"""Auto-regressive rollouts: sample frame after frame from a trained model (A-MDM §3.1).

Given initial states :math:`x_0` (one per character), :func:`rollout` draws ``n_samples``
futures per character, all in one batch: each new frame :math:`x_f` is sampled conditioned on
the previous one, :math:`x_f \\sim p_\\theta(x_f | x_{f-1})`, by the reverse diffusion chain for
A-MDM (DDPM over all T steps, or DDIM over fewer), by the prior of the MVAE-style baseline, or
by the deterministic regressor. Frames are normalized before they enter the model and
denormalized after; decoded global joint positions come with them.

:func:`autoregress` is the frame-after-frame loop of every technique whose step makes one frame
from the last: random rollouts, inpainting and inbetweening (:mod:`minimdm.control.inpaint`),
RL steering (:mod:`minimdm.rl.rollout`), AAMDM rollouts (:mod:`minimdm.aamdm.eval`) and the
Squ-9 chains of the studies differ only in the per-frame step they hand it. (Beam search and
CAMDM's controller plan several frames at a time: they are plain loops of their own, with the
same non-finite check.) It never returns NaN: a non-finite frame raises
:class:`NonFiniteFrameError` naming the frame and the first bad batch row (which the caller
names as a character and sample).

:class:`Sampler` is the one reader of a checkpoint's sampler settings (normalizer, schedule,
``predicts``, ``clip_x0``, layout, skeleton) and draws one frame; :func:`rollout`, the control
techniques, the RL environment and the fast graphs all sample through it.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from minimdm.amdm.models import MVAE, MLPDenoiser, MLPRegressor
from minimdm.checkpoint import (
    DEFAULT_FPS,
    Checkpoint,
    check_same_model,
    load_checkpoint,
    model_spec,
)
from minimdm.diffusion import (
    ClipX0,
    Hook,
    NoiseSchedule,
    StepSettings,
    clamp_x0,
    clip_bounds,
    hook_list,
    reverse_chain,
    start_chain,
)
from minimdm.motion.features import FeatureLayout, Normalizer, StartPose, decode, start_state
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

__all__ = [
    "NonFiniteFrameError",
    "Rollout",
    "FrameStep",
    "check_finite",
    "autoregress",
    "Sampler",
    "history_of",
    "rollout",
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
    who: Callable[[int], str] | None = None,
    desc: str = "rollout",
    progress: bool = False,
) -> Tensor:
    """The auto-regressive loop (A-MDM §3.1): :math:`x_f = \\mathrm{step}(f, x_{f-1})`.

    Starting from ``x0`` (B, ...), it calls ``step`` for the frames ``f = 1, ..., n_frames``
    and feeds each result back as the next condition, so that
    :math:`x_f \\sim p_\\theta(x_f | x_{f-1})` when ``step`` samples the model (one reverse
    diffusion chain per frame, :meth:`Sampler.frame`). Each technique is a step: random
    sampling, inpainting (a hook), inbetweening (a chain started from a noised keyframe), RL
    steering (a residual hook), AAMDM (GAN draft + polishing + decoding). The loop owns what
    they share: the tqdm bar, the output buffer and the non-finite check
    (:func:`check_finite`, with ``who`` naming a batch row and ``desc`` the technique).

    Args:
        step: ``step(f, x_prev) -> x_f``, (B, ...) -> (B, ...); all randomness comes from the
            generator it closes over, consumed in frame order.
        x0: (B, ...) the condition of the first frame (frame 0).
        n_frames: frames to generate, >= 1.
        who: names batch row ``b`` in the error (default "batch row b").
        desc: the bar's label and the error's subject.
        progress: show a tqdm bar over frames.

    Returns:
        (B, F, ...) the generated frames :math:`x_1..x_F`, float32 on the CPU (the steps'
        own outputs, which stay on the device, are what is fed back).

    Raises:
        NonFiniteFrameError: a frame holds NaN/Inf; names the frame and the row.
    """
    n_frames = check_int("n_frames", n_frames, low=1)
    out: Tensor | None = None  # (B, F, ...) float32, CPU
    x = x0
    for f in tqdm(range(1, n_frames + 1), disable=not progress, desc=desc, unit="frame"):
        x = check_finite(step(f, x), f, who, desc)
        if out is None:
            out = torch.empty(x.shape[0], n_frames, *x.shape[1:], dtype=torch.float32)
        out[:, f - 1] = x.float().cpu()
    return out


@dataclass
class Sampler:
    """A trained next-frame model and everything sampling a frame from it needs (A-MDM §3.1).

    :meth:`load` reads it from a checkpoint: the normalizer, the noise schedule, what the
    denoiser predicts, the clamp it was trained with, the feature layout and the skeleton.
    :meth:`frame` draws :math:`x_f \\sim p_\\theta(x_f | x_{f-1})` in normalized space: one
    reverse diffusion chain for A-MDM, the prior for the MVAE-style baseline, the regressor's
    output (plus ``noise``) for MSE. :func:`rollout` and every control technique
    (:mod:`minimdm.control`, :mod:`minimdm.rl`, :mod:`minimdm.fast`) sample through it.
    """

    net: nn.Module
    """The network: an MLPDenoiser (A-MDM), an MVAE or an MLPRegressor."""
    normalizer: Normalizer | None = None
    """Feature standardisation; None if the network works in feature units."""
    schedule: NoiseSchedule | None = None
    """The denoiser's noise schedule (None for the baselines)."""
    settings: StepSettings = field(default_factory=StepSettings)
    """How a frame's chain runs: steps (None: all T, DDPM), eta, predicts, clip_x0."""
    noise: float | Tensor = 0.0
    """Std (normalized units, scalar or (D,)) of Gaussian noise added to a regressor's output."""
    layout: FeatureLayout | None = None
    """The feature layout (joint names, fps), from the checkpoint."""
    skeleton: Skeleton | None = None
    """The skeleton, from the checkpoint."""
    checkpoint: Checkpoint | None = None
    """The checkpoint it was read from (None for a bare network)."""

    @classmethod
    def load(
        cls,
        model: Checkpoint | Sampler | nn.Module | str | os.PathLike,
        *,
        normalizer: Normalizer | None = None,
        schedule: NoiseSchedule | None = None,
        predicts: str | None = None,
        clip_x0: ClipX0 | str = "checkpoint",
        steps: int | None = None,
        eta: float = 1.0,
        noise: float | Tensor = 0.0,
        device: torch.device | str | None = None,
    ) -> Sampler:
        """A sampler from a Checkpoint, a checkpoint path or a bare network (a Sampler is
        returned as it is, and refuses overrides: they belong to the call that made it).

        From a checkpoint, the normalizer, schedule, ``predicts``, ``clip_x0``, layout and
        skeleton come from its metadata; explicit arguments win. ``clip_x0="checkpoint"`` is
        the clamp the model was trained with (none for a bare network). A bare denoiser needs
        ``schedule``. ``noise`` (regressors only) turns the deterministic MSE baseline into a
        Gaussian :math:`\\mathcal N(f(x_{f-1}), \\sigma^2 I)`, the likelihood MSE training fits,
        so that its samples can differ.
        """
        if isinstance(model, Sampler):
            given = {
                "normalizer": normalizer is not None,
                "schedule": schedule is not None,
                "predicts": predicts is not None,
                "clip_x0": not _from_checkpoint(clip_x0),
                "steps": steps is not None,
                "eta": eta != 1.0,
                "noise": isinstance(noise, Tensor) or noise != 0.0,
                "device": device is not None,
            }
            given = [k for k, v in given.items() if v]
            if given:
                raise InputError(
                    f"model is a Sampler: its settings are fixed, so {', '.join(given)} cannot "
                    "be given again (pass the checkpoint to change them)"
                )
            return model
        device = check_device("device", device)
        if steps is not None:
            steps = check_int("steps", steps, low=1)
        eta = check_number("eta", eta, low=0.0)
        ckpt = _checkpoint(model, device)
        net = ckpt.model if ckpt is not None else model
        _check_kind(net, ckpt)
        layout = skeleton = None
        if ckpt is not None:
            meta = ckpt.diffusion
            if normalizer is None and ckpt.normalizer is not None:
                normalizer = Normalizer.from_dict(ckpt.normalizer)
            if schedule is None and meta:
                schedule = ckpt.schedule(device or "cpu")
            predicts = predicts or meta.get("predicts") or getattr(net, "predicts", None)
            clip_x0 = meta.get("clip_x0") if _from_checkpoint(clip_x0) else clip_x0
            layout = FeatureLayout.from_dict(ckpt.feature_layout) if ckpt.feature_layout else None
            skeleton = Skeleton.from_dict(ckpt.skeleton) if ckpt.skeleton else None
        clip_x0 = None if _from_checkpoint(clip_x0) else clip_x0
        if clip_x0 is not None:
            clip_bounds(clip_x0, _x_dim(net))  # checked before any frame is sampled
        if isinstance(net, MLPDenoiser):
            predicts = predicts or net.predicts
            if schedule is None:
                raise InputError("schedule is required to sample from a bare denoiser, got None")
        net = (net.to(device) if device is not None else net).eval()
        dev = next(net.parameters()).device
        if schedule is not None:
            schedule = schedule.to(dev)
            if steps is not None and not 1 <= steps <= schedule.T:
                raise InputError(f"steps must lie in [1, T={schedule.T}], got {steps}")
        if isinstance(noise, Tensor) and noise.numel() > 1:
            noise = noise.to(dev)
        settings = StepSettings(steps=steps, eta=eta, predicts=predicts or "eps", clip_x0=clip_x0)
        return cls(net, normalizer, schedule, settings, noise, layout, skeleton, ckpt)

    @property
    def is_diffusion(self) -> bool:
        return isinstance(self.net, MLPDenoiser)

    @property
    def dim(self) -> int:
        """D, the frame dimension."""
        return _x_dim(self.net)

    @property
    def history(self) -> int:
        """H, how many previous frames the model conditions on (the paper's model: 1)."""
        return history_of(self.net)

    @property
    def fps(self) -> float:
        return self.layout.fps if self.layout is not None else DEFAULT_FPS

    @property
    def device(self) -> torch.device:
        return next(self.net.parameters()).device

    def normalize(self, x: Tensor) -> Tensor:
        return self.normalizer.normalize(x) if self.normalizer is not None else x

    def denormalize(self, x: Tensor) -> Tensor:
        return self.normalizer.denormalize(x) if self.normalizer is not None else x

    @torch.no_grad()
    def frame(
        self,
        cond: Tensor,
        generator: torch.Generator | None = None,
        *,
        hook: Hook | None = None,
        t_start: int | None = None,
        x_start: Tensor | None = None,
    ) -> Tensor:
        """One auto-regressive step in normalized space: :math:`x_f` (B, D) from
        :math:`x_{f-1}` (B, D), or from the H frames before it (B, H D), oldest first, for a
        model with a :attr:`history` of H.

        For a denoiser this runs one reverse chain (:attr:`settings`: DDPM over all T levels or
        DDIM over fewer) with ``hook`` on :math:`x_t` (inpainting, RL residuals...); ``t_start``
        and ``x_start`` start the chain at that level from that sample (keyframe
        inbetweening, A-MDM eq. 5). For a delta model the chain's variable is the change from
        ``cond``: ``hook`` and ``x_start`` see it (:meth:`chain_target`); the result is the
        frame.
        """
        net, H = self.net, self.history
        if H > 1 and (cond.dim() != 2 or cond.shape[1] != H * self.dim):
            raise InputError(
                f"this model conditions on the {H} frames before x_f: cond must have shape "
                f"(B, {H * self.dim}), got {tuple(cond.shape)} (techniques that feed one frame "
                "need a model with history 1)"
            )
        if isinstance(net, MLPDenoiser):
            rule, levels = self.settings.chain(net, self.schedule, t_start)
            delta = net.is_delta
            x, clamp = start_chain(
                (cond.shape[0], self.dim),
                self.schedule,
                cond=cond,
                generator=generator,
                x_start=x_start,
                clip_x0=None if delta else self.settings.clip_x0,
            )  # x at the chain's first level, and the clamp of x0_hat
            if delta:  # the chain runs on the change; its clamp still bounds the frame
                clamp = self._frame_clamp(cond)
            x = reverse_chain(rule, x, levels, cond, generator, hook_list(hook), clamp)
            return net.from_delta(x, cond) if delta else x
        if hook is not None or t_start is not None or x_start is not None:
            raise ValueError(
                f"hook, t_start and x_start need a diffusion model, got {type(net).__name__}"
            )
        if isinstance(net, MVAE):
            return net.sample(cond, generator)
        x = net(cond)
        if (torch.as_tensor(self.noise) != 0).any():
            eps = torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype)
            x = x + torch.as_tensor(self.noise, device=x.device, dtype=x.dtype) * eps
        return x

    def chain_target(self, x: Tensor, cond: Tensor) -> Tensor:
        """What the chain of the frame after ``cond`` (B, D) denoises for a frame ``x`` (B, D),
        both normalized: ``x`` itself, or for a delta model its change from ``cond``
        (:meth:`~minimdm.amdm.models.MLPDenoiser.to_delta`). Hooks and ``x_start`` of
        :meth:`frame` live in this variable: inpainting noises ``chain_target`` of its targets,
        inbetweening of its keyframe."""
        net = self.net
        return net.to_delta(x, cond) if isinstance(net, MLPDenoiser) and net.is_delta else x

    def _frame_clamp(self, cond: Tensor) -> list:
        """A delta model's clamp of :math:`\\hat z_0`: the frame's box (``settings.clip_x0``)
        seen from the change after ``cond``; [] without a box."""
        net = self.net
        bounds = clip_bounds(self.settings.clip_x0, self.dim, cond.device, cond.dtype)
        if bounds is None:
            return []

        def clamp_frame(t: int, z_t: Tensor, z0_hat: Tensor) -> Tensor:
            return net.to_delta(clamp_x0(net.from_delta(z0_hat, cond), bounds), cond)

        return [clamp_frame]


def history_of(net: nn.Module) -> int:
    """How many previous frames a next-frame network conditions on: a denoiser's
    ``config.history``; for the baselines, their condition's size over the frame's."""
    if isinstance(net, MLPDenoiser):
        return net.config.history
    return max(1, int(getattr(getattr(net, "config", net), "cond_dim", 0)) // _x_dim(net))


def _from_checkpoint(clip_x0: Any) -> bool:
    return isinstance(clip_x0, str) and clip_x0 == "checkpoint"


def _x_dim(net: nn.Module) -> int:
    return int(getattr(getattr(net, "config", None), "x_dim", None) or net.x_dim)


def _checkpoint(model: Any, device) -> Checkpoint | None:
    """The checkpoint ``model`` is or names (loaded on ``device``), or None for a network."""
    if isinstance(model, (str, os.PathLike)):
        return load_checkpoint(model, device=device or "cpu")
    if isinstance(model, Checkpoint):
        return model
    if isinstance(model, nn.Module):
        return None
    raise InputTypeError(
        "model must be a Checkpoint, a checkpoint path, an nn.Module or a Sampler, "
        f"got {type(model).__name__}"
    )


def _check_kind(net: nn.Module, ckpt: Checkpoint | None) -> None:
    if not isinstance(net, (MLPDenoiser, MVAE, MLPRegressor)):
        where = f"checkpoint {ckpt.paths.weights} holds" if ckpt is not None else "got"
        raise InputError(
            "model must be an A-MDM denoiser, an MVAE or an MSE regressor "
            f"(kinds amdm, mvae, mse); {where} a {type(net).__name__}"
            + (f" (kind {ckpt.kind!r})" if ckpt is not None else "")
        )


@torch.no_grad()
def rollout(
    model: Sampler | Checkpoint | str | os.PathLike | nn.Module,
    init_states: Tensor,
    n_frames: int,
    n_samples: int = 1,
    *,
    steps: int | None = None,
    generator: torch.Generator | None = None,
    start_pose: StartPose | dict | None = None,
    eta: float = 1.0,
    clip_x0: ClipX0 | str = "checkpoint",
    normalizer: Normalizer | None = None,
    schedule: NoiseSchedule | None = None,
    decode_positions: bool = True,
    device: torch.device | str | None = None,
    progress: bool = False,
    fast: Callable[[Tensor, torch.Generator | None], Tensor] | None = None,
) -> Rollout:
    """Sample ``n_samples`` futures of ``n_frames`` frames from each initial state.

    Args:
        model: a :class:`Sampler`, a loaded :class:`~minimdm.checkpoint.Checkpoint`, a
            checkpoint path, or a bare network (then pass ``schedule`` for a denoiser and
            ``normalizer`` unless ``init_states`` are already normalized).
        init_states: (C, D) or (D,) initial frames x_0, in feature units (``features.encode``);
            for a model with a :attr:`~Sampler.history` of H > 1, (C, H, D) or (H, D): the H
            recorded frames that end with x_0, oldest first.
        n_frames: frames to generate after each initial state, >= 1.
        n_samples: futures per character; the batch is C * n_samples.
        steps: denoising steps per frame (None: the model's T; fewer: DDIM).
        generator: the source of randomness (seed it for reproducible rollouts).
        start_pose: root ground position ``xy`` (C, 2) and ``heading`` (C,) at the initial
            frame, where decoding starts (default: the origin, heading 0).
        eta: DDIM stochasticity when ``steps`` < T.
        clip_x0: clamp the denoiser's clean estimate at every step (normalized units): None,
            a float c for [-c, c], or a per-feature range ``(lo, hi)``
            (:func:`minimdm.diffusion.clip_bounds`); ``"checkpoint"``: the model's own.
        decode_positions: also decode global joint positions.
        progress: show a tqdm bar over frames.
        fast: ``fast(x_prev, generator) -> x_f`` (normalized, (B, D)) replaces
            :meth:`Sampler.frame`, e.g. a :class:`minimdm.fast.FastFrame` of the same
            checkpoint: the same chain as one graph, with its own steps, eta and clamp.

    Threads are the caller's (``torch.set_num_threads`` or :func:`minimdm.utils.num_threads`):
    on the CPU, small batches are bound by per-operation overhead and run fastest on one.

    Returns:
        A :class:`Rollout` with features (C, K, F, D), positions (C, K, F, J, 3), normalized.

    Raises:
        ValueError: bad ``init_states`` (shape, non-finite), ``n_frames`` or ``n_samples``.
        NonFiniteFrameError: a generated frame holds NaN/Inf; names the frame.
    """
    n_frames = check_int("n_frames", n_frames, low=1)
    n_samples = check_int("n_samples", n_samples, low=1)
    if fast is not None and steps is not None:
        raise InputError("steps belong to the fast graph when one is given: pass steps=None")
    overrides = dict(normalizer=normalizer, schedule=schedule, clip_x0=clip_x0, steps=steps)
    sampler = Sampler.load(model, **overrides, eta=eta, device=device)
    check_generator("generator", generator, sampler.device)
    if fast is not None:  # a graph exported from another checkpoint is refused
        _check_fast(fast, sampler)
    x0, start_pose = _start_states(sampler, init_states, start_pose)  # (C, D) or (C, H, D)
    C, K, H = x0.shape[0], n_samples, sampler.history
    cond = sampler.normalize(x0.to(sampler.device)).repeat_interleave(K, dim=0)  # (C K, [H,] D)
    past = cond.flatten(1) if H > 1 else None  # the H frames before x_f, (C K, H D)
    if H > 1:
        cond = cond[:, -1]  # x_0

    def step(f: int, x_prev: Tensor) -> Tensor:  # x_f (C K, D) from x_{f-1}
        nonlocal past
        if past is not None:  # x_{f-1} joins the history, the oldest frame leaves
            if f > 1:
                past = torch.cat([past[:, x_prev.shape[1] :], x_prev], dim=1)
            x_prev = past
        return fast(x_prev, generator) if fast is not None else sampler.frame(x_prev, generator)

    def who(b: int) -> str:
        return f"character {b // K}, sample {b % K}"

    normalized = autoregress(step, cond, n_frames, who=who, progress=progress)
    normalized = normalized.reshape(C, K, n_frames, -1)  # (C, K, F, D)
    feats = sampler.denormalize(normalized)
    feats = feats.clone() if feats is normalized else feats
    positions = _positions(feats, start_pose) if decode_positions else None
    return Rollout(features=feats, positions=positions, normalized=normalized)


def _positions(feats: Tensor, start_pose: Any) -> Tensor:
    """(C, K, F, J, 3) global joint positions of (C, K, F, D) frames, each character's K
    futures decoded from its own start pose."""
    C, K = feats.shape[:2]
    sp = StartPose.broadcast(start_pose, C)
    sp = StartPose(sp.xy[:, None].expand(C, K, 2), sp.heading[:, None].expand(C, K))
    return decode(feats.double(), sp).float()


def _check_fast(fast: Any, sampler: Sampler) -> None:
    ckpt, net = sampler.checkpoint, sampler.net
    where = str(ckpt.paths.weights) if ckpt is not None else f"a {type(net).__name__}"
    kind = ckpt.kind if ckpt is not None else model_spec(net)["kind"]
    check_same_model("fast", fast, net, kind, where)


def _start_states(sampler: Sampler, init_states: Any, start_pose: Any) -> tuple[Tensor, Any]:
    """The initial frames (C, D), checked against the model, and their start pose."""
    layout, H = sampler.layout, sampler.history
    init_states, start_pose = start_state(
        init_states,
        start_pose,
        skeleton=sampler.skeleton,
        layout=layout,
        name="init_states",
        history=H,
    )
    D = sampler.dim
    words = f"(C, {D}) or ({D},)" if H == 1 else f"(C, {H}, {D}) or ({H}, {D}) for a history of {H}"
    x0 = check_frames(
        "init_states",
        init_states,
        D,
        joints=layout.joint_names if layout is not None else None,
        ndim=(1, 2) if H == 1 else (2, 3),
        shape_words=words,
    )
    if H > 1 and x0.shape[-2] != H:
        raise InputError(f"init_states must have shape {words}, got {tuple(x0.shape)}")
    return (x0[None] if x0.dim() == (1 if H == 1 else 2) else x0), start_pose
