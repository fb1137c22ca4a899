"""Skeleton animation: animated 3D stick figures that show in a live kernel and a static book.

Every function takes *motions* of global joint positions, shape ``(F, J, 3)`` in metres, in
the z-up world used everywhere in minimdm (the ground is the plane ``z = 0``), as numpy arrays
or torch tensors, and the skeleton's *parents* (``-1`` for the root): a
:class:`minimdm.skeleton.Skeleton`, anything with a ``.parents`` attribute (its ``.names``, if
any, let us draw a head), or a plain list of parent indices. The root's (the first joint with
parent ``-1``) ground projection is the trail, and the camera follows it.

* :func:`animate` renders one or several motions to a GIF or MP4 and returns an
  :class:`Animation`, which Jupyter shows inline as a base64 ``<img>`` (GIF) or ``<video>``
  (MP4), so the published book shows it without a kernel.
* :func:`render_frame` renders one still pose to an image array; :func:`filmstrip` puts a row of
  still frames in a matplotlib figure (the static figure beside a widget).
* :func:`scrubber` is an ipywidgets frame scrubber (Play + slider) for live kernels.
* :func:`plot_trajectories` draws top-down root paths of several runs, with optional targets.

Rendering uses pyvista off-screen (EGL, no display needed): one bone ``PolyData`` per character
feeds a tube filter and a sphere glyph, and only its points change from frame to frame. If
pyvista or EGL fails, we warn once and fall back to a matplotlib renderer (``backend=
"matplotlib"`` picks it by choice).

Colours tell real from generated motion: :data:`REAL` (steel blue) for data, :data:`GENERATED`
(orange) for samples, and :data:`PALETTE` for several samples (its first two entries are
``REAL`` and ``GENERATED``); :data:`TARGET` (red) draws goals and keyframes. Any matplotlib
colour, or the words ``"real"``, ``"generated"`` and ``"target"``, can be passed as a colour.
"""

from __future__ import annotations

import base64
import io
import os
import shutil
import tempfile
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

# Off-screen VTK through EGL; must be set before vtk is first imported (pyvista is imported
# lazily, inside the functions that render).
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

__all__ = [
    "REAL",
    "GENERATED",
    "TARGET",
    "PALETTE",
    "Animation",
    "animate",
    "render_frame",
    "filmstrip",
    "scrubber",
    "plot_trajectories",
]

REAL = "#4e79a7"  # steel blue: motion capture data
GENERATED = "#f28e2b"  # orange: model samples
TARGET = "#d62728"  # red: goals, target paths, keyframes
PALETTE = (REAL, GENERATED, "#59a14f", "#b07aa1", "#76b7b2", "#edc948", "#9c755f", "#ff9da7")
"""Default colours, one per character, in order: real, generated, then more samples."""

GROUND = ((0.94, 0.94, 0.94), (0.86, 0.86, 0.86))  # checkerboard tiles, RGB in [0, 1]
TILE = 1.0  # checkerboard tile size in metres
GIF_COLORS = 64  # one global GIF palette (no flicker); 32 merged the hues of 4 characters

Layout = Literal["side_by_side", "overlay"]
Backend = Literal["pyvista", "matplotlib"]

_PYVISTA_ERROR: str | None = None  # set once pyvista failed; later calls go to matplotlib


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


# --------------------------------------------------------------------------- pyvista renderer


def _pyvista():
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv

    pv.OFF_SCREEN = True
    return pv


class _PyvistaRenderer:
    """One off-screen plotter; actors are built once and their points updated per frame."""

    GROUND_HALF = 5.0  # the checkerboard is a 10 m square that follows the camera

    def __init__(self, scene: _Scene) -> None:
        pv = _pyvista()
        from vtkmodules.vtkFiltersCore import vtkGlyph3D, vtkTubeFilter
        from vtkmodules.vtkFiltersSources import vtkSphereSource

        self.s = s = scene
        w, h = s.size
        n = len(s.panels)
        self.pl = pl = pv.Plotter(
            off_screen=True, window_size=(w * n, h), shape=(1, n), border=False
        )
        pl.set_background("white")
        lines = np.array([[2, j, p] for j, p in enumerate(s.parents) if p >= 0]).reshape(-1)
        ground = self._ground(pv)
        self.ground_actors, self.chars, self.trails = [], {}, {}
        for p, chars in enumerate(s.panels):
            pl.subplot(0, p)
            self.ground_actors.append(
                pl.add_mesh(ground, scalars="rgb", rgb=True, lighting=False, show_scalar_bar=False)
            )
            for c in chars:
                bones = pv.PolyData(s.motions[c][0].copy(), lines=lines if len(lines) else None)
                tube = vtkTubeFilter()
                tube.SetInputData(bones)
                tube.SetRadius(s.bone_radius)
                tube.SetNumberOfSides(10)
                tube.CappingOn()
                centres, radii = s.joints(c, 0)
                balls = pv.PolyData(centres.copy())
                balls.point_data["diameter"] = 2 * radii
                sphere = vtkSphereSource()
                sphere.SetRadius(0.5)
                sphere.SetThetaResolution(14)
                sphere.SetPhiResolution(10)
                glyph = vtkGlyph3D()
                glyph.SetInputData(balls)
                glyph.SetSourceConnection(sphere.GetOutputPort())
                glyph.SetScaleModeToScaleByScalar()
                glyph.SetInputArrayToProcess(0, 0, 0, 0, "diameter")
                kw = dict(color=s.colors[c], smooth_shading=True, ambient=0.25, diffuse=0.8)
                pl.add_mesh(tube, specular=0.2, **kw)
                pl.add_mesh(glyph, specular=0.3, show_scalar_bar=False, **kw)
                self.chars[(p, c)] = (bones, balls)
                if s.trail_frames > 1:
                    pts, fade = s.trail(c, 0)
                    trail = pv.lines_from_points(pts)
                    trail.point_data["rgb"] = self._trail_rgb(c, fade)
                    pl.add_mesh(trail, scalars="rgb", rgb=True, line_width=4, lighting=False)
                    self.trails[(p, c)] = trail
            self._add_targets(pv, pl)
            for k, (text, col) in enumerate(s.captions(p)):
                pl.add_text(text, position=(6, h - 21 - 15 * k), font_size=9, color=col)
            pl.camera.view_angle = s.VIEW_ANGLE
            pl.camera.up = (0.0, 0.0, 1.0)

    def _ground(self, pv):
        half = self.GROUND_HALF
        n = int(2 * half / TILE)
        ground = pv.Plane(
            direction=(0, 0, 1), i_size=2 * half, j_size=2 * half, i_resolution=n, j_resolution=n
        )
        cc = ground.cell_centers().points
        ground.cell_data["rgb"] = (_ground_colors(cc[:, 0], cc[:, 1]) * 255).astype(np.uint8)
        return ground

    def _trail_rgb(self, c: int, fade: np.ndarray) -> np.ndarray:
        base = np.asarray(GROUND[0])
        rgb = base + fade[:, None] * (np.asarray(self.s.colors[c]) - base)
        return (rgb * 255).astype(np.uint8)

    def _add_targets(self, pv, pl) -> None:
        s = self.s
        lines = np.array([[2, j, p] for j, p in enumerate(s.parents) if p >= 0]).reshape(-1)
        for t in s.targets:
            if t.ndim == 2:  # points or a path
                balls = pv.PolyData(t).glyph(
                    geom=pv.Sphere(radius=2.5 * s.bone_radius), scale=False, orient=False
                )
                pl.add_mesh(balls, color=TARGET, smooth_shading=True)
                if len(t) > 1:
                    pl.add_mesh(pv.lines_from_points(t), color=TARGET, line_width=2)
            else:  # keyframe poses as translucent skeletons
                for pose in t:
                    tube = pv.PolyData(pose, lines=lines).tube(radius=s.bone_radius)
                    pl.add_mesh(tube, color=TARGET, opacity=0.35, smooth_shading=True)

    def render(self, f: int) -> np.ndarray:
        s = self.s
        for (_, c), (bones, balls) in self.chars.items():
            bones.points = s.motions[c][f]
            centres, radii = s.joints(c, f)
            balls.points = centres
            balls.point_data["diameter"] = 2 * radii
        for (_, c), trail in self.trails.items():
            pts, fade = s.trail(c, f)
            trail.points = pts
        for p in range(len(s.panels)):
            self.pl.subplot(0, p)
            pos, focal = s.camera(p, f)
            cam = self.pl.camera
            cam.focal_point, cam.position = focal.tolist(), pos.tolist()
            step = 2 * TILE  # move the ground in whole tile pairs so the pattern stays put
            gx, gy = np.round(focal[:2] / step) * step
            self.ground_actors[p].SetPosition(gx, gy, 0.0)
            self.pl.renderer.ResetCameraClippingRange()
        self.pl.render()
        return np.asarray(self.pl.screenshot(return_img=True))[..., :3].copy()

    def close(self) -> None:
        self.pl.close()


# --------------------------------------------------------------------------- matplotlib renderer


def _mpl_version() -> tuple[int, int]:
    import matplotlib

    return tuple(int(v) for v in matplotlib.__version__.split(".")[:2])


_EMPTY = [[(0.0, 0.0, 0.0), (0.0, 0.0, 0.0)]]  # a degenerate segment (empty ones break autoscale)


class _MplRenderer:
    """Fallback: 3D axes with line collections; the same scene, a plainer look."""

    DPI = 100

    def __init__(self, scene: _Scene) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from mpl_toolkits.mplot3d.art3d import Line3DCollection

        self.s = s = scene
        w, h = s.size
        n = len(s.panels)
        self.fig = Figure(figsize=(w * n / self.DPI, h / self.DPI), dpi=self.DPI)
        self.canvas = FigureCanvasAgg(self.fig)
        self.bones = [(j, p) for j, p in enumerate(s.parents) if p >= 0]
        self.axes, self.arts = [], {}
        # matplotlib >= 3.10 can clip 3D artists to the axes box (targets far away, trails)
        clip = {"axlim_clip": True} if _mpl_version() >= (3, 10) else {}
        for p, chars in enumerate(s.panels):
            ax = self.fig.add_axes((p / n, 0, 1 / n, 1), projection="3d")
            ax.set_axis_off()
            ax.view_init(elev=s.view[1], azim=s.view[0])
            ax.set_box_aspect((1, 1, 1), zoom=1.4)
            grid = Line3DCollection(_EMPTY, colors=[GROUND[1]], linewidths=0.8, **clip)
            ax.add_collection3d(grid)
            for t in s.targets:
                pts = t.reshape(-1, 3) if t.ndim == 2 else None
                if pts is not None:
                    ax.plot(*pts.T, color=TARGET, marker="o", ms=4, lw=1.5, **clip)
                else:
                    for pose in t:
                        segs = [pose[[j, q]] for j, q in self.bones]
                        col = Line3DCollection(segs, colors=TARGET, alpha=0.35, **clip)
                        ax.add_collection3d(col)
            for c in chars:
                col = s.colors[c]
                trail = Line3DCollection(_EMPTY, linewidths=2, **clip)
                ax.add_collection3d(trail)
                bones = Line3DCollection(_EMPTY, colors=[col], linewidths=3)
                ax.add_collection3d(bones)
                (dots,) = ax.plot([], [], [], "o", color=col, ms=3.5)
                (head,) = ax.plot([], [], [], "o", color=col, ms=12)
                self.arts[(p, c)] = (trail, bones, dots, head)
            for k, (text, col) in enumerate(s.captions(p)):
                y = 1 - (18 + 15 * k) / h
                ax.text2D(0.03, y, text, transform=ax.transAxes, fontsize=8, color=col)
            self.axes.append((ax, grid))

    def render(self, f: int) -> np.ndarray:
        s = self.s
        for p, (ax, grid) in enumerate(self.axes):
            _, focal = s.camera(p, f)
            half = 0.5 * s.distance[p] * np.tan(np.radians(s.VIEW_ANGLE / 2)) * 2.2
            ax.set_xlim(focal[0] - half, focal[0] + half)
            ax.set_ylim(focal[1] - half, focal[1] + half)
            ax.set_zlim(focal[2] - half, focal[2] + half)
            ticks = np.arange(np.ceil((focal[0] - half) / TILE), (focal[0] + half) / TILE) * TILE
            yt = np.arange(np.ceil((focal[1] - half) / TILE), (focal[1] + half) / TILE) * TILE
            lo, hi = focal[:2] - half, focal[:2] + half
            segs = [[(x, lo[1], 0), (x, hi[1], 0)] for x in ticks]
            segs += [[(lo[0], y, 0), (hi[0], y, 0)] for y in yt]
            grid.set_segments(segs)
        for (_, c), (trail, bones, dots, head) in self.arts.items():
            pos = s.motions[c][f]
            bones.set_segments([pos[[j, q]] for j, q in self.bones])
            centres, _ = s.joints(c, f)
            dots.set_data_3d(*pos.T)
            if s.head is not None:
                head.set_data_3d(*centres[-1:].T)
            if s.trail_frames > 1:
                pts, fade = s.trail(c, f)
                trail.set_segments(np.stack([pts[:-1], pts[1:]], 1))
                trail.set_color([(*s.colors[c], a) for a in fade[1:]])
        self.canvas.draw()
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()

    def close(self) -> None:
        self.fig.clear()


def _renderer(scene: _Scene, backend: str):
    """Make a renderer; pyvista failures warn once and fall back to matplotlib."""
    global _PYVISTA_ERROR
    if backend not in ("pyvista", "matplotlib"):
        raise ValueError(f"backend must be 'pyvista' or 'matplotlib', got {backend!r}")
    if backend == "pyvista" and _PYVISTA_ERROR is None:
        try:
            r = _PyvistaRenderer(scene)
            r.render(0)
            return r
        except Exception as e:  # no vtk, no EGL, no GPU driver: keep going with matplotlib
            _PYVISTA_ERROR = f"{type(e).__name__}: {e}"
            warnings.warn(
                f"pyvista rendering failed ({_PYVISTA_ERROR}); using matplotlib instead",
                RuntimeWarning,
                stacklevel=3,
            )
    return _MplRenderer(scene)


def _render(scene: _Scene, frames: Sequence[int], backend: str) -> list[np.ndarray]:
    r = _renderer(scene, backend)
    try:
        return [r.render(int(f)) for f in frames]
    finally:
        r.close()


# --------------------------------------------------------------------------- files and display


def _write(frames: Sequence[np.ndarray], path: Path, fps: float) -> None:
    """Write RGB frames (H, W, 3) to a GIF (one global palette) or an MP4 (H.264)."""
    if path.suffix.lower() == ".gif":
        from PIL import Image

        sample = np.concatenate(frames[:: max(1, len(frames) // 12)], axis=0)
        pal = Image.fromarray(sample).quantize(
            colors=GIF_COLORS, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE
        )
        ims = [Image.fromarray(f).quantize(palette=pal, dither=Image.Dither.NONE) for f in frames]
        ms = max(20, int(round(100.0 / fps)) * 10)  # GIF delays are in 1/100 s
        ims[0].save(path, save_all=True, append_images=ims[1:], duration=ms, loop=0)
    elif path.suffix.lower() == ".mp4":
        import imageio.v2 as imageio

        h, w = (d - d % 2 for d in frames[0].shape[:2])  # yuv420p wants even sizes
        with imageio.get_writer(
            path, fps=fps, codec="libx264", quality=6, pixelformat="yuv420p", macro_block_size=1
        ) as wr:
            for f in frames:
                wr.append_data(np.ascontiguousarray(f[:h, :w]))
    else:
        raise ValueError(f"out must end in .gif or .mp4, got {str(path)!r}")


@dataclass
class Animation:
    """A rendered animation file that Jupyter shows inline (GIF as <img>, MP4 as <video>)."""

    path: Path
    """Where the GIF or MP4 lies."""
    fps: float
    """Playback frames per second."""
    n_frames: int
    """Number of rendered frames (a GIF stores runs of identical frames as one, longer)."""
    size: tuple[int, int]
    """Width and height of a frame in pixels."""

    @property
    def data(self) -> bytes:
        """The file's bytes."""
        return Path(self.path).read_bytes()

    def save(self, path: str | os.PathLike) -> Path:
        """Copy to ``path`` (.gif or .mp4; a different suffix re-encodes the frames)."""
        path = Path(path)
        if path.suffix.lower() == Path(self.path).suffix.lower():
            if path.resolve() != Path(self.path).resolve():
                shutil.copyfile(self.path, path)
        else:
            import imageio.v3 as iio

            _write(list(iio.imread(self.path, index=None)[..., :3]), path, self.fps)
        return path

    def _repr_html_(self) -> str:
        b64 = base64.b64encode(self.data).decode("ascii")
        w = self.size[0]
        if Path(self.path).suffix.lower() == ".mp4":
            return (
                f'<video width="{w}" style="max-width:100%" autoplay loop muted controls '
                f'playsinline><source type="video/mp4" src="data:video/mp4;base64,{b64}">'
                "</video>"
            )
        return f'<img width="{w}" style="max-width:100%" src="data:image/gif;base64,{b64}"/>'

    def _repr_mimebundle_(self, include=None, exclude=None) -> dict[str, str]:
        return {"text/html": self._repr_html_(), "text/plain": repr(self)}


def _frame_indices(n_frames: int, fps: float, motion_fps: float, stride: int | None) -> range:
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    if stride is None:
        stride = max(1, int(round(motion_fps / fps)))  # play at real speed
    if int(stride) < 1:
        raise ValueError(f"stride must be an integer >= 1, got {stride}")
    return range(0, n_frames, int(stride))


# --------------------------------------------------------------------------- public API


def animate(
    motions: Any,
    parents: Any,
    *,
    labels: Sequence[str] | None = None,
    colors: Sequence[Any] | Any | None = None,
    layout: Layout = "side_by_side",
    fps: float = 15,
    size: tuple[int, int] = (320, 240),
    out: str | os.PathLike | None = None,
    trail: bool | float = True,
    follow: bool = True,
    targets: Any = None,
    stride: int | None = None,
    motion_fps: float = 30.0,
    view: tuple[float, float] = (-60.0, 15.0),
    backend: Backend = "pyvista",
) -> Animation:
    """Render motions as animated skeletons to a GIF or MP4 that shows inline in Jupyter.

    Args:
        motions: one motion (F, J, 3), a batch (B, F, J, 3), or a list of motions, global
            joint positions in metres, z-up. Shorter motions hold their last frame.
        parents: a Skeleton, anything with ``.parents``, or a list of parent indices (-1 root).
        labels: one caption per motion.
        colors: one colour per motion (or one for all); default :data:`PALETTE` in order, so
            ``[real, generated]`` come out blue and orange.
        layout: ``"side_by_side"``: one panel per motion, each with its own camera (same
            angle and distance rule); ``"overlay"``: all motions in one panel.
        fps: playback frames per second of the file.
        size: (width, height) in pixels *per panel*; side by side makes the file n times wider.
        out: a ``.gif`` or ``.mp4`` path; ``None`` writes a GIF to a temporary file.
        trail: fading trail of the root on the ground; ``True`` is 3 s, a number is seconds.
        follow: the camera follows the (smoothed) root centroid; else it frames all motion.
        targets: static things to draw in red: (K, 2|3) points or a path, (K, J, 3) keyframe
            poses, or a list of these.
        stride: render every stride-th motion frame; default ``round(motion_fps / fps)``
            (real-time playback).
        motion_fps: the motions' frame rate (trail length, camera smoothing, default stride).
        view: camera azimuth and elevation in degrees.
        backend: ``"pyvista"`` (falls back to matplotlib with a warning if it fails) or
            ``"matplotlib"``.
    """
    scene = _build_scene(
        motions, parents, labels, colors, layout, size, trail, follow, targets, motion_fps, view
    )
    idx = _frame_indices(len(scene.motions[0]), fps, motion_fps, stride)
    if out is None:
        fd, out = tempfile.mkstemp(prefix="minimdm_", suffix=".gif")
        os.close(fd)
    out = Path(out)
    if out.suffix.lower() not in (".gif", ".mp4"):
        raise ValueError(f"out must end in .gif or .mp4, got {str(out)!r}")
    frames = _render(scene, idx, backend)
    _write(frames, out, fps)
    h, w = frames[0].shape[:2]
    return Animation(path=out, fps=float(fps), n_frames=len(frames), size=(w, h))


def render_frame(
    positions: Any,
    parents: Any,
    *,
    colors: Sequence[Any] | Any | None = None,
    labels: Sequence[str] | None = None,
    targets: Any = None,
    size: tuple[int, int] = (480, 360),
    view: tuple[float, float] = (-60.0, 15.0),
    backend: Backend = "pyvista",
) -> np.ndarray:
    """Render one pose (J, 3), or a list of poses overlaid, to an RGB image (H, W, 3) uint8."""
    if isinstance(positions, (list, tuple)):
        motions = [_to_numpy(p)[None] for p in positions]
    else:
        p = _to_numpy(positions)
        if p.ndim != 2 or p.shape[-1] != 3:
            raise ValueError(f"positions must have shape (J, 3), got {tuple(p.shape)}")
        motions = [p[None]]
    scene = _build_scene(
        motions, parents, labels, colors, "overlay", size, False, True, targets, 30.0, view
    )
    return _render(scene, [0], backend)[0]


def filmstrip(
    motion: Any,
    parents: Any,
    n: int = 6,
    *,
    colors: Sequence[Any] | Any | None = None,
    labels: Sequence[str] | None = None,
    size: tuple[int, int] = (240, 240),
    trail: bool | float = True,
    targets: Any = None,
    motion_fps: float = 30.0,
    view: tuple[float, float] = (-60.0, 15.0),
    backend: Backend = "pyvista",
):
    """A row of n evenly spaced still frames per motion, as a matplotlib Figure.

    ``motion`` may be one (F, J, 3) motion or a list (one row each, labelled by ``labels``).
    """
    from matplotlib.figure import Figure

    if not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be an integer >= 1, got {n!r}")
    ms = _check_motions(motion, "motion")
    colors = _colors(colors, len(ms))
    if labels is not None and len(labels) != len(ms):
        raise ValueError(f"labels has {len(labels)} entries for {len(ms)} motions")
    w, h = _check_size(size)
    fig = Figure(figsize=(1.6 * n, 1.6 * h / w * len(ms) + 0.3), dpi=120, layout="constrained")
    axes = np.asarray(fig.subplots(len(ms), n, squeeze=False))
    for r, m in enumerate(ms):
        scene = _build_scene(
            [m], parents, None, [colors[r]], "overlay", size, trail, True, targets,
            motion_fps, view,
        )  # fmt: skip
        idx = np.linspace(0, len(m) - 1, n).round().astype(int)
        for k, (f, img) in enumerate(zip(idx, _render(scene, idx, backend), strict=True)):
            ax = axes[r, k]
            ax.imshow(img)
            ax.set_xticks([]), ax.set_yticks([])
            ax.set_title(f"t = {f / motion_fps:.2f} s", fontsize=7)
            if k == 0 and labels is not None:
                ax.set_ylabel(labels[r], fontsize=8)
    return fig


def scrubber(
    motions: Any,
    parents: Any,
    *,
    labels: Sequence[str] | None = None,
    colors: Sequence[Any] | Any | None = None,
    layout: Layout = "side_by_side",
    fps: float = 15,
    size: tuple[int, int] = (320, 240),
    trail: bool | float = True,
    follow: bool = True,
    targets: Any = None,
    stride: int | None = None,
    motion_fps: float = 30.0,
    view: tuple[float, float] = (-60.0, 15.0),
    backend: Backend = "pyvista",
):
    """An ipywidgets frame scrubber (Play + slider over pre-rendered PNG frames).

    Arguments as in :func:`animate`. Live kernels only: put a static :func:`animate` or
    :func:`filmstrip` beside it for the published book.
    """
    import ipywidgets as widgets
    from PIL import Image

    scene = _build_scene(
        motions, parents, labels, colors, layout, size, trail, follow, targets, motion_fps, view
    )
    idx = _frame_indices(len(scene.motions[0]), fps, motion_fps, stride)
    pngs = []
    for img in _render(scene, idx, backend):
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, format="png")
        pngs.append(buf.getvalue())
    image = widgets.Image(value=pngs[0], format="png")
    play = widgets.Play(min=0, max=len(pngs) - 1, interval=int(1000 / fps), description="play")
    slider = widgets.IntSlider(min=0, max=len(pngs) - 1, description="frame")
    widgets.jslink((play, "value"), (slider, "value"))

    def show(change) -> None:
        image.value = pngs[change["new"]]

    slider.observe(show, names="value")
    return widgets.VBox([image, widgets.HBox([play, slider])])


def plot_trajectories(
    trajectories: Any,
    *,
    labels: Sequence[str] | None = None,
    colors: Sequence[Any] | Any | None = None,
    targets: Any = None,
    ax: Any = None,
    title: str | None = None,
):
    """Top-down root paths (x right, y up) of several runs; returns the matplotlib Figure.

    Args:
        trajectories: one or a list of motions (F, J, 3) (joint 0 is used), root paths
            (F, 2|3), or a batch of either.
        labels, colors: one per trajectory (default :data:`PALETTE`).
        targets: (K, 2|3) target points/path, or a list of them, drawn as red stars/dashes.
        ax: draw into these axes instead of a new figure.
    """
    from matplotlib.figure import Figure

    if isinstance(trajectories, (list, tuple)):
        items = [_to_numpy(t) for t in trajectories]
    else:
        arr = _to_numpy(trajectories)  # (B, F, J, 3) and (B, F, 2) are batches
        items = list(arr) if arr.ndim == 4 or (arr.ndim == 3 and arr.shape[-1] == 2) else [arr]
    paths = []
    for i, t in enumerate(items):
        if t.ndim == 3 and t.shape[-1] == 3:
            t = t[:, 0]
        if t.ndim != 2 or t.shape[-1] not in (2, 3):
            raise ValueError(
                f"trajectories[{i}] must be (F, J, 3) or (F, 2|3), got {tuple(t.shape)}"
            )
        if not np.isfinite(t).all():
            raise ValueError(f"trajectories[{i}] holds NaN/Inf")
        paths.append(t[:, :2])
    if labels is not None and len(labels) != len(paths):
        raise ValueError(f"labels has {len(labels)} entries for {len(paths)} trajectories")
    colors = _colors(colors, len(paths))
    if ax is None:
        fig = Figure(figsize=(4.5, 4.5), dpi=100, layout="constrained")
        ax = fig.add_subplot()
    fig = ax.figure
    for i, xy in enumerate(paths):
        col = _rgb(colors[i])
        ax.plot(*xy.T, color=col, lw=1.5, label=labels[i] if labels else None)
        ax.plot(*xy[0], "o", color=col, ms=5)
        ax.plot(*xy[-1], "x", color=col, ms=6, mew=2)
    for t in _check_targets(targets):
        t = t.reshape(-1, 3)
        ax.plot(*t[:, :2].T, "--", color=TARGET, lw=1)
        ax.plot(*t[:, :2].T, "*", color=TARGET, ms=10)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.3)
    if title:
        ax.set_title(title)
    if labels:
        ax.legend(fontsize=8)
    return fig
