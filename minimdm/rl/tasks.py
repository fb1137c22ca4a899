"""The three steering tasks of A-MDM §6: target reaching, joystick control, path following.

A task sees the characters' root state (:class:`Characters`: ground position, heading, speed,
frame count) and keeps its own goals, one row per environment. It gives the task part of the
observation, in the character's heading frame (so the policy's answer does not depend on where
the character stands or faces), the reward and the termination. The frame itself is the rest of
the observation; :mod:`minimdm.rl.env` joins them.

All tensors are batched over the N environments; ``idx`` selects the environments to reset.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from minimdm.motion.skeleton import rotate_about_z, to_heading_frame, wrap_angle
from minimdm.validate import check_number

__all__ = [
    "Characters",
    "Task",
    "TargetTask",
    "JoystickTask",
    "PathTask",
    "TASKS",
    "make_task",
    "joystick_reward",
    "procedural_paths",
    "to_heading_frame",
]


@dataclass
class Characters:
    """The root state of N characters (world frame, z up, metres and radians)."""

    xy: Tensor
    """(N, 2) root ground position."""
    heading: Tensor
    """(N,) root heading (0: facing +x)."""
    velocity: Tensor
    """(N, 2) root planar velocity over the last frame, world frame, metres per second."""
    frame: Tensor
    """(N,) frames since the episode started (0 at reset), long."""
    fps: float = 30.0

    @classmethod
    def zeros(cls, n: int, fps: float = 30.0) -> Characters:
        z = torch.zeros
        return cls(z(n, 2), z(n), z(n, 2), z(n, dtype=torch.long), fps)

    @property
    def speed(self) -> Tensor:
        """(N,) planar speed, m/s."""
        return self.velocity.norm(dim=-1)


def joystick_reward(heading: Tensor, speed: Tensor, goal_heading: Tensor, goal_speed: Tensor):
    """A-MDM eq. 8: :math:`r = e^{\\cos(d_r - d_r^g) - 1} \\cdot e^{-|d_v - d_v^g|}`.

    ``heading`` :math:`d_r` and ``goal_heading`` in radians, ``speed`` :math:`d_v` and
    ``goal_speed`` in m/s (:class:`JoystickTask` passes the velocity along the command). 1 when
    both match; the two terms multiply, so that neither can be traded for the other.
    """
    return torch.exp(torch.cos(heading - goal_heading) - 1) * torch.exp(-(speed - goal_speed).abs())


@dataclass
class Task:
    """What every task shares; subclasses keep per-environment goals."""

    max_frames: int = 300
    """Episode length; the episode is truncated (not terminated) there."""
    name: str = field(default="task", init=False)

    obs_dim: int = field(default=0, init=False)
    """Size of the task observation."""

    def setup(self, n: int, generator: torch.Generator) -> None:
        """Allocate goals for ``n`` environments."""
        self.n, self.generator = n, generator

    def reset(self, idx: Tensor, ch: Characters) -> None:
        """New goals for the environments ``idx`` (their characters were just reset)."""
        raise NotImplementedError

    def observe(self, ch: Characters) -> Tensor:
        """(N, obs_dim) float32 task observation."""
        raise NotImplementedError

    def step(self, ch: Characters, prev_xy: Tensor) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        """After the characters moved from ``prev_xy``: ``(reward (N,), terminated (N,),
        info)``; may update goals (a reached target is replaced)."""
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        """The task's name and options (its init fields), as stored in a policy checkpoint."""
        opts = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.init}
        return {"name": self.name, **opts}

    def _uniform(self, n: int, lo: float, hi: float) -> Tensor:
        return lo + (hi - lo) * torch.rand(n, generator=self.generator)


@dataclass
class TargetTask(Task):
    """Target reaching (§6.1): walk to a target; a new one appears when the hips are close.

    The target lies uniformly in a ``2 region`` x ``2 region`` square around the character (the
    paper's 20 m x 20 m). It is reached when the root (hips) is within ``radius`` of it, checked
    along the segment the root moved over in the frame (a fast character must not skip over it).
    The reward adds a distance term, the progress towards the target in m/s counted only as
    far as the character faces it (times :math:`(1 + \\cos\\theta) / 2` for the target's angle
    :math:`\\theta` from the heading: without it PPO found that lunging backwards to the target
    pays as well), and a one-time ``bonus`` on reaching it; the new target then appears.
    With ``max_progress`` (m/s) the progress pays up to that speed and every m/s beyond it is
    taken back (a tent peaked at ``max_progress``): walk to the target. Without it the fastest
    approach pays best, and PPO learns to run, with a run's joint acceleration. Clipping the
    progress at the speed alone was not enough: the policy still ran, at 2.2 m/s (chapter 7).

    Observation: the target in the heading frame, divided by ``region``, and its direction
    (cos, sin) -- 4 numbers.
    """

    max_frames: int = 300
    region: float = 10.0
    radius: float = 0.15
    min_distance: float = 1.0
    """New targets are at least this far from the character."""
    w_distance: float = 0.5
    w_progress: float = 1.0
    bonus: float = 10.0
    max_progress: float | None = None
    """Progress towards the target pays up to this speed, m/s, and costs beyond it (None: the
    faster the better)."""

    def __post_init__(self) -> None:
        self.name, self.obs_dim = "target", 4
        if self.max_progress is not None:
            check_number("max_progress", self.max_progress, low=0.0, low_open=True)

    def setup(self, n: int, generator: torch.Generator) -> None:
        super().setup(n, generator)
        self.target = torch.zeros(n, 2)
        self.queue = torch.zeros(n, 0, 2)  # (N, Q, 2) fixed targets to come (set_targets)
        self.queue_pos = torch.zeros(n, dtype=torch.long)
        self.reached = torch.zeros(n, dtype=torch.long)
        self.first_reach = torch.full((n,), -1, dtype=torch.long)

    def place(self, idx: Tensor, ch: Characters) -> None:
        """New targets for ``idx``: the next of their queue (:meth:`set_targets`), else drawn
        around the characters' current positions."""
        m = len(idx)
        r = (
            self.min_distance
            + (self.region - self.min_distance) * torch.rand(m, generator=self.generator).sqrt()
        )
        a = self._uniform(m, -math.pi, math.pi)
        # uniform over the annulus between min_distance and region: the square's corners left
        # out keep every direction equally likely
        new = ch.xy[idx] + torch.stack([r * torch.cos(a), r * torch.sin(a)], -1)
        pos = self.queue_pos[idx]
        queued = pos < self.queue.shape[1]
        if queued.any():
            q = idx[queued]
            new[queued] = self.queue[q, pos[queued]]
        self.queue_pos[idx] = pos + 1
        self.target[idx] = new

    def reset(self, idx: Tensor, ch: Characters) -> None:
        self.queue_pos[idx] = self.queue.shape[1]  # random targets unless a queue is set
        self.place(idx, ch)
        self.reached[idx] = 0
        self.first_reach[idx] = -1

    def set_targets(self, targets: Tensor, idx: Tensor | None = None) -> None:
        """Fix the targets of the environments ``idx`` (default: all), world metres: (M, 2) one
        each, or (M, Q, 2) a sequence of Q, each appearing when the previous is reached (then
        random ones again)."""
        idx = torch.arange(self.n) if idx is None else torch.as_tensor(idx)
        t = torch.as_tensor(targets, dtype=torch.float32)
        t = t.reshape(len(idx), -1, 2) if t.dim() != 3 else t
        if t.shape[1] != self.queue.shape[1]:
            queue = torch.zeros(self.n, t.shape[1], 2)
            self.queue, self.queue_pos = queue, torch.full((self.n,), t.shape[1], dtype=torch.long)
        self.queue[idx] = t
        self.target[idx] = t[:, 0]
        self.queue_pos[idx] = 1

    def observe(self, ch: Characters) -> Tensor:
        local = to_heading_frame(self.target - ch.xy, ch.heading)  # (N, 2)
        dist = local.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        return torch.cat([local / self.region, local / dist], -1)

    def step(self, ch, prev_xy):
        before = (self.target - prev_xy).norm(dim=-1)
        after = (self.target - ch.xy).norm(dim=-1)
        seg = ch.xy - prev_xy  # closest approach along the segment moved this frame
        u = ((self.target - prev_xy) * seg).sum(-1) / seg.pow(2).sum(-1).clamp_min(1e-12)
        closest = (prev_xy + u.clamp(0, 1)[:, None] * seg - self.target).norm(dim=-1)
        hit = closest < self.radius
        ahead = to_heading_frame(self.target - ch.xy, ch.heading)  # (N, 2)
        cos = ahead[:, 0] / ahead.norm(dim=-1).clamp_min(1e-6)
        progress = (before - after) * ch.fps  # m/s towards the target
        if self.max_progress is not None:  # the tent: what exceeds the speed is paid back
            progress = torch.where(
                progress > self.max_progress, 2 * self.max_progress - progress, progress
            )
        facing = 0.5 * (1 + cos)
        reward = (
            self.w_distance * torch.exp(-0.5 * after)
            + self.w_progress * torch.where(progress > 0, progress * facing, progress)
            + self.bonus * hit.float()
        )
        first = hit & (self.first_reach < 0)
        self.first_reach[first] = ch.frame[first]
        self.reached += hit.long()
        info = {"distance": after, "hit": hit}
        if hit.any():
            self.place(hit.nonzero()[:, 0], ch)
        return reward, torch.zeros_like(hit), info


@dataclass
class JoystickTask(Task):
    """Joystick control (§6.2): follow a commanded facing direction and speed, reward eq. 8.

    The direction is redrawn uniformly in ``direction_range`` (default [0, 2 pi), world
    radians; characters start facing 0) every ``direction_every`` frames, the speed uniformly
    in ``speed_range`` (m/s) every ``speed_every`` frames. Speeds outside
    ``corpus_speed`` (what the training motion holds) are accepted and counted in
    ``info["out_of_range"]``.

    The speed :math:`d_v` of eq. 8 is the root's planar velocity *along the commanded
    direction* (m/s, negative when moving away from it): with the speed's magnitude, a first
    policy faced the commanded way and walked backwards, which eq. 8 with a magnitude pays in
    full.

    Observation: the commanded direction relative to the heading (cos, sin), the commanded
    speed and its difference from the current velocity along it (both / 3 m/s) -- 4 numbers.
    """

    max_frames: int = 400
    direction_every: int = 120
    speed_every: int = 240
    speed_range: tuple[float, float] = (0.5, 2.5)
    direction_range: tuple[float, float] = (0.0, 2 * math.pi)
    corpus_speed: tuple[float, float] = (0.0, 4.5)

    def __post_init__(self) -> None:
        self.name, self.obs_dim = "joystick", 4
        lo, hi = (float(v) for v in self.speed_range)
        if not 0 <= lo <= hi:
            raise ValueError(
                f"speed_range must be (lo, hi) with 0 <= lo <= hi, got {self.speed_range}"
            )
        self.speed_range = (lo, hi)

    def setup(self, n, generator):
        super().setup(n, generator)
        self.goal_heading = torch.zeros(n)
        self.goal_speed = torch.zeros(n)
        self.out_of_range = torch.zeros(n, dtype=torch.bool)
        self.preset_heading: Tensor | None = None
        self.preset_speed: Tensor | None = None

    def preset(self, heading: Any, speed: Any) -> None:
        """Drive every environment by preset commands (N, P) per frame (radians, m/s) instead
        of random ones: frame f's command is column f (the last one after P frames). The same
        sequences for every method make their tracking errors comparable."""
        h = torch.as_tensor(heading, dtype=torch.float32)
        v = torch.as_tensor(speed, dtype=torch.float32)
        if h.shape != v.shape or h.dim() != 2 or h.shape[0] != self.n:
            raise ValueError(
                f"heading and speed must both have shape ({self.n}, P), got "
                f"{tuple(h.shape)} and {tuple(v.shape)}"
            )
        self.preset_heading, self.preset_speed = h, v
        self.command(h[:, 0], v[:, 0])

    def command(self, heading: Any, speed: Any, idx: Tensor | None = None) -> None:
        """Set the command (radians, m/s) of ``idx`` (default all) -- the user's joystick."""
        idx = torch.arange(self.n) if idx is None else idx
        self.goal_heading[idx] = torch.as_tensor(heading, dtype=torch.float32)
        speed = torch.as_tensor(speed, dtype=torch.float32).expand(len(idx))
        self.goal_speed[idx] = speed
        lo, hi = self.corpus_speed
        self.out_of_range[idx] = (speed < lo) | (speed > hi)

    def reset(self, idx, ch):
        m = len(idx)
        direction = self._uniform(m, *self.direction_range)
        self.command(direction, self._uniform(m, *self.speed_range), idx)

    def _redraw(self, ch: Characters) -> None:
        if self.preset_heading is not None:
            f = ch.frame.clamp(max=self.preset_heading.shape[1] - 1)
            rows = torch.arange(self.n)
            self.command(self.preset_heading[rows, f], self.preset_speed[rows, f])
            return
        f = ch.frame
        new_dir = ((f % self.direction_every) == 0) & (f > 0)
        new_speed = ((f % self.speed_every) == 0) & (f > 0)
        if new_dir.any():
            i = new_dir.nonzero()[:, 0]
            self.goal_heading[i] = self._uniform(len(i), *self.direction_range)
        if new_speed.any():
            i = new_speed.nonzero()[:, 0]
            self.command(self.goal_heading[i], self._uniform(len(i), *self.speed_range), i)

    def along(self, ch: Characters) -> Tensor:
        """(N,) the root's planar velocity along the commanded direction, m/s."""
        u = torch.stack([torch.cos(self.goal_heading), torch.sin(self.goal_heading)], -1)
        return (ch.velocity * u).sum(-1)

    def observe(self, ch):
        d = self.goal_heading - ch.heading
        gap = (self.goal_speed - self.along(ch)) / 3
        return torch.stack([torch.cos(d), torch.sin(d), self.goal_speed / 3, gap], -1)

    def step(self, ch, prev_xy):
        v = self.along(ch)
        reward = joystick_reward(ch.heading, v, self.goal_heading, self.goal_speed)
        info = {
            "heading_error": wrap_angle(ch.heading - self.goal_heading, include_pi=False),
            "speed_error": v - self.goal_speed,
            "out_of_range": self.out_of_range.clone(),
        }
        self._redraw(ch)
        return reward, torch.zeros(self.n, dtype=torch.bool), info


def procedural_paths(
    n: int,
    n_frames: int,
    generator: torch.Generator,
    speed_range: tuple[float, float] = (0.8, 1.8),
    turn_max: float = 0.8,
    segment: int = 30,
    fps: float = 30.0,
) -> Tensor:
    """``n`` random paths of ``n_frames + 1`` points (n, F + 1, 2), from the origin facing +x.

    As in §6.3, the path is integrated from random linear and angular accelerations drawn at
    each waypoint (every ``segment`` frames): the speed stays in ``speed_range`` (m/s) and the
    turning rate within ``turn_max`` (rad/s), so a path is smooth and walkable.
    """
    k = n_frames // segment + 2
    lo, hi = speed_range
    speed = torch.empty(n, k)
    turn = torch.empty(n, k)
    speed[:, 0] = lo + (hi - lo) * torch.rand(n, generator=generator)
    turn[:, 0] = 0
    for i in range(1, k):  # accelerations per waypoint, the state kept in range
        acc = (torch.rand(n, generator=generator) - 0.5) * (hi - lo)
        speed[:, i] = (speed[:, i - 1] + acc).clamp(lo, hi)
        ang = (torch.rand(n, generator=generator) - 0.5) * turn_max
        turn[:, i] = (turn[:, i - 1] + ang).clamp(-turn_max, turn_max)
    t = torch.arange(n_frames) / segment  # linear interpolation between waypoints, per frame
    i0 = t.floor().long()
    a = (t - i0)[None]
    v = speed[:, i0] * (1 - a) + speed[:, i0 + 1] * a  # (n, F)
    w = turn[:, i0] * (1 - a) + turn[:, i0 + 1] * a
    heading = torch.cumsum(w / fps, dim=1)
    step = torch.stack([v * torch.cos(heading), v * torch.sin(heading)], -1) / fps
    return torch.cat([torch.zeros(n, 1, 2), torch.cumsum(step, dim=1)], dim=1)


@dataclass
class PathTask(Task):
    """Path following (§6.3): stay on a moving waypoint along a procedural path.

    The path point of frame f is where the character should be then, so it must reach the
    waypoints in order and on time. A fresh path starts at the character, along its heading.
    The reward is :math:`e^{-2 d}` for the distance d (metres) to the current path point, plus
    ``w_facing`` :math:`(1 + \\cos\theta) / 2` for the angle between the heading and the path's
    direction (walk along the path facing forward, not sideways or backwards); the episode ends
    early (terminated) when d exceeds ``max_deviation``.

    Observation: the path points ``lookahead`` frames ahead (and now), in the heading frame,
    divided by 5 m -- 2 (len(lookahead) + 1) numbers.
    """

    max_frames: int = 450
    lookahead: tuple[int, ...] = (10, 20, 30, 45)
    speed_range: tuple[float, float] = (0.8, 1.8)
    turn_max: float = 0.8
    max_deviation: float = 2.0
    w_facing: float = 0.5

    def __post_init__(self) -> None:
        self.name = "path"
        self.lookahead = tuple(int(k) for k in self.lookahead)
        self.obs_dim = 2 * (len(self.lookahead) + 1)

    def setup(self, n, generator):
        super().setup(n, generator)
        self.horizon = self.max_frames + max(self.lookahead) + 1
        self.path = torch.zeros(n, self.horizon + 1, 2)

    def set_paths(self, paths: Tensor, idx: Tensor | None = None) -> None:
        """Give the environments ``idx`` world paths (M, P, 2), one point per frame from the
        episode's start; a path shorter than the episode holds its last point."""
        idx = torch.arange(self.n) if idx is None else idx
        paths = torch.as_tensor(paths, dtype=torch.float32).reshape(len(idx), -1, 2)
        P = min(paths.shape[1], self.horizon + 1)
        self.path[idx, :P] = paths[:, :P]
        self.path[idx, P:] = paths[:, P - 1 : P]

    def reset(self, idx, ch):
        p = procedural_paths(
            len(idx), self.horizon, self.generator, self.speed_range, self.turn_max, fps=ch.fps
        )
        self.path[idx] = ch.xy[idx, None] + rotate_about_z(p, ch.heading[idx])  # (M, P, 2)

    def _points(self, ch: Characters, offsets) -> Tensor:
        f = (ch.frame[:, None] + torch.as_tensor(offsets)[None]).clamp(max=self.horizon)
        return torch.gather(self.path, 1, f[..., None].expand(-1, -1, 2))  # (N, K, 2)

    def observe(self, ch):
        pts = self._points(ch, (0, *self.lookahead)) - ch.xy[:, None]
        return (to_heading_frame(pts, ch.heading) / 5).flatten(1)

    def step(self, ch, prev_xy):
        now, ahead = self._points(ch, (0, 5)).unbind(1)
        d = (now - ch.xy).norm(dim=-1)
        tangent = to_heading_frame(ahead - now, ch.heading)  # the path's direction
        cos = tangent[:, 0] / tangent.norm(dim=-1).clamp_min(1e-6)
        reward = torch.exp(-2 * d) * (1 - self.w_facing + self.w_facing * 0.5 * (1 + cos))
        return reward, d > self.max_deviation, {"deviation": d}


TASKS: dict[str, type[Task]] = {"target": TargetTask, "joystick": JoystickTask, "path": PathTask}


def make_task(name: str, **options: Any) -> Task:
    """A task by name (``"target"``, ``"joystick"``, ``"path"``) with its options."""
    if name not in TASKS:
        raise ValueError(f"task must be one of {sorted(TASKS)}, got {name!r}")
    try:
        return TASKS[name](**options)
    except TypeError as e:
        known = [f for f in TASKS[name].__dataclass_fields__ if f not in ("name", "obs_dim")]
        raise ValueError(f"bad options for task {name!r}: {e}; it knows {known}") from None
