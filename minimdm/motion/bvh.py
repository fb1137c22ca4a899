"""BVH motion files, both ways: :func:`load_bvh` (a file or a folder) and :func:`save_bvh`.

BVH files are y-up and, by convention, the rest pose faces +Z with +X on its left. They are
mapped into the z-up world of minimdm (x forward, y left, see :mod:`minimdm.motion.skeleton`) by the
cyclic permutation ``(X, Y, Z) -> (Z, X, Y)`` (:data:`BVH_TO_WORLD`); :func:`save_bvh` applies
the inverse, so a saved clip faces +Z in the file. Clips come back as
:class:`minimdm.motion.data.Clip`
(resampled to 30 Hz by default); :mod:`minimdm.motion.data` re-exports ``BVHError``, ``load_bvh``
and
``save_bvh``.
"""

from __future__ import annotations

import math
import os
import re
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch

from minimdm.utils import num_threads

from .data import Clip, MotionDataset, resample_clip
from .skeleton import (
    Skeleton,
    axis_rotation,
    euler_to_matrix,
    matrix_to_euler,
    matrix_to_quat,
    quat_to_matrix,
)

__all__ = ["BVHError", "load_bvh", "save_bvh", "BVH_TO_WORLD"]

_F64 = torch.float64

# BVH (X, Y, Z) -> world: X left -> y, Y up -> z, Z forward -> x.
BVH_TO_WORLD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


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
    with num_threads(1):
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
