"""Motion clips: the DeepMimic humanoid clips of ``pybullet_data``, resampling, BVH both ways.

Axis convention (the one world of minimdm, see :mod:`minimdm.skeleton`): **z up**,
right-handed, metres; a character in its rest pose faces **+x** with **+y on its left**.

* DeepMimic clips and the humanoid URDF are y-up with x forward and z to the character's right.
  They are rotated by +90 degrees about x: ``(x, y, z) -> (x, -z, y)``.
* BVH files are y-up and, by convention, the rest pose faces +Z with +X on its left. They are
  mapped by the cyclic permutation ``(X, Y, Z) -> (Z, X, Y)``; :func:`save_bvh` applies the
  inverse, so a saved clip faces +Z in the file.

A :class:`Clip` stores the root position ``(F, 3)`` and **local joint rotations as unit
quaternions** ``(F, J, 4)``, w-first, relative to the parent joint (the root's is global).
Quaternions are normalised when a clip is made; a zero-norm quaternion or a NaN/Inf raises
``ValueError`` naming the frame. Global joint positions ``(F, J, 3)`` come from forward
kinematics. Everything is resampled to 30 Hz by default: slerp for rotations, linear
interpolation for the root position.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import re
import tempfile
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .skeleton import (
    Y_UP_TO_Z_UP,
    Skeleton,
    axis_angle_to_quat,
    axis_rotation,
    euler_to_matrix,
    forward_kinematics,
    heading_angle,
    humanoid_skeleton,
    humanoid_urdf_joints,
    matrix_to_euler,
    matrix_to_quat,
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
    "BVHError",
    "load_clips",
    "load_deepmimic",
    "resample_clip",
    "load_bvh",
    "save_bvh",
    "CLIP_NAMES",
]

_F64 = torch.float64

# The 20 humanoid clips of pybullet_data/data/motions (the quadruped laikago_walk is left out).
CLIP_NAMES = [
    "backflip", "cartwheel", "crawl", "dance_a", "dance_b", "getup_facedown", "getup_faceup",
    "jump", "kick", "punch", "roll", "run", "spin", "spinkick", "walk",
    "walker/0walk_forward", "walker/turn_left0", "walker/turn_left1", "walker/turn_right0",
    "walker/turn_right1",
]  # fmt: skip

# The joints stored in a DeepMimic frame after duration (1), root position (3), root quat (4).
_DEEPMIMIC_ORDER = [
    "chest", "neck", "right_hip", "right_knee", "right_ankle", "right_shoulder", "right_elbow",
    "left_hip", "left_knee", "left_ankle", "left_shoulder", "left_elbow",
]  # fmt: skip
_DEEPMIMIC_WIDTH = 44

# BVH (X, Y, Z) -> world: X left -> y, Y up -> z, Z forward -> x.
BVH_TO_WORLD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


@contextlib.contextmanager
def _one_thread() -> Iterator[None]:
    """Run torch on one thread: loading does many small ops, where threads only add latency."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


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
            pos, _ = self.fk()
            self.positions = pos.numpy().astype(np.float32)
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
    """Resample a clip to ``fps`` (slerp for rotations, linear for the root position)."""
    if abs(clip.fps - fps) <= 1e-3 * fps:
        return Clip(
            clip.name, fps, clip.skeleton, clip.root_pos, clip.local_rot, clip.positions, clip.loop
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
    return Clip(clip.name, fps, clip.skeleton, r.numpy(), q.numpy(), loop=clip.loop)


# --------------------------------------------------------------------------- DeepMimic


def _yaw_quat(yaw: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(yaw)
    return torch.stack([torch.cos(yaw / 2), z, z, torch.sin(yaw / 2)], -1)


@functools.lru_cache(maxsize=1)
def _humanoid_joints() -> tuple[dict, ...]:
    return tuple(humanoid_urdf_joints())


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
    a = torch.tensor(frames, dtype=_F64)  # (K, 44)
    skeleton = skeleton or humanoid_skeleton()
    urdf = {j["name"]: j for j in _humanoid_joints()}
    K, J = a.shape[0], len(skeleton)
    if not torch.isfinite(a[:, :4]).all():
        f = int((~torch.isfinite(a[:, :4])).any(-1).nonzero()[0])
        raise ValueError(f"{what}: frame {f} has NaN/Inf in its duration or root position")
    dur = a[:-1, 0]
    if (dur <= 0).any():
        raise ValueError(f"{what}: frame {int((dur <= 0).nonzero()[0])} has a duration <= 0")

    # Local rotations in skeleton order, source (y-up) frame.
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
    M = torch.tensor(Y_UP_TO_Z_UP, dtype=_F64)
    qm = torch.tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0], dtype=_F64)
    q = quat_mul(quat_mul(qm.expand_as(q), q), quat_conjugate(qm).expand_as(q))
    root = a[:, 1:4] @ M.T  # (K, 3)

    times = torch.cat([torch.zeros(1, dtype=_F64), torch.cumsum(dur, 0)])
    period = float(times[-1])
    loop = data.get("Loop") == "wrap"
    if not (loop and loop_frames is not None):
        t = (torch.arange(_n_samples(period, fps), dtype=_F64) / fps).clamp(max=period)
        r, qs = _interpolate(times, root, q, t)
        return Clip(name, fps, skeleton, r.numpy(), qs.numpy(), loop=loop)
    if loop_frames < 1:
        raise ValueError(f"loop_frames must be >= 1, got {loop_frames}")

    # Close the cycle: spread the end-to-start mismatch over it (see docstring).
    h = heading_angle(quat_to_matrix(q[[0, -1], 0]), skeleton.lateral_axis)
    dh = float(wrap_angle(h[1] - h[0]))
    s = (times / period)[:, None]  # (K, 1)
    end = q[0].clone()  # (J, 4) where the last frame should be
    end[0] = quat_mul(_yaw_quat(torch.tensor(dh, dtype=_F64)), q[0, 0])
    delta = quat_mul(quat_conjugate(q[-1]), end)  # (J, 4)
    ident = torch.zeros_like(delta)
    ident[:, 0] = 1.0
    q = quat_mul(q, quat_slerp(ident.expand_as(q), delta.expand_as(q), s.expand(K, J)))
    root = root.clone()
    root[:, 2] += (root[0, 2] - root[-1, 2]) * s[:, 0]

    # Sample cycle k at local time t - k * period, then move it by T^k.
    t = torch.arange(loop_frames, dtype=_F64) / fps
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
    with _one_thread():
        for n in names or CLIP_NAMES:
            if n not in CLIP_NAMES:
                raise ValueError(f"unknown clip {n!r}; expected one of {CLIP_NAMES}")
            file = folder / (f"{n}.txt" if n.startswith("walker/") else f"humanoid3d_{n}.txt")
            clips.append(load_deepmimic(file, fps, loop_frames, name=n, skeleton=skeleton))
    return MotionDataset(clips)


# --------------------------------------------------------------------------- BVH


class BVHError(ValueError):
    """A malformed BVH file; the message names the file and line."""


_POS = {"xposition": 0, "yposition": 1, "zposition": 2}
_ROT = {"xrotation": "X", "yrotation": "Y", "zrotation": "Z"}


def _parse_bvh(text: str, src: str):
    """Hierarchy and motion of a BVH file; raises :class:`BVHError` naming the line."""
    lines = text.splitlines()
    toks: list[tuple[str, int]] = []
    motion_line = None
    for ln, line in enumerate(lines, start=1):
        words = line.replace("{", " { ").replace("}", " } ").split()
        if words and words[0].upper() == "MOTION":
            motion_line = ln
            break
        toks += [(w, ln) for w in words]
    pos = 0

    def err(expected: str, tok: tuple[str, int] | None = None) -> BVHError:
        if tok is None:
            at = motion_line or len(lines)
            return BVHError(f"{src}:{at}: expected {expected}, got end of hierarchy")
        return BVHError(f"{src}:{tok[1]}: expected {expected}, got {tok[0]!r}")

    def take(expected: str, check=None) -> tuple[str, int]:
        nonlocal pos
        if pos >= len(toks):
            raise err(expected)
        tok = toks[pos]
        if check is not None and not check(tok[0]):
            raise err(expected, tok)
        pos += 1
        return tok

    def number(expected: str) -> float:
        tok = take(expected)
        try:
            v = float(tok[0])
        except ValueError:
            raise err(expected, tok) from None
        if not math.isfinite(v):
            raise err(expected, tok)
        return v

    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[list[str]] = []

    def joint(parent: int, root: bool) -> None:
        name = take("a joint name", lambda w: w not in "{}")[0]
        j = len(names)
        names.append(name)
        parents.append(parent)
        take("'{'", lambda w: w == "{")
        take("OFFSET", lambda w: w.upper() == "OFFSET")
        offsets.append([number("an OFFSET number") for _ in range(3)])
        chans: list[str] = []
        if pos < len(toks) and toks[pos][0].upper() == "CHANNELS":
            take("CHANNELS")
            tok = take("a channel count", lambda w: w.isdigit())
            for _ in range(int(tok[0])):
                c = take(
                    "a channel name (Xposition ... Zrotation)",
                    lambda w: w.lower() in _POS or w.lower() in _ROT,
                )
                chans.append(c[0].lower())
        elif root:
            raise err("CHANNELS", toks[pos] if pos < len(toks) else None)
        channels.append(chans)
        while True:
            tok = take("JOINT, End Site or '}'")
            key = tok[0].upper()
            if key == "}":
                return
            if key == "JOINT":
                joint(j, False)
            elif key == "END":
                take("Site", lambda w: w.upper() == "SITE")
                take("'{'", lambda w: w == "{")
                take("OFFSET", lambda w: w.upper() == "OFFSET")
                [number("an OFFSET number") for _ in range(3)]  # End Sites are dropped
                take("'}'", lambda w: w == "}")
            else:
                raise err("JOINT, End Site or '}'", tok)

    take("HIERARCHY", lambda w: w.upper() == "HIERARCHY")
    take("ROOT", lambda w: w.upper() == "ROOT")
    joint(-1, True)
    if pos < len(toks):
        raise err("MOTION", toks[pos])
    if motion_line is None:
        raise BVHError(f"{src}:{len(lines)}: expected MOTION, got end of file")

    def header(ln: int, label: str) -> str:
        if ln > len(lines):
            raise BVHError(f"{src}:{ln}: expected '{label} ...', got end of file")
        line = lines[ln - 1].strip()
        if not line.lower().replace(" ", "").startswith(label.lower().replace(" ", "")):
            raise BVHError(f"{src}:{ln}: expected '{label} ...', got {line!r}")
        return line.split(":", 1)[-1].strip()

    value = header(motion_line + 1, "Frames:")
    try:
        n_frames = int(value)
    except ValueError:
        raise BVHError(
            f"{src}:{motion_line + 1}: expected 'Frames: <integer>', got {value!r}"
        ) from None
    value = header(motion_line + 2, "Frame Time:")
    try:
        frame_time = float(value)
    except ValueError:
        raise BVHError(
            f"{src}:{motion_line + 2}: expected 'Frame Time: <seconds>', got {value!r}"
        ) from None
    if not frame_time > 0:
        raise BVHError(f"{src}:{motion_line + 2}: expected a Frame Time > 0, got {frame_time}")
    n_chan = sum(len(c) for c in channels)
    first = motion_line + 3  # 1-based line of the first frame
    rows = [ln.split() for ln in lines[first - 1 : first - 1 + n_frames]]
    if len(rows) < n_frames:
        raise BVHError(
            f"{src}:{len(lines)}: expected {n_frames} frames (as line {motion_line + 1} says), "
            f"got {len(rows)}"
        )
    for i, r in enumerate(rows):
        if len(r) != n_chan:
            raise BVHError(f"{src}:{first + i}: expected {n_chan} channel values, got {len(r)}")
    for i, extra in enumerate(lines[first - 1 + n_frames :]):
        if extra.strip():
            raise BVHError(
                f"{src}:{first + n_frames + i}: expected end of file after {n_frames} frames"
            )
    try:
        motion = np.array(rows, dtype=np.float64).reshape(n_frames, n_chan)
    except ValueError:
        for i, r in enumerate(rows):
            for w in r:
                try:
                    float(w)
                except ValueError:
                    raise BVHError(f"{src}:{first + i}: expected a number, got {w!r}") from None
        raise
    if not np.isfinite(motion).all():
        i = int(np.argwhere(~np.isfinite(motion))[0, 0])
        raise BVHError(f"{src}:{first + i}: frame {i} holds NaN/Inf")
    return names, parents, np.array(offsets), channels, frame_time, motion


def _guess_feet(names: list[str]) -> list[str]:
    for keys in (("foot", "ankle"), ("toe",)):
        found = [n for n in names if any(k in n.lower() for k in keys) and "end" not in n.lower()]
        if found:
            return found
    return []


def _guess_lateral_axis(names: list[str], parents: list[int], rest: np.ndarray) -> tuple:
    """Root-local left axis from the rest pose of a left/right joint pair (e.g. the hips)."""

    def depth(j: int) -> int:
        return 0 if parents[j] < 0 else 1 + depth(parents[j])

    def swap(n: str) -> str | None:
        if re.search("left", n, re.I):
            return re.sub(
                "left", lambda m: "Right" if m.group()[0].isupper() else "right", n, flags=re.I
            )
        if re.match(r"[lL](?=[_A-Z])", n):
            return ("R" if n[0] == "L" else "r") + n[1:]
        return None

    pairs = [(depth(j), j, names.index(swap(n))) for j, n in enumerate(names) if swap(n) in names]
    for _, left, right in sorted(pairs):
        v = rest[left] - rest[right]
        if np.linalg.norm(v) > 1e-6:
            return tuple(v / np.linalg.norm(v))
    return (0.0, 1.0, 0.0)


def _load_one_bvh(path: Path, fps: float | None, scale: float | None, name: str) -> Clip:
    try:
        text = path.read_text()
    except UnicodeDecodeError as e:
        raise BVHError(f"{path}: not a text file ({e})") from None
    names, parents, offsets, channels, frame_time, motion = _parse_bvh(text, str(path))
    F, J = motion.shape[0], len(names)
    if F < 1:
        raise BVHError(f"{path}: expected at least one frame")
    trans = np.broadcast_to(offsets, (F, J, 3)).copy()  # (F, J, 3) local translations
    rot = torch.eye(3, dtype=_F64).repeat(F, J, 1, 1)  # (F, J, 3, 3)
    col = 0
    for j, chans in enumerate(channels):
        order = "".join(_ROT[c] for c in chans if c in _ROT)
        cols = {c: col + i for i, c in enumerate(chans)}
        for c, axis in _POS.items():
            if c in cols:  # position channels replace the offset (as Blender and most tools do)
                trans[:, j, axis] = motion[:, cols[c]]
        if order:
            ang = np.radians(motion[:, [cols[c] for c in chans if c in _ROT]])
            if len(order) == 3 and len(set(order)) == 3:
                rot[:, j] = euler_to_matrix(torch.from_numpy(ang), order)
            else:  # fewer or repeated rotation channels: multiply them in order
                for i, ax in enumerate(order):
                    rot[:, j] = rot[:, j] @ axis_rotation(ax, torch.from_numpy(ang[:, i]))
        col += len(chans)
    for j in range(1, J):
        if np.ptp(trans[:, j], axis=0).max() > 1e-6 * max(1.0, np.abs(trans[:, j]).max()):
            warnings.warn(
                f"{path}: joint {names[j]!r} has animated translation; using frame 0's",
                stacklevel=3,
            )
    off_file = offsets.copy()
    off_file[1:] = trans[0, 1:]
    if scale is None:  # a body is about 1.7 m: pick the power of ten nearest that, at most 1
        rest = Skeleton(names, parents, off_file).rest_positions()
        extent = float(np.ptp(rest, axis=0).max())
        scale = min(1.0, 10.0 ** round(math.log10(1.7 / extent))) if extent > 0 else 1.0
    C = torch.tensor(BVH_TO_WORLD, dtype=_F64)
    world_offsets = off_file @ BVH_TO_WORLD.T * scale
    rest = Skeleton(names, parents, world_offsets).rest_positions()
    skeleton = Skeleton(
        names,
        parents,
        world_offsets,
        foot_joints=_guess_feet(names),
        lateral_axis=_guess_lateral_axis(names, parents, rest),
    )
    root = trans[:, 0] @ BVH_TO_WORLD.T * scale
    quats = matrix_to_quat(C @ rot @ C.T)
    clip = Clip(name, 1.0 / frame_time, skeleton, root, quats.numpy())
    return clip if fps is None else resample_clip(clip, fps)


def load_bvh(
    path: str | Path, fps: float | None = 30.0, scale: float | None = None
) -> Clip | MotionDataset:
    """Load a BVH file as a :class:`Clip`, or every ``*.bvh`` under a folder as a dataset.

    Args:
        path: a ``.bvh`` file or a folder (searched recursively; clip names are the relative
            paths without ``.bvh``).
        fps: resample to this rate (None keeps the file's rate).
        scale: file units -> metres. None guesses from the rest pose: the power of ten (at
            most 1) that brings its largest extent nearest 1.7 m, so centimetre files (LaFAN1,
            100STYLE) get 0.01 and metre files 1.

    The skeleton comes from the file: every ROOT/JOINT becomes a joint (End Sites are dropped),
    with any channel order. Position channels give the joint's translation (replacing its
    OFFSET); only the root's may be animated. The file's y-up frame is turned into the z-up
    world (module docstring). Foot joints are guessed from names containing foot/ankle (else
    toe), the heading axis from a left/right joint pair such as the hips.
    """
    path = Path(path)
    with _one_thread():
        if not path.is_dir():
            return _load_one_bvh(path, fps, scale, path.stem)
        files = sorted(path.rglob("*.bvh"))
        if not files:
            raise FileNotFoundError(f"no .bvh files under {path}")
        names = [f.relative_to(path).with_suffix("").as_posix() for f in files]
        return MotionDataset(
            [_load_one_bvh(f, fps, scale, n) for f, n in zip(files, names, strict=True)]
        )


def save_bvh(path: str | Path, clip: Clip, scale: float = 1.0) -> None:
    """Write ``clip`` as a y-up BVH that Blender imports (root: position + ZYX rotation).

    ``scale`` converts metres to file units (1 writes metres; 100 writes centimetres). Joints
    are written depth first; leaves get an End Site half their bone long. The write is atomic.
    """
    sk = clip.skeleton
    C = torch.tensor(BVH_TO_WORLD, dtype=_F64)
    names = [re.sub(r"\s+", "_", n) for n in sk.names]
    off = sk.offsets @ BVH_TO_WORLD * scale  # world -> BVH: v_bvh = C^T v
    out = ["HIERARCHY"]
    order: list[int] = []

    def write(j: int, depth: int) -> None:
        tab = "\t" * depth
        order.append(j)
        out.append(f"{tab}{'ROOT' if j == 0 else 'JOINT'} {names[j]}")
        out.append(f"{tab}{{")
        out.append(f"{tab}\tOFFSET {off[j, 0]:.6f} {off[j, 1]:.6f} {off[j, 2]:.6f}")
        pos = "Xposition Yposition Zposition " if j == 0 else ""
        out.append(f"{tab}\tCHANNELS {6 if j == 0 else 3} {pos}Zrotation Yrotation Xrotation")
        kids = sk.children(j)
        for c in kids:
            write(c, depth + 1)
        if not kids:
            end = (
                off[j] * 0.5
                if np.linalg.norm(off[j]) > 1e-6
                else np.array([0.0, 0.05 * scale, 0.0])
            )
            end_offset = f"OFFSET {end[0]:.6f} {end[1]:.6f} {end[2]:.6f}"
            out.extend([f"{tab}\tEnd Site", f"{tab}\t{{", f"{tab}\t\t{end_offset}", f"{tab}\t}}"])
        out.append(f"{tab}}}")

    write(0, 0)
    R = quat_to_matrix(torch.from_numpy(clip.local_rot).to(_F64))  # (F, J, 3, 3)
    eul = torch.rad2deg(matrix_to_euler(C.T @ R[:, order] @ C, "ZYX")).numpy()  # (F, J, 3)
    root = clip.root_pos.astype(np.float64) @ BVH_TO_WORLD * scale
    data = np.concatenate([root, eul.reshape(clip.n_frames, -1)], axis=1)
    out += ["MOTION", f"Frames: {clip.n_frames}", f"Frame Time: {1.0 / clip.fps:.8f}"]
    out += [" ".join(f"{v:.6f}" for v in row) for row in data]
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".bvh.tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write("\n".join(out) + "\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
