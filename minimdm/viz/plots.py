"""Static and interactive views: :func:`filmstrip`, :func:`scrubber`, :func:`plot_trajectories`,
and :func:`book_style`, the figure settings that the book's column shows at their own size."""

from __future__ import annotations

import functools
import io
from collections.abc import Sequence
from typing import Any

import numpy as np

from .animation import _frame_indices
from .render import _render
from .scene import (
    TARGET,
    Backend,
    Layout,
    _build_scene,
    _check_motions,
    _check_size,
    _check_targets,
    _colors,
    _rgb,
    _to_numpy,
)

COLUMN_INCHES = 6.8
"""The widest figure, in inches at :func:`book_style`'s 100 dpi, that the book's 688-pixel text
column shows at its own size; a wider one is shrunk, and its text with it."""


def book_style() -> None:
    """Matplotlib settings for the book's figures: 100 dpi, so that a figure's inches times 100
    are its pixels on the page; :data:`COLUMN_INCHES` wide by default, with text sized to be read
    at that size (9-point labels, 8-point ticks and legends). Call it once, after importing
    pyplot, at the top of a chapter."""
    import matplotlib.pyplot as plt

    plt.rcParams.update(
        {
            "figure.dpi": 100,
            "savefig.dpi": 100,
            "figure.figsize": (COLUMN_INCHES, 3.0),
            "font.size": 9,
            "axes.titlesize": 9,
            "axes.labelsize": 9,
            "xtick.labelsize": 8,
            "ytick.labelsize": 8,
            "legend.fontsize": 8,
            "figure.titlesize": 10,
        }
    )


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
    cell = min(1.6, COLUMN_INCHES / n)  # inches a frame: the row fits the book's column
    fig = Figure(figsize=(cell * n, cell * h / w * len(ms) + 0.3), dpi=100, layout="constrained")
    axes = np.asarray(fig.subplots(len(ms), n, squeeze=False))
    scene_options = ("overlay", size, trail, True, targets, motion_fps, view)  # follow: True
    for r, m in enumerate(ms):
        scene = _build_scene([m], parents, None, [colors[r]], *scene_options)
        idx = np.linspace(0, len(m) - 1, n).round().astype(int)
        for k, (f, img) in enumerate(zip(idx, _render(scene, idx, backend), strict=True)):
            ax = axes[r, k]
            ax.imshow(img)
            ax.set_xticks([]), ax.set_yticks([])
            ax.set_title(f"t = {f / motion_fps:.2f} s", fontsize=8)
            if k == 0 and labels is not None:
                ax.set_ylabel(labels[r], fontsize=9)
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
    w, h = _check_size(size)  # shown at its own size, not stretched to the cell's width
    image = widgets.Image(value=pngs[0], format="png", width=w, height=h)
    play = widgets.Play(min=0, max=len(pngs) - 1, interval=int(1000 / fps), description="play")
    slider = widgets.IntSlider(min=0, max=len(pngs) - 1, description="frame")
    widgets.jslink((play, "value"), (slider, "value"))

    def show(change) -> None:
        image.value = pngs[change["new"]]

    slider.observe(show, names="value")
    return _scrubber_box()([image, widgets.HBox([play, slider])])


@functools.cache
def _scrubber_box() -> type:
    import ipywidgets as widgets

    class Scrubber(widgets.VBox):
        """A VBox whose text form, which a notebook shows where the widget cannot run (its
        kernel is gone), is a sentence rather than the repr of every frame's PNG bytes."""

        def __repr__(self) -> str:
            return "Frame scrubber (a live widget): run the cell to use it."

    return Scrubber


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
