"""Skeletons, rotation utilities and batched forward kinematics.

World convention (used by every module of minimdm): **z is up**, right-handed, metres. A
character in its rest pose faces **+x** and has **+y on its left**. Source data in other
conventions (the y-up DeepMimic humanoid, y-up BVH files) is rotated into this world once, on
load, by :mod:`minimdm.motion.data`.

Rotations are torch tensors batched over any leading dimensions:

* quaternions ``(..., 4)`` are **w-first** ``(w, x, y, z)``;
* rotation matrices ``(..., 3, 3)`` act on column vectors, ``v_parent = R @ v_local``;
* the 6D representation of Zhou et al. (2019) is the first two *columns* of the matrix,
  ``(..., 6) = [R[:, 0], R[:, 1]]``; Gram–Schmidt maps any 6 numbers back to a rotation;
* Euler angles (BVH) are intrinsic: order ``"ZYX"`` means ``R = Rz(a) @ Ry(b) @ Rx(c)``.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "Skeleton",
    "humanoid_skeleton",
    "humanoid_urdf_joints",
    "pybullet_data_path",
    "forward_kinematics",
    "quat_normalize",
    "quat_mul",
    "quat_conjugate",
    "quat_inverse",
    "quat_rotate",
    "quat_to_matrix",
    "matrix_to_quat",
    "axis_angle_to_quat",
    "axis_angle_to_matrix",
    "quat_slerp",
    "matrix_to_6d",
    "sixd_to_matrix",
    "axis_rotation",
    "euler_to_matrix",
    "matrix_to_euler",
    "yaw_matrix",
    "heading_angle",
    "wrap_angle",
    "rotate_about_z",
    "to_heading_frame",
    "bone_pairs",
]

HUMANOID_SCALE = 0.25
"""The DeepMimic humanoid URDF is loaded with ``globalScaling=0.25``: URDF units x 0.25 = metres."""

# y-up (x forward, z right) -> z-up (x forward, y left): a +90 degree rotation about x.
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


# --------------------------------------------------------------------------- quaternions


def quat_normalize(q: Tensor, eps: float = 1e-12) -> Tensor:
    """Scale quaternions ``(..., 4)`` to unit norm (zero quaternions stay zero)."""
    return q / q.norm(dim=-1, keepdim=True).clamp_min(eps)


def quat_mul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a ⊗ b`` of w-first quaternions; ``R(a ⊗ b) = R(a) @ R(b)``."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def quat_conjugate(q: Tensor) -> Tensor:
    """``(w, -x, -y, -z)``: the inverse of a unit quaternion."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_inverse(q: Tensor) -> Tensor:
    """Inverse of any non-zero quaternion: conjugate over squared norm."""
    return quat_conjugate(q) / (q * q).sum(-1, keepdim=True)


def quat_rotate(q: Tensor, v: Tensor) -> Tensor:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``."""
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * torch.cross(u, v, dim=-1)
    return v + w * t + torch.cross(u, t, dim=-1)


def quat_to_matrix(q: Tensor) -> Tensor:
    """Unit quaternions ``(..., 4)`` -> rotation matrices ``(..., 3, 3)``."""
    w, x, y, z = q.unbind(-1)
    row0 = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]
    row1 = [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]
    row2 = [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]
    return torch.stack(row0 + row1 + row2, dim=-1).reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(R: Tensor) -> Tensor:
    """Rotation matrices ``(..., 3, 3)`` -> unit quaternions ``(..., 4)`` with ``w >= 0``.

    Uses the largest of the four candidate denominators (Shepperd's method), so it is accurate
    for every rotation, including 180-degree ones.
    """
    m = R
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    # Four candidates, each exact when its leading component is the largest.
    cands = torch.stack(
        [
            torch.stack(
                [
                    1 + tr,
                    m[..., 2, 1] - m[..., 1, 2],
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 1, 0] - m[..., 0, 1],
                ],
                -1,
            ),
            torch.stack(
                [
                    m[..., 2, 1] - m[..., 1, 2],
                    1 + 2 * m[..., 0, 0] - tr,
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                ],
                -1,
            ),
            torch.stack(
                [
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 0, 1] + m[..., 1, 0],
                    1 + 2 * m[..., 1, 1] - tr,
                    m[..., 1, 2] + m[..., 2, 1],
                ],
                -1,
            ),
            torch.stack(
                [
                    m[..., 1, 0] - m[..., 0, 1],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1 + 2 * m[..., 2, 2] - tr,
                ],
                -1,
            ),
        ],
        dim=-2,
    )  # (..., 4, 4)
    diag = torch.stack([tr, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1)
    best = diag.argmax(-1, keepdim=True)  # (..., 1)
    q = torch.gather(cands, -2, best[..., None].expand(best.shape[:-1] + (1, 4))).squeeze(-2)
    q = quat_normalize(q)
    return torch.where(q[..., :1] < 0, -q, q)


def axis_angle_to_quat(aa: Tensor) -> Tensor:
    """Rotation vectors ``(..., 3)`` (axis times angle in radians) -> quaternions ``(..., 4)``."""
    angle = aa.norm(dim=-1, keepdim=True)
    half = 0.5 * angle
    # sin(half)/angle, with its Taylor series near zero.
    small = angle < 1e-6
    k = torch.where(small, 0.5 - angle**2 / 48.0, torch.sin(half) / angle.clamp_min(1e-12))
    return torch.cat([torch.cos(half), aa * k], dim=-1)


def axis_angle_to_matrix(aa: Tensor) -> Tensor:
    """Rotation vectors ``(..., 3)`` -> rotation matrices ``(..., 3, 3)``."""
    return quat_to_matrix(axis_angle_to_quat(aa))


def quat_slerp(q0: Tensor, q1: Tensor, t: Tensor | float) -> Tensor:
    """Spherical linear interpolation along the shorter arc; ``t`` broadcasts as ``(...,)``.

    ``t = 0`` gives ``q0`` and ``t = 1`` gives ``q1`` (or ``-q1``, the same rotation).
    """
    t = torch.as_tensor(t, dtype=q0.dtype, device=q0.device)[..., None]
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    dot = dot.abs().clamp(max=1.0)
    theta = torch.acos(dot)
    sin_theta = torch.sin(theta)
    near = sin_theta < 1e-6  # almost identical: fall back to normalised lerp
    w0 = torch.where(near, 1 - t, torch.sin((1 - t) * theta) / sin_theta.clamp_min(1e-12))
    w1 = torch.where(near, t, torch.sin(t * theta) / sin_theta.clamp_min(1e-12))
    return quat_normalize(w0 * q0 + w1 * q1)


# --------------------------------------------------------------------------- 6D and Euler


def matrix_to_6d(R: Tensor) -> Tensor:
    """Zhou et al. (2019) 6D representation: the first two columns, ``(..., 3, 3) -> (..., 6)``."""
    return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)


def sixd_to_matrix(d6: Tensor, eps: float = 1e-8) -> Tensor:
    """Gram–Schmidt from 6 numbers to a rotation (Zhou et al. 2019, eq. 16), ``(..., 3, 3)``."""
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = a1 / a1.norm(dim=-1, keepdim=True).clamp_min(eps)
    a2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = a2 / a2.norm(dim=-1, keepdim=True).clamp_min(eps)
    b3 = torch.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)


def axis_rotation(axis: str, angle: Tensor) -> Tensor:
    """Rotations by ``angle (...)`` radians about ``axis`` ("X", "Y" or "Z"): ``(..., 3, 3)``."""
    c, s = torch.cos(angle), torch.sin(angle)
    o, z = torch.ones_like(angle), torch.zeros_like(angle)
    rows = {
        "X": [o, z, z, z, c, -s, z, s, c],
        "Y": [c, z, s, z, o, z, -s, z, c],
        "Z": [c, -s, z, s, c, z, z, z, o],
    }[axis]
    return torch.stack(rows, -1).reshape(angle.shape + (3, 3))


def _check_order(order: str) -> str:
    order = order.upper()
    if len(order) != 3 or set(order) != {"X", "Y", "Z"}:
        raise ValueError(f"order must be a permutation of 'XYZ', got {order!r}")
    return order


def euler_to_matrix(angles: Tensor, order: str = "ZYX") -> Tensor:
    """Intrinsic Euler angles ``(..., 3)``, radians: ``R = R_{o0}(a0) R_{o1}(a1) R_{o2}(a2)``."""
    order = _check_order(order)
    R = axis_rotation(order[0], angles[..., 0])
    for k in (1, 2):
        R = R @ axis_rotation(order[k], angles[..., k])
    return R


def matrix_to_euler(R: Tensor, order: str = "ZYX") -> Tensor:
    """Inverse of :func:`euler_to_matrix`: ``(..., 3, 3) -> (..., 3)`` radians.

    At gimbal lock (middle angle at +-90 degrees) the last angle is set to zero.
    """
    order = _check_order(order)
    i, j, k = ("XYZ".index(a) for a in order)
    s = 1.0 if (i, j, k) in ((0, 1, 2), (1, 2, 0), (2, 0, 1)) else -1.0  # cyclic order?
    sin_b = (s * R[..., i, k]).clamp(-1.0, 1.0)
    b = torch.asin(sin_b)
    a = torch.atan2(-s * R[..., j, k], R[..., k, k])
    c = torch.atan2(-s * R[..., i, j], R[..., i, i])
    lock = sin_b.abs() > 1 - 1e-9
    a_lock = torch.atan2(s * R[..., k, j], R[..., j, j])
    a = torch.where(lock, a_lock, a)
    c = torch.where(lock, torch.zeros_like(c), c)
    return torch.stack([a, b, c], dim=-1)


# --------------------------------------------------------------------------- heading (yaw)


def wrap_angle(a: Tensor, include_pi: bool = True) -> Tensor:
    """Wrap angles ``(...)`` to ``(-pi, pi]``, or with ``include_pi=False`` to ``[-pi, pi)``.

    The result differs from ``a`` by a multiple of 2 pi. The two intervals differ only in which
    end they keep; they are computed in two ways (``ceil``, ``remainder``), so their last bits
    may differ too.
    """
    if not include_pi:
        return torch.remainder(a + math.pi, 2 * math.pi) - math.pi
    return a - 2 * math.pi * torch.ceil((a - math.pi) / (2 * math.pi))


def _cos_sin(angle: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """cos and sin of ``angle``, with trailing dimensions added to broadcast over ``v[..., 0]``."""
    c, s = torch.cos(angle), torch.sin(angle)
    while c.dim() < v.dim() - 1:
        c, s = c[..., None], s[..., None]
    return c, s


def rotate_about_z(v: Tensor, angle: Tensor) -> Tensor:
    """Vectors ``v (..., 2)`` or ``(..., 3)`` rotated by ``angle`` radians about the up axis z.

    :math:`R_z(a)\\,(x, y) = (x \\cos a - y \\sin a,\\; x \\sin a + y \\cos a)`; a z component
    passes through. ``angle`` has the leading shape of ``v``'s batch dimensions, e.g. ``(N,)``
    for ``v (N, ..., 2)``. From a heading frame to the world is ``rotate_about_z(v, heading)``.
    Returns the shape of ``v``.
    """
    c, s = _cos_sin(angle, v)
    x, y = v[..., 0], v[..., 1]
    return torch.stack([c * x - s * y, s * x + c * y, *v[..., 2:].unbind(-1)], dim=-1)


def to_heading_frame(v: Tensor, heading: Tensor) -> Tensor:
    """World vectors ``v (..., 2)`` or ``(..., 3)`` in the heading frame of ``heading``.

    The heading frame has +x ahead and +y on the left (a heading of 0 faces +x):
    :math:`R_z(-h)\\,(x, y) = (x \\cos h + y \\sin h,\\; -x \\sin h + y \\cos h)`, the inverse
    of :func:`rotate_about_z`; a z component passes through. ``heading`` has the leading shape
    of ``v``'s batch dimensions, e.g. ``(N,)`` for ``v (N, ..., 2)``. Returns the shape of ``v``.
    """
    c, s = _cos_sin(heading, v)
    x, y = v[..., 0], v[..., 1]
    return torch.stack([c * x + s * y, -s * x + c * y, *v[..., 2:].unbind(-1)], dim=-1)


def yaw_matrix(yaw: Tensor) -> Tensor:
    """Rotations about the up axis z: ``(...,) -> (..., 3, 3)``."""
    return axis_rotation("Z", yaw)


def heading_angle(R: Tensor, lateral_axis: Any = (0.0, 1.0, 0.0)) -> Tensor:
    """The character's heading: yaw about z of rotations ``R (..., 3, 3)`` -> ``(...,)``.

    The heading is the direction ``left x up`` where ``left = R @ lateral_axis`` is the
    root's left-pointing axis. A rest-pose character (``R = I``) has heading 0 (facing +x).
    Using the lateral axis, not the forward one, keeps the heading well defined while the
    body pitches (crawling, rolls, flips, lying down); only sideways tilts of 90 degrees
    (the middle of a cartwheel) make it singular.
    """
    axis = torch.as_tensor(lateral_axis, dtype=R.dtype, device=R.device)
    left = R @ axis  # (..., 3)
    return torch.atan2(-left[..., 0], left[..., 1])


# --------------------------------------------------------------------------- skeleton


def bone_pairs(parents: Sequence[int]) -> tuple[list[int], list[int]]:
    """The bones of a kinematic tree: ``(children, parents)``, one entry per joint with a parent
    (``parents[j] >= 0``), in joint order. Index joint positions ``(..., J, 3)`` with them."""
    children = [j for j, p in enumerate(parents) if p >= 0]
    return children, [parents[j] for j in children]


@dataclass(eq=False)
class Skeleton:
    """A kinematic tree in the z-up world (metres)."""

    names: list[str]
    """Joint names, unique; joint 0 is the root."""
    parents: list[int]
    """Parent index of each joint, -1 for the root; parents come before their children."""
    offsets: np.ndarray
    """(J, 3) offset of each joint from its parent in the parent's rest frame, metres."""
    foot_joints: list[str] = field(default_factory=list)
    """Names of the joints used for foot contact metrics (ankles, feet or toes)."""
    lateral_axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    """The root-local axis pointing to the character's left; defines the heading."""

    def __post_init__(self) -> None:
        self.names = [str(n) for n in self.names]
        self.parents = [int(p) for p in self.parents]
        self.offsets = np.asarray(self.offsets, dtype=np.float64).reshape(-1, 3)
        J = len(self.names)
        if len(set(self.names)) != J:
            raise ValueError(f"names must be unique, got {self.names}")
        if len(self.parents) != J or self.offsets.shape != (J, 3):
            raise ValueError(
                f"names, parents and offsets must describe the same J={J} joints, got "
                f"{len(self.parents)} parents and offsets of shape {self.offsets.shape}"
            )
        if J == 0 or self.parents[0] != -1:
            raise ValueError(f"joint 0 must be the root (parent -1), got parents {self.parents}")
        for j, p in enumerate(self.parents[1:], start=1):
            if not 0 <= p < j:
                raise ValueError(
                    f"parent of joint {j} ({self.names[j]}) must be in [0, {j}), got {p}"
                )
        if not np.isfinite(self.offsets).all():
            raise ValueError("offsets must be finite")
        self.foot_joints = [
            self.names[f] if isinstance(f, int) else str(f) for f in self.foot_joints
        ]
        for f in self.foot_joints:
            self.index(f)
        self.lateral_axis = tuple(float(a) for a in self.lateral_axis)

    @property
    def n_joints(self) -> int:
        return len(self.names)

    def __len__(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        """Index of the joint called ``name``."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no joint named {name!r}; joints are {self.names}") from None

    @property
    def foot_indices(self) -> list[int]:
        return [self.index(f) for f in self.foot_joints]

    def children(self, j: int) -> list[int]:
        return [c for c, p in enumerate(self.parents) if p == j]

    def bone_lengths(self) -> np.ndarray:
        """(J,) length of the bone from each joint's parent to it; 0 for the root."""
        lengths = np.linalg.norm(self.offsets, axis=-1)
        lengths[0] = 0.0
        return lengths

    def rest_positions(self) -> np.ndarray:
        """(J, 3) joint positions in the rest pose (all rotations identity), root at offsets[0]."""
        pos = np.zeros((len(self), 3))
        pos[0] = self.offsets[0]
        for j in range(1, len(self)):
            pos[j] = pos[self.parents[j]] + self.offsets[j]
        return pos

    def reordered(self, names: list[str]) -> Skeleton:
        """The same tree with joints listed in the order ``names`` (parents first)."""
        if sorted(names) != sorted(self.names):
            raise ValueError(f"names must be a permutation of {self.names}, got {names}")
        old = [self.index(n) for n in names]
        parents = [
            -1 if self.parents[o] < 0 else names.index(self.names[self.parents[o]]) for o in old
        ]
        return Skeleton(names, parents, self.offsets[old], self.foot_joints, self.lateral_axis)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description, for checkpoint metadata."""
        return {
            "names": list(self.names),
            "parents": list(self.parents),
            "offsets": self.offsets.tolist(),
            "foot_joints": list(self.foot_joints),
            "lateral_axis": list(self.lateral_axis),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Skeleton:
        return cls(
            names=d["names"],
            parents=d["parents"],
            offsets=np.asarray(d["offsets"], dtype=np.float64),
            foot_joints=d.get("foot_joints", []),
            lateral_axis=tuple(d.get("lateral_axis", (0.0, 1.0, 0.0))),
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Skeleton):
            return NotImplemented
        return (
            self.names == other.names
            and self.parents == other.parents
            and self.foot_joints == other.foot_joints
            and np.allclose(self.lateral_axis, other.lateral_axis, atol=1e-6)
            and np.allclose(self.offsets, other.offsets, atol=1e-6)
        )

    def __repr__(self) -> str:
        return f"Skeleton({len(self)} joints: {', '.join(self.names)})"


def pybullet_data_path() -> Path:
    """The folder of ``pybullet_data``; raises ``ImportError`` naming the install command."""
    try:
        import pybullet_data
    except ImportError as e:
        raise ImportError(
            "The DeepMimic humanoid and its motion clips ship with pybullet. Install them with "
            "`pip install pybullet` (or `pip install 'minimdm[data]'`)."
        ) from e
    return Path(pybullet_data.getDataPath())


def humanoid_urdf_joints(urdf: str | Path | None = None) -> list[dict[str, Any]]:
    """The joints of the DeepMimic humanoid URDF, in file order, in its own y-up units.

    Each entry has ``name``, ``type`` (fixed/spherical/revolute), ``parent`` (joint name or
    None), ``xyz`` (origin, URDF units) and ``axis`` (for revolute joints).
    """
    path = Path(urdf) if urdf is not None else pybullet_data_path() / "humanoid" / "humanoid.urdf"
    # The shipped file ends with a NUL byte, which XML parsers reject: strip it.
    root = ET.fromstring(path.read_bytes().rstrip(b"\x00\r\n\t "))
    joints = root.findall("joint")
    by_child = {j.find("child").get("link"): j.get("name") for j in joints}
    out = []
    for j in joints:
        origin = j.find("origin")
        rpy = [float(v) for v in origin.get("rpy", "0 0 0").split()]
        if any(abs(v) > 1e-9 for v in rpy):
            raise ValueError(f"{path}: joint {j.get('name')} has rpy {rpy}; expected 0 0 0")
        axis = j.find("axis")
        out.append(
            {
                "name": j.get("name"),
                "type": j.get("type"),
                "parent": by_child.get(j.find("parent").get("link")),
                "xyz": [float(v) for v in origin.get("xyz").split()],
                "axis": None if axis is None else [float(v) for v in axis.get("xyz").split()],
            }
        )
    return out


def humanoid_skeleton(urdf: str | Path | None = None) -> Skeleton:
    """The 15-joint DeepMimic humanoid (``pybullet_data/humanoid/humanoid.urdf``), z-up metres.

    Offsets are the URDF joint origins times 0.25 (pybullet's ``globalScaling``), rotated from
    the URDF's y-up frame (x forward, z right) into the z-up world (x forward, y left).
    """
    joints = humanoid_urdf_joints(urdf)
    names = [j["name"] for j in joints]
    parents = [-1 if j["parent"] is None else names.index(j["parent"]) for j in joints]
    offsets = np.array([j["xyz"] for j in joints]) * HUMANOID_SCALE @ Y_UP_TO_Z_UP.T
    return Skeleton(names, parents, offsets, foot_joints=["right_ankle", "left_ankle"])


# --------------------------------------------------------------------------- kinematics


def forward_kinematics(
    skeleton: Skeleton, root_pos: Tensor, local_rot: Tensor
) -> tuple[Tensor, Tensor]:
    """Global joint positions and rotations from the root position and local rotations.

    Args:
        skeleton: the kinematic tree.
        root_pos: ``(..., 3)`` global position of the root joint.
        local_rot: ``(..., J, 4)`` unit quaternions or ``(..., J, 3, 3)`` matrices, each joint's
            rotation relative to its parent (the root's is global).

    Returns:
        positions ``(..., J, 3)`` and rotations ``(..., J, 3, 3)``:
        ``R_j = R_parent @ L_j`` and ``p_j = p_parent + R_parent @ offset_j``.
    """
    J = len(skeleton)
    if local_rot.shape[-1] == 4:
        local_rot = quat_to_matrix(local_rot)
    if local_rot.shape[-3:] != (J, 3, 3) or root_pos.shape[-1] != 3:
        raise ValueError(
            f"expected root_pos (..., 3) and local_rot (..., {J}, 4 or 3x3), got "
            f"{tuple(root_pos.shape)} and {tuple(local_rot.shape)}"
        )
    offsets = torch.as_tensor(skeleton.offsets, dtype=local_rot.dtype, device=local_rot.device)
    rots: list[Tensor] = [local_rot[..., 0, :, :]]
    pos: list[Tensor] = [root_pos.to(local_rot.dtype).expand(rots[0].shape[:-2] + (3,))]
    for j in range(1, J):
        p = skeleton.parents[j]
        rots.append(rots[p] @ local_rot[..., j, :, :])
        pos.append(pos[p] + (rots[p] @ offsets[j, :, None])[..., 0])
    return torch.stack(pos, dim=-2), torch.stack(rots, dim=-3)
