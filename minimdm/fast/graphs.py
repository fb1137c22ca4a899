"""The per-frame graphs: each model's own eager frame step, with its noise as an input.

A :class:`FrameGraph` wraps the library's per-frame step of one kind of checkpoint, the very
function the eager rollout loop calls, and runs it with a
:class:`~minimdm.diffusion.NoiseTape` in place of the generator. Its ``forward(state, *extra,
noise)`` is therefore a pure function of tensors: the whole frame, every denoising step, that
:mod:`minimdm.fast.onnx` traces into one graph. Nothing here restates a sampler:

* ``amdm``: :func:`minimdm.control.core.sample_frame` (DDPM over all T levels, or DDIM over
  ``steps`` of them), which calls :func:`minimdm.amdm.sampling.next_frame`;
* ``aamdm_motion``: :func:`minimdm.aamdm.eval.aamdm_frame` (3 DD-GAN steps, 2 polishing steps,
  then the pose decoder);
* ``policy``: the steering policy's mean action, then its steerer, the residual hook of A-MDM
  eq. 7 on the base model's chain (:mod:`minimdm.rl`), as :func:`minimdm.rl.rollout.steer` runs
  them.

:data:`FRAME_GRAPHS` maps a checkpoint kind to its graph. Adding a model (CAMDM's conditional
transformer, whose planning call is its sampler with classifier-free guidance) is one more
entry: a :class:`FrameGraph` whose :meth:`~FrameGraph.frame` calls that model's own step with
the generator it is given.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from minimdm.checkpoint import Checkpoint
from minimdm.diffusion import NoiseTape, ddim_timesteps
from minimdm.validate import InputError

__all__ = [
    "FrameGraph",
    "AMDMFrame",
    "AAMDMFrame",
    "SteeredFrame",
    "FRAME_GRAPHS",
    "frame_graph",
    "load",
]

_RECORD_COLUMNS = 1 << 20
"""Columns of the zero tape that records a chain's draws (more than any chain here takes)."""


class FrameGraph(nn.Module):
    """One frame of a model, all its denoising steps, as a function of tensors.

    ``state`` (B, S) is what the rollout loop feeds back (normalized features for A-MDM,
    ``[xz, y]`` for AAMDM); ``extra`` are per-frame inputs besides it (a policy's task
    observation); ``noise`` (B, N) is every Gaussian draw of the frame, in the order the chain
    makes them (:attr:`noise_widths`).
    """

    kind: str = ""
    """The checkpoint kind this graph runs."""
    extra_inputs: tuple[tuple[str, int, str], ...] = ()
    """``(name, width, meaning)`` of each input between ``state`` and ``noise``."""

    def __init__(self, state_dim: int) -> None:
        super().__init__()
        self.state_dim = int(state_dim)
        self.noise_widths: tuple[int, ...] = ()
        self.settings: dict[str, Any] = {}
        """The checkpoint's skeleton, feature layout, fps and provenance (:func:`frame_graph`)."""

    def frame(self, state: Tensor, generator: Any, *extra: Tensor) -> Tensor:
        """The library's eager step: the next state (B, S) from ``state`` (B, S).

        ``generator`` is a ``torch.Generator`` (eager) or a :class:`NoiseTape` (traced).
        """
        raise NotImplementedError

    @torch.no_grad()
    def forward(self, state: Tensor, *rest: Tensor) -> Tensor:
        """``forward(state, *extra, noise)``: :meth:`frame` with the noise as an input."""
        *extra, noise = rest
        return self.frame(state, NoiseTape(noise), *extra)

    @torch.no_grad()
    def _record(self) -> None:
        """Run the frame once on zeros to learn the widths of its draws."""
        tape = NoiseTape(torch.zeros(1, _RECORD_COLUMNS, device=self.device))
        extra = [torch.zeros(1, w, device=self.device) for _, w, _ in self.extra_inputs]
        self.frame(torch.zeros(1, self.state_dim, device=self.device), tape, *extra)
        self.noise_widths = tuple(tape.widths)

    @property
    def noise_dim(self) -> int:
        """N, the noise columns of one frame."""
        return sum(self.noise_widths)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def noise(self, batch: int, generator: torch.Generator | None = None) -> Tensor:
        """(batch, N) the noise of one frame, drawn exactly as the eager chain draws it."""
        return NoiseTape.draw(self.noise_widths, batch, generator, self.device)

    def example_inputs(self, batch: int = 1) -> tuple[Tensor, ...]:
        """Inputs of the right shapes (the tracer's examples): zeros and the noise."""
        g = torch.Generator(device=self.device).manual_seed(0)
        extra = [torch.zeros(batch, w, device=self.device) for _, w, _ in self.extra_inputs]
        state = torch.zeros(batch, self.state_dim, device=self.device)
        return (state, *extra, self.noise(batch, g))

    def describe(self) -> dict[str, Any]:
        """What a game engine needs besides the graph (stored as the ONNX file's metadata)."""
        return {}


def feature_columns(layout: dict | None) -> dict[str, Any] | None:
    """Where each quantity lives in a frame's features, for readers without minimdm.

    ``[start, stop)`` column ranges of :class:`~minimdm.motion.features.FeatureLayout` with their
    meaning: every vector is in the heading frame of its own frame, z up, metres and radians
    per frame.
    """
    if layout is None:
        return None
    from minimdm.motion.features import FeatureLayout

    lay = FeatureLayout.from_dict(layout)
    what = {
        "root_vel": "root ground displacement (x, y) from the previous frame",
        "yaw_rate": "heading change from the previous frame, radians",
        "joint_pos": "joint positions (x, y, z per joint) relative to the root's ground point",
        "joint_vel": "joint displacements from the previous frame",
        "joint_rot": "global joint rotations, 6D (two matrix columns per joint), yaw removed",
    }
    cols = {
        k: {"columns": [getattr(lay, k).start, getattr(lay, k).stop], "what": w}
        for k, w in what.items()
    }
    cols["decode"] = (
        "heading_f = heading_{f-1} + yaw_rate; xy_f = xy_{f-1} + Rz(heading_f) root_vel; "
        "joint j in the world (z up, metres) = Rz(heading_f) joint_pos_j + (xy_f, 0)"
    )
    return cols


def _settings(ckpt: Checkpoint) -> dict[str, Any]:
    """The checkpoint's skeleton, feature layout, fps and provenance, as stored."""
    layout = ckpt.feature_layout
    fps = (layout or {}).get("fps") or ckpt.config.get("fps")
    return {
        "feature_layout": layout,
        "feature_columns": feature_columns(layout),
        "skeleton": ckpt.skeleton,
        "fps": float(fps) if fps is not None else None,
        "checkpoint": {
            "kind": ckpt.kind,
            "name": ckpt.paths.weights.parent.name,  # the folder, not this machine's path
            "command": ckpt.metadata.get("command"),
            "step": ckpt.metadata.get("step"),
            "minimdm_version": ckpt.metadata.get("minimdm_version"),
        },
    }


def _schedule_dict(schedule) -> dict[str, Any]:
    return {
        "kind": schedule.kind,
        "T": schedule.T,
        "betas": schedule.betas.double().cpu().tolist(),
    }


def _amdm_description(cm) -> dict[str, Any]:
    """The sampler, schedule and normalizer of an A-MDM :class:`ControlModel`."""
    T = cm.schedule.T
    ddpm = cm.steps in (None, T)
    clip = cm.clip_x0
    return {
        "sampler": {
            "name": "ddpm" if ddpm else "ddim",
            "levels": list(range(T - 1, -1, -1)) if ddpm else ddim_timesteps(T, cm.steps),
            "eta": None if ddpm else cm.eta,
            "predicts": cm.predicts,
            "clip_x0": clip.tolist() if isinstance(clip, Tensor) else clip,
        },
        "schedule": _schedule_dict(cm.schedule),
        "normalizer": cm.normalizer.to_dict() if cm.normalizer is not None else None,
        "state": {"what": "the previous frame, normalized: (features - mean) / std"},
    }


class AMDMFrame(FrameGraph):
    """A-MDM (A-MDM §3.1): one frame of the denoiser's reverse chain, DDPM or DDIM.

    ``state`` is the previous frame, normalized (the checkpoint's normalizer); the output is
    the next one. ``steps`` None or T: DDPM over all T levels; fewer: DDIM with ``eta``.
    """

    kind = "amdm"

    def __init__(self, cm) -> None:
        super().__init__(cm.dim)
        self.cm = cm
        self.net = cm.net  # registered, so that the graph holds the weights
        self._record()

    @classmethod
    def from_checkpoint(cls, ckpt: Checkpoint, steps: int | None = None, eta: float = 1.0):
        from minimdm.control.core import as_control_model

        return cls(as_control_model(ckpt, steps=steps, eta=eta))

    def frame(self, state, generator, *extra):
        from minimdm.control.core import sample_frame

        return sample_frame(self.cm, state, generator)

    def describe(self):
        return _amdm_description(self.cm)


class AAMDMFrame(FrameGraph):
    """AAMDM on motion (AAMDM §3.4): DD-GAN generation + polishing in the latent, then decoding.

    ``state`` is ``[xz, y]`` (B, XZ + D): the standardised latent and the pose features (A-MDM
    units) of the previous frame; only ``xz`` conditions the next frame.
    """

    kind = "aamdm_motion"

    def __init__(self, model) -> None:
        super().__init__(model.xz_dim + model.config.y_dim)
        self.model = model.eval()
        self._record()

    @classmethod
    def from_checkpoint(cls, ckpt: Checkpoint, steps: int | None = None, eta: float = 1.0):
        if steps is not None:
            raise InputError(
                f"steps: an AAMDM checkpoint runs its own {ckpt.model.transition.T_gan} + "
                f"{ckpt.model.transition.T_adm} steps, got steps={steps}"
            )
        return cls(ckpt.model)

    def frame(self, state, generator, *extra):
        from minimdm.aamdm.eval import aamdm_frame

        return aamdm_frame(self.model, state, generator)

    def describe(self):
        m = self.model
        t = m.transition
        XZ = m.xz_dim
        buffers = {k: v.double().cpu().tolist() for k, v in m.named_buffers() if k.endswith(
            ("_mean", "_std"))}  # fmt: skip
        return {
            "sampler": {
                "name": "aamdm",
                "T_gan": t.T_gan,
                "T_adm": t.T_adm,
                "latent_dim": t.config.latent_dim,
                "clip_x0": t.config.clip_x0,
            },
            "schedule": _schedule_dict(t.schedule("cpu")),
            "normalizer": buffers,
            "state": {
                "what": "[xz, y]: the standardised latent (columns 0..XZ-1), then the pose "
                "features in A-MDM units (XZ..); only xz conditions the next frame",
                "xz": [0, XZ],
                "features": [XZ, XZ + m.config.y_dim],
            },
        }


class SteeredFrame(FrameGraph):
    """A steering policy on A-MDM (A-MDM §5.2): its mean action, then the residual-steered chain.

    ``state`` is the previous frame, normalized; ``task`` (B, task_dim) is the task's
    observation (:meth:`minimdm.rl.tasks.Task.observe`, e.g. the joystick's command in the
    heading frame); the policy sees the frame (or its root, ``observe: root``) and the task.
    """

    kind = "policy"

    def __init__(self, steering) -> None:
        cm = steering.cm
        if not cm.is_diffusion:
            raise InputError(
                f"a fast path steers an A-MDM base model (residual steering), but this policy's "
                f"base is a {type(cm.net).__name__}"
            )
        super().__init__(cm.dim)
        self.steering = steering
        self.policy, self.net = steering.policy, cm.net  # registered: the graph's weights
        layout = cm.layout
        self.seen: list[int] | None = None
        if steering.observe == "root":
            self.seen = [*range(layout.root_vel.start, layout.root_vel.stop), layout.yaw_rate.start]
        self.extra_inputs = (
            ("task", steering.task.obs_dim, f"the {steering.task.name} task's observation"),
        )
        self._record()

    @classmethod
    def from_checkpoint(cls, ckpt: Checkpoint, steps: int | None = None, eta: float = 1.0):
        from minimdm.rl.policy import load_steering

        if steps is not None:
            raise InputError(f"steps: a policy runs its base model's own steps, got {steps}")
        return cls(load_steering(ckpt))

    def observation(self, state: Tensor, task: Tensor) -> Tensor:
        """What the policy sees: the frame (or its root) then the task (SteeringVecEnv's obs)."""
        seen = state if self.seen is None else state[:, self.seen]
        return torch.cat([seen, task], dim=1)

    def frame(self, state, generator, *extra):
        (task,) = extra
        actions = self.policy.act(self.observation(state, task), True)  # (B, A), the mean
        return self.steering.steerer(state, actions, generator)

    def describe(self):
        s = self.steering
        d = _amdm_description(s.cm)
        meta = s.checkpoint.metadata
        d["policy"] = {
            "task": meta.get("task"),
            "steering": meta.get("steering"),
            "observe": s.observe,
            "observed_state_columns": self.seen,
            "base": meta.get("base"),
        }
        return d


FRAME_GRAPHS: dict[str, Callable[..., FrameGraph]] = {
    "amdm": AMDMFrame.from_checkpoint,
    "aamdm_motion": AAMDMFrame.from_checkpoint,
    "policy": SteeredFrame.from_checkpoint,
}
"""Checkpoint kind -> ``build(checkpoint, steps=None, eta=1.0)``, the kinds with a fast path."""


def load(checkpoint: Checkpoint | str | os.PathLike) -> Checkpoint:
    """A loaded checkpoint (on the CPU) from itself, a path, or a shipped name such as "amdm"."""
    if isinstance(checkpoint, Checkpoint):
        return checkpoint
    from minimdm import CHECKPOINT_DIR, pretrained
    from minimdm.checkpoint import load_checkpoint

    p = Path(checkpoint)
    if not p.exists() and (CHECKPOINT_DIR / str(checkpoint) / "model.safetensors").exists():
        return pretrained(str(checkpoint))
    return load_checkpoint(p)


def frame_graph(
    checkpoint: Checkpoint | str | os.PathLike, steps: int | None = None, eta: float = 1.0
) -> FrameGraph:
    """The :class:`FrameGraph` of a checkpoint (loaded, a path or a shipped name; CPU, eval).

    Raises:
        InputError: a kind without a fast path, naming it and the supported kinds.
    """
    ckpt = load(checkpoint)
    build = FRAME_GRAPHS.get(ckpt.kind)
    if build is None:
        raise InputError(
            f"checkpoint kind {ckpt.kind!r} ({ckpt.paths.weights}) has no fast path; supported "
            f"kinds: {', '.join(FRAME_GRAPHS)}"
        )
    graph = build(ckpt, steps=steps, eta=eta).eval()
    graph.settings = _settings(ckpt)
    return graph
