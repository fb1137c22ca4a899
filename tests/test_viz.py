"""Skeleton animation: files, frame counts, inline HTML, real/generated colours, bad input."""

import base64
import re
import warnings
from types import SimpleNamespace

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from minimdm import viz

# A 5-joint stick figure: pelvis, chest, head, left foot, right foot.
PARENTS = [-1, 0, 1, 0, 0]
BACKENDS = ["pyvista", "matplotlib"]


def walker(F: int = 8, speed: float = 0.05, y: float = 0.0) -> np.ndarray:
    """A stick figure that walks along +x, swinging its feet; (F, 5, 3) in metres, z-up."""
    base = np.array([[0, 0, 0.9], [0, 0, 1.3], [0, 0, 1.6], [0, 0.15, 0.05], [0, -0.15, 0.05]])
    m = np.repeat(base[None], F, 0)  # (F, J, 3)
    m[..., 0] += speed * np.arange(F)[:, None]
    m[..., 1] += y
    swing = 0.25 * np.sin(0.8 * np.arange(F))
    m[:, 3, 0] += swing
    m[:, 4, 0] -= swing
    return m


def orange(img: np.ndarray) -> np.ndarray:
    """Pixels in the GENERATED hue (shaded orange): red > green > blue, well apart."""
    r, g, b = (img[..., i].astype(int) for i in range(3))
    return (r - b > 60) & (g - b > 30) & (r > g + 20)


def blue(img: np.ndarray) -> np.ndarray:
    """Pixels in the REAL hue (steel blue)."""
    r, _, b = (img[..., i].astype(int) for i in range(3))
    return b - r > 40


@pytest.fixture(autouse=True)
def _pyvista_works():
    yield
    err = viz.render._PYVISTA_ERROR
    assert err is None, f"pyvista fell back to matplotlib: {err}"


@pytest.mark.parametrize("backend", BACKENDS)
def test_animate_gif_frames_and_size(tmp_path, backend):
    out = tmp_path / "walk.gif"
    anim = viz.animate(walker(8), PARENTS, out=out, stride=1, size=(96, 72), backend=backend)
    assert anim.path == out and out.stat().st_size > 0
    frames = iio.imread(out, index=None)
    assert frames.shape[:3] == (8, 72, 96) and anim.n_frames == 8 and anim.size == (96, 72)
    # side by side: one panel per motion; stride 2 halves the frames
    two = viz.animate(
        [walker(8), walker(6)], PARENTS, out=tmp_path / "two.gif", stride=2, size=(96, 72),
        labels=["real", "generated"], backend=backend,
    )  # fmt: skip
    assert iio.imread(two.path, index=None).shape[:3] == (4, 72, 192)


def test_ncols_wraps_panels_into_a_grid(tmp_path):
    # 5 motions in rows of 2: a 3 x 2 grid whose last cell is white; each character is in
    # its own cell, in order, in its own colour
    colors = ["real", "generated", "real", "generated", "real"]
    anim = viz.animate(
        [walker(6, y=0.1 * i) for i in range(5)], PARENTS, ncols=2, stride=3, size=(80, 64),
        colors=colors, labels=list("abcde"), trail=False, out=tmp_path / "grid.gif",
    )  # fmt: skip
    frames = iio.imread(anim.path, index=None)
    assert frames.shape[:3] == (2, 3 * 64, 2 * 80) and anim.size == (160, 192)
    cells = [
        frames[0, r * 64 : (r + 1) * 64, c * 80 : (c + 1) * 80] for r in range(3) for c in (0, 1)
    ]
    for cell, col in zip(cells[:5], colors, strict=True):
        assert (blue(cell) if col == "real" else orange(cell)).sum() > 20
        assert (orange(cell) if col == "real" else blue(cell)).sum() == 0
    assert (cells[5] >= 250).all()  # the empty cell
    with pytest.raises(ValueError, match="ncols"):
        viz.animate(walker(4), PARENTS, ncols=0)


def test_default_stride_plays_real_time_and_temp_file():
    anim = viz.animate(walker(12), PARENTS, fps=15, motion_fps=30, size=(64, 48))
    assert anim.path.exists() and anim.path.suffix == ".gif"
    assert anim.n_frames == 6  # every 2nd frame of a 30 Hz motion at 15 fps


def test_html_repr_embeds_gif_and_mp4(tmp_path):
    anim = viz.animate(walker(6), PARENTS, out=tmp_path / "a.gif", stride=1, size=(64, 48))
    html = anim._repr_html_()
    data = re.search(r'src="data:image/gif;base64,([^"]+)"', html)
    assert html.startswith("<img") and data is not None
    assert base64.b64decode(data.group(1)) == anim.data and anim.data[:4] == b"GIF8"
    assert anim._repr_mimebundle_()["text/html"] == html
    mp4 = anim.save(tmp_path / "a.mp4")  # another suffix re-encodes
    assert mp4.stat().st_size > 0 and len(iio.imread(mp4, index=None)) == 6
    vid = viz.animate(walker(6), PARENTS, out=tmp_path / "b.mp4", stride=1, size=(64, 48))
    assert "<video" in vid._repr_html_() and "data:video/mp4;base64," in vid._repr_html_()
    assert anim.save(tmp_path / "copy.gif").read_bytes() == anim.data


@pytest.mark.parametrize("backend", BACKENDS)
def test_real_and_generated_colours_differ(backend):
    kw = dict(size=(160, 120), backend=backend)
    real = viz.render_frame(walker(1)[0], PARENTS, colors="real", **kw)
    gen = viz.render_frame(walker(1)[0], PARENTS, colors="generated", **kw)
    assert real.shape == (120, 160, 3) and real.dtype == np.uint8
    assert orange(gen).sum() > 100 and orange(real).sum() < 5
    assert blue(real).sum() > 100 and blue(gen).sum() < 5
    both = viz.render_frame([walker(1)[0], walker(1, y=0.6)[0]], PARENTS, **kw)  # overlay
    assert orange(both).sum() > 100 and blue(both).sum() > 100
    # side by side: real (first in PALETTE) left, generated right
    anim = viz.animate([walker(4), walker(4)], PARENTS, stride=1, **kw)
    frame = iio.imread(anim.path, index=0)[..., :3]
    left, right = frame[:, :160], frame[:, 160:]
    assert blue(left).sum() > 100 and orange(left).sum() < 5
    assert orange(right).sum() > 100 and blue(right).sum() < 5


def test_targets_are_drawn_in_target_colour():
    red = lambda img: img[..., 0].astype(int) - img[..., 1] > 100  # noqa: E731
    pose = walker(1)[0]
    plain = viz.render_frame(pose, PARENTS, size=(160, 120))
    path = np.array([[0.5, -0.5], [1.0, 0.0], [1.5, 0.5]])  # (K, 2) ground points
    keyframe = walker(1, y=-0.5)  # (1, J, 3) pose
    marked = viz.render_frame(pose, PARENTS, size=(160, 120), targets=[path, keyframe])
    assert red(marked).sum() > red(plain).sum() + 50


def test_skeleton_object_and_torch_input(tmp_path):
    names = ["root", "chest", "head", "left_ankle", "right_ankle"]
    skel = SimpleNamespace(parents=PARENTS, names=names)
    motion = torch.tensor(walker(4), dtype=torch.float32)
    anim = viz.animate(motion, skel, out=tmp_path / "t.gif", stride=1, size=(64, 48))
    assert anim.n_frames == 4
    scene = viz._build_scene(
        motion, skel, None, None, "overlay", (64, 48), True, True, None, 30.0, (-60, 15)
    )
    assert scene.head == 2  # the leaf called "head" gets a head sphere
    batch = torch.stack([motion, motion])  # (B, F, J, 3) is a list of B motions
    assert viz.animate(batch, PARENTS, stride=1, size=(64, 48)).size == (128, 48)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: viz.animate(walker(4)[..., 0], PARENTS), r"motions must have shape \(F, J, 3\)"),
        (lambda: viz.animate([walker(4), np.zeros((4, 5, 2))], PARENTS), r"motions\[1\]"),
        (lambda: viz.animate(walker(4), PARENTS[:4]), "parents has length 4.*J = 5"),
        (lambda: viz.animate(walker(4), [-1, 0, 1, 9, 0]), r"parents\[3\] = 9"),
        (lambda: viz.animate(walker(4), [1, 0, -1, 0, 0]), "cycle"),
        (lambda: viz.animate(_nan(walker(4), 2), PARENTS), "NaN/Inf, first at frame 2"),
        (lambda: viz.animate(walker(4), PARENTS, layout="grid"), "layout"),
        (lambda: viz.animate(walker(4), PARENTS, out="x.png"), "out must end in .gif or .mp4"),
        (lambda: viz.animate(walker(4), PARENTS, labels=["a", "b"]), "labels has 2"),
        (lambda: viz.animate(walker(4), PARENTS, colors=["red", "blue"]), "colors has 2"),
        (lambda: viz.animate(walker(4), PARENTS, targets=np.zeros((3, 4))), "targets"),
        (lambda: viz.animate(walker(4), PARENTS, backend="blender"), "backend"),
        (lambda: viz.animate(walker(4), PARENTS, stride=0), "stride"),
        (lambda: viz.render_frame(walker(4), PARENTS), r"positions must have shape \(J, 3\)"),
        (lambda: viz.plot_trajectories([np.zeros((4, 4))]), r"trajectories\[0\]"),
    ],
)
def test_bad_input_names_the_argument(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def _nan(m: np.ndarray, f: int) -> np.ndarray:
    m = m.copy()
    m[f, 1, 2] = np.nan
    return m


def test_pyvista_failure_falls_back_to_matplotlib_once(monkeypatch, tmp_path):
    def broken(scene):
        raise RuntimeError("no EGL here")

    monkeypatch.setattr(viz.render, "_PyvistaRenderer", broken)
    monkeypatch.setattr(viz.render, "_PYVISTA_ERROR", None)  # undone (to None) after the test
    with pytest.warns(RuntimeWarning, match="no EGL here"):
        anim = viz.animate(walker(4), PARENTS, out=tmp_path / "f.gif", stride=1, size=(64, 48))
    assert iio.imread(anim.path, index=None).shape[:3] == (4, 48, 64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # warned once: the second call is quiet
        viz.animate(walker(4), PARENTS, out=tmp_path / "g.gif", stride=1, size=(64, 48))


def test_filmstrip_scrubber_and_trajectories():
    fig = viz.filmstrip([walker(10), walker(10)], PARENTS, n=4, labels=["real", "gen"])
    assert len(fig.axes) == 8 and fig.axes[0].images
    box = viz.scrubber(walker(8), PARENTS, stride=1, size=(64, 48))
    image, (play, slider) = box.children[0], box.children[1].children
    assert slider.max == play.max == 7
    first = image.value
    slider.value = 5
    assert image.value != first and image.value[:4] == b"\x89PNG"
    assert (image.width, image.height) == ("64", "48")  # its own size, not the cell's width
    assert "run the cell" in repr(box) and "PNG" not in box._repr_mimebundle_()["text/plain"]
    fig = viz.filmstrip(walker(10), PARENTS, n=8)  # 8 frames still fit the book's column
    assert fig.get_size_inches()[0] <= viz.COLUMN_INCHES and fig.dpi == 100
    fig = viz.plot_trajectories(
        [walker(10), walker(10, y=1.0)], labels=["a", "b"], targets=[[1.0, 0.0], [2.0, 1.0]]
    )
    ax = fig.axes[0]
    assert len(ax.get_legend().get_texts()) == 2
    xy = ax.lines[0].get_xydata()
    np.testing.assert_allclose(xy[:, 0], walker(10)[:, 0, 0])  # the root's top-down path


def test_gif_stays_small():
    """About 320 x 240 px at 15 fps: 30 frames of one character stay well under 200 kB."""
    anim = viz.animate(walker(30, speed=0.04), PARENTS, stride=1)
    assert anim.size == (320, 240)
    assert len(anim.data) < 200_000, len(anim.data)
