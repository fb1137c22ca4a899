"""Renderers: pyvista off-screen (EGL) and a matplotlib fallback, both drawing a :class:`_Scene`.

:func:`_render` renders a list of frames to RGB arrays ``(H, W, 3)``. If pyvista fails, it warns
once, remembers why in ``_PYVISTA_ERROR`` and uses matplotlib from then on.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence

import numpy as np

from .scene import GROUND, TARGET, TILE, _ground_colors, _Scene

_PYVISTA_ERROR: str | None = None  # set once pyvista failed; later calls go to matplotlib


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
