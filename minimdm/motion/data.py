"""Motion clips: the DeepMimic humanoid clips of ``pybullet_data``, resampling, BVH both ways.

Axis convention (the one world of minimdm, see :mod:`minimdm.motion.skeleton`): **z up**,
right-handed, metres; a character in its rest pose faces **+x** with **+y on its left**.

* DeepMimic clips and the humanoid URDF are y-up with x forward and z to the character's right.
  They are rotated by +90 degrees about x: ``(x, y, z) -> (x, -z, y)``.
* BVH files are y-up and, by convention, the rest pose faces +Z with +X on its left. They are
  mapped by the cyclic permutation ``(X, Y, Z) -> (Z, X, Y)``; :func:`save_bvh` applies the
  inverse, so a saved clip faces +Z in the file. The BVH code lives in :mod:`minimdm.motion.bvh`.

A :class:`Clip` stores the root position ``(F, 3)`` and **local joint rotations as unit
quaternions** ``(F, J, 4)``, w-first, relative to the parent joint (the root's is global).
Quaternions are normalised when a clip is made; a zero-norm quaternion or a NaN/Inf raises
``ValueError`` naming the frame. Global joint positions ``(F, J, 3)`` come from forward
kinematics. Everything is resampled to 30 Hz by default: slerp for rotations, linear
interpolation for the root position.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from minimdm.utils import num_threads
from minimdm.validate import InputError, check_number

from .skeleton import (
    Y_UP_TO_Z_UP,
    Skeleton,
    axis_angle_to_quat,
    forward_kinematics,
    heading_angle,
    humanoid_skeleton,
    humanoid_urdf_joints,
    pybullet_data_path,
    quat_conjugate,
    quat_mul,
    quat_slerp,
    quat_to_matrix,
    wrap_angle,
    yaw_matrix,
)

__all__ = [
    "Clip",
    "MotionDataset",
    "load_clips",
    "load_deepmimic",
    "resample_clip",
    "CLIP_NAMES",
    "MAX_FRAMES",
]

_F64 = torch.float64

# The 20 humanoid clips of pybullet_data/data/motions (the quadruped laikago_walk is left out).
CLIP_NAMES = (
    "backflip cartwheel crawl dance_a dance_b getup_facedown getup_faceup "
    "jump kick punch roll run spin spinkick walk "
    "walker/0walk_forward walker/turn_left0 walker/turn_left1 walker/turn_right0 walker/turn_right1"
).split()

# The joints stored in a DeepMimic frame after duration (1), root position (3), root quat (4).
_DEEPMIMIC_ORDER = (
    "chest neck right_hip right_knee right_ankle right_shoulder right_elbow "
    "left_hip left_knee left_ankle left_shoulder left_elbow"
).split()
_DEEPMIMIC_WIDTH = 44


def _check_quats(q: np.ndarray, what: str, names: Sequence[str]) -> np.ndarray:
    """Reject NaN/Inf and zero-norm quaternions ``(F, J, 4)`` naming the frame; normalise."""
    bad = ~np.isfinite(q).all(-1)
    if bad.any():
        f, j = np.argwhere(bad)[0]
        raise ValueError(f"{what}: rotation of joint {names[j]!r} at frame {f} holds NaN/Inf")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if (norm < 1e-8).any():
        f, j = np.argwhere(norm[..., 0] < 1e-8)[0]
        raise ValueError(f"{what}: quaternion of joint {names[j]!r} at frame {f} has zero norm")
    return q / norm


def _global_positions(
    skeleton: Skeleton, root_pos: np.ndarray, local_rot: np.ndarray
) -> np.ndarray:
    """Global joint positions ``(F, J, 3)`` (float32) by forward kinematics, in blocks of frames
    so that long clips keep small temporaries."""
    if not len(root_pos):
        return np.zeros((0, len(skeleton), 3), np.float32)
    root = torch.from_numpy(root_pos).to(_F64)
    rot = torch.from_numpy(local_rot).to(_F64)
    blocks = zip(root.split(4096), rot.split(4096), strict=True)
    return np.concatenate(
        [forward_kinematics(skeleton, r, q)[0].numpy().astype(np.float32) for r, q in blocks]
    )


@dataclass(eq=False)
class Clip:
    """One motion: a skeleton, a frame rate, root positions and local rotations."""

    name: str
    """Clip name, e.g. ``"walk"`` or ``"walker/turn_left0"``."""
    fps: float
    """Frames per second."""
    skeleton: Skeleton
    """The kinematic tree (z-up, metres)."""
    root_pos: np.ndarray
    """(F, 3) global root position, metres."""
    local_rot: np.ndarray
    """(F, J, 4) unit quaternions (w, x, y, z), each joint relative to its parent."""
    positions: np.ndarray | None = None
    """(F, J, 3) global joint positions, metres; computed by forward kinematics if None."""
    loop: bool = False
    """True when the source motion is a loop (DeepMimic ``"Loop": "wrap"``)."""
    labels: dict[str, str] = field(default_factory=dict)
    """What the clip shows, e.g. ``{"content": "walk", "style": "happy"}`` (empty if unknown)."""

    def __post_init__(self) -> None:
        J = len(self.skeleton)
        self.root_pos = np.asarray(self.root_pos, dtype=np.float32)
        q = np.asarray(self.local_rot, dtype=np.float64)
        F = q.shape[0] if q.ndim == 3 else -1
        if q.shape != (F, J, 4) or self.root_pos.shape != (F, 3):
            raise ValueError(
                f"clip {self.name!r}: expected root_pos (F, 3) and local_rot (F, {J}, 4), got "
                f"{self.root_pos.shape} and {q.shape}"
            )
        if not np.isfinite(self.root_pos).all():
            f = int(np.argwhere(~np.isfinite(self.root_pos))[0, 0])
            raise ValueError(f"clip {self.name!r}: root_pos holds NaN/Inf at frame {f}")
        if not self.fps > 0:
            raise ValueError(f"clip {self.name!r}: fps must be > 0, got {self.fps}")
        self.local_rot = _check_quats(q, f"clip {self.name!r}", self.skeleton.names).astype(
            np.float32
        )
        if self.positions is None:
            self.positions = _global_positions(self.skeleton, self.root_pos, self.local_rot)
        self.positions = np.asarray(self.positions, dtype=np.float32)
        if self.positions.shape != (F, J, 3):
            raise ValueError(
                f"clip {self.name!r}: expected positions ({F}, {J}, 3), got {self.positions.shape}"
            )

    @property
    def n_frames(self) -> int:
        return self.root_pos.shape[0]

    def __len__(self) -> int:
        return self.n_frames

    @property
    def duration(self) -> float:
        """Seconds from the first to the last frame."""
        return (self.n_frames - 1) / self.fps

    def fk(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Float64 forward kinematics: positions ``(F, J, 3)`` and rotations ``(F, J, 3, 3)``."""
        return forward_kinematics(
            self.skeleton,
            torch.from_numpy(self.root_pos).to(_F64),
            torch.from_numpy(self.local_rot).to(_F64),
        )

    def slice(self, start: int, stop: int | None = None, name: str | None = None) -> Clip:
        """Frames ``start:stop`` as a new clip."""
        s = slice(start, stop)
        return Clip(
            name or self.name,
            self.fps,
            self.skeleton,
            self.root_pos[s],
            self.local_rot[s],
            self.positions[s],
            self.loop,
            dict(self.labels),
        )

    def reorder(self, names: list[str]) -> Clip:
        """The same motion with joints in the order ``names`` (e.g. after a BVH round trip)."""
        idx = [self.skeleton.index(n) for n in names]
        return Clip(
            self.name,
            self.fps,
            self.skeleton.reordered(names),
            self.root_pos,
            self.local_rot[:, idx],
            self.positions[:, idx],
            self.loop,
            dict(self.labels),
        )

    def __repr__(self) -> str:
        J = len(self.skeleton)
        return f"Clip({self.name!r}, {self.n_frames} frames @ {self.fps:g} Hz, {J} joints)"


class MotionDataset(Sequence):
    """An ordered collection of clips, indexable by position or by name."""

    def __init__(self, clips: Sequence[Clip]) -> None:
        self.clips = list(clips)
        names = [c.name for c in self.clips]
        if len(set(names)) != len(names):
            raise ValueError(f"clip names must be unique, got {names}")

    def __len__(self) -> int:
        return len(self.clips)

    def __iter__(self) -> Iterator[Clip]:
        return iter(self.clips)

    def __getitem__(self, key: int | str) -> Clip:  # type: ignore[override]
        if isinstance(key, str):
            for c in self.clips:
                if c.name == key:
                    return c
            raise KeyError(f"no clip named {key!r}; clips are {self.names}")
        return self.clips[key]

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.clips]

    @property
    def skeleton(self) -> Skeleton:
        """The skeleton shared by every clip (``ValueError`` if they differ)."""
        sk = self.clips[0].skeleton
        for c in self.clips[1:]:
            if c.skeleton != sk:
                raise ValueError(
                    f"clips {self.clips[0].name!r} and {c.name!r} have different skeletons"
                )
        return sk

    @property
    def n_frames(self) -> int:
        return sum(c.n_frames for c in self.clips)

    def train_test_split(self, test_fraction: float = 0.2) -> tuple[MotionDataset, MotionDataset]:
        """Split every clip in time: the first frames train, the last ``test_fraction`` test.

        Each clip of F frames gives a train clip of its first ``F - round(F * test_fraction)``
        frames and a test clip (same name) of the rest, so no frame is in both. Split clips
        loaded without unrolling (``loop_frames=None``): unrolled loops repeat their cycle.
        """
        if not 0.0 < test_fraction < 1.0:
            raise ValueError(f"test_fraction must be in (0, 1), got {test_fraction}")
        train, test = [], []
        for c in self.clips:
            n_test = min(max(1, round(c.n_frames * test_fraction)), c.n_frames - 1)
            train.append(c.slice(0, c.n_frames - n_test))
            test.append(c.slice(c.n_frames - n_test))
        return MotionDataset(train), MotionDataset(test)

    def __repr__(self) -> str:
        rows = "\n".join(
            f"  {c.name:24s} {c.n_frames:5d} frames @ {c.fps:g} Hz" for c in self.clips
        )
        return f"MotionDataset({len(self)} clips, {self.n_frames} frames)\n{rows}"


# --------------------------------------------------------------------------- resampling


MAX_FRAMES = 1_000_000
"""The most frames a resampled clip may have (about 9 hours at 30 Hz)."""


def _n_samples(duration: float, fps: float) -> int:
    return int(math.floor(duration * fps + 0.01)) + 1


def _interpolate(times: torch.Tensor, root: torch.Tensor, quats: torch.Tensor, t: torch.Tensor):
    """Root ``(K, 3)`` linearly and quaternions ``(K, J, 4)`` by slerp at times ``t (N,)``."""
    if len(times) == 1:
        return root.expand(len(t), 3), quats.expand((len(t),) + quats.shape[1:])
    i = (torch.searchsorted(times, t, right=True) - 1).clamp(0, len(times) - 2)
    span = times[i + 1] - times[i]
    a = torch.where(span > 0, (t - times[i]) / span.clamp_min(1e-12), torch.zeros_like(t))
    a = a.clamp(0.0, 1.0)
    r = root[i] * (1 - a[:, None]) + root[i + 1] * a[:, None]  # (N, 3)
    q = quat_slerp(quats[i], quats[i + 1], a[:, None].expand(-1, quats.shape[1]))  # (N, J, 4)
    return r, q


def resample_clip(clip: Clip, fps: float = 30.0) -> Clip:
    """Resample a clip to ``fps`` (slerp for rotations, linear for the root position).

    Raises:
        InputError: ``fps`` is not a finite number > 0, or the result would hold more than
            :data:`MAX_FRAMES` frames.
    """
    fps = check_number("fps", fps, low=0.0, low_open=True)
    if _n_samples(clip.duration, fps) > MAX_FRAMES:
        raise InputError(
            f"fps must keep clip {clip.name!r} ({clip.duration:g} s) under {MAX_FRAMES} frames, "
            f"got {fps:g}, which would make {_n_samples(clip.duration, fps)}"
        )
    if abs(clip.fps - fps) <= 1e-3 * fps:
        return Clip(
            clip.name,
            fps,
            clip.skeleton,
            clip.root_pos,
            clip.local_rot,
            clip.positions,
            clip.loop,
            dict(clip.labels),
        )
    times = torch.arange(clip.n_frames, dtype=_F64) / clip.fps
    n = _n_samples(clip.duration, fps)
    t = (torch.arange(n, dtype=_F64) / fps).clamp(max=clip.duration)
    r, q = _interpolate(
        times,
        torch.from_numpy(clip.root_pos).to(_F64),
        torch.from_numpy(clip.local_rot).to(_F64),
        t,
    )
    return Clip(
        clip.name,
        fps,
        clip.skeleton,
        r.numpy(),
        q.numpy(),
        loop=clip.loop,
        labels=dict(clip.labels),
    )


# --------------------------------------------------------------------------- DeepMimic


def _yaw_quat(yaw: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(yaw)
    return torch.stack([torch.cos(yaw / 2), z, z, torch.sin(yaw / 2)], -1)


@functools.lru_cache(maxsize=1)
def _humanoid_joints() -> tuple[dict, ...]:
    return tuple(humanoid_urdf_joints())


def _read_deepmimic(path: Path, what: str) -> tuple[dict, torch.Tensor]:
    """A DeepMimic file's JSON and its frames ``(K, 44)``, each checked for its width."""
    try:
        data = json.loads(path.read_text())
        frames = data["Frames"]
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise ValueError(f"{what}: expected DeepMimic JSON with a 'Frames' list ({e})") from None
    for f, row in enumerate(frames):
        if len(row) != _DEEPMIMIC_WIDTH:
            raise ValueError(
                f"{what}: frame {f} has {len(row)} numbers, expected {_DEEPMIMIC_WIDTH}"
            )
    if len(frames) < 1:
        raise ValueError(f"{what}: expected at least one frame")
    return data, torch.tensor(frames, dtype=_F64)


def _frame_durations(a: torch.Tensor, what: str) -> torch.Tensor:
    """The durations ``(K - 1,)`` between frames ``a (K, 44)``, checked with the root position."""
    if not torch.isfinite(a[:, :4]).all():
        f = int((~torch.isfinite(a[:, :4])).any(-1).nonzero()[0])
        raise ValueError(f"{what}: frame {f} has NaN/Inf in its duration or root position")
    dur = a[:-1, 0]
    if (dur <= 0).any():
        raise ValueError(f"{what}: frame {int((dur <= 0).nonzero()[0])} has a duration <= 0")
    return dur


def _deepmimic_rotations(
    a: torch.Tensor, skeleton: Skeleton, urdf: dict[str, dict], what: str
) -> torch.Tensor:
    """Local rotations ``(K, J, 4)`` in skeleton order from frames ``a (K, 44)``, turned z-up."""
    K, J = a.shape[0], len(skeleton)
    q = torch.zeros(K, J, 4, dtype=_F64)
    q[..., 0] = 1.0  # fixed joints (wrists) stay identity
    q[:, 0] = a[:, 4:8]
    col = 8
    for jname in _DEEPMIMIC_ORDER:
        j = skeleton.index(jname)
        if urdf[jname]["type"] == "revolute":  # 1 DoF: an angle about the URDF axis
            axis = torch.tensor(urdf[jname]["axis"], dtype=_F64)
            q[:, j] = axis_angle_to_quat(a[:, col, None] * axis)
            col += 1
        else:
            q[:, j] = a[:, col : col + 4]
            col += 4
    q = torch.from_numpy(_check_quats(q.numpy(), what, skeleton.names))

    # y-up -> z-up: conjugate every rotation by the fixed +90 degree turn about x.
    qm = torch.tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0], dtype=_F64)
    return quat_mul(quat_mul(qm.expand_as(q), q), quat_conjugate(qm).expand_as(q))


def _close_cycle(
    times: torch.Tensor, root: torch.Tensor, q: torch.Tensor, lateral_axis: Sequence[float]
) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Spread a cycle's end-to-start mismatch over it (see :func:`load_deepmimic`).

    Returns the closed rotations ``(K, J, 4)``, root ``(K, 3)`` and the turn ``dh`` (radians)
    of one cycle."""
    K, J = q.shape[:2]
    h = heading_angle(quat_to_matrix(q[[0, -1], 0]), lateral_axis)
    dh = float(wrap_angle(h[1] - h[0]))
    s = (times / float(times[-1]))[:, None]  # (K, 1)
    end = q[0].clone()  # (J, 4) where the last frame should be
    end[0] = quat_mul(_yaw_quat(torch.tensor(dh, dtype=_F64)), q[0, 0])
    delta = quat_mul(quat_conjugate(q[-1]), end)  # (J, 4)
    ident = torch.zeros_like(delta)
    ident[:, 0] = 1.0
    q = quat_mul(q, quat_slerp(ident.expand_as(q), delta.expand_as(q), s.expand(K, J)))
    root = root.clone()
    root[:, 2] += (root[0, 2] - root[-1, 2]) * s[:, 0]
    return q, root, dh


def _unroll_cycles(
    times: torch.Tensor, root: torch.Tensor, q: torch.Tensor, dh: float, n: int, fps: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` frames at ``fps`` of a closed cycle repeated: root ``(n, 3)``, rotations ``(n, J, 4)``.

    Cycle k is sampled at local time t - k * period, then moved by T^k, the planar rigid
    transform (translation and yaw ``dh``) from the cycle's first root to its last."""
    period = float(times[-1])
    t = torch.arange(n, dtype=_F64) / fps
    k = torch.floor(t / period + 1e-9)
    r, qs = _interpolate(times, root, q, (t - k * period).clamp(0.0, period))
    c0, cn = root[0, :2], root[-1, :2]
    n_cycles = int(k.max()) + 1
    centres = [c0]
    Rd = yaw_matrix(torch.tensor(dh, dtype=_F64))[:2, :2]
    for _ in range(n_cycles - 1):
        centres.append(Rd @ (centres[-1] - c0) + cn)
    ck = torch.stack(centres)[k.long()]  # (N, 2)
    Rk = yaw_matrix(k * dh)[:, :2, :2]  # (N, 2, 2)
    r = r.clone()
    r[:, :2] = (Rk @ (r[:, :2] - c0)[..., None])[..., 0] + ck
    qs = qs.clone()
    qs[:, 0] = quat_mul(_yaw_quat(k * dh), qs[:, 0])
    return r, qs


def load_deepmimic(
    path: str | Path,
    fps: float = 30.0,
    loop_frames: int | None = None,
    name: str | None = None,
    skeleton: Skeleton | None = None,
) -> Clip:
    """Load one DeepMimic humanoid clip (JSON, 44 numbers a frame) as a z-up clip at ``fps``.

    Args:
        path: the ``.txt`` file.
        fps: output frame rate; the source rate comes from the per-frame durations.
        loop_frames: for a looping clip (``"Loop": "wrap"``), unroll it to exactly this many
            frames; None keeps one cycle. Non-looping clips are never unrolled.
        name: clip name (default: the file stem without ``humanoid3d_``).
        skeleton: the humanoid (default: :func:`humanoid_skeleton`).

    Unrolling repeats the cycle, each repeat moved by the planar rigid transform (translation
    and yaw) that takes the root of the first frame to the root of the last. The mocap cycles
    do not close exactly (up to ~30 degrees at a joint), so an unrolled clip first spreads each
    joint's mismatch (and the root's height and tilt mismatch) linearly over the cycle: the
    seam is then as smooth as any other frame.
    """
    path = Path(path)
    name = name or path.stem.removeprefix("humanoid3d_")
    what = f"{path.name}"
    data, a = _read_deepmimic(path, what)  # (K, 44)
    skeleton = skeleton or humanoid_skeleton()
    urdf = {j["name"]: j for j in _humanoid_joints()}
    dur = _frame_durations(a, what)  # (K - 1,)
    q = _deepmimic_rotations(a, skeleton, urdf, what)  # (K, J, 4), z-up
    root = a[:, 1:4] @ torch.tensor(Y_UP_TO_Z_UP, dtype=_F64).T  # (K, 3)

    times = torch.cat([torch.zeros(1, dtype=_F64), torch.cumsum(dur, 0)])
    period = float(times[-1])
    loop = data.get("Loop") == "wrap"
    if not (loop and loop_frames is not None):
        t = (torch.arange(_n_samples(period, fps), dtype=_F64) / fps).clamp(max=period)
        r, qs = _interpolate(times, root, q, t)
        return Clip(name, fps, skeleton, r.numpy(), qs.numpy(), loop=loop)
    if loop_frames < 1:
        raise ValueError(f"loop_frames must be >= 1, got {loop_frames}")
    q, root, dh = _close_cycle(times, root, q, skeleton.lateral_axis)
    r, qs = _unroll_cycles(times, root, q, dh, loop_frames, fps)
    return Clip(name, fps, skeleton, r.numpy(), qs.numpy(), loop=True)


def load_clips(
    fps: float = 30.0, loop_frames: int | None = None, names: Sequence[str] | None = None
) -> MotionDataset:
    """The 20 DeepMimic humanoid clips of ``pybullet_data`` (see ``CLIP_NAMES``), z-up, at ``fps``.

    ``loop_frames`` unrolls every looping clip to that many frames (see :func:`load_deepmimic`).
    Needs ``pip install pybullet`` (``minimdm[data]``); raises ``ImportError`` saying so.
    """
    folder = pybullet_data_path() / "data" / "motions"
    skeleton = humanoid_skeleton()
    clips = []
    with num_threads(1):  # many small ops: more threads only add latency
        for n in names or CLIP_NAMES:
            if n not in CLIP_NAMES:
                raise ValueError(f"unknown clip {n!r}; expected one of {CLIP_NAMES}")
            file = folder / (f"{n}.txt" if n.startswith("walker/") else f"humanoid3d_{n}.txt")
            clips.append(load_deepmimic(file, fps, loop_frames, name=n, skeleton=skeleton))
    return MotionDataset(clips)
