"""BVH motion files, both ways: :func:`load_bvh` (a file or a folder) and :func:`save_bvh`.

BVH files are y-up and, by convention, the rest pose faces +Z with +X on its left. They are
mapped into the z-up world of minimdm (x forward, y left, see :mod:`minimdm.motion.skeleton`)
by the cyclic permutation ``(X, Y, Z) -> (Z, X, Y)`` (:data:`BVH_TO_WORLD`); :func:`save_bvh`
applies the inverse, so a saved clip faces +Z in the file. Clips come back as
:class:`minimdm.motion.data.Clip`, resampled to 30 Hz by default.

Real files differ in ways the loader absorbs:

* **a root on the floor** (Bandai-Namco's ``joint_Root``, Mixamo's armature) whose only child,
  the hips, carries the path: such a root is folded into the hips (:func:`_fold_root`), so the
  clip's root is the body's and the global path is kept;
* **any channels**: 3 or 6 on any joint, in any order, with any rotation order;
* **any units**: the scale is guessed from the body's standing size (:func:`_guess_scale`);
  ``scale=`` wins;
* **any frame rate** from :data:`MIN_FPS` to :data:`MAX_FPS`, resampled; UTF-8 with or without
  a byte-order mark, or Latin-1.

A malformed file raises :class:`BVHError` naming the file and the line.
"""

from __future__ import annotations

import codecs
import contextlib
import io
import math
import os
import re
import stat
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from minimdm.files import atomic_write
from minimdm.utils import num_threads
from minimdm.validate import InputTypeError, check_number, describe, skeleton_difference

from .data import MAX_FRAMES, Clip, MotionDataset, _n_samples, resample_clip
from .skeleton import (
    Skeleton,
    axis_rotation,
    euler_to_matrix,
    matrix_to_euler,
    matrix_to_quat,
    quat_to_matrix,
)

__all__ = ["BVHError", "load_bvh", "save_bvh", "BVH_TO_WORLD", "MAX_FRAMES"]

_F64 = torch.float64

# BVH (X, Y, Z) -> world: X left -> y, Y up -> z, Z forward -> x.
BVH_TO_WORLD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


class BVHError(ValueError):
    """A malformed BVH file; the message names the file and line."""


_POS = {"xposition": 0, "yposition": 1, "zposition": 2}
_ROT = {"xrotation": "X", "yrotation": "Y", "zrotation": "Z"}


def _tokens(lines: Iterator[tuple[int, str]], src: str) -> tuple[list[tuple[str, int]], int]:
    """The hierarchy's words with their lines, up to the MOTION line (its number returned);
    a hierarchy of more than :data:`MAX_TOKENS` words is refused before it fills memory."""
    toks: list[tuple[str, int]] = []
    for ln, line in lines:
        words = line.replace("{", " { ").replace("}", " } ").split()
        if words and words[0].upper() == "MOTION":
            return toks, ln
        toks += [(w, ln) for w in words]
        if len(toks) > MAX_TOKENS:
            raise BVHError(
                f"{src}:{ln}: expected MOTION within {MAX_TOKENS} words of hierarchy (a "
                f"skeleton of at most {MAX_JOINTS} joints), got more"
            )
    if not toks:
        raise BVHError(f"{src}:1: expected HIERARCHY, got an empty file")
    return toks, -1


class _Words:
    """A cursor over the hierarchy's words (:func:`_tokens`); its errors name the line."""

    def __init__(self, toks: list[tuple[str, int]], src: str, motion_line: int) -> None:
        self.toks, self.src, self.motion_line = toks, src, motion_line
        self.last_line = toks[-1][1] if toks else 1
        self.pos = 0

    def peek(self) -> tuple[str, int] | None:
        """The next word and its line, or None at the end of the hierarchy."""
        return self.toks[self.pos] if self.pos < len(self.toks) else None

    def error(self, expected: str, tok: tuple[str, int] | None = None) -> BVHError:
        """``expected ..., got <tok>`` (or ``got end of hierarchy``), naming the line."""
        if tok is None:
            at = self.motion_line if self.motion_line > 0 else self.last_line
            return BVHError(f"{self.src}:{at}: expected {expected}, got end of hierarchy")
        return BVHError(f"{self.src}:{tok[1]}: expected {expected}, got {tok[0]!r}")

    def take(self, expected: str, check: Callable[[str], bool] | None = None) -> tuple[str, int]:
        """The next word, which must pass ``check``."""
        tok = self.peek()
        if tok is None:
            raise self.error(expected)
        if check is not None and not check(tok[0]):
            raise self.error(expected, tok)
        self.pos += 1
        return tok

    def keyword(self, word: str) -> None:
        """The next word, which must be ``word`` (any case)."""
        self.take(word, lambda w: w.upper() == word.upper())

    def number(self, expected: str) -> float:
        """The next word as a finite number."""
        tok = self.take(expected)
        try:
            v = float(tok[0])
        except ValueError:
            raise self.error(expected, tok) from None
        if not math.isfinite(v):
            raise self.error(expected, tok)
        return v


@dataclass
class _Joints:
    """The joints of a hierarchy, in file order (depth first)."""

    names: list[str] = field(default_factory=list)
    parents: list[int] = field(default_factory=list)
    offsets: list[list[float]] = field(default_factory=list)
    channels: list[list[str]] = field(default_factory=list)
    """Each joint's channel names, lower-cased (``xposition`` ... ``zrotation``)."""


def _is_channel(word: str) -> bool:
    return word.lower() in _POS or word.lower() in _ROT


def _parse_channels(words: _Words, root: bool) -> list[str]:
    """A joint's ``CHANNELS n name...`` (lower-cased); only the root must have one."""
    tok = words.peek()
    if tok is None or tok[0].upper() != "CHANNELS":
        if root:
            raise words.error("CHANNELS", tok)
        return []
    words.take("CHANNELS")
    count = words.take("a channel count", lambda w: w.isdigit())
    expected = "a channel name (Xposition ... Zrotation)"
    return [words.take(expected, _is_channel)[0].lower() for _ in range(int(count[0]))]


def _skip_end_site(words: _Words) -> None:
    """An ``End Site { OFFSET x y z }`` block after its ``End``; End Sites are dropped."""
    words.keyword("Site")
    words.take("'{'", lambda w: w == "{")
    words.keyword("OFFSET")
    for _ in range(3):
        words.number("an OFFSET number")
    words.take("'}'", lambda w: w == "}")


def _parse_joint(words: _Words, joints: _Joints, parent: int, root: bool, depth: int = 0) -> None:
    """A ROOT or JOINT block after its keyword, and its children, into ``joints``."""
    name, ln = words.take("a joint name", lambda w: w not in "{}")
    if len(joints.names) >= MAX_JOINTS or depth >= MAX_DEPTH:
        raise BVHError(
            f"{words.src}:{ln}: expected a skeleton of at most {MAX_JOINTS} joints nested at "
            f"most {MAX_DEPTH} deep, got more"
        )
    if name in joints.names:
        raise BVHError(f"{words.src}:{ln}: joint name {name!r} is used twice; names must be unique")
    j = len(joints.names)
    joints.names.append(name)
    joints.parents.append(parent)
    words.take("'{'", lambda w: w == "{")
    words.keyword("OFFSET")
    joints.offsets.append([words.number("an OFFSET number") for _ in range(3)])
    joints.channels.append(_parse_channels(words, root))
    while True:
        tok = words.take("JOINT, End Site or '}'")
        key = tok[0].upper()
        if key == "}":
            return
        if key == "JOINT":
            _parse_joint(words, joints, j, False, depth + 1)
        elif key == "END":
            _skip_end_site(words)
        else:
            raise words.error("JOINT, End Site or '}'", tok)


def _parse_hierarchy(lines: Iterator[tuple[int, str]], src: str) -> tuple[_Joints, int]:
    """The HIERARCHY section, up to and with the MOTION line, and its last line's number."""
    toks, motion_line = _tokens(lines, src)
    words = _Words(toks, src, motion_line)
    words.keyword("HIERARCHY")
    words.keyword("ROOT")
    joints = _Joints()
    _parse_joint(words, joints, -1, True)
    if words.peek() is not None:
        raise words.error("MOTION", words.peek())
    if motion_line < 0:
        raise BVHError(f"{src}:{words.last_line}: expected MOTION, got end of file")
    return joints, words.last_line


def _header_line(
    lines: Iterator[tuple[int, str]], src: str, last_line: int, label: str
) -> tuple[int, str]:
    """The next line, which must start with ``label``: its number and the text after the colon."""
    ln, line = next(lines, (None, None))
    if ln is None:
        raise BVHError(f"{src}:{last_line + 1}: expected '{label} ...', got end of file")
    line = line.strip()
    if not line.lower().replace(" ", "").startswith(label.lower().replace(" ", "")):
        raise BVHError(f"{src}:{ln}: expected '{label} ...', got {line[:80]!r}")
    return ln, line.split(":", 1)[-1].strip()


class _MotionHeader(NamedTuple):
    """The ``Frames:`` and ``Frame Time:`` lines after MOTION: the line and value of each."""

    frames_line: int
    n_frames: int
    time_line: int
    frame_time: float
    """Seconds."""


def _parse_motion_header(
    lines: Iterator[tuple[int, str]], src: str, last_line: int
) -> _MotionHeader:
    """The motion's header, on the lines after MOTION (the hierarchy ends at ``last_line``)."""
    frames_line, value = _header_line(lines, src, last_line, "Frames:")
    try:
        n_frames = int(value)
    except ValueError:
        raise BVHError(
            f"{src}:{frames_line}: expected 'Frames: <integer>', got {value!r}"
        ) from None
    time_line, value = _header_line(lines, src, last_line, "Frame Time:")
    try:
        frame_time = float(value)
    except ValueError:
        raise BVHError(
            f"{src}:{time_line}: expected 'Frame Time: <seconds>', got {value!r}"
        ) from None
    if not frame_time > 0:
        raise BVHError(f"{src}:{time_line}: expected a Frame Time > 0, got {frame_time}")
    if not MIN_FPS <= 1.0 / frame_time <= MAX_FPS:
        raise BVHError(
            f"{src}: Frame Time {frame_time:g} s means {1.0 / frame_time:.3g} frames per second; "
            f"expected {MIN_FPS:g} to {MAX_FPS:g} (1 / Frame Time)"
        )
    return _MotionHeader(frames_line, n_frames, time_line, frame_time)


def _check_motion_size(
    src: str, header: _MotionHeader, n_chan: int, size: int, fps: float | None
) -> None:
    """Refuse a motion too large to read (:func:`_parse_bvh`) before it is read."""
    frames_line, n_frames, _, frame_time = header
    if n_frames < 1:
        raise BVHError(f"{src}:{frames_line}: expected at least one frame, got {n_frames}")
    too_many = n_frames > MAX_FRAMES or (
        fps is not None and _n_samples((n_frames - 1) * frame_time, fps) > MAX_FRAMES
    )
    if too_many:
        at = "" if fps is None else f" resampled to {fps:g} Hz"
        raise BVHError(
            f"{src}:{frames_line}: {n_frames} frames of {frame_time:g} s{at} would make more "
            f"than {MAX_FRAMES} frames"
        )
    if n_frames * n_chan > MAX_VALUES:
        raise BVHError(
            f"{src}:{frames_line}: {n_frames} frames of {n_chan} channels are "
            f"{n_frames * n_chan} numbers, more than the {MAX_VALUES} this loader reads from one "
            "file; split the take"
        )
    if 2 * n_frames * n_chan > size:  # a number takes at least a digit and a separator
        raise BVHError(
            f"{src}:{frames_line}: expected {n_frames} frames (as line {frames_line} says) of "
            f"{n_chan} numbers, but the file's {size} bytes cannot hold them"
        )


def _read_frames(
    lines: Iterator[tuple[int, str]], src: str, header: _MotionHeader, n_chan: int
) -> np.ndarray:
    """The motion ``(n_frames, n_chan)`` after its header, then nothing but blank lines."""
    frames_line, n_frames, time_line, _ = header
    first = time_line + 1  # the line of the first frame
    motion = np.empty((n_frames, n_chan))
    for i in range(n_frames):
        ln, line = next(lines, (None, None))
        if ln is None:
            raise BVHError(
                f"{src}:{first + i - 1}: expected {n_frames} frames (as line {frames_line} "
                f"says), got {i}"
            )
        words = line.split()
        if len(words) != n_chan:
            raise BVHError(f"{src}:{ln}: expected {n_chan} channel values, got {len(words)}")
        try:
            motion[i] = [float(w) for w in words]
        except ValueError:
            bad = next(w for w in words if not _is_float(w))
            raise BVHError(f"{src}:{ln}: expected a number, got {bad!r}") from None
        if not np.isfinite(motion[i]).all():
            raise BVHError(f"{src}:{ln}: frame {i} holds NaN/Inf")
    for ln, extra in lines:
        if extra.strip():
            raise BVHError(f"{src}:{ln}: expected end of file after {n_frames} frames")
    return motion


def _parse_bvh(lines: Iterator[tuple[int, str]], src: str, size: int, fps: float | None):
    """Hierarchy and motion of a BVH file's numbered lines (``size`` bytes); raises
    :class:`BVHError` naming the line.

    The motion is read line by line into one array allocated once the header has said its
    size, and that size is checked first: at most :data:`MAX_FRAMES` frames (also after
    resampling to ``fps``), :data:`MAX_VALUES` numbers, and no more than the file's bytes can
    hold. So memory stays a small multiple of the file, and a file that is too large is refused
    before it is parsed."""
    joints, last_line = _parse_hierarchy(lines, src)
    header = _parse_motion_header(lines, src, last_line)
    n_chan = sum(len(c) for c in joints.channels)
    _check_motion_size(src, header, n_chan, size, fps)
    motion = _read_frames(lines, src, header, n_chan)
    offsets = np.array(joints.offsets)
    return joints.names, joints.parents, offsets, joints.channels, header.frame_time, motion


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
        if re.search(r"[_.][lL]$", n):  # Bandai-Namco's UpperLeg_L, Blender's thigh.L
            return n[:-1] + ("R" if n[-1] == "L" else "r")
        return None

    pairs = [(depth(j), j, names.index(swap(n))) for j, n in enumerate(names) if swap(n) in names]
    for _, left, right in sorted(pairs):
        v = rest[left] - rest[right]
        if np.linalg.norm(v) > 1e-6:
            return tuple(v / np.linalg.norm(v))
    return (0.0, 1.0, 0.0)


MIN_FPS, MAX_FPS = 1.0, 1000.0
"""Frame rates a BVH file may declare (``1 / Frame Time``); outside them the file is refused."""
HUMAN_EXTENT = (1.2, 2.0)
"""Metres: the typical vertical extent of a standing human's joints (ankles to head joint)."""


_BLOCK = 4096
"""Frames converted at a time after parsing (bounds the temporaries of long takes)."""
MAX_BVH_BYTES = 1 << 30
"""The largest BVH file :func:`load_bvh` reads (1 GiB)."""
MAX_VALUES = 1 << 26
"""The most numbers one file's motion may hold (frames x channels; 512 MB as float64)."""
MAX_JOINTS, MAX_DEPTH = 1024, 256
"""The most joints a skeleton may have, and how deep they may nest."""
MAX_TOKENS = 64 * MAX_JOINTS
"""The most words a hierarchy may hold (a joint takes about 15)."""


def _is_float(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


@contextlib.contextmanager
def _numbered_lines(path: Path) -> Iterator[tuple[Iterator[tuple[int, str]], int]]:
    """The file's lines, numbered from 1, read as they are parsed, and its size in bytes.

    Only a regular file is read: a device (``/dev/zero``), a FIFO or a socket, also behind a
    ``.bvh`` symlink, is refused without reading a byte (opening does not block on a FIFO), and
    so is a file larger than :data:`MAX_BVH_BYTES`. The text is UTF-8 (a byte-order mark is
    dropped), else Latin-1 (old exporters)."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            what = "a folder" if stat.S_ISDIR(st.st_mode) else "a device, FIFO or socket"
            raise BVHError(f"{path}: not a regular file ({what}); expected a BVH text file")
        if st.st_size > MAX_BVH_BYTES:
            raise BVHError(
                f"{path}: {st.st_size} bytes, more than the {MAX_BVH_BYTES} bytes this loader "
                "reads from one file; split the take"
            )
        f = os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
    size = st.st_size
    with f:
        if b"\x00" in f.read(4096):
            raise BVHError(f"{path}: not a text file (it holds NUL bytes)")
        f.seek(0)
        decoder = codecs.getincrementaldecoder("utf-8")()
        encoding = "utf-8-sig"
        try:  # decided before parsing, block by block, so that nothing is parsed twice
            for block in iter(lambda: f.read(1 << 20), b""):
                decoder.decode(block)
            decoder.decode(b"", final=True)
        except UnicodeDecodeError:
            encoding = "latin-1"
        f.seek(0)
        text = io.TextIOWrapper(f, encoding=encoding, newline=None)
        try:
            yield enumerate((line.rstrip("\n") for line in text), start=1), size
        finally:
            text.detach()


def _local_transforms(channels, offsets, motion) -> tuple[np.ndarray, torch.Tensor]:
    """Per-frame local translations (F, J, 3) and rotations (F, J, 3, 3), file units and axes."""
    F, J = motion.shape[0], len(channels)
    trans = np.broadcast_to(offsets, (F, J, 3)).copy()  # (F, J, 3)
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
    return trans, rot


def _fold_root(names, parents, channels, trans, rot):
    """Fold a root whose one child has position channels into that child (lossless).

    Some exporters (Bandai-Namco, Mixamo) put a ``joint_Root`` on the floor and let its child,
    the hips, carry the body's path; in some Bandai-Namco takes the path is even split between
    the two. The clip's root must be the hips: its position is the character's path. Composing
    the root's transform into its only child, frame by frame, keeps every other joint exactly
    where the file puts it. One level is folded, so that every take of a skeleton, a one-frame
    take included, comes out with the same joints.
    """
    kept = list(range(len(names)))  # the file's joint index of each joint left
    child = parents.index(0) if parents.count(0) == 1 else None
    has_pos = child is not None and any(c in _POS for c in channels[child])
    if len(names) > 1 and has_pos:
        c = child  # BVH lists joints depth first: the root's one child is joint 1
        R0, t0 = rot[:, 0], torch.from_numpy(trans[:, 0])  # (F, 3, 3), (F, 3)
        tc = (R0 @ torch.from_numpy(trans[:, c])[..., None])[..., 0] + t0
        rot[:, c] = R0 @ rot[:, c]
        trans[:, c] = tc.numpy()
        keep = [j for j in range(len(names)) if j != 0]
        remap = {old: new for new, old in enumerate(keep)}
        names = [names[j] for j in keep]
        parents = [remap[parents[j]] if parents[j] > 0 else -1 for j in keep]
        trans, rot, kept = trans[:, keep], rot[:, keep], [kept[j] for j in keep]
    return names, parents, trans, rot, kept


def _standing_extent(names, parents, trans, rot) -> float:
    """Median over frames of the joints' vertical (file Y) extent, in file units."""
    F = trans.shape[0]
    idx = np.linspace(0, F - 1, min(F, 64)).round().astype(int)  # a sample of frames is enough
    sk = Skeleton(names, parents, np.zeros((len(names), 3)))
    pos = np.zeros((len(idx), len(names), 3))
    glob = [None] * len(names)
    R, t = rot[idx].numpy(), trans[idx]
    for j, p in enumerate(sk.parents):
        if p < 0:
            glob[j] = R[:, j]
            pos[:, j] = t[:, j]
        else:
            glob[j] = glob[p] @ R[:, j]
            pos[:, j] = pos[:, p] + (glob[p] @ t[:, j][..., None])[..., 0]
    return float(np.median(np.ptp(pos[..., 1], axis=1)))


def _guess_scale(path: Path, extent: float) -> float:
    """File units -> metres from the body's standing extent (:data:`HUMAN_EXTENT`).

    A power of ten is preferred (centimetres, millimetres, metres, decimetres) when it makes
    the body a human's size; other units (inches, CMU's) are scaled to the middle of the range.
    """
    lo, hi = HUMAN_EXTENT
    if not math.isfinite(extent) or extent <= 0:
        raise BVHError(
            f"{path}: cannot guess the units: the joints have no vertical extent (all offsets "
            "zero?); pass scale= (file units -> metres, e.g. 0.01 for centimetres)"
        )
    for s in (1.0, 0.01, 0.1, 0.001):
        if lo <= extent * s <= hi:
            return s
    s = 0.5 * (lo + hi) / extent
    if not 1e-5 <= s <= 1e3:
        raise BVHError(
            f"{path}: cannot guess the units: the body's vertical extent is {extent:.3g} file "
            f"units, which would need a scale of {s:.3g}; pass scale= (file units -> metres)"
        )
    return s


def _first_difference(a: Skeleton, b: Skeleton) -> str:
    """The first joint where two skeletons' names or parents differ, in words."""
    return skeleton_difference(a.names, a.parents, b.names, b.parents) or "no difference"


def _load_one_bvh(
    path: Path, fps: float | None, scale: float | None, name: str
) -> tuple[Clip, float]:
    """The clip of one file and the scale it used (given or guessed)."""
    with _numbered_lines(path) as (lines, size):
        parsed = _parse_bvh(lines, str(path), size, fps)
    names, parents, offsets, channels, frame_time, motion = parsed
    trans, rot = _local_transforms(channels, offsets, motion)
    del parsed, motion  # long takes: only what is still needed stays in memory
    names, parents, trans, rot, kept = _fold_root(names, parents, channels, trans, rot)
    J = len(names)
    for j in range(1, J):
        dev = np.abs(trans[:, j] - trans[:1, j]).max()
        if dev > 1e-6 * max(1.0, np.abs(trans[:, j]).max()):
            warnings.warn(
                f"{path}: joint {names[j]!r} has animated translation (it moves up to {dev:.3g} "
                "file units from frame 0); only the root's translation is kept, frame 0's is "
                "used for the others",
                stacklevel=3,
            )
    if scale is None:
        scale = _guess_scale(path, _standing_extent(names, parents, trans, rot))
    C = torch.tensor(BVH_TO_WORLD, dtype=_F64)
    world_offsets = trans[0] @ BVH_TO_WORLD.T * scale
    world_offsets[0] = offsets[kept[0]] @ BVH_TO_WORLD.T * scale  # the file's rest offset
    rest = Skeleton(names, parents, world_offsets).rest_positions()
    skeleton = Skeleton(
        names,
        parents,
        world_offsets,
        foot_joints=_guess_feet(names),
        lateral_axis=_guess_lateral_axis(names, parents, rest),
    )
    root = trans[:, 0] @ BVH_TO_WORLD.T * scale
    # frame by frame, in blocks: the conversion's temporaries stay small for long takes
    quats = torch.cat([matrix_to_quat(C @ r @ C.T) for r in rot.split(_BLOCK)]).numpy()
    del rot, trans
    clip = Clip(name, 1.0 / frame_time, skeleton, root, quats)
    return (clip if fps is None else resample_clip(clip, fps)), float(scale)


def load_bvh(
    path: str | Path, fps: float | None = 30.0, scale: float | None = None
) -> Clip | MotionDataset:
    """Load a BVH file as a :class:`Clip`, or every ``*.bvh`` under a folder as a dataset.

    Args:
        path: a ``.bvh`` file or a folder (searched recursively; clip names are the relative
            paths without ``.bvh``).
        fps: resample to this rate (None keeps the file's rate).
        scale: file units -> metres. None guesses it from the body's standing height
            (:func:`_guess_scale`); in a folder, every file takes the guess most of its files
            agree on (a crouched or leaning take alone would look short).

    The skeleton comes from the file: every ROOT/JOINT becomes a joint (End Sites are dropped),
    with any channel order. Position channels give the joint's translation (replacing its
    OFFSET); only the root's may be animated. The file's y-up frame is turned into the z-up
    world (module docstring). Foot joints are guessed from names containing foot/ankle (else
    toe), the heading axis from a left/right joint pair such as the hips.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise InputTypeError(f"path must be a .bvh file or a folder, got {describe(path)}")
    path = Path(path)
    if fps is not None:
        fps = check_number("fps", fps, low=MIN_FPS, high=MAX_FPS)
    if scale is not None:  # file units -> metres
        scale = check_number("scale", scale, low=0.0, low_open=True)
    if not path.exists():
        raise FileNotFoundError(f"no BVH file or folder at {path}")
    with num_threads(1):  # many small ops: threads only add latency
        if not path.is_dir():
            return _load_one_bvh(path, fps, scale, path.stem)[0]
        files = sorted(path.rglob("*.bvh"))
        if not files:
            raise FileNotFoundError(f"no .bvh files under {path}")
        names = [f.relative_to(path).with_suffix("").as_posix() for f in files]
        loaded = [_load_one_bvh(f, fps, scale, n) for f, n in zip(files, names, strict=True)]
        clips = [c for c, _ in loaded]
        if scale is None:  # one folder, one unit: the guess most files agree on
            scales = [s for _, s in loaded]
            common = max(set(scales), key=scales.count)
            clips = [
                c if s == common else _load_one_bvh(f, fps, common, c.name)[0]
                for f, c, s in zip(files, clips, scales, strict=True)
            ]
        first = clips[0].skeleton
        for f, c in zip(files[1:], clips[1:], strict=True):
            sk = c.skeleton
            if (sk.names, list(sk.parents)) != (first.names, list(first.parents)):
                diff = _first_difference(first, sk)
                raise BVHError(
                    f"{path}: the files hold different skeletons, e.g. {files[0].name} and "
                    f"{f.name} ({diff}); a folder must hold one skeleton (bone lengths may differ)"
                )
        return MotionDataset(clips)


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
    atomic_write(path, "\n".join(out) + "\n")
