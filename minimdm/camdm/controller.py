"""The CAMDM run-time controller (Chen et al. 2024, §3.2-3.3).

A joystick gives, per frame and character, a desired ground velocity, a facing and a style
(:class:`Commands`). The controller keeps the character's last P frames and a *plan* of F
future frames. :meth:`CAMDMController.run` is a plain loop over frames: each applies the next
frame of the plan, after the library's one non-finite check
(:func:`minimdm.amdm.sampling.check_finite`); it re-plans when M frames (15) have been applied,
or at once when the input changes. Unlike A-MDM, a frame is not sampled from the one before
it: a plan samples F frames at once. A plan:

1. puts the last P frames in the frame of the current one (:func:`~minimdm.camdm.data.
   to_canonical`);
2. draws the user's future trajectory, a critically damped spring from the character's
   velocity and turning rate to the joystick's (:mod:`~minimdm.camdm.trajectory`);
3. takes what is left of the last plan's predicted trajectory, extends it to F points by
   recycling its last K points (HFTE; ``extend=False``: the user's points fill the gap, the
   ablation "w/o HFTE"), and blends it with the user's;
4. samples the future with 8 denoising steps (:func:`~minimdm.camdm.sampling.sample_future`),
   with CFG on the past motion at ``gamma_switch`` (0.7) for re-plans within ``switch_frames``
   of a style change, else at ``gamma`` (1: the conditional model alone); ``guide`` and
   ``guide_switch`` choose what each guides on (CFG on the style at steady state is ours);
5. inertializes the new plan (``halflife_replan``, 0.1 s; our addition, not in the paper). A
   plan's first frame does not quite continue the last applied one: on the shipped model the
   joint acceleration at a re-plan frame is several times that of the other frames, a small pop
   every M frames. The gap between the new plan and the old plan's continuation, in position and
   in velocity, is added to the new plan and dies out through a critically damped spring
   (:func:`~minimdm.camdm.trajectory.inertialize`): the character goes on from where the old
   plan was going and joins the new one within a few tenths of a second. The next re-plan's HFTE
   reads the inertialized plan, since those are the frames that are applied. A cross-fade of the
   two plans' first frames smoothed the pop as well but followed the commanded speed less well
   (``benchmarks/camdm.py --only hfte`` measures the half-lives). The seam costs some
   responsiveness: a sharp change of command (turning around) starts later, since each plan's
   first frames lean on the old plan; 0.1 s is the compromise measured there.

:meth:`CAMDMController.plan` is one such sampling call from given past motion and trajectory;
:meth:`~CAMDMController.sample_plan` is its arithmetic on checked tensors, which the fast path
traces into one ONNX graph (:class:`minimdm.fast.CAMDMPlan`). ``planner=`` hands the planning
calls to such a graph: ``CAMDMController(ckpt, planner=minimdm.fast.fast_frame(ckpt))`` gives
the eager controller's frames within float rounding (1e-4) for the same generator.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from minimdm.amdm.sampling import check_finite
from minimdm.checkpoint import Checkpoint, check_same_model
from minimdm.diffusion import NoiseTape
from minimdm.motion.data import Clip
from minimdm.motion.features import Normalizer
from minimdm.motion.skeleton import Skeleton, rotate_about_z, wrap_angle
from minimdm.validate import (
    MAX_FEATURE,
    InputError,
    InputTypeError,
    check_generator,
    check_int,
    check_number,
    check_skeleton,
    describe,
)

from .data import (
    CAMDMLayout,
    frame_positions,
    headings,
    orthonormalize,
    to_canonical,
    to_world,
    world_frames,
)
from .model import CAMDM, Conditions
from .sampling import check_guide, gamma_per_sample, sample_future
from .train import load_camdm
from .trajectory import (
    blend_trajectories,
    extend_trajectory,
    inertialize,
    spring_headings,
    spring_positions,
)

__all__ = ["ControlConfig", "Commands", "ControlResult", "CAMDMController"]


@dataclass
class ControlConfig:
    """How the controller runs (CAMDM §3.3)."""

    M: int = 15
    """Generated frames applied before re-planning while the input is unchanged (at most F: a
    plan used up is followed by one on the user's trajectory alone, as without HFTE)."""
    M_turning: int | None = None
    """M while a character faces more than ``turning_deg`` away from its commanded facing (our
    addition; None: always M). Each plan turns only part of the way, so short plans finish a
    sharp turn sooner; long ones at steady state keep the plans' diversity and cost."""
    turning_deg: float = 45.0
    """How far from the commanded facing (degrees) counts as turning, for ``M_turning``."""
    K: int = 15
    """Predicted trajectory points HFTE recycles."""
    extend: bool = True
    """HFTE on; False is the ablation w/o HFTE."""
    gamma: float = 1.0
    """CFG-PM scale while the style is unchanged (1: the conditional model alone)."""
    gamma_styles: dict[str, float] | None = None
    """CFG scale for the styles named here instead of ``gamma``, while the style is unchanged
    and the character faces within ``turning_deg`` of its command (our addition; None:
    ``gamma`` for every style). A style the model renders weakly can be guided harder without
    sharpening, and sliding, the others; while turning it gets ``gamma``, since a strong pull
    towards the style's training takes, which never turn, slows the turn."""
    gamma_switch: float = 0.7
    """CFG scale for re-plans within ``switch_frames`` of a style change."""
    switch_frames: int = 30
    """Frames after a style change that re-plans use ``gamma_switch``."""
    guide: str = "past"
    """What CFG drops while the style is unchanged: 'past' (CFG-PM) or 'style' (CFG-S)."""
    guide_switch: str | None = None
    """What CFG drops within ``switch_frames`` of a style change; None: ``guide``. With
    ``guide="style", gamma=2, guide_switch="past"`` the controller sharpens the style at steady
    state and loosens the past right after a change (each sample guides on one, so a plan still
    costs two model calls, batched). A fast-path planner then needs the graph that takes each
    sample's guide: ``minimdm.fast.fast_planner(ckpt, guide="each")``."""
    halflife: float = 0.3
    """Half-life of the velocity spring, seconds."""
    halflife_facing: float = 0.3
    """Half-life of the facing spring, seconds."""
    blend_bias: float = 1.0
    """The user's weight at point k of F is (k / F) ** blend_bias."""
    halflife_replan: float = 0.1
    """Half-life (seconds) of the spring that absorbs a new plan's jump from the old plan's
    continuation (our addition; 0: off, the paper's controller). It needs the old plan's next two
    frames, so it does nothing at re-plans with fewer left (M >= F - 1)."""


@dataclass
class Commands:
    """A joystick over N frames for B characters (world frame)."""

    velocity: Tensor
    """(B, N, 2) desired ground velocity, metres per second."""
    facing: Tensor
    """(B, N) desired heading, radians."""
    style: Tensor
    """(B, N) long: style indices (:meth:`CAMDMLayout.style_index` turns names into them)."""

    @classmethod
    def hold(cls, velocity: Any, facing: Any, style: Tensor, n: int, batch: int = 1) -> Commands:
        """The same command for ``n`` frames: velocity (2,), facing (), style index ()."""
        v = torch.as_tensor(velocity, dtype=torch.float32).expand(batch, n, 2)
        h = torch.as_tensor(facing, dtype=torch.float32).expand(batch, n)
        s = torch.as_tensor(style, dtype=torch.long).reshape(()).expand(batch, n)
        return cls(v.clone(), h.clone(), s.clone())

    def then(self, other: Commands) -> Commands:
        """This command, then ``other``."""
        return Commands(
            torch.cat([self.velocity, other.velocity], 1),
            torch.cat([self.facing, other.facing], 1),
            torch.cat([self.style, other.style], 1),
        )


@dataclass
class ControlResult:
    """What :meth:`CAMDMController.run` made."""

    frames: Tensor
    """(B, N, D) world frames: root position and 6D local rotations."""
    positions: Tensor
    """(B, N, J, 3) global joint positions, metres, z-up."""
    replans: list[int] = field(default_factory=list)
    """The frames (0-based, of this run) at which a plan began."""
    gammas: list[Tensor] = field(default_factory=list)
    """The CFG scale of each plan, (B,) each."""
    trajectories: list[Tensor] = field(default_factory=list)
    """The controlling trajectory of each plan in the world, (B, F, 3): x, y, heading."""


class CAMDMController:
    """Drives characters with a CAMDM checkpoint (module docstring).

    ``reset(start)`` sets the characters' last P frames; ``run(commands, n_frames)`` continues
    from where the last run stopped, so a widget can drive it piece by piece.

    ``planner`` (None: the eager chain in PyTorch) makes the planning calls instead of
    :meth:`sample_plan`: ``planner(past, generator, style=, trajectory=, gamma=) -> (B, F, D)``
    with :meth:`plan`'s units, e.g. a :class:`minimdm.fast.FastFrame` of this checkpoint's
    ``camdm`` graph, which draws the same noise from the generator. Its ``metadata`` (if any)
    must name this model's P, F, D and the config's ``guide``.
    """

    def __init__(
        self,
        checkpoint: Checkpoint | str | os.PathLike,
        config: ControlConfig | None = None,
        device: torch.device | str = "cpu",
        planner: Callable[..., Tensor] | None = None,
    ) -> None:
        if isinstance(checkpoint, (str, os.PathLike)):
            checkpoint = load_camdm(checkpoint, device=device)
        if not isinstance(checkpoint, Checkpoint) or not isinstance(checkpoint.model, CAMDM):
            raise InputTypeError(
                f"checkpoint must be a CAMDM checkpoint, got {describe(checkpoint)}"
            )
        self.checkpoint = checkpoint
        self.model: CAMDM = checkpoint.model.eval()
        self.config = config or ControlConfig()
        for name in ("guide", "guide_switch"):
            value = getattr(self.config, name)
            if value not in ("past", "style") and not (name == "guide_switch" and value is None):
                raise InputError(f"ControlConfig.{name} must be 'past' or 'style', got {value!r}")
        check_number("ControlConfig.halflife_replan", self.config.halflife_replan, low=0.0)
        check_int("ControlConfig.M", self.config.M, low=1)
        if self.config.M_turning is not None:
            check_int("ControlConfig.M_turning", self.config.M_turning, low=1)
        self.device = torch.device(device)
        self.layout = CAMDMLayout.from_dict(checkpoint.feature_layout)
        self.skeleton = Skeleton.from_dict(checkpoint.skeleton)
        self._steady_gamma = self._gamma_of_each_style()  # (n_styles,)
        norms = checkpoint.normalizer
        self.window_norm = Normalizer.from_dict(norms["window"])
        self.traj_norm = Normalizer.from_dict(norms["traj"])
        self.schedule = checkpoint.schedule(self.device)
        self.history: Tensor | None = None
        self.planner = self._check_planner(planner)

    def _gamma_of_each_style(self) -> Tensor:
        """The steady-state CFG scale of every style: ``gamma``, or its ``gamma_styles`` entry."""
        cfg = self.config
        out = torch.full((len(self.layout.styles),), float(cfg.gamma))
        if cfg.gamma_styles is None:
            return out
        if not isinstance(cfg.gamma_styles, dict):
            raise InputTypeError(
                "ControlConfig.gamma_styles must be a dict of style name to CFG scale, got "
                f"{describe(cfg.gamma_styles)}"
            )
        for name, value in cfg.gamma_styles.items():
            i = self.layout.style_index(name, "a ControlConfig.gamma_styles key")
            out[i] = check_number(f"ControlConfig.gamma_styles[{name!r}]", value, low=0.0)
        return out

    def _check_planner(self, planner: Any) -> Callable[..., Tensor] | None:
        if planner is None:
            return None
        if not callable(planner):
            raise InputTypeError(f"planner must be callable or None, got {describe(planner)}")
        meta = getattr(planner, "metadata", None)
        if meta is not None:
            L, plan, guide = self.layout, meta.get("plan", {}), self.config.guide
            if self.config.guide_switch not in (None, guide):
                guide = "each"  # two guides: the graph takes each sample's (fast_planner)
            want = {"kind": "camdm", "P": L.past, "F": L.future, "D": L.dim, "guide": guide}
            got = {"kind": meta.get("kind"), **{k: plan.get(k) for k in ("P", "F", "D", "guide")}}
            if got["guide"] == "each":  # a graph that takes each sample's guide serves any
                want["guide"] = "each"
            if got != want:
                raise InputError(f"planner must be a CAMDM planning call with {want}, got {got}")
        where = str(self.checkpoint.paths.weights)
        check_same_model("planner", planner, self.model, "camdm", where)
        return planner

    # ---------------------------------------------------------------- one planning call
    @torch.no_grad()
    def plan(
        self,
        past: Tensor,
        style: Any,
        trajectory: Tensor,
        generator: torch.Generator | None = None,
        gamma: float | Tensor = 1.0,
        guide: str | Tensor = "past",
    ) -> Tensor:
        """Sample the future ``(B, F, D)`` from past frames ``(B, P, D)`` and a trajectory
        ``(B, F, 4)`` (x, y, cos, sin), all in the frame of the last past frame, and styles.

        ``guide``: 'past', 'style', or a (B,) bool tensor, True where a sample guides on its
        style (:func:`~minimdm.camdm.sampling.guided_x0`). The inputs are checked, then
        :meth:`sample_plan` (or the ``planner``) samples."""
        L = self.layout
        past = self._check("past", past, (L.past, L.dim), "frames of the model's skeleton")
        B = past.shape[0]
        traj = self._check("trajectory", trajectory, (L.future, 4), "x, y, cos, sin per point")
        if traj.shape[0] != B:
            raise InputError(
                f"trajectory must have shape ({B}, {L.future}, 4) (one per past motion), got "
                f"{tuple(traj.shape)}"
            )
        s = L.style_index(style).to(self.device)
        if s.numel() == 1:
            s = s.expand(B)
        elif s.shape != (B,):
            raise InputError(f"style must be one style or {B} (one per past motion), got {len(s)}")
        check_generator("generator", generator, self.device)
        guide = check_guide(guide, B)
        if not isinstance(gamma, Tensor):
            gamma = check_number("gamma", gamma)
        gamma = gamma_per_sample(gamma, B, self.device)
        past, traj = past.to(self.device), traj.to(self.device)
        if self.planner is None:
            return self.sample_plan(past, s, traj, generator, gamma, guide)
        meta = getattr(self.planner, "metadata", None) or {}
        if meta.get("plan", {}).get("guide") == "each":
            on_style = guide if isinstance(guide, Tensor) else torch.full((B,), guide == "style")
            future = self.planner(
                past, generator, style=s, trajectory=traj, gamma=gamma, on_style=on_style.long()
            )
            return future.to(self.device)
        if not isinstance(guide, str) or guide != self.config.guide:
            guide = "per sample" if isinstance(guide, Tensor) else guide
            raise InputError(
                f"guide: the planner guides on {self.config.guide!r} (the config's), got {guide!r}"
            )
        future = self.planner(past, generator, style=s, trajectory=traj, gamma=gamma)
        return future.to(self.device)

    def sample_plan(
        self,
        past: Tensor,
        style: Tensor,
        trajectory: Tensor,
        generator: torch.Generator | NoiseTape | None,
        gamma: Tensor | None,
        guide: str | Tensor = "past",
    ) -> Tensor:
        """One planning call on checked tensors: the future ``(B, F, D)`` from ``past``
        ``(B, P, D)``, ``style`` (B,) indices, ``trajectory`` (B, F, 4) and ``gamma`` (B,)
        (None: no guidance, the conditional model).

        It normalizes the conditions, samples 8 denoising steps with CFG (:func:`~minimdm.camdm.
        sampling.sample_future`) and denormalizes. ``generator`` may be a
        :class:`~minimdm.diffusion.NoiseTape`: the fast path traces this call.
        """
        L = self.layout
        P = L.past
        mean = self.window_norm.mean.view(-1, L.dim).to(self.device)
        std = self.window_norm.std.view(-1, L.dim).to(self.device)
        cond = Conditions(
            (past - mean[:P]) / std[:P],
            style,
            self.traj_norm.normalize(trajectory.flatten(1)).view_as(trajectory),
        )
        x0 = sample_future(self.model, self.schedule, cond, generator, gamma=gamma, guide=guide)
        return x0 * std[P:] + mean[P:]  # (B, F, D)

    def _check(self, name: str, x: Any, shape: tuple[int, int], words: str) -> Tensor:
        if not isinstance(x, Tensor):
            raise InputTypeError(
                f"{name} must be a tensor of shape (B, {shape[0]}, {shape[1]}), got {describe(x)}"
            )
        if x.dim() != 3 or tuple(x.shape[1:]) != shape:
            raise InputError(
                f"{name} must have shape (B, {shape[0]}, {shape[1]}) ({words}), "
                f"got {tuple(x.shape)}"
            )
        if not torch.isfinite(x).all():
            where = (~torch.isfinite(x)).nonzero()[0].tolist()
            raise InputError(
                f"{name} must be finite (shape (B, {shape[0]}, {shape[1]})), but {name}{where} is "
                f"{x[tuple(where)].item()}"
            )
        if (x.abs() > MAX_FEATURE).any():  # metres and 6D components: beyond it, not motion
            where = (x.abs() > MAX_FEATURE).nonzero()[0].tolist()
            raise InputError(
                f"{name} must hold values within ±{MAX_FEATURE:g} (metres, rotation components), "
                f"but {name}{where} is {x[tuple(where)].item():.3g}"
            )
        return x.float()

    # ---------------------------------------------------------------- the characters
    def reset(self, start: Clip | Tensor, n_characters: int = 1, style: Any = None) -> None:
        """Start from a clip's last P frames (the same for ``n_characters``), or from world frames
        ``(B, >= P, D)`` (:func:`~minimdm.camdm.data.world_frames`). ``style`` is the start's
        style (a name, an index, or one per character): a command of another style is then a
        style change (None: the first command's style is the start's)."""
        L = self.layout
        n_characters = check_int("n_characters", n_characters, low=1)
        if isinstance(start, Clip):
            check_skeleton(
                "start",
                start.skeleton,
                self.skeleton,
                given_fps=start.fps,
                expected_fps=L.fps,
                model="the CAMDM model",
            )
            if start.n_frames < L.past:
                raise InputError(
                    f"start must be a clip of at least P = {L.past} frames, got {start.n_frames}"
                )
            frames = world_frames(start)[-L.past :][None].expand(n_characters, -1, -1)
        elif isinstance(start, Tensor):
            if start.dim() != 3 or start.shape[1] < L.past or start.shape[2] != L.dim:
                raise InputError(
                    f"start must be world frames of shape (B, >= {L.past}, {L.dim}), got "
                    f"{tuple(start.shape)}"
                )
            frames = self._check("start", start[:, -L.past :], (L.past, L.dim), "world frames")
        else:
            raise InputTypeError(
                f"start must be a Clip or a tensor of world frames, got {describe(start)}"
            )
        self.history = frames.to(self.device).float().clone()
        self._plan: Tensor | None = None
        self._applied = 0
        self._command: tuple[Tensor, Tensor, Tensor] | None = None
        self._style: Tensor | None = None
        if style is not None:
            s = self.layout.style_index(style, "style")
            if s.numel() not in (1, frames.shape[0]):
                raise InputError(
                    f"style must be one style or {frames.shape[0]} (one per character), got "
                    f"{s.numel()}"
                )
            self._style = s.expand(frames.shape[0]).to(self.device)
        self._changed_at = torch.full((frames.shape[0],), -(10**9), dtype=torch.long)
        self._frame = 0

    def _check_commands(self, commands: Commands, n_frames: int) -> Commands:
        if not isinstance(commands, Commands):
            raise InputTypeError(f"commands must be a Commands, got {describe(commands)}")
        B = self.history.shape[0]
        parts = [("velocity", commands.velocity, (2,)), ("facing", commands.facing, ())]
        for name, x, tail in [*parts, ("style", commands.style, ())]:
            words = f"({B}, N >= {n_frames}{''.join(f', {t}' for t in tail)})"
            if not _has_shape(x, B, n_frames, tail):
                got = tuple(x.shape) if isinstance(x, Tensor) else describe(x)
                raise InputError(f"commands.{name} must have shape {words}, got {got}")
            if x.is_floating_point() and not torch.isfinite(x).all():
                raise InputError(
                    f"commands.{name} must be finite (shape {words}), but it holds NaN/Inf"
                )
        bad = (commands.style < 0) | (commands.style >= len(self.layout.styles))
        if bad.any():
            raise InputError(
                f"commands.style must hold style indices in [0, {len(self.layout.styles) - 1}] "
                f"(styles {list(self.layout.styles)}), got {commands.style[bad][0].item()}"
            )
        return commands

    @torch.no_grad()
    def run(
        self, commands: Commands, n_frames: int, generator: torch.Generator | None = None
    ) -> ControlResult:
        """Animate ``n_frames`` frames under ``commands``, continuing the last run: each frame
        re-plans if it must (:meth:`_needs_plan`: M frames applied, or a new input; CAMDM
        §3.3), then applies the plan's next frame. A plan's frames are checked as they are
        applied: a non-finite one raises :class:`~minimdm.amdm.sampling.NonFiniteFrameError`
        naming the frame (1-based, of this run) and the character."""
        if self.history is None:
            raise InputError("call reset(start) before run()")
        n_frames = check_int("n_frames", n_frames, low=1)
        commands = self._check_commands(commands, n_frames)
        check_generator("generator", generator, self.device)
        result = ControlResult(frames=torch.empty(0), positions=torch.empty(0))
        B = self.history.shape[0]
        frames = torch.empty(B, n_frames, self.layout.dim, dtype=torch.float32)  # (B, N, D) CPU
        parts = (commands.velocity, commands.facing, commands.style)
        for i in range(n_frames):
            cmd = tuple(c[:, i].to(self.device) for c in parts)  # velocity, facing, style
            if self._needs_plan(cmd):
                self._make_plan(cmd, generator, result, i)
            frame = self._plan[:, self._applied]  # (B, D)
            check_finite(frame, i + 1, lambda b: f"character {b}", "camdm control")
            self._applied += 1
            self._frame += 1
            self.history = torch.cat([self.history[:, 1:], frame[:, None]], 1)
            frames[:, i] = frame.float().cpu()
        result.frames = frames
        result.positions = frame_positions(frames.double(), self.skeleton).float()
        return result

    def _turning(self, cmd: tuple[Tensor, Tensor, Tensor]) -> Tensor:
        """(B,) bool: which characters face more than ``turning_deg`` from their command."""
        facing = headings(self.history[:, -1:], self.skeleton.lateral_axis)[:, 0]
        return wrap_angle(cmd[1] - facing).abs() > math.radians(self.config.turning_deg)

    def _needs_plan(self, cmd: tuple[Tensor, Tensor, Tensor]) -> bool:
        cfg = self.config
        M = cfg.M
        if cfg.M_turning is not None and self._plan is not None:
            if self._turning(cmd).any():
                M = cfg.M_turning
        if self._plan is None or self._applied >= min(M, self.layout.future):
            return True
        v, h, s = self._command
        return bool(
            (cmd[2] != s).any()
            or ((cmd[0] - v).norm(dim=-1) > 1e-4).any()
            or (wrap_angle(cmd[1] - h).abs() > 1e-4).any()
        )

    def _make_plan(self, cmd, generator, result: ControlResult, i: int) -> None:
        L, cfg = self.layout, self.config
        axis = self.skeleton.lateral_axis
        past, xy, h = to_canonical(self.history, L.past - 1, axis)  # (B, P, D), (B, 2), (B,)
        fps = L.fps
        root = self.history[:, :, :2]
        hist_h = headings(self.history, axis)  # (B, P)
        k = min(2, L.past - 1)  # over two frames: less of the bob within a step
        velocity = (root[:, -1] - root[:, -1 - k]) * fps / k
        rate = wrap_angle(hist_h[:, -1] - hist_h[:, -1 - k]) * fps / k
        times = torch.arange(1, L.future + 1, dtype=torch.float32, device=self.device) / fps
        user_xy = spring_positions(root[:, -1], velocity, cmd[0], cfg.halflife, times)  # (B, F, 2)
        user_h = spring_headings(hist_h[:, -1], rate, cmd[1], cfg.halflife_facing, times)
        if self._plan is None:
            traj_xy, traj_h = user_xy, user_h
        else:
            rest = self._plan[:, self._applied :]  # (B, F - m, D) world
            pred_xy, pred_h = rest[:, :, :2], headings(rest, axis)
            if cfg.extend and pred_xy.shape[1] > 0:  # M >= F uses a plan up: nothing to extend
                anchor = torch.cat([self.history[:, -1:, :2], pred_xy], 1)
                anchor_h = torch.cat([hist_h[:, -1:], pred_h], 1)
                ext_xy, ext_h = extend_trajectory(anchor, anchor_h, L.future + 1, cfg.K)
                pred_xy, pred_h = ext_xy[:, 1:], ext_h[:, 1:]
            else:  # w/o HFTE: the missing points are the user's
                k = pred_xy.shape[1]
                pred_xy = torch.cat([pred_xy, user_xy[:, k:]], 1)
                pred_h = torch.cat([pred_h, user_h[:, k:]], 1)
            pred_h = hist_h[:, -1:] + torch.cumsum(
                wrap_angle(torch.diff(torch.cat([hist_h[:, -1:], pred_h], 1), dim=1)), 1
            )  # unwrapped, so that blending never turns the long way
            traj_xy, traj_h = blend_trajectories(pred_xy, pred_h, user_xy, user_h, cfg.blend_bias)
        # the controlling trajectory in the current frame
        local = rotate_about_z(traj_xy - xy[:, None], -h)  # (B, F, 2)
        rel = traj_h - h[:, None]
        traj = torch.cat([local, torch.cos(rel)[..., None], torch.sin(rel)[..., None]], -1)
        # CFG-PM at a style change
        if self._style is not None:
            changed = (cmd[2] != self._style).cpu()
            self._changed_at[changed] = self._frame
        since = self._frame - self._changed_at
        near = since < cfg.switch_frames
        steady = self._steady_gamma[cmd[2].cpu()]  # gamma, or the style's gamma_styles
        steady = torch.where(self._turning(cmd).cpu(), torch.tensor(float(cfg.gamma)), steady)
        gamma = torch.where(near, torch.tensor(cfg.gamma_switch), steady).float()
        guide: str | Tensor = cfg.guide
        if cfg.guide_switch not in (None, cfg.guide):  # per sample: True guides on the style
            guide = torch.where(near, cfg.guide_switch == "style", cfg.guide == "style")
            guide = guide.to(self.device)
        future = self.plan(past, cmd[2], traj, generator, gamma.to(self.device), guide)
        new = to_world(future, xy, h)  # (B, F, D)
        old = None if self._plan is None else self._plan[:, self._applied :]
        if cfg.halflife_replan > 0 and old is not None and old.shape[1] >= 2:
            new = orthonormalize(inertialize(old[:, :2], new, cfg.halflife_replan, L.fps))
        self._plan = new
        self._applied = 0
        self._command = cmd
        self._style = cmd[2]
        result.replans.append(i)
        result.gammas.append(gamma)
        result.trajectories.append(torch.cat([traj_xy, traj_h[..., None]], -1).cpu())


def _has_shape(x: Any, B: int, n_frames: int, tail: tuple[int, ...]) -> bool:
    """Whether ``x`` is a tensor of shape (B, N >= n_frames, *tail)."""
    if not isinstance(x, Tensor) or x.dim() != 2 + len(tail):
        return False
    return x.shape[0] == B and x.shape[1] >= n_frames and tuple(x.shape[2:]) == tail
