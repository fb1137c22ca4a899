"""The scene both renderers draw: input checks, colours, panels, camera tracks and trails.

:func:`_build_scene` validates the arguments of every public function and turns them into a
:class:`_Scene` (motions padded to one length, one panel per character or one for all, a
camera that follows the smoothed root, a fading root trail on the ground).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

REAL = "#4e79a7"  # steel blue: motion capture data
GENERATED = "#f28e2b"  # orange: model samples
TARGET = "#d62728"  # red: goals, target paths, keyframes
PALETTE = (REAL, GENERATED, "#59a14f", "#b07aa1", "#76b7b2", "#edc948", "#9c755f", "#ff9da7")
"""Default colours, one per character, in order: real, generated, then more samples."""

GROUND = ((0.94, 0.94, 0.94), (0.86, 0.86, 0.86))  # checkerboard tiles, RGB in [0, 1]
TILE = 1.0  # checkerboard tile size in metres

Layout = Literal["side_by_side", "overlay"]
Backend = Literal["pyvista", "matplotlib"]


# --------------------------------------------------------------------------- input checks


def _to_numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _check_motions(motions: Any, name: str = "motions") -> list[np.ndarray]:
    """One ``(F, J, 3)`` motion, a batch ``(B, F, J, 3)`` or a list -> list of float arrays."""
    if isinstance(motions, (list, tuple)):
        items, single = list(motions), False
    else:
        arr = _to_numpy(motions)
        items, single = (list(arr), False) if arr.ndim == 4 else ([arr], True)
    if not items:
        raise ValueError(f"{name} must hold at least one motion, got an empty list")
    out = []
    for i, m in enumerate(items):
        label = name if single else f"{name}[{i}]"
        m = _to_numpy(m)
        if m.ndim != 3 or m.shape[-1] != 3 or m.shape[0] < 1 or m.shape[1] < 1:
            raise ValueError(
                f"{label} must have shape (F, J, 3) (frames, joints, xyz), got {tuple(m.shape)}"
            )
        bad = ~np.isfinite(m).all(axis=(1, 2))
        if bad.any():
            raise ValueError(f"{label} holds NaN/Inf, first at frame {int(np.argmax(bad))}")
        out.append(m)
    if len({m.shape[1] for m in out}) > 1:
        raise ValueError(f"{name} must share one joint count, got {[m.shape[1] for m in out]}")
    return out


def _check_parents(parents: Any, n_joints: int) -> tuple[np.ndarray, list[str] | None]:
    """Parent indices (and joint names, if the skeleton has them), validated against J."""
    names = getattr(parents, "names", None)
    par = getattr(parents, "parents", parents)
    try:
        par = np.asarray(_to_numpy(par), dtype=np.int64).reshape(-1)
    except (TypeError, ValueError) as e:
        raise ValueError(f"parents must be a list of parent indices, got {parents!r}") from e
    if len(par) != n_joints:
        raise ValueError(
            f"parents has length {len(par)}, but the motions have J = {n_joints} joints"
        )
    for j, p in enumerate(par):
        if not -1 <= p < n_joints or p == j:
            raise ValueError(f"parents[{j}] = {p} must be -1 or another joint in [0, {n_joints})")
    if (par == -1).sum() < 1:
        raise ValueError("parents must have at least one root (-1)")
    for j in range(n_joints):  # no cycles: every chain reaches a root within J steps
        k, steps = j, 0
        while k != -1:
            k, steps = par[k], steps + 1
            if steps > n_joints:
                raise ValueError(f"parents has a cycle through joint {j}")
    if names is not None and len(names) != n_joints:
        names = None
    return par, (list(names) if names is not None else None)


def _rgb(color: Any) -> tuple[float, float, float]:
    from matplotlib.colors import to_rgb

    alias = {"real": REAL, "generated": GENERATED, "target": TARGET}
    if isinstance(color, str) and color.lower() in alias:
        color = alias[color.lower()]
    return tuple(float(c) for c in to_rgb(color))


def _colors(colors: Any, n: int) -> list[Any]:
    """One colour per character: default PALETTE in order, or one colour for all."""
    if colors is None:
        return [PALETTE[i % len(PALETTE)] for i in range(n)]
    numbers = len(colors) in (3, 4) and all(isinstance(c, (int, float)) for c in colors)
    if isinstance(colors, str) or numbers:  # one colour (a name or an RGB tuple) for all
        return [colors] * n
    if len(colors) != n:
        raise ValueError(f"colors has {len(colors)} entries for {n} motions")
    return list(colors)


def _check_size(size: Any) -> tuple[int, int]:
    try:
        w, h = (int(s) for s in size)
    except (TypeError, ValueError) as e:
        raise ValueError(f"size must be (width, height) in pixels, got {size!r}") from e
    if not (16 <= w <= 4096 and 16 <= h <= 4096):
        raise ValueError(f"size must be (width, height) between 16 and 4096 px, got {size!r}")
    return w, h


def _check_targets(targets: Any) -> list[np.ndarray]:
    """Targets: (K, 2|3) points or paths, or (K, J, 3) keyframe poses; one or a list."""
    if targets is None:
        return []
    if isinstance(targets, (list, tuple)):  # a list of points is one target, else each item
        one = len(targets) > 0 and _to_numpy(targets[0]).ndim <= 1
        items = [_to_numpy(targets)] if one else [_to_numpy(t) for t in targets]
    else:
        items = [_to_numpy(targets)]
    out = []
    for i, t in enumerate(items):
        if t.ndim == 1 and t.shape[0] in (2, 3):
            t = t[None]
        if t.ndim == 2 and t.shape[-1] == 2:
            t = np.concatenate([t, np.zeros((len(t), 1))], axis=1)  # ground points
        if not ((t.ndim == 2 and t.shape[-1] == 3) or (t.ndim == 3 and t.shape[-1] == 3)):
            raise ValueError(
                f"targets[{i}] must be (K, 2) or (K, 3) points or (K, J, 3) poses, got "
                f"{tuple(t.shape)}"
            )
        if not np.isfinite(t).all():
            raise ValueError(f"targets[{i}] holds NaN/Inf")
        out.append(t)
    return out


# --------------------------------------------------------------------------- scene layout


@dataclass
class _Scene:
    """Everything both renderers need: padded motions, panels, colours and camera tracks."""

    motions: list[np.ndarray]
    """Motions padded to a common length by holding the last frame, each (F, J, 3)."""
    parents: np.ndarray
    """Parent index per joint, -1 for roots."""
    names: list[str] | None
    """Joint names, if known (used to find the head)."""
    colors: list[tuple[float, float, float]]
    """One RGB colour per character."""
    labels: list[str]
    """One label per character ('' for none), drawn in its colour in its panel's corner."""
    panels: list[list[int]]
    """Characters drawn in each panel."""
    size: tuple[int, int]
    """Pixels per panel (width, height)."""
    trail_frames: int
    """Length of the fading root trail in frames (0: none)."""
    targets: list[np.ndarray]
    """Static points/paths (K, 3) and poses (K, J, 3) drawn in every panel."""
    view: tuple[float, float]
    """Camera azimuth and elevation in degrees."""
    focal: np.ndarray = field(init=False)
    """Camera focal point per panel and frame, (P, F, 3)."""
    distance: np.ndarray = field(init=False)
    """Camera distance per panel, (P,)."""
    bone_radius: float = field(init=False)
    """Tube radius in metres (scaled with the skeleton)."""
    head: int | None = field(init=False)
    """Index of the joint that carries a head sphere, if any."""
    head_gap: float = field(init=False)
    """Head centre beyond that joint, along its bone, in head radii."""
    root: int = field(init=False)
    """The root joint (the first with parent -1): its ground track is the trail."""

    VIEW_ANGLE = 30.0  # vertical field of view in degrees

    def setup(self, follow: bool, motion_fps: float) -> None:
        F = len(self.motions[0])
        bones = [(j, p) for j, p in enumerate(self.parents) if p >= 0]
        m0 = self.motions[0]
        lengths = [np.linalg.norm(m0[:, j] - m0[:, p], axis=-1).mean() for j, p in bones]
        scale = float(np.median(lengths)) if lengths else 0.25
        self.bone_radius = float(np.clip(0.13 * scale, 0.004, 0.06))
        self.head, self.head_gap = None, 0.0
        self.root = int(np.flatnonzero(self.parents == -1)[0])
        if self.names is not None:
            # a leaf joint called head (or neck, as in the DeepMimic humanoid) gets a head sphere
            leaves = [j for j in range(len(self.parents)) if j not in set(self.parents)]
            for key in ("head", "neck"):
                hits = [j for j in leaves if key in self.names[j].lower() and self.parents[j] >= 0]
                if hits:
                    self.head = hits[0]
                    self.head_gap = 0.6 if key == "head" else 1.75
                    break
        tan = np.tan(np.radians(self.VIEW_ANGLE / 2))
        aspect = self.size[0] / self.size[1]
        focal, dist = [], []
        for chars in self.panels:
            pos = np.concatenate(  # (F, n * (J + head), 3), with the head's top
                [np.stack([self._tops(c, f) for f in range(F)]) for c in chars], axis=1
            )
            height = max(float(np.percentile(pos[..., 2].max(axis=1), 90)), 4 * scale)
            root = np.stack([self.motions[c][:, self.root, :2] for c in chars]).mean(0)  # (F, 2)
            if follow:  # a moving average of the root centroid (a steady camera)
                k = max(1, int(round(motion_fps)))
                pad = np.concatenate([np.repeat(root[:1], k, 0), root, np.repeat(root[-1:], k, 0)])
                kern = np.ones(2 * k + 1) / (2 * k + 1)
                xy = np.stack([np.convolve(pad[:, d], kern, mode="valid") for d in (0, 1)], -1)
            else:
                lo, hi = pos[..., :2].min(axis=(0, 1)), pos[..., :2].max(axis=(0, 1))
                xy = np.repeat(((lo + hi) / 2)[None], F, 0)
            spread = float(np.linalg.norm(pos[..., :2] - xy[:, None], axis=-1).max())
            z = np.full((F, 1), 0.45 * height)
            focal.append(np.concatenate([xy, z], axis=1))
            half_h = 0.62 * height + 0.15
            half_w = spread + 0.3
            dist.append(max(half_h / tan, half_w / (tan * aspect)))
        self.focal = np.stack(focal)  # (P, F, 3)
        self.distance = np.array(dist)

    def captions(self, panel: int) -> list[tuple[str, tuple[float, float, float]]]:
        """(label, darkened colour) of each labelled character in a panel."""
        dark = [tuple(0.75 * np.asarray(self.colors[c])) for c in self.panels[panel]]
        return [
            (self.labels[c], d)
            for c, d in zip(self.panels[panel], dark, strict=True)
            if self.labels[c]
        ]

    def _tops(self, c: int, f: int) -> np.ndarray:
        centres, radii = self.joints(c, f)
        return centres + np.array([0.0, 0.0, 1.0]) * radii[:, None]

    def camera(self, panel: int, f: int) -> tuple[np.ndarray, np.ndarray]:
        """Camera position and focal point for a panel at frame f."""
        az, el = np.radians(self.view[0]), np.radians(self.view[1])
        direction = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        focal = self.focal[panel, f]
        return focal + self.distance[panel] * direction, focal

    def joints(self, c: int, f: int) -> tuple[np.ndarray, np.ndarray]:
        """Sphere centres (J [+1 head], 3) and radii for character c at frame f."""
        pos = self.motions[c][f]  # (J, 3)
        r = 1.5 * self.bone_radius
        radii = np.full(len(pos), r)
        if self.head is None:
            return pos, radii
        p = pos[self.head] - pos[self.parents[self.head]]
        head_r = 2.0 * r
        centre = pos[self.head] + p / max(np.linalg.norm(p), 1e-9) * head_r * self.head_gap
        return np.concatenate([pos, centre[None]]), np.append(radii, head_r)

    def trail(self, c: int, f: int) -> tuple[np.ndarray, np.ndarray]:
        """Root trail points (L, 3) on the ground and their fade weights in [0, 1]."""
        L = self.trail_frames
        idx = np.clip(np.arange(f - L + 1, f + 1), 0, None)
        pts = self.motions[c][idx, self.root].copy()
        pts[:, 2] = 0.004
        return pts, np.linspace(0.0, 1.0, L) ** 1.5


def _build_scene(
    motions: Any,
    parents: Any,
    labels: Sequence[str] | None,
    colors: Sequence[Any] | None,
    layout: str,
    size: Any,
    trail: bool | float,
    follow: bool,
    targets: Any,
    motion_fps: float,
    view: tuple[float, float],
) -> _Scene:
    ms = _check_motions(motions)
    par, names = _check_parents(parents, ms[0].shape[1])
    n = len(ms)
    if layout not in ("side_by_side", "overlay"):
        raise ValueError(f"layout must be 'side_by_side' or 'overlay', got {layout!r}")
    if labels is not None and len(labels) != n:
        raise ValueError(f"labels has {len(labels)} entries for {n} motions")
    colors = _colors(colors, n)
    if not motion_fps > 0:
        raise ValueError(f"motion_fps must be > 0, got {motion_fps}")
    F = max(len(m) for m in ms)
    ms = [np.concatenate([m, np.repeat(m[-1:], F - len(m), 0)]) for m in ms]  # hold last frame
    labels = [str(s) for s in labels] if labels is not None else [""] * n
    panels = [[i] for i in range(n)] if layout == "side_by_side" else [list(range(n))]
    seconds = 3.0 if trail is True else float(trail or 0)
    scene = _Scene(
        motions=ms,
        parents=par,
        names=names,
        colors=[_rgb(c) for c in colors],
        labels=labels,
        panels=panels,
        size=_check_size(size),
        trail_frames=max(0, int(round(seconds * motion_fps))),
        targets=_check_targets(targets),
        view=(float(view[0]), float(view[1])),
    )
    scene.setup(follow, motion_fps)
    return scene


def _ground_colors(cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
    parity = (np.floor(cx / TILE) + np.floor(cy / TILE)).astype(int) % 2
    return np.asarray(GROUND)[parity]
