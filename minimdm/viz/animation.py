"""Animations to GIF or MP4 files (:func:`animate`, :class:`Animation`) and still frames."""

from __future__ import annotations

import base64
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from minimdm.files import atomic_output, atomic_write

from .render import _render
from .scene import Backend, Layout, _build_scene, _check_motions, _colors, _to_numpy

GIF_COLORS = 64  # one global GIF palette (no flicker); 32 merged the hues of 4 characters


# --------------------------------------------------------------------------- files and display


def _write(frames: Sequence[np.ndarray], path: Path, fps: float) -> None:
    """Write RGB frames (H, W, 3) to a GIF (one global palette) or an MP4 (H.264), atomically."""
    if path.suffix.lower() not in (".gif", ".mp4"):
        raise ValueError(f"out must end in .gif or .mp4, got {str(path)!r}")
    with atomic_output(path) as tmp:
        _encode(frames, tmp, fps)


def _encode(frames: Sequence[np.ndarray], path: Path, fps: float) -> None:
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
                atomic_write(path, self.data)
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


def _panel_rows(n: int, ncols: int | None, layout: Layout) -> list[list[int]]:
    """The motions of each row of panels: one row, or rows of ``ncols`` side by side."""
    if ncols is None or layout != "side_by_side" or n <= ncols:
        return [list(range(n))]
    return [list(range(r, min(r + ncols, n))) for r in range(0, n, ncols)]


def _stack_rows(rows: list[list[np.ndarray]]) -> list[np.ndarray]:
    """Stack each frame's rows of panels ``(H, W, 3)`` top to bottom; a row narrower than the
    first (the last may have fewer panels) is padded with white on the right."""
    grid = rows[0]
    for frames in rows[1:]:
        h, w = frames[0].shape[:2]
        blank = np.full((h, grid[0].shape[1] - w, 3), 255, np.uint8)
        grid = [
            np.concatenate([g, np.concatenate([f, blank], 1)], 0)
            for g, f in zip(grid, frames, strict=True)
        ]
    return grid


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
    ncols: int | None = None,
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
        ncols: side by side only: wrap the panels into rows of this many (a grid; empty
            panels of the last row are white). None: one row.
    """
    if ncols is not None and not (isinstance(ncols, int) and ncols >= 1):
        raise ValueError(f"ncols must be an integer >= 1 or None, got {ncols!r}")
    ms = _check_motions(motions)
    n = len(ms)
    rows = _panel_rows(n, ncols, layout)
    if labels is not None and len(labels) != n:
        raise ValueError(f"labels has {len(labels)} entries for {n} motions")
    colors = _colors(colors, n)
    F = max(len(m) for m in ms)
    ms = [np.concatenate([m, np.repeat(m[-1:], F - len(m), 0)]) for m in ms]  # hold last frame
    idx = _frame_indices(F, fps, motion_fps, stride)
    if out is not None and Path(out).suffix.lower() not in (".gif", ".mp4"):
        raise ValueError(f"out must end in .gif or .mp4, got {str(out)!r}")
    scene_options = (layout, size, trail, follow, targets, motion_fps, view)  # the same each row
    row_frames = []
    for row in rows:  # each row is one side-by-side scene; the rows are stacked
        row_labels = None if labels is None else [labels[i] for i in row]
        row_motions, row_colors = [ms[i] for i in row], [colors[i] for i in row]
        scene = _build_scene(row_motions, parents, row_labels, row_colors, *scene_options)
        row_frames.append(_render(scene, idx, backend))  # each (H, w * len(row), 3)
    frames = _stack_rows(row_frames)
    if out is None:
        fd, out = tempfile.mkstemp(prefix="minimdm_", suffix=".gif")
        os.close(fd)
    out = Path(out)
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
