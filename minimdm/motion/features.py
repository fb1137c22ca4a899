"""The A-MDM frame representation (Shi et al. 2024, §3.1), its inverse, a normalizer, windows.

A frame ``x_f`` holds, in this order (see :class:`FeatureLayout`), with J joints:

=============  =====  =========================================================================
slice          size   meaning
=============  =====  =========================================================================
``root_vel``   2      root planar velocity (d_x, d_y): root ground displacement f-1 -> f
``yaw_rate``   1      d_r: heading change f-1 -> f, radians, wrapped to (-pi, pi]
``joint_pos``  3J     j_p: joint positions relative to the root's ground projection at f
``joint_vel``  3J     j_v: joint displacements f-1 -> f
``joint_rot``  6J     j_o: global joint rotations as 6D (Zhou et al. 2019), yaw removed
=============  =====  =========================================================================

``D = 3 + 12 J`` (183 for the 15-joint humanoid). Every vector in row f is expressed in the
**heading frame of frame f**: the z-up world rotated by ``-heading_f`` about z, where the
heading is the root's yaw (:func:`minimdm.motion.skeleton.heading_angle`). Velocities are per-frame
differences at the clip's rate (metres and radians per frame; multiply by fps for per second).

Frame 0 of a clip has no predecessor, so ``encode`` gives ``F - 1`` rows: row ``r`` describes
clip frame ``r + 1``. ``decode`` integrates the root from a :class:`StartPose` -- the root's
ground position and heading at the frame *before* the first row -- so
``decode(encode(clip), start_pose_of(clip, 0))`` reproduces ``clip.positions[1:]``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from minimdm.validate import InputError, InputTypeError, check_int, check_skeleton, describe

from .data import Clip
from .skeleton import (
    Skeleton,
    heading_angle,
    matrix_to_6d,
    matrix_to_quat,
    rotate_about_z,
    sixd_to_matrix,
    wrap_angle,
    yaw_matrix,
)

__all__ = [
    "FeatureLayout",
    "StartPose",
    "start_pose_of",
    "start_state",
    "encode",
    "encode_motion",
    "decode",
    "decode_root",
    "decode_clip",
    "Normalizer",
    "WindowDataset",
]


@dataclass(frozen=True)
class FeatureLayout:
    """Where each quantity lives in a frame vector (A-MDM §3.1); stored in checkpoints."""

    joint_names: tuple[str, ...]
    """The skeleton's joint names, in feature order."""
    fps: float = 30.0
    """Frame rate the per-frame velocities refer to."""

    @classmethod
    def for_skeleton(cls, skeleton: Skeleton, fps: float = 30.0) -> FeatureLayout:
        return cls(tuple(skeleton.names), float(fps))

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def dim(self) -> int:
        """D = 3 + 12 J."""
        return 3 + 12 * self.n_joints

    @property
    def root_vel(self) -> slice:
        return slice(0, 2)

    @property
    def yaw_rate(self) -> slice:
        return slice(2, 3)

    @property
    def joint_pos(self) -> slice:
        return slice(3, 3 + 3 * self.n_joints)

    @property
    def joint_vel(self) -> slice:
        return slice(3 + 3 * self.n_joints, 3 + 6 * self.n_joints)

    @property
    def joint_rot(self) -> slice:
        return slice(3 + 6 * self.n_joints, self.dim)

    def names(self) -> list[str]:
        """One name per dimension, e.g. ``"pos/left_ankle/z"`` or ``"rot/chest/3"``."""
        out = ["root_vel/x", "root_vel/y", "yaw_rate"]
        for kind, comps in (("pos", "xyz"), ("vel", "xyz"), ("rot", "012345")):
            out += [f"{kind}/{j}/{c}" for j in self.joint_names for c in comps]
        return out

    def check(self, features: Tensor, what: str = "features") -> None:
        """``ValueError`` unless ``features`` is ``(..., D)`` and finite (naming the frame)."""
        if features.shape[-1] != self.dim:
            raise ValueError(
                f"{what} must have last dim D={self.dim}, got shape {tuple(features.shape)}"
            )
        if not torch.isfinite(features).all():
            bad = (~torch.isfinite(features)).any(-1).nonzero()[0].tolist()
            raise ValueError(f"{what} holds NaN/Inf at frame index {bad}")

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": "amdm",
            "joint_names": list(self.joint_names),
            "fps": self.fps,
            "dim": self.dim,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FeatureLayout:
        layout = cls(tuple(d["joint_names"]), float(d.get("fps", 30.0)))
        if "dim" in d and d["dim"] != layout.dim:
            raise ValueError(
                f"layout dim {d['dim']} does not match {layout.n_joints} joints ({layout.dim})"
            )
        return layout


@dataclass
class StartPose:
    """The root's ground position and heading that decoding starts from."""

    xy: Tensor
    """(..., 2) root ground position, metres."""
    heading: Tensor
    """(...,) heading, radians."""
    skeleton: Skeleton | None = None
    """The skeleton of the motion this pose comes from, when known (:func:`start_pose_of` sets
    it); samplers compare it with their model's (:func:`start_state`)."""
    fps: float | None = None
    """The frame rate of that motion, when known; samplers compare it with their model's."""

    @staticmethod
    def broadcast(start_pose: StartPose | dict | None, n: int) -> StartPose:
        """``n`` start poses, float64: xy (n, 2), heading (n,); ``None`` is the origin facing +x.

        Accepts one pose (xy (2,), heading ()) or ``n`` of them, as a StartPose or a dict.
        """
        if start_pose is None:
            return StartPose(
                torch.zeros(n, 2, dtype=torch.float64), torch.zeros(n, dtype=torch.float64)
            )
        sp = _as_start_pose(start_pose)
        try:
            xy = torch.as_tensor(sp.xy, dtype=torch.float64).reshape(-1, 2)
            heading = torch.as_tensor(sp.heading, dtype=torch.float64).reshape(-1)
        except (TypeError, ValueError, RuntimeError):
            raise InputError(
                f"start_pose must have xy ({n}, 2) or (2,) and heading ({n},) or () of numbers, "
                f"got xy {describe(sp.xy)} and heading {describe(sp.heading)}"
            ) from None
        if xy.shape[0] not in (1, n) or heading.shape[0] not in (1, n):
            raise InputError(
                f"start_pose must have xy ({n}, 2) or (2,) and heading ({n},) or (), "
                f"got {tuple(xy.shape)} and {tuple(heading.shape)}"
            )
        if not (torch.isfinite(xy).all() and torch.isfinite(heading).all()):
            raise InputError("start_pose must be finite, but it holds NaN/Inf")
        return StartPose(xy.expand(n, 2).clone(), heading.expand(n).clone(), sp.skeleton, sp.fps)


def _as_start_pose(start_pose: Any) -> StartPose:
    """A StartPose from a StartPose or a dict with ``xy`` and ``heading``."""
    if isinstance(start_pose, StartPose):
        return start_pose
    if isinstance(start_pose, dict):
        try:
            return StartPose(**start_pose)
        except TypeError:
            pass
    raise InputTypeError(
        "start_pose must be a StartPose, a dict with keys 'xy' and 'heading', or None, got "
        f"{describe(start_pose)}"
    )


def start_state(
    start: Any,
    start_pose: StartPose | dict | None,
    *,
    skeleton: Skeleton | None = None,
    layout: FeatureLayout | None = None,
    name: str = "start",
    history: int = 1,
) -> tuple[Any, StartPose | dict | None]:
    """Resolve what a sampler starts from, and check that it fits the model.

    ``start`` is frames in feature units, returned as they are, or a :class:`Clip`: then the
    motion continues the clip, from its last frame (its last encoded row, and its start pose
    unless ``start_pose`` is given); for a model with a ``history`` of H > 1 frames, its last
    H encoded rows (H, D). The skeleton and frame rate the start came from (the
    clip's, or those a :class:`StartPose` carries) are compared with the model's ``skeleton``
    and ``layout`` (:func:`minimdm.validate.check_skeleton`); what is unknown is not compared.

    Returns:
        ``(frames, start_pose)``.

    Raises:
        MismatchError: another skeleton or frame rate; names both and the first difference.
    """
    given_sk = given_fps = None
    if isinstance(start, Clip):
        if start.n_frames < history + 1:
            raise InputError(
                f"{name} must be a clip of at least {history + 1} frames (a frame's features "
                f"need the one before it, and the model conditions on {history}), got clip "
                f"{start.name!r} of {start.n_frames}"
            )
        given_sk, given_fps = start.skeleton, start.fps
        frames = encode(start)[-1] if history == 1 else encode(start)[-history:]  # (D,), (H, D)
        if start_pose is None:
            start_pose = start_pose_of(start, start.n_frames - 1)
    else:
        frames = start
    if start_pose is not None:
        sp = _as_start_pose(start_pose)
        given_sk = given_sk if given_sk is not None else sp.skeleton
        given_fps = given_fps if given_fps is not None else sp.fps
    expected = skeleton
    if expected is None and layout is not None:
        expected = {"names": list(layout.joint_names)}
    elif (
        expected is not None
        and layout is not None
        and list(layout.joint_names) != list(skeleton.names)
    ):
        expected = {"names": list(layout.joint_names)}  # the features follow the layout
    check_skeleton(
        name,
        given_sk,
        expected,
        given_fps=given_fps,
        expected_fps=layout.fps if layout is not None else None,
    )
    return frames, start_pose


def _as_start(start: StartPose | dict, like: Tensor) -> tuple[Tensor, Tensor]:
    if isinstance(start, dict):
        start = StartPose(start["xy"], start["heading"])
    xy = torch.as_tensor(start.xy, dtype=like.dtype, device=like.device)
    h = torch.as_tensor(start.heading, dtype=like.dtype, device=like.device)
    return xy, h


def start_pose_of(clip: Clip, frame: int = 0) -> StartPose:
    """The root ground position and heading of ``clip`` at ``frame`` (float64), with the
    clip's skeleton and frame rate (which samplers compare with their model's)."""
    frame = check_int("frame", frame, low=-clip.n_frames, high=clip.n_frames - 1)
    _, rot = clip.fk()
    return StartPose(
        xy=torch.as_tensor(clip.root_pos[frame, :2], dtype=torch.float64),
        heading=heading_angle(rot[frame, 0], clip.skeleton.lateral_axis),
        skeleton=clip.skeleton,
        fps=float(clip.fps),
    )


def encode_motion(
    positions: Tensor, rotations: Tensor, lateral_axis: Any = (0.0, 1.0, 0.0)
) -> Tensor:
    """A-MDM §3.1 features from global joint positions and rotations.

    Args:
        positions: ``(..., F, J, 3)`` global joint positions (joint 0 is the root).
        rotations: ``(..., F, J, 3, 3)`` global joint rotations.
        lateral_axis: the root's left axis (``Skeleton.lateral_axis``), defines the heading.

    Returns:
        ``(..., F - 1, 3 + 12 J)`` features of frames 1..F-1, in the input dtype.
    """
    if positions.shape[-3] < 2:
        raise ValueError(f"need at least 2 frames to encode, got shape {tuple(positions.shape)}")
    heading = heading_angle(rotations[..., 0, :, :], lateral_axis)  # (..., F)
    inv = yaw_matrix(-heading)  # (..., F, 3, 3) world -> heading frame
    root = positions[..., 0, :] * positions.new_tensor([1.0, 1.0, 0.0])  # ground projection
    local_pos = (inv[..., None, :, :] @ (positions - root[..., None, :])[..., None])[..., 0]
    step = positions[..., 1:, :, :] - positions[..., :-1, :, :]  # (..., F-1, J, 3)
    inv1 = inv[..., 1:, :, :]
    vel = (inv1[..., None, :, :] @ step[..., None])[..., 0]
    root_vel = vel[..., 0, :2]  # the root's planar displacement, heading frame of f
    yaw_rate = wrap_angle(heading[..., 1:] - heading[..., :-1])[..., None]
    rot6 = matrix_to_6d(inv1[..., None, :, :] @ rotations[..., 1:, :, :, :])  # (..., F-1, J, 6)
    flat = local_pos.shape[:-3] + (local_pos.shape[-3] - 1, -1)
    return torch.cat(
        [
            root_vel,
            yaw_rate,
            local_pos[..., 1:, :, :].reshape(flat),
            vel.reshape(flat),
            rot6.reshape(flat),
        ],
        dim=-1,
    )


def encode(clip: Clip) -> Tensor:
    """Features ``(F - 1, D)`` float32 of frames 1..F-1 of ``clip`` (computed in float64)."""
    pos, rot = clip.fk()
    return encode_motion(pos, rot, clip.skeleton.lateral_axis).float()


def decode_root(features: Tensor, start_pose: StartPose | dict) -> tuple[Tensor, Tensor]:
    """Integrate the root: ground positions ``(..., N, 2)`` and headings ``(..., N)``.

    ``heading_f = heading_{f-1} + d_r`` and ``xy_f = xy_{f-1} + Rz(heading_f) (d_x, d_y)``.
    """
    xy0, h0 = _as_start(start_pose, features)
    heading = h0[..., None] + torch.cumsum(features[..., 2], dim=-1)  # (..., N)
    step = rotate_about_z(features[..., :2], heading)  # (..., N, 2)
    return xy0[..., None, :] + torch.cumsum(step, dim=-2), heading


def decode(
    features: Tensor, start_pose: StartPose | dict, return_rotations: bool = False
) -> Tensor | tuple[Tensor, Tensor]:
    """Global joint positions ``(..., N, J, 3)`` from features ``(..., N, D)``.

    Positions come from ``j_p`` placed at the integrated root (:func:`decode_root`); with
    ``return_rotations`` also the global rotations ``(..., N, J, 3, 3)`` from ``j_o``.
    """
    features = torch.as_tensor(features)
    J, rest = divmod(features.shape[-1] - 3, 12)
    if rest or J < 1:
        raise ValueError(f"features must have last dim 3 + 12 J, got shape {tuple(features.shape)}")
    FeatureLayout(tuple(str(j) for j in range(J))).check(features)
    xy, heading = decode_root(features, start_pose)
    R = yaw_matrix(heading)  # (..., N, 3, 3)
    local = features[..., 3 : 3 + 3 * J].unflatten(-1, (J, 3))
    pos = (R[..., None, :, :] @ local[..., None])[..., 0]
    pos = pos + torch.cat([xy, torch.zeros_like(xy[..., :1])], -1)[..., None, :]
    if not return_rotations:
        return pos
    rot6 = features[..., 3 + 6 * J :].unflatten(-1, (J, 6))
    return pos, R[..., None, :, :] @ sixd_to_matrix(rot6)


def decode_clip(
    features: Tensor,
    start_pose: StartPose | dict,
    skeleton: Skeleton,
    fps: float = 30.0,
    name: str = "decoded",
) -> Clip:
    """A :class:`Clip` (e.g. for :func:`minimdm.motion.data.save_bvh`) from features ``(N, D)``.

    Local rotations come from ``j_o`` and the root position from ``j_p``; the clip's
    positions are then recomputed by forward kinematics with the skeleton's bone lengths.
    """
    pos, rot = decode(torch.as_tensor(features, dtype=torch.float64), start_pose, True)
    parents = torch.tensor([max(p, 0) for p in skeleton.parents])
    local = rot[..., parents, :, :].transpose(-1, -2) @ rot  # R_parent^T R_j
    local[..., 0, :, :] = rot[..., 0, :, :]
    return Clip(name, fps, skeleton, pos[:, 0].numpy(), matrix_to_quat(local).numpy())


class Normalizer:
    """Per-dimension standardisation ``(x - mean) / std``, with ``std >= floor``.

    Constant dimensions (e.g. the root's own ground-relative x and y, always 0) get
    ``std = floor`` instead of 0, so they map to 0 and never divide by zero.
    """

    def __init__(self, mean: Tensor, std: Tensor, floor: float = 1e-3) -> None:
        self.mean = torch.as_tensor(mean, dtype=torch.float32)
        self.std = torch.as_tensor(std, dtype=torch.float32).clamp_min(floor)
        self.floor = float(floor)
        if self.mean.shape != self.std.shape or self.mean.ndim != 1:
            raise ValueError(
                f"mean and std must be (D,), got {tuple(self.mean.shape)} and "
                f"{tuple(self.std.shape)}"
            )

    @classmethod
    def fit(cls, x: Tensor | np.ndarray | Sequence, floor: float = 1e-3) -> Normalizer:
        """Statistics of ``x (..., D)`` (or a list of ``(F_i, D)`` arrays) over all frames."""
        if isinstance(x, (list, tuple)):
            x = torch.cat([torch.as_tensor(a, dtype=torch.float64) for a in x])
        x = torch.as_tensor(x, dtype=torch.float64).reshape(-1, x.shape[-1])
        if not torch.isfinite(x).all():
            raise ValueError("cannot fit a Normalizer to data holding NaN/Inf")
        return cls(x.mean(0), x.std(0, unbiased=False), floor)

    @property
    def dim(self) -> int:
        return self.mean.shape[0]

    def _check(self, x: Tensor) -> None:
        if x.shape[-1] != self.dim:
            raise ValueError(f"expected last dim {self.dim}, got shape {tuple(x.shape)}")

    def normalize(self, x: Tensor) -> Tensor:
        self._check(x)
        return (x - self.mean.to(x)) / self.std.to(x)

    def denormalize(self, x: Tensor) -> Tensor:
        self._check(x)
        return x * self.std.to(x) + self.mean.to(x)

    def to_dict(self) -> dict[str, Any]:
        return {"mean": self.mean.tolist(), "std": self.std.tolist(), "floor": self.floor}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Normalizer:
        return cls(torch.tensor(d["mean"]), torch.tensor(d["std"]), d.get("floor", 1e-3))


class WindowDataset(Dataset):
    """Windows of ``n + 1`` consecutive frames ``(n + 1, D)``, never crossing clips.

    For scheduled sampling (A-MDM §4): frame 0 of a window conditions the rollout and frames
    1..n are its targets. ``windows[i]`` is ``(clip index, first frame)``; clips shorter than
    ``n + 1`` frames give no window.
    """

    def __init__(
        self, feature_arrays: Sequence[Tensor | np.ndarray], n: int, stride: int = 1
    ) -> None:
        if n < 1 or stride < 1:
            raise ValueError(f"n and stride must be >= 1, got n={n}, stride={stride}")
        self.arrays = [torch.as_tensor(a, dtype=torch.float32) for a in feature_arrays]
        dims = {a.shape[-1] for a in self.arrays}
        if len(dims) != 1 or any(a.ndim != 2 for a in self.arrays):
            raise ValueError(
                "feature arrays must all be (F_i, D) with one D, got "
                f"{[tuple(a.shape) for a in self.arrays]}"
            )
        self.n = n
        self.windows = [
            (c, s) for c, a in enumerate(self.arrays) for s in range(0, a.shape[0] - n, stride)
        ]
        if not self.windows:
            raise ValueError(f"no clip has the {n + 1} frames a window needs")

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, i: int) -> Tensor:
        c, s = self.windows[i]
        return self.arrays[c][s : s + self.n + 1]
