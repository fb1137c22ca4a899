"""The motion payload of the 3D player: checked input, quantised positions, JSON for the page.

:func:`build_payload` checks everything :func:`minimdm.viz.player` is given and turns it into
one JSON-ready dict, so that bad input raises :class:`~minimdm.validate.InputError` (a
``ValueError``) naming the argument *before* any HTML is written. :func:`decode_positions` is its
inverse for the positions; the tests use it, and ``player.js`` does the same in the page.

Positions are stored compactly. Per motion and axis, ``lo`` and ``step`` map the range onto
int16 codes: ``q = round((x - lo) / step) - 32767`` with ``step = max((max - lo) / 65534,
1 mm)``, so the error is at most ``step / 2`` (0.5 mm; a finer step only feeds gzip noise). The
codes are laid out channel by channel ``(J * 3, T)``, differenced along time (wrapping in int16),
split into a plane of low bytes then a plane of high bytes, gzipped and base64-encoded: smooth
motion makes small differences, which gzip packs to about 3 bytes per joint and frame.

Coordinates stay in minimdm's z-up world (metres); the page turns them into three.js's y-up.
"""

from __future__ import annotations

import base64
import gzip
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from matplotlib.colors import to_hex

from ..motion.skeleton import Skeleton, forward_kinematics
from ..validate import InputError, check_choice, check_number, describe
from .scene import PALETTE, _rgb, _to_numpy

__all__ = ["PAYLOAD_VERSION", "build_payload", "decode_positions", "decode_contacts"]

PAYLOAD_VERSION = 1
"""Bumped when the payload's layout changes; ``player.js`` refuses other versions."""

_Q = 32767  # int16 codes run over [-_Q, _Q]
MIN_STEP = 1e-3  # metres per code at least: the quantisation error is at most half of it
LANE_GAP = 0.6  # metres between the lanes of side-by-side characters
CONTACT_HEIGHT = 0.025  # a foot within 2.5 cm of its resting height ...
CONTACT_SPEED = 0.6  # ... and slower than 0.6 m/s is on the ground (detected contacts)


# --------------------------------------------------------------------------- encoding


def _b64gz(raw: bytes) -> str:
    return base64.b64encode(gzip.compress(raw, compresslevel=9, mtime=0)).decode("ascii")


def _unb64gz(text: str) -> bytes:
    return gzip.decompress(base64.b64decode(text))


def _quantise(x: np.ndarray) -> dict[str, Any]:
    """(T, J, 3) positions -> ``{"n", "lo", "step", "data"}`` (see the module docstring)."""
    T, J, _ = x.shape
    lo = x.min(axis=(0, 1))
    step = np.maximum((x.max(axis=(0, 1)) - lo) / (2 * _Q), MIN_STEP)  # metres per code, (3,)
    q = (np.rint((x - lo) / step) - _Q).astype(np.int64)  # (T, J, 3) in [-_Q, _Q]
    q = q.reshape(T, J * 3).T  # (J * 3, T): one channel's time series is contiguous
    d = np.diff(q, axis=1, prepend=0)  # first column is the value itself
    d16 = ((d + 32768) % 65536 - 32768).astype("<i2")  # wrap into int16
    planes = np.frombuffer(d16.tobytes(), np.uint8).reshape(-1, 2).T  # (2, C * T): low, high
    return {
        "n": int(T),
        "lo": [float(v) for v in lo],
        "step": [float(v) for v in step],
        "data": _b64gz(planes.tobytes()),
    }


def decode_positions(motion: dict[str, Any], n_joints: int) -> np.ndarray:
    """Positions ``(T, J, 3)`` from one entry of ``payload["motions"]`` (what player.js does)."""
    T = int(motion["n"])
    raw = np.frombuffer(_unb64gz(motion["data"]), dtype=np.uint8)
    if raw.size != 2 * T * n_joints * 3:
        raise InputError(
            f"motion data must hold T * J * 3 = {T * n_joints * 3} int16 values, got "
            f"{raw.size / 2:g}"
        )
    d = np.frombuffer(raw.reshape(2, -1).T.tobytes(), dtype="<i2").astype(np.int64)
    q = np.cumsum(d.reshape(n_joints * 3, T), axis=1)
    q = (q + 32768) % 65536 - 32768  # int16 wrap-around, as in the page
    x = q.T.reshape(T, n_joints, 3) + _Q
    return x * np.asarray(motion["step"]) + np.asarray(motion["lo"])


def decode_contacts(motion: dict[str, Any], n_feet: int) -> np.ndarray:
    """Contacts ``(T, n_feet)`` bool from one entry of ``payload["motions"]``."""
    bits = np.frombuffer(_unb64gz(motion["contacts"]), dtype=np.uint8)
    return (bits[:, None] >> np.arange(n_feet)) & 1 == 1


# --------------------------------------------------------------------------- input checks


def _array(name: str, value: Any) -> np.ndarray:
    try:
        x = _to_numpy(value)
    except (TypeError, ValueError) as e:
        raise InputError(f"{name} must be an array of numbers, got {describe(value)}") from e
    return x


def _finite(name: str, x: np.ndarray) -> np.ndarray:
    if not np.isfinite(x).all():
        where = tuple(int(i) for i in np.argwhere(~np.isfinite(x))[0])
        frame = f" (frame {where[0]})" if x.ndim == 3 else ""
        raise InputError(f"{name} must be finite, but {name}{list(where)} is {x[where]}{frame}")
    return x


def _is_rotations(item: Any) -> bool:
    """``(root_pos (T, 3), local_rot (T, J, 4) or (T, J, 3, 3))``: motion given for FK."""
    if not (isinstance(item, tuple) and len(item) == 2):
        return False
    shapes = [getattr(_to_numpy(v), "ndim", 0) for v in item]
    return shapes[0] == 2 and shapes[1] in (3, 4)


def _motion_items(motions: Any) -> list[Any]:
    if isinstance(motions, list) or (isinstance(motions, tuple) and not _is_rotations(motions)):
        return list(motions)
    if hasattr(motions, "positions") and hasattr(motions, "skeleton"):  # a Clip
        return [motions]
    if _is_rotations(motions):
        return [motions]
    x = _array("motions", motions)
    return list(x) if x.ndim == 4 else [x]


def _positions(name: str, item: Any, skeleton: Any) -> np.ndarray:
    """One motion as (T, J, 3) float64 positions, from positions, a Clip or (root, rotations)."""
    if hasattr(item, "positions") and hasattr(item, "skeleton"):  # a minimdm Clip
        item = item.positions
    elif _is_rotations(item):
        if not isinstance(skeleton, Skeleton):
            raise InputError(
                f"{name} is (root_pos, local_rot): skeleton must then be a minimdm Skeleton "
                f"(its offsets are needed for forward kinematics), got {describe(skeleton)}"
            )
        root, rot = (torch.as_tensor(_finite(name, _array(name, v))) for v in item)
        try:
            item = forward_kinematics(skeleton, root, rot)[0]
        except ValueError as e:
            raise InputError(f"{name}: {e}") from None
    x = _array(name, item)
    if x.ndim != 3 or x.shape[-1] != 3:
        raise InputError(
            f"{name} must have shape (T, J, 3) (frames, joints, xyz), got {tuple(x.shape)}"
        )
    if x.shape[0] == 0:
        raise InputError(f"{name} must hold at least one frame, got shape {tuple(x.shape)}")
    if x.shape[1] == 0:
        raise InputError(f"{name} must hold at least one joint, got shape {tuple(x.shape)}")
    return _finite(name, x)


def _parents(skeleton: Any, J: int) -> tuple[list[int], list[str] | None]:
    par = getattr(skeleton, "parents", skeleton)
    names = getattr(skeleton, "names", None)
    try:
        par = [int(p) for p in _array("skeleton", par).reshape(-1)]
    except (TypeError, ValueError) as e:
        raise InputError(
            f"skeleton must be a Skeleton or a list of parent indices, got {describe(skeleton)}"
        ) from e
    if len(par) != J:
        raise InputError(
            f"skeleton's parents list must have one entry per joint: the motions have J = {J} "
            f"joints, the parents list has {len(par)}"
        )
    for j, p in enumerate(par):
        if not -1 <= p < j:
            raise InputError(
                f"skeleton's parents[{j}] must be -1 (a root) or a joint before it, in [0, {j}), "
                f"got {p}"
            )
    names = [str(n) for n in names] if names is not None and len(names) == J else None
    return par, names


def _ndim(value: Any) -> int:
    try:
        return _to_numpy(value).ndim
    except (TypeError, ValueError):  # ragged or not numbers
        return -1


def _per_motion(name: str, value: Any, n: int, item_ndim: int) -> list[tuple[int, Any]]:
    """``value`` for every character (index -1), or a list with one entry (or None) per motion.

    A list or tuple of ``n`` entries, each None, a dict, a ``(frames, poses)`` pair or an array
    of at least ``item_ndim`` dimensions, is per motion; anything else is for all characters.
    """
    if value is None:
        return []
    if isinstance(value, (list, tuple)) and len(value) == n and any(v is not None for v in value):
        per = all(
            v is None
            or isinstance(v, dict)
            or (name == "keyframes" and isinstance(v, tuple) and len(v) == 2)
            or _ndim(v) >= item_ndim
            for v in value
        )
        if per:
            return [(i, v) for i, v in enumerate(value) if v is not None]
    return [(-1, value)]


def _points(name: str, value: Any) -> np.ndarray:
    """(K, 2) ground points or (K, 3) points -> (K, 3) finite."""
    x = _array(name, value)
    if x.ndim == 1 and x.shape[0] in (2, 3):
        x = x[None]
    if x.ndim != 2 or x.shape[-1] not in (2, 3) or len(x) == 0:
        raise InputError(f"{name} must have shape (K, 2) or (K, 3), got {tuple(x.shape)}")
    if x.shape[-1] == 2:
        x = np.concatenate([x, np.zeros((len(x), 1))], axis=1)  # on the ground
    return _finite(name, x)


def _keyframes(name: str, value: Any, J: int, T: int) -> dict[str, Any]:
    if isinstance(value, dict):
        frames, poses = value.get("frames"), value.get("poses")
    elif isinstance(value, tuple) and len(value) == 2:
        frames, poses = value
    else:
        frames, poses = None, value
    x = _array(f"{name} poses", poses)
    if x.ndim == 2:
        x = x[None]
    if x.ndim != 3 or x.shape[1:] != (J, 3) or len(x) == 0:
        raise InputError(
            f"{name} must be poses of shape (K, {J}, 3) with K >= 1, got {tuple(x.shape)}"
        )
    _finite(name, x)
    out: dict[str, Any] = {"poses": np.round(x, 4).reshape(len(x), -1).tolist()}
    if frames is not None:
        f = [int(v) for v in np.asarray(frames).reshape(-1)]
        if len(f) != len(x):
            raise InputError(f"{name} has {len(x)} poses but {len(f)} frames")
        bad = [v for v in f if not 0 <= v < T]
        if bad:
            raise InputError(f"{name} frames must lie in [0, {T}) (the horizon), got {bad}")
        out["frames"] = f
    return out


def _feet(feet: Any, skeleton: Any, names: list[str] | None, J: int) -> list[int]:
    if feet is None:
        feet = list(getattr(skeleton, "foot_joints", []) or [])
    if feet is False:
        return []
    out = []
    for f in list(feet):
        if isinstance(f, str):
            if names is None or f not in names:
                raise InputError(f"feet names joint {f!r}, but the skeleton's joints are {names}")
            out.append(names.index(f))
        elif not (isinstance(f, (int, np.integer)) and 0 <= int(f) < J):
            raise InputError(f"feet must be joint names or indices in [0, {J}), got {f!r}")
        else:
            out.append(int(f))
    if len(out) > 8:
        raise InputError(f"feet may name at most 8 joints, got {len(out)}")
    return out


def detect_contacts(x: np.ndarray, feet: Sequence[int], fps: float) -> np.ndarray:
    """(T, n_feet) bool: the foot is within 2.5 cm of its resting height and slower than
    0.6 m/s. The resting height is the 5 % quantile of the foot's height over the motion."""
    z = x[:, feet, 2]  # (T, N)
    rest = np.quantile(z, 0.05, axis=0)
    v = np.diff(x[:, feet, :2], axis=0, prepend=x[:1, feet, :2])
    speed = np.linalg.norm(v, axis=-1) * fps
    return (z - rest < CONTACT_HEIGHT) & (speed < CONTACT_SPEED)


def _lane_offsets(ms: list[np.ndarray]) -> tuple[list[list[float]], int]:
    """Side by side: one lane per character, in order, across the ground axis (0: x, 1: y)
    that the motions travel least along, :data:`LANE_GAP` apart; the lanes are centred on 0."""
    lo = np.stack([m[..., :2].min(axis=(0, 1)) for m in ms])  # (n, 2)
    hi = np.stack([m[..., :2].max(axis=(0, 1)) for m in ms])
    axis = int(np.argmin((hi - lo).max(axis=0)))
    widths = hi[:, axis] - lo[:, axis]
    starts = np.concatenate([[0.0], np.cumsum(widths + LANE_GAP)[:-1]])
    centres = starts + widths / 2 - (widths.sum() + LANE_GAP * (len(ms) - 1)) / 2
    offsets = np.zeros((len(ms), 3))
    offsets[:, axis] = centres - (lo[:, axis] + hi[:, axis]) / 2
    return (np.round(offsets, 4) + 0.0).tolist(), axis


# --------------------------------------------------------------------------- the payload


def _check_labels(labels: Sequence[str] | None, n: int) -> None:
    if labels is not None:
        if isinstance(labels, str) or len(labels) != n:
            raise InputError(f"labels must hold one label per motion ({n}), got {labels!r}")


def _hex_colors(colors: Any, n: int) -> list[str]:
    """One ``#rrggbb`` per motion: the palette in order, one colour for all, or one each."""
    if colors is None:
        cols = [PALETTE[i % len(PALETTE)] for i in range(n)]
    elif isinstance(colors, str) or (
        len(colors) in (3, 4) and all(isinstance(c, (int, float)) for c in colors)
    ):
        cols = [colors] * n
    elif len(colors) != n:
        raise InputError(f"colors must hold one colour per motion ({n}), got {len(colors)}")
    else:
        cols = list(colors)
    try:
        return [to_hex(_rgb(c)) for c in cols]
    except ValueError as e:
        raise InputError(f"colors must be matplotlib colours, got {colors!r}: {e}") from None


def _given_contacts(contacts: Any, foot: list[int], n: int) -> dict[int, Any]:
    """The contact flags given for each motion, by motion index (none: all detected)."""
    if contacts is not None and not foot:
        raise InputError("contacts needs feet: name the foot joints the flags belong to")
    contact_list = _per_motion("contacts", contacts, n, 2) if contacts is not None else []
    if contacts is not None and contact_list and contact_list[0][0] == -1 and n > 1:
        raise InputError(f"contacts must be a list of one (T, n_feet) array per motion ({n})")
    return {i if i >= 0 else 0: c for i, c in contact_list}


def _contact_bits(i: int, x: np.ndarray, foot: list[int], given: dict[int, Any], fps: float) -> str:
    """Motion ``i``'s foot contacts ``(T, n_feet)``, given or detected, as one byte per frame
    (bit k: foot k down), gzipped and base64-encoded."""
    if i in given:
        c = np.asarray(_to_numpy(given[i]))
        if c.shape != (len(x), len(foot)):
            raise InputError(
                f"contacts[{i}] must have shape (T, n_feet) = ({len(x)}, {len(foot)}), "
                f"got {tuple(c.shape)}"
            )
        c = c.astype(bool)
    else:
        c = detect_contacts(x, foot, fps)
    bits = (c.astype(np.uint8) << np.arange(len(foot), dtype=np.uint8)).sum(axis=1)
    return _b64gz(bits.astype(np.uint8).tobytes())


def _shapes(targets: Any, paths: Any, keyframes: Any, n: int, J: int, T: int) -> list[dict]:
    """The targets, paths and keyframes drawn over the motions (``motion`` -1: in every lane)."""
    shapes = []
    for kind, value in (("target", targets), ("path", paths)):
        for i, v in _per_motion(kind + "s", value, n, 2):
            label = f"{kind}s" if i < 0 else f"{kind}s[{i}]"
            pts = _points(label, v)
            shapes.append({"kind": kind, "motion": i, "points": np.round(pts, 4).tolist()})
    for i, v in _per_motion("keyframes", keyframes, n, 2):
        label = "keyframes" if i < 0 else f"keyframes[{i}]"
        shapes.append({"kind": "keyframes", "motion": i, **_keyframes(label, v, J, T)})
    return shapes


def _check_view(view: Any) -> tuple[float, float]:
    if not (isinstance(view, (tuple, list)) and len(view) == 2):
        raise InputError(f"view must be (azimuth, elevation) in degrees, got {view!r}")
    return (check_number("view[0]", view[0]), check_number("view[1]", view[1], low=-89, high=89))


def build_payload(
    motions: Any,
    skeleton: Any,
    *,
    fps: float = 30.0,
    labels: Sequence[str] | None = None,
    colors: Any = None,
    layout: str = "side",
    targets: Any = None,
    paths: Any = None,
    keyframes: Any = None,
    feet: Any = None,
    contacts: Any = None,
    follow: bool = True,
    view: tuple[float, float] | None = None,
    autoplay: bool = True,
) -> dict[str, Any]:
    """Check the player's arguments and build its JSON payload (see :func:`minimdm.viz.player`).

    Raises:
        InputError: a ``ValueError`` naming the argument and the problem: NaN/Inf, no frames,
            wrong shapes, a parents list that does not fit the joints, and so on.
    """
    fps = check_number("fps", fps, low=0, low_open=True)
    if layout == "side_by_side":
        layout = "side"
    check_choice("layout", layout, ("side", "overlay"))
    items = _motion_items(motions)
    if not items:
        raise InputError("motions must hold at least one motion, got an empty list")
    single = len(items) == 1 and not isinstance(motions, (list, tuple))
    ms = [
        _positions("motions" if single else f"motions[{i}]", m, skeleton)
        for i, m in enumerate(items)
    ]
    Js = [m.shape[1] for m in ms]
    if len(set(Js)) > 1:
        raise InputError(f"motions must share one skeleton, got joint counts {Js}")
    n, J = len(ms), Js[0]
    parents, names = _parents(skeleton, J)
    _check_labels(labels, n)
    hexes = _hex_colors(colors, n)
    foot = _feet(feet, skeleton, names, J)
    given = _given_contacts(contacts, foot, n)

    offsets, lane_axis = _lane_offsets(ms) if layout == "side" and n > 1 else ([], -1)
    if view is None:  # look across the lanes: from the front when they lie along y
        view = (-25.0, 20.0) if lane_axis == 1 else (-65.0, 18.0)
    out_motions = []
    for i, x in enumerate(ms):
        entry = _quantise(x)
        entry["label"] = "" if labels is None else str(labels[i])
        entry["color"] = hexes[i]
        entry["offset"] = offsets[i] if offsets else [0.0, 0.0, 0.0]
        if foot:
            entry["contacts"] = _contact_bits(i, x, foot, given, fps)
        out_motions.append(entry)
    shapes = _shapes(targets, paths, keyframes, n, J, max(len(m) for m in ms))
    view = _check_view(view)
    return {
        "version": PAYLOAD_VERSION,
        "fps": fps,
        "parents": parents,
        "names": names,
        "feet": foot,
        "layout": layout,
        "lane_axis": lane_axis,
        "follow": bool(follow),
        "autoplay": bool(autoplay),
        "view": [view[0], view[1]],
        "motions": out_motions,
        "shapes": shapes,
    }
