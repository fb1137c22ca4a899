"""Targets and masks for inpainting (A-MDM §4.3, Fig. 7), built from paths and trajectories.

The features of frame f live in the heading frame of frame f (:mod:`minimdm.motion.features`), so a
world-space wish must be turned into those features:

* a 2D root path :math:`p_0..p_F` (p_0 the start) gives the root velocity and yaw rate: the
  heading :math:`h_f` is the direction of travel :math:`p_f - p_{f-1}` (facing +x is heading 0),
  :math:`(d_x, d_y)_f = R_z(-h_f)(p_f - p_{f-1})` and :math:`d_{r,f} = h_f - h_{f-1}`;
  the start pose is :math:`(p_0, h_1)`, so the decoded root follows the path exactly. The root
  joint's own heading-frame x, y (0 in all data) are pinned to 0 as well;
* a joint height (e.g. the head) is the z of that joint's ``joint_pos`` entry, which the
  heading rotation leaves alone;
* a world trajectory of a joint becomes heading-frame ``joint_pos`` once the root path is fixed.

A :class:`Constraint` holds targets (F, D), mask (F, D) and, for a root path, the start pose;
``a | b`` merges two constraints.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from minimdm.motion.data import Clip
from minimdm.motion.features import FeatureLayout, StartPose, encode
from minimdm.motion.skeleton import to_heading_frame, wrap_angle

__all__ = [
    "Constraint",
    "root_path_targets",
    "joint_height_targets",
    "joint_path_targets",
    "circle_path",
    "figure_eight_path",
    "polyline_path",
    "clip_frame",
]


@dataclass
class Constraint:
    """Inpainting targets in feature units and the mask of specified features."""

    targets: Tensor
    """(F, D) desired features of frames 1..F (0 where the mask is False)."""
    mask: Tensor
    """(F, D) bool, True where a feature is specified."""
    start_pose: StartPose | None = None
    """Root position and heading at the start, when the constraint fixes the root path."""
    path: Tensor | None = None
    """(F + 1, 2) the root path p_0..p_F it came from, metres (for plots)."""

    @property
    def n_frames(self) -> int:
        return self.targets.shape[0]

    def __or__(self, other: Constraint) -> Constraint:
        """Both constraints at once; they must agree where both specify a feature."""
        if self.targets.shape != other.targets.shape:
            raise ValueError(
                f"constraints must have the same (F, D), got {tuple(self.targets.shape)} and "
                f"{tuple(other.targets.shape)}"
            )
        both = self.mask & other.mask
        if both.any() and not torch.allclose(self.targets[both], other.targets[both]):
            raise ValueError("constraints disagree on features they both specify")
        if self.start_pose is not None and other.start_pose is not None:
            raise ValueError("only one constraint may fix the start pose (the root path)")
        return Constraint(
            torch.where(self.mask, self.targets, other.targets),
            self.mask | other.mask,
            self.start_pose or other.start_pose,
            self.path if self.path is not None else other.path,
        )


def _as_path(name: str, path: Any, min_points: int = 2) -> Tensor:
    p = torch.as_tensor(np.asarray(path, dtype=np.float64))
    if p.dim() != 2 or p.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {tuple(p.shape)}")
    if p.shape[0] < min_points:
        raise ValueError(f"{name} must hold at least {min_points} points, got {p.shape[0]}")
    if not torch.isfinite(p).all():
        bad = (~torch.isfinite(p)).any(1).nonzero()[0].item()
        raise ValueError(f"{name} must be finite, but point {bad} holds NaN/Inf")
    return p


def path_headings(path: Tensor, eps: float = 1e-6) -> Tensor:
    """Heading of each step p_{f-1} -> p_f, (F,); a step shorter than ``eps`` keeps the last."""
    step = path[1:] - path[:-1]  # (F, 2)
    h = torch.atan2(step[:, 1], step[:, 0])
    moving = step.norm(dim=1) > eps
    if not moving.any():
        return torch.zeros(len(step), dtype=path.dtype)
    first = int(moving.nonzero()[0])
    out = h.clone()
    out[:first] = h[first]
    for f in range(first + 1, len(step)):
        if not moving[f]:
            out[f] = out[f - 1]
    return out


def root_path_targets(layout: FeatureLayout, path: Any) -> Constraint:
    """Root velocity and yaw rate of a 2D root path :math:`p_0..p_F` (module docstring).

    Args:
        layout: the model's feature layout (``Sampler.layout``).
        path: (F + 1, 2) root ground positions in metres, one per frame, p_0 the start
            (make one with :func:`circle_path`, :func:`figure_eight_path` or
            :func:`polyline_path`).

    Returns:
        A :class:`Constraint` over F frames with the start pose :math:`(p_0, h_1)`.
    """
    p = _as_path("path", path)
    step = p[1:] - p[:-1]  # (F, 2) world displacements
    h = path_headings(p)  # (F,)
    local = to_heading_frame(step, h)  # (F, 2)
    yaw = wrap_angle(torch.diff(h, prepend=h[:1]))
    F, D = len(step), layout.dim
    targets = torch.zeros(F, D, dtype=torch.float64)
    mask = torch.zeros(F, D, dtype=torch.bool)
    targets[:, layout.root_vel] = local
    targets[:, 2] = yaw
    mask[:, layout.root_vel] = True
    mask[:, layout.yaw_rate] = True
    # the root joint sits on its own ground projection: its heading-frame x, y are 0 (encode)
    mask[:, layout.joint_pos.start : layout.joint_pos.start + 2] = True
    return Constraint(targets.float(), mask, StartPose(p[0].clone(), h[0].clone()), p.float())


def _joint(layout: FeatureLayout, joint: str | int) -> int:
    if isinstance(joint, str):
        if joint not in layout.joint_names:
            raise ValueError(f"joint must be one of {list(layout.joint_names)}, got {joint!r}")
        return layout.joint_names.index(joint)
    if not 0 <= int(joint) < layout.n_joints:
        raise ValueError(f"joint must lie in [0, {layout.n_joints}), got {joint}")
    return int(joint)


def joint_height_targets(layout: FeatureLayout, joint: str | int, heights: Any) -> Constraint:
    """Constrain a joint's height above the ground, e.g. the head (A-MDM Fig. 7).

    Args:
        joint: a joint name (``layout.joint_names``) or index.
        heights: (F,) heights in metres, one per frame.
    """
    j = _joint(layout, joint)
    z = torch.as_tensor(np.asarray(heights, dtype=np.float64)).reshape(-1)
    if z.numel() < 1 or not torch.isfinite(z).all():
        raise ValueError(f"heights must hold >= 1 finite values, got {z.tolist()[:5]}...")
    F, D = z.numel(), layout.dim
    targets = torch.zeros(F, D)
    mask = torch.zeros(F, D, dtype=torch.bool)
    col = layout.joint_pos.start + 3 * j + 2  # pos/<joint>/z
    targets[:, col] = z.float()
    mask[:, col] = True
    return Constraint(targets, mask)


def joint_path_targets(
    layout: FeatureLayout, joint: str | int, positions: Any, root: Constraint
) -> Constraint:
    """Constrain a joint's world trajectory (F, 3), given the root path that fixes the frames.

    The heading-frame ``joint_pos`` is :math:`R_z(-h_f)(p_f - (r_f, 0))` with the root ground
    position :math:`r_f` and heading :math:`h_f` of ``root`` (from :func:`root_path_targets`).
    Returns the joint's constraint merged with ``root``.
    """
    if root.path is None or root.start_pose is None:
        raise ValueError("root must be a root path constraint (from root_path_targets)")
    j = _joint(layout, joint)
    p = torch.as_tensor(np.asarray(positions, dtype=np.float64))
    F = root.n_frames
    if p.shape != (F, 3) or not torch.isfinite(p).all():
        raise ValueError(f"positions must be finite with shape ({F}, 3), got {tuple(p.shape)}")
    h = path_headings(root.path.double())  # (F,)
    rel = p[:, :2] - root.path[1:].double()
    local = torch.cat([to_heading_frame(rel, h), p[:, 2:]], -1)  # (F, 3)
    targets = torch.zeros(F, layout.dim)
    mask = torch.zeros(F, layout.dim, dtype=torch.bool)
    cols = slice(layout.joint_pos.start + 3 * j, layout.joint_pos.start + 3 * j + 3)
    targets[:, cols] = local.float()
    mask[:, cols] = True
    return root | Constraint(targets, mask)


def _check_motion(speed: float, n_frames: int, fps: float) -> None:
    if not (math.isfinite(speed) and speed > 0):
        raise ValueError(f"speed must be > 0 m/s, got {speed}")
    if not isinstance(n_frames, int) or n_frames < 1:
        raise ValueError(f"n_frames must be an integer >= 1, got {n_frames!r}")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")


def circle_path(
    radius: float, speed: float, n_frames: int, fps: float = 30.0, left: bool = True
) -> Tensor:
    """(n_frames + 1, 2) points on a circle, from the origin heading +x, at ``speed`` m/s.

    ``left``: turn counter-clockwise (centre at (0, radius)), else clockwise.
    """
    _check_motion(speed, n_frames, fps)
    if not radius > 0:
        raise ValueError(f"radius must be > 0, got {radius}")
    a = torch.arange(n_frames + 1, dtype=torch.float64) * speed / fps / radius  # arc angle
    sign = 1.0 if left else -1.0
    return torch.stack([radius * torch.sin(a), sign * radius * (1 - torch.cos(a))], -1).float()


def figure_eight_path(radius: float, speed: float, n_frames: int, fps: float = 30.0) -> Tensor:
    """(n_frames + 1, 2) a figure-eight of two circles of ``radius`` meeting at the origin.

    Starts at the origin heading +x, loops left, then right, at ``speed`` m/s.
    """
    _check_motion(speed, n_frames, fps)
    if not radius > 0:
        raise ValueError(f"radius must be > 0, got {radius}")
    s = torch.arange(n_frames + 1, dtype=torch.float64) * speed / fps  # arc length
    a = (s / radius) % (4 * math.pi)
    left = a < 2 * math.pi
    al = torch.where(left, a, a - 2 * math.pi)
    x = radius * torch.sin(al)
    y = torch.where(left, radius * (1 - torch.cos(al)), -radius * (1 - torch.cos(al)))
    return torch.stack([x, y], -1).float()


def polyline_path(points: Any, speed: float, fps: float = 30.0) -> Tensor:
    """Resample a drawn polyline (N >= 2 points) at constant ``speed``: (F + 1, 2).

    F is the number of whole frames the polyline's length takes at that speed (at least 1).
    """
    p = _as_path("points", points)
    _check_motion(speed, 1, fps)
    seg = (p[1:] - p[:-1]).norm(dim=1)
    cum = torch.cat([torch.zeros(1, dtype=p.dtype), torch.cumsum(seg, 0)])
    if cum[-1] <= 0:
        raise ValueError("points must not all coincide (the polyline has zero length)")
    F = max(1, int(cum[-1] * fps / speed))
    s = torch.arange(F + 1, dtype=p.dtype) * speed / fps
    i = torch.searchsorted(cum, s, right=True).clamp(1, len(p) - 1)
    w = ((s - cum[i - 1]) / seg[i - 1].clamp_min(1e-12)).clamp(0, 1)[:, None]
    return (p[i - 1] + w * (p[i] - p[i - 1])).float()


def clip_frame(clip: Clip, frame: int, layout: FeatureLayout | None = None) -> Tensor:
    """Features (D,) of ``clip``'s frame ``frame`` (>= 1), e.g. a start state or a keyframe.

    With ``layout`` (the model's), the clip's skeleton must match it: a keyframe from another
    skeleton raises, naming both.
    """
    if layout is not None and tuple(clip.skeleton.names) != tuple(layout.joint_names):
        raise ValueError(
            f"clip {clip.name!r} has the skeleton {list(clip.skeleton.names)}, but the model "
            f"expects {list(layout.joint_names)}"
        )
    if not 1 <= frame < clip.n_frames:
        raise ValueError(
            f"frame must lie in [1, {clip.n_frames - 1}] for {clip.name!r}, got {frame}"
        )
    return encode(clip.slice(frame - 1, frame + 1))[0]
