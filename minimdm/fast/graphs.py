"""The per-frame graphs: each model's own eager frame step, with its noise as an input.

A :class:`FrameGraph` wraps the library's per-frame step of one kind of checkpoint, the very
function the eager rollout loop calls, and runs it with a
:class:`~minimdm.diffusion.NoiseTape` in place of the generator. Its ``forward(state, *extra,
noise)`` is therefore a pure function of tensors: the whole frame, every denoising step, that
:mod:`minimdm.fast.onnx` traces into one graph. Nothing here restates a sampler:

* ``amdm``: :meth:`minimdm.amdm.sampling.Sampler.frame` (DDPM over all T levels, or DDIM over
  ``steps`` of them);
* ``aamdm_motion``: :func:`minimdm.aamdm.eval.aamdm_frame` (3 DD-GAN steps, 2 polishing steps,
  then the pose decoder);
* ``policy``: the steering policy's mean action, then its steerer, the residual hook of A-MDM
  eq. 7 on the base model's chain (:mod:`minimdm.rl`), as :func:`minimdm.rl.rollout.steer` runs
  them;
* ``camdm``: a planning call, not one frame: :meth:`minimdm.camdm.controller.CAMDMController.
  sample_plan`, the F = 45 future frames from the P past ones, all 8 denoising steps of
  :func:`minimdm.camdm.sampling.sample_future` with classifier-free guidance (CAMDM eq. 5; both
  model calls in one forward pass), the CFG scale ``gamma`` an input.

:data:`FRAME_GRAPHS` maps a checkpoint kind to its graph. Adding a model is one more entry: a
:class:`FrameGraph` whose :meth:`~FrameGraph.frame` calls that model's own step with the
generator it is given. A graph's inputs and output are :class:`Port` s: by default a state
(B, S) in, the next state (B, S) out, and ``extra_inputs`` (B, width); a graph whose step is
not "state -> next state" (CAMDM's plan) lists its own (:meth:`FrameGraph.inputs`,
:meth:`FrameGraph.output`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from minimdm.checkpoint import Checkpoint, fingerprint
from minimdm.diffusion import NoiseTape
from minimdm.validate import InputError

__all__ = [
    "Port",
    "FrameGraph",
    "AMDMFrame",
    "AAMDMFrame",
    "SteeredFrame",
    "CAMDMPlan",
    "FRAME_GRAPHS",
    "frame_graph",
    "load",
]

_RECORD_COLUMNS = 1 << 20
"""Columns of the zero tape that records a chain's draws (more than any chain here takes)."""


class Port(NamedTuple):
    """One input or output of a graph: its name, its shape after the batch, what it means."""

    name: str
    shape: tuple[int, ...]
    """The shape of one sample; () for one number per sample."""
    what: str = ""
    dtype: str = "float32"
    """'float32' or 'int64' (indices)."""
    classes: int | None = None
    """For indices: how many there are (valid indices are 0..classes-1)."""


class FrameGraph(nn.Module):
    """One frame of a model, all its denoising steps, as a function of tensors.

    ``state`` (B, S) is what the rollout loop feeds back (normalized features for A-MDM,
    ``[xz, y]`` for AAMDM); ``extra`` are per-frame inputs besides it (a policy's task
    observation); ``noise`` (B, N) is every Gaussian draw of the frame, in the order the chain
    makes them (:attr:`noise_widths`). A graph may name other inputs and output
    (:meth:`inputs`, :meth:`output`; CAMDM's planning call): the first input then plays the
    state's part, the others the extra inputs'.
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

    def inputs(self) -> tuple[Port, ...]:
        """Every input but the noise, in order: the state (B, S), then :attr:`extra_inputs`."""
        return (
            Port("state", (self.state_dim,)),
            *(Port(n, (w,), what) for n, w, what in self.extra_inputs),
        )

    def output(self) -> Port:
        """The graph's one output: the next state (B, S)."""
        return Port("next_state", (self.state_dim,))

    def zeros(self, batch: int = 1) -> list[Tensor]:
        """Zeros of every input's shape and dtype (but the noise), for ``batch`` samples."""
        return [
            torch.zeros(batch, *p.shape, dtype=getattr(torch, p.dtype), device=self.device)
            for p in self.inputs()
        ]

    @torch.no_grad()
    def forward(self, state: Tensor, *rest: Tensor) -> Tensor:
        """``forward(state, *extra, noise)``: :meth:`frame` with the noise as an input."""
        *extra, noise = rest
        return self.frame(state, NoiseTape(noise), *extra)

    @torch.no_grad()
    def _record(self) -> None:
        """Run the frame once on zeros to learn the widths of its draws."""
        tape = NoiseTape(torch.zeros(1, _RECORD_COLUMNS, device=self.device))
        state, *extra = self.zeros(1)
        self.frame(state, tape, *extra)
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
        return (*self.zeros(batch), self.noise(batch, g))

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
    if layout.get("kind") == "camdm":
        return _camdm_columns(layout)
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


def _camdm_columns(layout: dict) -> dict[str, Any]:
    """Where each quantity lives in a CAMDM frame (:mod:`minimdm.camdm.data`)."""
    names = list(layout["joint_names"])
    return {
        "root": {
            "columns": [0, 3],
            "what": "the root's position relative to the reference frame's root ground point, "
            "in the reference's heading frame (x forward, z up, metres; z is the height)",
        },
        "rot": {
            "columns": [3, 3 + 6 * len(names)],
            "what": "local joint rotations, 6D (the first two columns of each rotation matrix), "
            "joints in joint_names order; the root's is relative to the reference heading",
        },
        "joint_names": names,
        "reference": "the last past frame: the character stands at the origin facing +x there",
        "trajectory": "(F, 4) per future frame: the root's ground position x, y and cos, sin of "
        "its heading, in the reference frame",
    }


def _settings(ckpt: Checkpoint) -> dict[str, Any]:
    """The checkpoint's skeleton, feature layout, fps and provenance, as stored."""
    layout = ckpt.feature_layout
    return {
        "feature_layout": layout,
        "feature_columns": feature_columns(layout),
        "skeleton": ckpt.skeleton,
        "fps": ckpt.fps,
        "checkpoint": {
            "kind": ckpt.kind,
            "name": ckpt.paths.weights.parent.name,  # the folder, not this machine's path
            "command": ckpt.metadata.get("command"),
            "step": ckpt.metadata.get("step"),
            "minimdm_version": ckpt.metadata.get("minimdm_version"),
            "fingerprint": fingerprint(ckpt.model),  # rollouts compare it with their model
        },
    }


def _schedule_dict(schedule) -> dict[str, Any]:
    return {
        "kind": schedule.kind,
        "T": schedule.T,
        "betas": schedule.betas.double().cpu().tolist(),
    }


def _amdm_description(cm) -> dict[str, Any]:
    """The sampler, schedule and normalizer of an A-MDM :class:`Sampler`."""
    T = cm.schedule.T
    ddpm = cm.settings.is_ddpm(T)
    clip = cm.settings.clip_x0
    return {
        "sampler": {
            "name": "ddpm" if ddpm else "ddim",
            "levels": cm.settings.levels(T),
            "eta": None if ddpm else cm.settings.eta,
            "predicts": cm.settings.predicts,
            "clip_x0": clip.tolist() if isinstance(clip, Tensor) else clip,
        },
        "schedule": _schedule_dict(cm.schedule),
        "normalizer": cm.normalizer.to_dict() if cm.normalizer is not None else None,
        "state": {"what": "the previous frame, normalized: (features - mean) / std"},
        "chain": _chain_description(cm.net),
    }


def _chain_description(net) -> dict[str, Any]:
    """What the reverse chain inside the graph denoises: the frame, or for a delta model
    (:meth:`~minimdm.amdm.models.MLPDenoiser.to_delta`) its change from the previous frame. The
    graph maps it back, so its output is always the next frame."""
    if not getattr(net, "is_delta", False):
        return {"what": "the next frame, normalized"}
    return {
        "what": "z = (x - m * x_prev) / k: the change from the previous frame where m is 1, the "
        "frame itself where m is 0 (normalized units); the output is x = m * x_prev + k * z",
        "k": net.delta_k.tolist(),
        "m": net.delta_m.tolist(),
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
        from minimdm.amdm.sampling import Sampler

        return cls(Sampler.load(ckpt, steps=steps, eta=eta))

    def frame(self, state, generator, *extra):
        return self.cm.frame(state, generator)

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
        buffers = {
            k: v.double().cpu().tolist()
            for k, v in m.named_buffers()
            if k.endswith(("_mean", "_std"))
        }
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


class CAMDMPlan(FrameGraph):
    """CAMDM (§3.2-3.3): one planning call, all T = 8 denoising steps with classifier-free guidance.

    The future F frames from the past P frames, as :meth:`minimdm.camdm.controller.
    CAMDMController.plan` computes them (in its units: frames in the frame of the last past
    frame, not normalized; the graph normalizes and denormalizes): both halves of CAMDM eq. 5 in
    one forward pass at every step, combined with the per-sample scale ``gamma`` (an input: 1
    gives the conditional model, within float rounding; 0.7 is the controller's value after a
    style change). ``guide`` ('past': CFG-PM, or 'style': CFG-S) is fixed at export;
    ``guide="each"`` adds an input ``on_style`` (1: that sample guides on its style, 0: on its
    past), for a controller that guides on the style at steady state and on the past after a
    change (:class:`~minimdm.camdm.controller.ControlConfig` ``guide_switch``).

    ``guide="none"`` traces the conditional model alone: no ``gamma`` input, half the rows, the
    plan at ``gamma = 1``. The controller's plans are at ``gamma = 1`` except in the second after
    a style change, so :class:`minimdm.fast.CAMDMPlanner` serves those from this graph and the
    others from a guided one.
    """

    kind = "camdm"

    def __init__(self, controller, guide: str = "past") -> None:
        if guide not in ("past", "style", "each", "none"):
            raise InputError(
                f"guide must be 'past' (CFG-PM), 'style' (CFG-S), 'each' (an input says which, "
                f"per sample) or 'none' (no guidance), got {guide!r}"
            )
        super().__init__(controller.layout.dim)
        self.controller = controller
        self.model = controller.model  # registered, so that the graph holds the weights
        self.guide = guide
        self._record()

    @classmethod
    def from_checkpoint(
        cls, ckpt: Checkpoint, steps: int | None = None, eta: float = 1.0, guide: str = "past"
    ):
        from minimdm.camdm.controller import CAMDMController

        if steps is not None:
            raise InputError(
                f"steps: a CAMDM checkpoint runs its own {ckpt.schedule().T} steps, got "
                f"steps={steps}"
            )
        return cls(CAMDMController(ckpt), guide)

    def inputs(self):
        L = self.controller.layout
        P, F, D = L.past, L.future, L.dim
        n_styles = len(L.styles)
        style = f"the style's index in styles (0..{n_styles - 1})"
        ports = (
            Port("past", (P, D), f"the last P = {P} frames, in the frame of the last one"),
            Port("style", (), style, "int64", n_styles),
            Port("trajectory", (F, 4), "the future trajectory: x, y, cos, sin per future frame"),
        )
        gamma = Port("gamma", (), "the CFG scale of CAMDM eq. 5 (1: the conditional model)")
        on_style = Port("on_style", (), "1: CFG on the style (CFG-S), 0: on the past", "int64", 2)
        if self.guide == "none":
            return ports
        return ports + (gamma,) + ((on_style,) if self.guide == "each" else ())

    def output(self):
        L = self.controller.layout
        return Port("future", (L.future, L.dim), "the F future frames, in the past's frame")

    def frame(self, past, generator, *extra):
        if self.guide == "none":
            (style, trajectory), gamma, guide = extra, None, "past"
        elif self.guide == "each":
            style, trajectory, gamma, on_style = extra
            guide = on_style == 1
        else:
            (style, trajectory, gamma), guide = extra, self.guide
        return self.controller.sample_plan(past, style, trajectory, generator, gamma, guide)

    def describe(self):
        c = self.controller
        L = c.layout
        T = c.schedule.T
        cfg = (
            "none: x0 = G(x_t; cond), the conditional model (gamma = 1)"
            if self.guide == "none"
            else "x0 = G(x_t; ∅) + gamma (G(x_t; cond) - G(x_t; ∅)), both halves in one "
            "forward pass of 2 B rows; ∅ drops the "
            + ("style or the past, as on_style says" if self.guide == "each" else self.guide)
        )
        return {
            "sampler": {
                "name": "ddpm" if self.guide == "none" else "ddpm_cfg",
                "levels": list(range(T - 1, -1, -1)),
                "predicts": "x0",
                "guide": self.guide,
                "cfg": cfg,
            },
            "plan": {"P": L.past, "F": L.future, "D": L.dim, "T": T, "guide": self.guide},
            "schedule": _schedule_dict(c.schedule),
            "normalizer": {
                "window": c.window_norm.to_dict(),
                "traj": c.traj_norm.to_dict(),
                "what": "window: (P + F) D values, the past's frames then the future's, "
                "normalized (x - mean) / std inside the graph; traj: F 4 values",
            },
        }


FRAME_GRAPHS: dict[str, Callable[..., FrameGraph]] = {
    "amdm": AMDMFrame.from_checkpoint,
    "aamdm_motion": AAMDMFrame.from_checkpoint,
    "policy": SteeredFrame.from_checkpoint,
    "camdm": CAMDMPlan.from_checkpoint,
}
"""Checkpoint kind -> ``build(checkpoint, steps=None, eta=1.0, **options)``, the kinds with a
fast path."""


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
    checkpoint: Checkpoint | str | os.PathLike,
    steps: int | None = None,
    eta: float = 1.0,
    **options: Any,
) -> FrameGraph:
    """The :class:`FrameGraph` of a checkpoint (loaded, a path or a shipped name; CPU, eval).

    ``options`` go to the kind's builder (``camdm``: ``guide``, 'past' or 'style').

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
    graph = build(ckpt, steps=steps, eta=eta, **options).eval()
    graph.settings = _settings(ckpt)
    return graph
