"""The CAMDM motion representation, its trajectory condition and the training windows.

CAMDM (Chen et al. 2024, §3.1) predicts F future frames from P past frames. A frame holds

=============  ======  ====================================================================
slice          size    meaning
=============  ======  ====================================================================
``root``       3       the root's position relative to the *reference* frame's root ground
                       point, in the reference's heading frame (metres; z is the height)
``rot``        6 J     local joint rotations as 6D (Zhou et al. 2019); the root's is its
                       rotation relative to the reference heading
=============  ======  ====================================================================

so ``D = 3 + 6 J``. The reference is the last past frame: the paper's "local root
displacements V", the root positions less that of one pose, expressed so that the character
stands at the origin facing +x at the reference and every window looks alike wherever and
whichever way it was captured. The same frames *in the world* (root position in metres, the
root's rotation global) are what a controller accumulates; :func:`to_canonical` and
:func:`to_world` move between the two.

The trajectory condition (eq. 1) of a future of F frames is ``(F, 4)``: the root's ground
positions ``c_rv`` (x, y) and its facing projected on the ground ``c_ro`` (cos, sin of the
heading), both in the reference frame (:func:`trajectory_of`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from minimdm.motion.data import Clip
from minimdm.motion.skeleton import (
    Skeleton,
    forward_kinematics,
    heading_angle,
    matrix_to_6d,
    quat_to_matrix,
    sixd_to_matrix,
    yaw_matrix,
)
from minimdm.validate import InputError, InputTypeError, describe

__all__ = [
    "CAMDMLayout",
    "world_frames",
    "to_canonical",
    "to_world",
    "orthonormalize",
    "trajectory_of",
    "frame_positions",
    "smooth_paths",
    "WindowBank",
]

LOCOMOTION = ("walk", "run", "dash", "walk-back", "walk-left", "walk-right")
"""The Bandai-Namco contents a locomotion controller learns from."""


@dataclass(frozen=True)
class CAMDMLayout:
    """What a CAMDM model's frames and conditions mean; stored in its checkpoint."""

    joint_names: tuple[str, ...]
    """The skeleton's joints, in feature order."""
    styles: tuple[str, ...]
    """The style labels c_l, in index order."""
    fps: float = 30.0
    """Frame rate."""
    past: int = 10
    """P: past frames (CAMDM: 10)."""
    future: int = 45
    """F: future frames (CAMDM: 45)."""

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def dim(self) -> int:
        """D = 3 + 6 J."""
        return 3 + 6 * self.n_joints

    @property
    def window(self) -> int:
        return self.past + self.future

    def style_index(self, style: str | int | Sequence[str | int], name: str = "style") -> Tensor:
        """Style names (or indices) as a long tensor; an unknown name lists the known styles."""
        many = isinstance(style, (list, tuple)) or (isinstance(style, Tensor) and style.dim() > 0)
        items = list(style) if many else [style]
        out = []
        for s in items:
            if isinstance(s, Tensor):
                s = s.item()
            if isinstance(s, str):
                if s not in self.styles:
                    raise InputError(
                        f"{name} must be one of the model's styles {list(self.styles)}, got {s!r}"
                    )
                out.append(self.styles.index(s))
            elif isinstance(s, (int, np.integer)) and not isinstance(s, bool):
                if not 0 <= int(s) < len(self.styles):
                    raise InputError(
                        f"{name} must be a style name or an index in [0, {len(self.styles) - 1}]"
                        f" (styles {list(self.styles)}), got {s}"
                    )
                out.append(int(s))
            else:
                raise InputTypeError(f"{name} must be a style name or index, got {describe(s)}")
        return torch.tensor(out if many else out[:1], dtype=torch.long)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": "camdm",
            "joint_names": list(self.joint_names),
            "styles": list(self.styles),
            "fps": self.fps,
            "past": self.past,
            "future": self.future,
            "dim": self.dim,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CAMDMLayout:
        return cls(
            tuple(d["joint_names"]),
            tuple(d["styles"]),
            float(d.get("fps", 30.0)),
            int(d.get("past", 10)),
            int(d.get("future", 45)),
        )


def world_frames(clip: Clip) -> Tensor:
    """A clip's frames in the world: ``(N, 3 + 6 J)`` float32, root position and 6D local
    rotations (the root's global)."""
    rot = quat_to_matrix(torch.from_numpy(clip.local_rot).double())  # (N, J, 3, 3)
    root = torch.from_numpy(clip.root_pos).double()  # (N, 3)
    return torch.cat([root, matrix_to_6d(rot).flatten(-2)], -1).float()


def _split(frames: Tensor) -> tuple[Tensor, Tensor]:
    """Root ``(..., 3)`` and rotation matrices ``(..., J, 3, 3)`` of frames ``(..., D)``."""
    J, rest = divmod(frames.shape[-1] - 3, 6)
    if rest or J < 1:
        raise InputError(f"frames must have last dim 3 + 6 J, got shape {tuple(frames.shape)}")
    return frames[..., :3], sixd_to_matrix(frames[..., 3:].unflatten(-1, (J, 6)))


def _join(root: Tensor, rot: Tensor) -> Tensor:
    return torch.cat([root, matrix_to_6d(rot).flatten(-2)], -1)


def to_canonical(
    world: Tensor, ref: int, lateral_axis: Sequence[float]
) -> tuple[Tensor, Tensor, Tensor]:
    """World frames ``(B, W, D)`` in the frame of their frame ``ref``: returns the canonical
    frames ``(B, W, D)``, the reference's ground point ``(B, 2)`` and its heading ``(B,)``."""
    root, rot = _split(world)
    heading = heading_angle(rot[:, ref, 0], lateral_axis)  # (B,)
    xy = root[:, ref, :2]  # (B, 2)
    inv = yaw_matrix(-heading)[:, None]  # (B, 1, 3, 3) world -> reference heading frame
    ground = torch.cat([xy, torch.zeros_like(xy[:, :1])], -1)[:, None]  # (B, 1, 3)
    root_c = (inv @ (root - ground)[..., None])[..., 0]  # (B, W, 3)
    rot_c = rot.clone()
    rot_c[:, :, 0] = inv @ rot[:, :, 0]  # (B, W, 3, 3)
    return _join(root_c, rot_c), xy, heading


def to_world(canonical: Tensor, xy: Tensor, heading: Tensor) -> Tensor:
    """Inverse of :func:`to_canonical`: frames ``(B, W, D)`` relative to a reference at ground
    point ``xy (B, 2)`` with ``heading (B,)`` back in the world."""
    root, rot = _split(canonical)
    R = yaw_matrix(heading)[:, None]  # (B, 1, 3, 3)
    ground = torch.cat([xy, torch.zeros_like(xy[:, :1])], -1)[:, None]
    root_w = (R @ root[..., None])[..., 0] + ground
    rot_w = rot.clone()
    rot_w[:, :, 0] = R @ rot[:, :, 0]
    return _join(root_w, rot_w)


def orthonormalize(frames: Tensor) -> Tensor:
    """Frames ``(..., D)`` with each 6D rotation replaced by the orthonormal one it stands for
    (Gram-Schmidt, as forward kinematics reads it), e.g. after frames were offset or blended."""
    return _join(*_split(frames))


def trajectory_of(frames: Tensor, lateral_axis: Sequence[float]) -> Tensor:
    """The trajectory condition ``(..., F, 4)`` of frames ``(..., F, D)``: the root's ground
    position ``c_rv`` and facing ``c_ro = (cos, sin)`` of its heading (CAMDM eq. 1)."""
    root, rot = _split(frames)
    h = heading_angle(rot[..., 0, :, :], lateral_axis)
    return torch.cat([root[..., :2], torch.cos(h)[..., None], torch.sin(h)[..., None]], -1)


def frame_positions(frames: Tensor, skeleton: Skeleton) -> Tensor:
    """Global joint positions ``(..., J, 3)`` of frames ``(..., D)`` by forward kinematics
    (differentiable: the FK of CAMDM eq. 3)."""
    root, rot = _split(frames)
    pos, _ = forward_kinematics(skeleton, root, rot)
    return pos


def headings(frames: Tensor, lateral_axis: Sequence[float]) -> Tensor:
    """The root's heading ``(...,)`` of frames ``(..., D)``."""
    _, rot = _split(frames[..., : 3 + 6])  # the root's rotation is the first 6D block
    return heading_angle(rot[..., 0, :, :], lateral_axis)


def _gaussian_kernel(sigma: float) -> Tensor:
    r = int(math.ceil(3 * sigma))
    x = torch.arange(-r, r + 1, dtype=torch.float32)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def smooth_paths(xy: Tensor, sigma: Tensor) -> Tensor:
    """Gaussian-smooth ground paths ``(B, W, 2)`` along time, each with its own ``sigma (B,)``
    in frames (0: unchanged); the ends are padded by repetition.

    CAMDM's official trainer smooths the trajectory condition so that the model also knows the
    smooth paths a spring controller draws at run time.
    """
    out = xy.clone()
    for s in sigma.unique().tolist():
        if s <= 0:
            continue
        rows = (sigma == s).nonzero()[:, 0]
        k = _gaussian_kernel(s).to(xy)
        r = (k.numel() - 1) // 2
        x = xy[rows].transpose(1, 2).reshape(-1, 1, xy.shape[1])  # (b * 2, 1, W)
        x = torch.nn.functional.pad(x, (r, r), mode="replicate")
        y = torch.nn.functional.conv1d(x, k[None, None])  # (b * 2, 1, W)
        out[rows] = y.reshape(len(rows), 2, -1).transpose(1, 2)
    return out


class WindowBank:
    """Every window of P + F consecutive frames of some clips, never crossing a clip.

    Holds the world frames of all clips in one tensor; :meth:`batch` gathers windows and puts
    each in the frame of its last past frame (:func:`to_canonical`).
    """

    def __init__(self, frames: Sequence[Tensor], styles: Sequence[int], layout: CAMDMLayout):
        if len(frames) != len(styles) or not frames:
            raise ValueError(f"need one style per clip, got {len(frames)} clips, {len(styles)}")
        self.layout = layout
        self.frames = torch.cat(list(frames))  # (N, D)
        starts, style_of = [], []
        offset = 0
        for f, s in zip(frames, styles, strict=True):
            n = f.shape[0] - layout.window + 1
            starts.append(torch.arange(max(n, 0)) + offset)
            style_of.append(torch.full((max(n, 0),), int(s), dtype=torch.long))
            offset += f.shape[0]
        self.starts = torch.cat(starts)  # (W,) first frame of each window
        self.style = torch.cat(style_of)  # (W,)
        if self.starts.numel() == 0:
            raise ValueError(f"no clip has the {layout.window} frames a window needs")

    def __len__(self) -> int:
        return self.starts.numel()

    def batch(self, idx: Tensor, lateral_axis: Sequence[float]) -> tuple[Tensor, Tensor]:
        """Canonical windows ``(B, P + F, D)`` and their styles ``(B,)`` for window indices."""
        rows = self.starts[idx][:, None] + torch.arange(self.layout.window)  # (B, W)
        canonical, _, _ = to_canonical(self.frames[rows], self.layout.past - 1, lateral_axis)
        return canonical, self.style[idx]
